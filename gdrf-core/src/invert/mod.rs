//! Photo inversion (paper §5): the shape feature w_s and the appearance modulation
//! (γ_a, β_a) that re-render a photo at its pose, found by Adam on
//!
//! ```text
//! mse_weight · MSE(I, Î) + perceptual_weight · P(I, Î) + silhouette_weight · mean (O − S)²
//!   + prior_shape · mean (w_s − w_s⁰)² + prior_appearance · mean (a − a⁰)²
//! ```
//!
//! where `a` is the appearance mapping network's raw output (f, β), with γ = 15 f + 30 (so
//! Adam's step size means the same for γ and β, as the raw output is what the mapping
//! network produces), and `P` the perceptual distance the caller supplies (real LPIPS, or
//! the EfficientNet-Lite0 distance offline). The paper sums squares in its priors; means keep
//! the weights independent of the network widths. The silhouette term, where the photo has
//! a silhouette `S` ([`photo::Photo::silhouette`]), matches the render's opacity `O` (the
//! object's share of each pixel) to it: the paper has no such term. It reaches the pose too
//! when the pose is refined.
//!
//! The speed options, each measured by `gdrf-invert bench`:
//! - `ray_fraction < 1`: each step renders the whole image without gradients, re-renders a
//!   random subset of its rays with gradients at the same sample depths and splices them in,
//!   so both terms see the full image but the backward pass only the subset;
//! - `coarse_fraction > 0`: the first steps compare at half resolution;
//! - `patience > 0`: stop once the loss has not improved by `min_improvement` (relative)
//!   for that many steps.
/// The commands of gdrf-invert (their flags and progress bars need the `cli` feature).
pub mod choice;
#[cfg(feature = "cli")]
pub mod command;
mod config;
pub mod framing;
pub mod init;
pub mod photo;

pub use config::InvertConfig;

use crate::camera::{Poses, Rays};
use crate::config::{CameraConfig, RenderConfig};
use crate::edit::Features;
use crate::field::generator::{Generator, TRUNCATION_MEAN_CODES};
use crate::io::resize;
use crate::nn::film::Film;
use crate::pretrained::effnet::EfficientNetLite0;
use crate::pretrained::lpips::Lpips;
use crate::pretrained::perceptual::{self, EffnetPerceptual};
use crate::render::occupancy::{GridConfig, OccupancyGrid};
use crate::render::Grids;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::train::optim::Adam;
use crate::{Error, Latents, Result};
use serde::Serialize;
use tch::{Device, Kind, Tensor};

/// A perceptual distance's first stage: the prepared target of a `(1, 3, H, W)` image in
/// [−1, 1] (its network features).
pub type PrepareTarget<'a> = Box<dyn Fn(&Tensor) -> Result<Vec<Tensor>> + 'a>;
/// Its second: `(B,)` distances of `(B, 3, H, W)` images in [−1, 1] to a prepared target.
pub type ToTarget<'a> = Box<dyn Fn(&Tensor, &[Tensor]) -> Result<Tensor> + 'a>;

/// A perceptual distance with the name the outputs report, in two stages: what the
/// distance needs of the fixed photo (its network features) is computed once per render
/// size, and each step runs the network on the render alone (forward and backward), not on
/// the render and the photo together.
pub struct Perceptual<'a> {
    pub name: String,
    pub target: PrepareTarget<'a>,
    pub to_target: ToTarget<'a>,
}

impl<'a> Perceptual<'a> {
    /// The offline default: the EfficientNet-Lite0 distance at 224² (LPIPS-style, not LPIPS).
    pub fn effnet(net: &'a EfficientNetLite0) -> Self {
        let d = EffnetPerceptual { net, size: 224 };
        Self {
            name: perceptual::NAME.into(),
            target: Box::new(move |y| d.target(y)),
            to_target: Box::new(move |x, t| d.to_target(x, t)),
        }
    }

    /// Real LPIPS on its backbone (`--perceptual lpips-*`).
    pub fn lpips(net: &'a Lpips) -> Self {
        Self {
            name: format!("LPIPS ({})", net.net().name()),
            target: Box::new(move |y| net.target(y)),
            to_target: Box::new(move |x, t| net.to_target(x, t)),
        }
    }
}

/// EfficientNet-Lite0 from the project's weights file, with an error that says how to get it.
pub fn load_effnet(device: Device) -> Result<EfficientNetLite0> {
    let p = EfficientNetLite0::default_path();
    EfficientNetLite0::load(&p, device).map_err(|e| {
        Error::Invalid(format!(
            "the inversion's perceptual term needs EfficientNet-Lite0's weights at {} (run scripts/setup.sh): {e}",
            p.display()
        ))
    })
}

/// Where the optimisation starts.
#[derive(Debug)]
pub struct Start {
    /// `(1, mapping_hidden)`.
    pub w_s: Tensor,
    /// `(1, 2·L_c·H)`: the appearance mapping network's raw output (f, β).
    pub appearance_raw: Tensor,
    /// (pitch, yaw) in radians.
    pub pose: (f64, f64),
}

impl Start {
    /// `n` fixed random codes `(n, latent)` of stream `seed` (the same every call). Shape
    /// and appearance use streams 0 and 1, as [`Generator::truncation`] does for its means.
    fn codes(g: &Generator, n: i64, seed: u64) -> Tensor {
        let (kind, device) = g.kind_device();
        StepRng::new(seed, 0, Purpose::Truncation, kind, device).normal(&[n, g.cfg.latent_dim as i64])
    }

    /// The paper's appearance start: the mean raw output over `n` random codes (10 000 in
    /// the paper); `w_s` as given (the initialiser's, or the mean shape feature).
    pub fn with_mean_appearance(g: &Generator, w_s: Tensor, pose: (f64, f64), n: i64) -> Self {
        let z = Self::codes(g, n, 1);
        let appearance_raw = tch::no_grad(|| g.appearance_raw(&z).mean_dim(0, true, z.kind()));
        Self { w_s, appearance_raw, pose }
    }

    /// The mean-code start: the mean w_s and the mean appearance over `n` random codes.
    pub fn mean(g: &Generator, pose: (f64, f64), n: i64) -> Self {
        let z = Self::codes(g, n, 0);
        let w_s = tch::no_grad(|| g.shape_w(&z).mean_dim(0, true, z.kind()));
        Self::with_mean_appearance(g, w_s, pose, n)
    }
}

/// One step's record.
#[derive(Debug, Clone, Serialize)]
pub struct StepLog {
    pub step: usize,
    pub resolution: i64,
    pub loss: f64,
    pub mse: f64,
    pub perceptual: f64,
    /// The silhouette term, unweighted (0 without one).
    pub silhouette: f64,
    pub prior: f64,
    /// Seconds spent in the optimisation's steps so far, this one included.
    pub seconds: f64,
}

/// What the optimisation found.
#[derive(Debug)]
pub struct Inversion {
    pub features: Features,
    pub history: Vec<StepLog>,
    /// Whether `patience` ended it before `steps`.
    pub stopped_early: bool,
}

/// The rendered image `(1, 3, res, res)` of (`w_s`, raw appearance) at `pose`, with
/// gradients through the rays in `subset` (all when `None`).
pub fn render_at_pose(
    renderer: &Renderer,
    latents: &Latents,
    pose: (f64, f64),
    res: i64,
    noise: &Noise,
    subset: Option<&Tensor>,
) -> Result<Tensor> {
    let (kind, device) = renderer.generator.kind_device();
    render_at_poses(renderer, latents, &Poses::from_angles(&[pose], kind, device), res, noise, subset, None)
}

/// [`render_at_pose`] at one pose given as tensors (gradients flow into the pose when it
/// requires them), sampled inside `grid` when one is given. A grid that samples only its
/// occupied cells ([`GridConfig::cells_only`]) renders as gdrf-edit's grids do
/// ([`crate::render::Grids::render_in_cells`]); otherwise each ray is sampled between its first and last
/// occupied cell, and a ray that meets none has every sample at the camera's far end, so
/// only that point, where the release's infinite last interval is, counts.
pub fn render_at_poses(
    renderer: &Renderer,
    latents: &Latents,
    poses: &Poses,
    res: i64,
    noise: &Noise,
    subset: Option<&Tensor>,
    grid: Option<&OccupancyGrid>,
) -> Result<Tensor> {
    Ok(render_with_opacity(renderer, latents, poses, res, noise, subset, grid)?.0)
}

/// [`render_at_poses`]' image, and the object's share of each pixel `(1, 1, res, res)` in
/// [0, 1] ([`crate::render::RenderedRays::object_share`]: the weights of every sample but
/// the far one, which stands for the background), with gradients as the image has them.
pub fn render_with_opacity(
    renderer: &Renderer,
    latents: &Latents,
    poses: &Poses,
    res: i64,
    noise: &Noise,
    subset: Option<&Tensor>,
    grid: Option<&OccupancyGrid>,
) -> Result<(Tensor, Tensor)> {
    let mut rays = Rays::from_poses(poses, res, renderer.camera.fov_deg);
    let (pixels, share) = match grid {
        Some(grid) if grid.cfg.cells_only => {
            Grids::new(renderer).render_in_cells(latents, &rays, grid, noise, subset)?
        }
        _ => {
            if let Some(grid) = grid {
                let end = renderer.camera.ray_end;
                let bounds = tch::no_grad(|| {
                    let (bounds, hit) = grid.clip(&rays, renderer.camera.ray_start, end);
                    bounds.where_self(&hit.unsqueeze(-1), &bounds.full_like(end))
                });
                rays = rays.with_bounds(bounds);
            }
            match subset {
                None => {
                    let out = renderer.render_rays(latents, &rays, noise)?;
                    let share = out.object_share();
                    (out.pixel, share)
                }
                Some(idx) => {
                    // The whole image without gradients, then the subset again with them at
                    // the very same sample depths, spliced in.
                    let full = tch::no_grad(|| renderer.render_rays(latents, &rays, noise))?;
                    let z = full.z.index_select(1, idx);
                    let part = renderer.render_at_depths(latents, &rays.select_rays(idx), &z)?;
                    (
                        full.pixel.detach().index_copy(1, idx, &part.pixel),
                        full.object_share().detach().index_copy(1, idx, &part.object_share()),
                    )
                }
            }
        }
    };
    // (1, R, 3) in [0, 1] → (1, 3, res, res) in [−1, 1]; (1, R, 1) → (1, 1, res, res).
    let rgb = pixels.view([1, res, res, 3]).permute([0, 3, 1, 2]) * 2.0 - 1.0;
    Ok((rgb, share.view([1, 1, res, res])))
}

/// The silhouette term: mean over pixels of (opacity − silhouette)², in float32 or wider,
/// of `opacity` and `silhouette` of one shape (opacities of any precision).
pub fn silhouette_loss(opacity: &Tensor, silhouette: &Tensor) -> Tensor {
    let o = crate::render::wide(opacity);
    let kind = o.kind();
    (o - silhouette.to_kind(kind)).square().mean(kind)
}

/// Adam with torch's defaults (betas 0.9, 0.999, eps 1e-8) over the inversion's tensors.
fn new_adam(params: Vec<(String, Tensor)>) -> Adam {
    Adam::for_tensors(params, 0.9, 0.999, 1e-8)
}

/// w_s and the raw appearance under their optimiser names.
fn named_features(params: &[Tensor; 2]) -> Vec<(String, Tensor)> {
    vec![("w_s".into(), params[0].shallow_clone()), ("appearance".into(), params[1].shallow_clone())]
}

fn named_pose(p: &Tensor) -> Vec<(String, Tensor)> {
    vec![("pose".into(), p.shallow_clone())]
}

/// The optimisation as explicit state, one [`Inverter::step`] at a time, so that a caller
/// (the benchmark) can look at the features between steps without its time counting.
pub struct Inverter<'a> {
    g: &'a Generator,
    camera: &'a CameraConfig,
    cfg: InvertConfig,
    perceptual: Option<&'a Perceptual<'a>>,
    rc: RenderConfig,
    pose: (f64, f64),
    w0: Tensor,
    a0: Tensor,
    /// w_s `(1, H)` and the raw appearance `(1, 2·L_c·H)`, both requiring grad.
    params: [Tensor; 2],
    adam: Adam,
    /// (pitch, yaw) `(2,)` requiring grad, and its optimiser, when the pose is refined.
    pose_param: Option<(Tensor, Adam)>,
    /// The photo at each render size used, and its prepared perceptual target.
    targets: std::collections::BTreeMap<i64, (Tensor, Option<Vec<Tensor>>)>,
    /// The photo's silhouette at each render size used, where it has one and the
    /// silhouette term is on ([`Inverter::with_silhouette`]).
    silhouettes: Option<std::collections::BTreeMap<i64, Tensor>>,
    /// The occupancy grid of the shape (`cfg.grid` > 0) and the step it was built at.
    grid: Option<(usize, OccupancyGrid)>,
    best: f64,
    since_best: usize,
    stopped_early: bool,
    /// Seconds spent inside `step`.
    seconds: f64,
    pub history: Vec<StepLog>,
}

impl<'a> Inverter<'a> {
    /// Checks the inputs and sets up the optimisation of `photo: (1, 3, R, R)` in [−1, 1]
    /// (any R; it is resized to each step's render size) from `start`.
    pub fn new(
        g: &'a Generator,
        camera: &'a CameraConfig,
        photo: &Tensor,
        start: &Start,
        cfg: &InvertConfig,
        perceptual: Option<&'a Perceptual<'a>>,
    ) -> Result<Self> {
        cfg.validate()?;
        let s = photo.size();
        if s.len() != 4 || s[0] != 1 || s[1] != 3 || s[2] != s[3] {
            return Err(Error::Shape(format!("the photo must be (1, 3, R, R), got {s:?}")));
        }
        let (kind, device) = g.kind_device();
        let hidden = g.cfg.mapping_hidden_dim as i64;
        let colour = 2 * (g.cfg.colour_layers * g.cfg.hidden_dim) as i64;
        if start.w_s.size() != [1, hidden] || start.appearance_raw.size() != [1, colour] {
            return Err(Error::Shape(format!(
                "start features have shapes {:?} and {:?}, expected [1, {hidden}] and [1, {colour}]",
                start.w_s.size(),
                start.appearance_raw.size()
            )));
        }
        let w0 = start.w_s.detach().to_kind(kind).to_device(device);
        let a0 = start.appearance_raw.detach().to_kind(kind).to_device(device);
        let params = [w0.copy().set_requires_grad(true), a0.copy().set_requires_grad(true)];
        let adam = new_adam(named_features(&params));
        let pose_param = cfg.refine_pose.then(|| {
            let p = Tensor::from_slice(&[start.pose.0, start.pose.1]).to_kind(kind).to_device(device);
            let p = p.set_requires_grad(true);
            let opt = new_adam(named_pose(&p));
            (p, opt)
        });
        let rc = RenderConfig { num_steps: cfg.samples, ..Default::default() };
        rc.validate()?;
        let photo = photo.to_kind(Kind::Float).to_device(device);
        let perceptual = perceptual.filter(|_| cfg.perceptual_weight > 0.0);
        let targets = [cfg.resolution_at(0), cfg.resolution]
            .into_iter()
            .map(|r| {
                let photo = resize(&photo, r);
                let features = perceptual.map(|pd| tch::no_grad(|| (pd.target)(&photo))).transpose()?;
                Ok((r, (photo, features)))
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            g,
            camera,
            cfg: cfg.clone(),
            perceptual,
            rc,
            pose: start.pose,
            w0,
            a0,
            params,
            adam,
            pose_param,
            targets,
            silhouettes: None,
            grid: None,
            best: f64::INFINITY,
            since_best: 0,
            stopped_early: false,
            seconds: 0.0,
            history: Vec::with_capacity(cfg.steps),
        })
    }

    /// Matches the rendered opacity to `silhouette: (1, 1, R, R)` in [0, 1] (the photo's,
    /// [`photo::Photo::silhouette`]) with weight `silhouette_weight`: mean over pixels of
    /// (opacity − silhouette)². Without it, or at weight 0, there is no such term.
    pub fn with_silhouette(mut self, silhouette: Option<&Tensor>) -> Result<Self> {
        let Some(s) = silhouette.filter(|_| self.cfg.silhouette_weight > 0.0) else {
            return Ok(self);
        };
        let z = s.size();
        if z.len() != 4 || z[0] != 1 || z[1] != 1 || z[2] != z[3] {
            return Err(Error::Shape(format!("the silhouette must be (1, 1, R, R), got {z:?}")));
        }
        let s = s.to_kind(Kind::Float).to_device(self.w0.device());
        self.silhouettes = Some(self.targets.keys().map(|&r| (r, resize(&s, r).clamp(0.0, 1.0))).collect());
        Ok(self)
    }

    /// Whether the optimisation has ended (all steps, or early stop).
    pub fn done(&self) -> bool {
        self.stopped_early || self.history.len() >= self.cfg.steps
    }

    /// One Adam step; `None` once [`Self::done`].
    pub fn step(&mut self) -> Result<Option<&StepLog>> {
        if self.done() {
            return Ok(None);
        }
        let t0 = std::time::Instant::now();
        let (cfg, g) = (&self.cfg, self.g);
        let step = self.history.len();
        let device = self.w0.device();
        let res = cfg.resolution_at(step);
        let rays = res * res;
        let rng = |p: u64| StepRng::new(cfg.seed, 3 * step as u64 + p, Purpose::InvertNoise, Kind::Float, device);
        let n = cfg.samples as i64;
        let noise =
            Noise { jitter: Some(rng(0).uniform(&[1, rays, n])), importance: Some(rng(1).uniform(&[1, rays, n])) };
        let subset = (cfg.ray_fraction < 1.0).then(|| {
            let k = ((rays as f64 * cfg.ray_fraction).round() as i64).clamp(1, rays);
            rng(2).uniform(&[rays]).argsort(0, false).narrow(0, 0, k).sort(0, false).0
        });
        let mut renderer = Renderer::new(g, self.camera, &self.rc)?;
        renderer.field.compute_kind = cfg.bf16.then_some(Kind::BFloat16);
        let p = &self.params;
        let latents = Latents { shape: g.shape_from_w(&p[0], None), appearance: Film::from_raw(&p[1]) };
        let poses = match &self.pose_param {
            Some((p, _)) => Poses { pitch: p.narrow(0, 0, 1).view([1, 1]), yaw: p.narrow(0, 1, 1).view([1, 1]) },
            None => Poses::from_angles(&[self.pose], self.w0.kind(), device),
        };
        if cfg.grid > 0 && self.grid.as_ref().is_none_or(|(at, _)| step - at >= cfg.grid_refresh) {
            let shape = tch::no_grad(|| g.shape_from_w(&p[0].detach(), None));
            let gc = GridConfig {
                resolution: cfg.grid,
                threshold: cfg.grid_threshold,
                cells_only: cfg.grid_cells,
                ..Default::default()
            };
            self.grid = Some((step, Grids::new(&renderer).occupancy_grid(&shape, gc)?));
        }
        let grid = self.grid.as_ref().map(|(_, grid)| grid);
        let (img, opacity) = render_with_opacity(&renderer, &latents, &poses, res, &noise, subset.as_ref(), grid)?;
        let (target, features) = &self.targets[&res];
        let silhouette = match &self.silhouettes {
            Some(s) => silhouette_loss(&opacity, &s[&res]),
            None => Tensor::zeros([], (Kind::Float, device)),
        };
        let mse = (&img - target).square().mean(Kind::Float);
        let perc = match (self.perceptual, features) {
            (Some(pd), Some(f)) => (pd.to_target)(&img, f)?.mean(Kind::Float),
            _ => Tensor::zeros([], (Kind::Float, device)),
        };
        let prior = (&p[0] - &self.w0).square().mean(Kind::Float) * cfg.prior_shape
            + (&p[1] - &self.a0).square().mean(Kind::Float) * cfg.prior_appearance;
        let loss = &mse * cfg.mse_weight + &perc * cfg.perceptual_weight + &silhouette * cfg.silhouette_weight + &prior;
        let value = loss.double_value(&[]);
        if !value.is_finite() {
            return Err(Error::Invalid(format!(
                "the inversion loss is not finite at step {step} (lower invert.lr or check the photo)"
            )));
        }
        for p in self.params.iter_mut().chain(self.pose_param.as_mut().map(|(p, _)| p)) {
            p.zero_grad();
        }
        loss.backward();
        self.adam.step_tensors(named_features(&self.params), cfg.lr);
        if let Some((p, opt)) = &mut self.pose_param {
            opt.step_tensors(named_pose(p), cfg.pose_lr);
            self.pose = (p.double_value(&[0]), p.double_value(&[1]));
        }
        self.seconds += t0.elapsed().as_secs_f64();
        let log = StepLog {
            step,
            resolution: res,
            loss: value,
            mse: mse.double_value(&[]),
            perceptual: perc.double_value(&[]),
            silhouette: silhouette.double_value(&[]),
            prior: prior.double_value(&[]),
            seconds: self.seconds,
        };
        // Patience counts at full resolution only (a coarse loss is not comparable).
        if res == cfg.resolution {
            if value < self.best * (1.0 - cfg.min_improvement) {
                self.best = value;
                self.since_best = 0;
            } else {
                self.since_best += 1;
                self.stopped_early = cfg.patience > 0 && self.since_best >= cfg.patience;
            }
        }
        self.history.push(log);
        Ok(self.history.last())
    }

    /// The current features (detached copies).
    pub fn features(&self) -> Features {
        tch::no_grad(|| Features {
            w_s: self.params[0].detach().copy(),
            appearance: Film::from_raw(&self.params[1].detach()),
            pose: Some(self.pose),
            z: None,
        })
    }

    /// Steps to the end, calling `progress` after each.
    pub fn run(mut self, progress: &mut dyn FnMut(&StepLog)) -> Result<Inversion> {
        while let Some(log) = self.step()? {
            progress(log);
        }
        Ok(Inversion { features: self.features(), history: self.history, stopped_early: self.stopped_early })
    }
}

/// [`Inverter`] from `start` to the end, calling `progress` after every step.
pub fn invert(
    g: &Generator,
    camera: &CameraConfig,
    photo: &Tensor,
    start: &Start,
    cfg: &InvertConfig,
    perceptual: Option<&Perceptual>,
    progress: &mut dyn FnMut(&StepLog),
) -> Result<Inversion> {
    Inverter::new(g, camera, photo, start, cfg, perceptual)?.run(progress)
}

/// [`invert`] of a prepared photo: its image, and its silhouette where it has one
/// ([`Inverter::with_silhouette`]).
pub fn invert_photo(
    g: &Generator,
    camera: &CameraConfig,
    photo: &photo::Photo,
    start: &Start,
    cfg: &InvertConfig,
    perceptual: Option<&Perceptual>,
    progress: &mut dyn FnMut(&StepLog),
) -> Result<Inversion> {
    Inverter::new(g, camera, &photo.rgb, start, cfg, perceptual)?
        .with_silhouette(photo.silhouette.as_ref())?
        .run(progress)
}

/// Where the pose of an inversion came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PoseFrom {
    /// Given by the caller (`--pose`).
    Given,
    /// The initialiser's prediction.
    Initialiser,
    /// Neither: the camera's mean pose.
    CameraMean,
}

/// Where an inversion of a photo starts ([`start_for_photo`]).
pub struct PhotoStart {
    pub start: Start,
    /// Where `start.pose` came from.
    pub pose_from: PoseFrom,
    /// The initialiser's estimate of the photo's pose, when it was given one.
    pub predicted_pose: Option<(f64, f64)>,
}

/// The start of an inversion of `photo: (1, 3, R, R)`: from the initialiser's prediction of
/// w_s when `init` is given (with its appearance when it predicts one, else the mean
/// appearance), else the mean code's features; at `pose` when given, else the
/// initialiser's, else the camera's mean pose.
pub fn start_for_photo(
    g: &Generator,
    camera: &CameraConfig,
    photo: &Tensor,
    pose: Option<(f64, f64)>,
    init: Option<&init::Initialiser>,
) -> Result<PhotoStart> {
    let predicted = init.map(|f| f.predict(photo)).transpose()?;
    let (pose, from) = match (pose, &predicted) {
        (Some(p), _) => (p, PoseFrom::Given),
        (None, Some(p)) => (p.pose, PoseFrom::Initialiser),
        (None, None) => ((camera.v_mean, camera.h_mean), PoseFrom::CameraMean),
    };
    let predicted_pose = predicted.as_ref().map(|p| p.pose);
    let start = match predicted {
        Some(p) => {
            let mut s = Start::with_mean_appearance(g, p.w_s, pose, TRUNCATION_MEAN_CODES);
            if let Some(a) = p.appearance_raw {
                s.appearance_raw = a;
            }
            s
        }
        None => Start::mean(g, pose, TRUNCATION_MEAN_CODES),
    };
    Ok(PhotoStart { start, pose_from: from, predicted_pose })
}

/// A photo as an editing source, prepared by [`photo::prepare_photo`] (its silhouette found,
/// framed as the training images are): inverted with `cfg` from [`start_for_photo`]'s start
/// with `init`, the pose refined as `refine` says, with the EfficientNet-Lite0 perceptual
/// distance when `cfg.perceptual_weight` is not 0 and the photo's silhouette when it has
/// one, telling `progress` each optimisation step. Returns the features and where the pose
/// came from.
#[allow(clippy::too_many_arguments)]
pub fn features_of_photo(
    g: &Generator,
    camera: &CameraConfig,
    photo: &photo::Photo,
    pose: Option<(f64, f64)>,
    init: Option<&init::Initialiser>,
    refine: choice::RefinePose,
    cfg: &InvertConfig,
    progress: &mut dyn FnMut(&StepLog),
) -> Result<(Features, PoseFrom)> {
    let (_, device) = g.kind_device();
    let started = start_for_photo(g, camera, &photo.rgb, pose, init)?;
    let cfg = InvertConfig { refine_pose: refine.resolve(started.pose_from), ..cfg.clone() };
    let net;
    let perceptual = if cfg.perceptual_weight > 0.0 {
        net = load_effnet(device)?;
        Some(Perceptual::effnet(&net))
    } else {
        None
    };
    let f = invert_photo(g, camera, photo, &started.start, &cfg, perceptual.as_ref(), progress)?.features;
    Ok((f, started.pose_from))
}

/// The features `f` on a turntable of `n` views from `pose` (radians), `(n, 3, res, res)`
/// in [−1, 1], rendered as [`render_views`] does, eight views at a time.
pub fn render_orbit(
    g: &Generator,
    camera: &CameraConfig,
    f: &Features,
    pose: (f64, f64),
    n: usize,
    res: i64,
    samples: usize,
) -> Result<Tensor> {
    let poses = crate::camera::turntable(pose.0, pose.1, n);
    let views = poses.chunks(8).map(|c| render_views(g, camera, f, c, res, samples)).collect::<Result<Vec<_>>>()?;
    Ok(Tensor::cat(&views, 0))
}

/// The loss curve of an inversion: the total, and its terms (MSE, perceptual, silhouette,
/// priors), on log axes.
pub fn loss_panels(history: &[StepLog]) -> Vec<crate::plot::Panel> {
    use crate::plot::{Panel, Series};
    let series = |name: &str, f: &dyn Fn(&StepLog) -> f64| Series {
        name: name.to_string(),
        points: history.iter().map(|l| (l.step as f64, f(l))).collect(),
    };
    vec![
        Panel { title: "loss".into(), series: vec![series("total", &|l| l.loss)], log_y: true, marks: vec![] },
        Panel {
            title: "terms".into(),
            series: vec![
                series("mse", &|l| l.mse),
                series("perceptual", &|l| l.perceptual),
                series("silhouette", &|l| l.silhouette),
                series("prior", &|l| l.prior),
            ],
            log_y: true,
            marks: vec![],
        },
    ]
}

/// A pose given as `PITCH,YAW` in degrees (pitch from +y, the command-line convention of
/// every binary) → radians; `flag` names the option in the error.
pub fn parse_pose_degrees(s: &str, flag: &str) -> Result<(f64, f64)> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let nums: Vec<f64> = parts.iter().filter_map(|p| p.parse().ok()).collect();
    if parts.len() != 2 || nums.len() != 2 || nums.iter().any(|v| !v.is_finite()) {
        return Err(Error::Invalid(format!("{flag} '{s}': expected PITCH,YAW in degrees, e.g. {flag} 60,-30")));
    }
    Ok((nums[0].to_radians(), nums[1].to_radians()))
}

/// The features `f` (shape and appearance) rendered at each of `poses` (radians), `(V, 3,
/// res, res)` in [−1, 1], without gradients or random draws (no jitter, importance samples
/// at mid-points), `n` + `n` samples per ray.
pub fn render_views(
    g: &Generator,
    camera: &CameraConfig,
    f: &Features,
    poses: &[(f64, f64)],
    res: i64,
    n: usize,
) -> Result<Tensor> {
    let rc = RenderConfig { num_steps: n, jitter: false, ..Default::default() };
    let r = Renderer::new(g, camera, &rc)?;
    let one = crate::edit::latents(g, f, f, None);
    let k = poses.len() as i64;
    let rep = |t: &Tensor| t.repeat([k, 1]);
    let lat = Latents {
        shape: Film { gamma: rep(&one.shape.gamma), beta: rep(&one.shape.beta) },
        appearance: Film { gamma: rep(&one.appearance.gamma), beta: rep(&one.appearance.beta) },
    };
    let (kind, device) = g.kind_device();
    let p = Poses::from_angles(poses, kind, device);
    Ok(tch::no_grad(|| r.render_image(&lat, &p, res, &Noise::midpoints(k, res * res, n as i64, device)))?.rgb)
}

#[cfg(test)]
mod tests;
