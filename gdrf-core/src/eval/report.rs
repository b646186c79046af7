//! `gdrf-train eval`: every score of a generator beside its two calibrated ends — real
//! held-out images (what a perfect generator would get) and a random-weight generator of
//! the same architecture (what learning nothing gets) — written as `eval.json` and a
//! one-page `report.png`.
//!
//! - **Fréchet / kernel distance** of pretrained features (EfficientNet-Lite0's pooled
//!   1280-d feature by default, FID's Inception-v3 with a user-supplied file) against the
//!   held-out split. The real end uses as many training-split images.
//! - **Topology coverage**: total variation between the probe's predicted structure classes
//!   over generated images and the held-out split's true classes, averaged over factors.
//! - **Disentanglement** on a k × k swap matrix (shape of i, appearance of j): over pairs
//!   whose originals differ, how often each structure factor follows i, and how often the
//!   part colours are nearer j's than i's. The real end renders the procedural dataset's
//!   own swaps.
//! - **Pose consistency**: the probe's yaw and pitch against the pose an image was rendered at.
use super::distance;
use super::probe::{self, class_histograms, total_variation, Predictions, Probe, FACTORS};
use crate::camera::Poses;
use crate::checkpoint::load_generator;
use crate::data::synth;
use crate::data::{Metadata, Split};
use crate::field::generator::Truncation;
use crate::paths::write_atomic;
use crate::pretrained::effnet::EfficientNetLite0;
use crate::pretrained::inception::InceptionV3;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{io, CameraConfig, Error, Generator, RenderConfig, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use tch::{nn, Device, Kind, Tensor};

/// The generator header's `info` key naming the discriminator it was trained against.
pub const DISCRIMINATOR_INFO: &str = "discriminator";

/// Said when a generator is scored at another resolution than the one it was trained at.
pub fn resolution_warning(header: &crate::checkpoint::Header, resolution: i64) -> Option<String> {
    let trained = header.trained_resolution()?;
    (trained != resolution).then(|| {
        let steps = header.trained_coarse_samples().map(|n| format!(" --steps {n}")).unwrap_or_default();
        format!(
            "this generator was trained at {trained}² and is rendered here at {resolution}²; \
             `--resolution {trained}{steps}` scores it where it learned, against the real images at {trained}²"
        )
    })
}

/// Said when a generator trained against the projected discriminator is scored with
/// EfficientNet-Lite0 features: the generator was optimised in that very feature space.
pub const SHARED_FEATURES_WARNING: &str = "this generator was trained against the projected discriminator, built on \
     EfficientNet-Lite0's frozen features, the very features the Fréchet and kernel distances use: the generator was \
     optimised in their space, so they are not independent judges of it (score it with --features inception, and \
     read the probe's scores and the images)";

/// Whether a generator (its header) was trained against the projected discriminator:
/// from the `info` its run wrote, or a training checkpoint's config.
pub fn trained_against_projected(h: &crate::checkpoint::Header) -> bool {
    let projected = crate::disc::DiscKind::Projected.name();
    h.info.get(DISCRIMINATOR_INFO).is_some_and(|k| k == projected)
        || h.training.as_ref().and_then(|t| t.pointer("/config/discriminator/kind")).and_then(|k| k.as_str())
            == Some(projected)
}

/// Which pretrained features the distances use.
#[derive(Debug, Clone)]
pub enum FeatureKind {
    Efficientnet,
    /// FID's Inception-v3 from this weights file.
    Inception(PathBuf),
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Generated images per distribution.
    pub num: i64,
    /// Side of the swap matrix.
    pub swap: i64,
    /// Render resolution (default: the dataset's).
    pub resolution: Option<i64>,
    /// Coarse samples per ray (as many fine).
    pub steps: i64,
    pub seed: u64,
    pub features: FeatureKind,
    pub effnet_weights: PathBuf,
    pub threads: usize,
    /// Also score the real images seen at this lower resolution (antialiased down, then
    /// bilinearly back up to the evaluation's): what the resolution alone costs real data,
    /// a reference for a generator trained at it. `None`: not scored.
    pub real_resolution: Option<i64>,
    /// Truncation ψ of the model's codes toward its mean mapping output (1 = none, the
    /// usual way to score a GAN). The random end is never truncated, so positions stay on
    /// one scale whatever ψ is.
    pub psi: f64,
}

/// One score at the model and at both ends.
#[derive(Debug, Clone, Serialize)]
pub struct Calibrated {
    pub model: f64,
    /// Real held-out images: what a perfect generator gets.
    pub real: f64,
    /// A random-weight generator of the same architecture.
    pub random: f64,
    /// Where the model stands: 0 at the random end, 1 at the real end.
    pub position: f64,
}

impl Calibrated {
    pub(crate) fn new(model: f64, real: f64, random: f64) -> Self {
        let span = real - random;
        let position = if span.abs() > 1e-12 { (model - random) / span } else { f64::NAN };
        Self { model, real, random, position }
    }
}

/// The real images' scores when seen at a lower resolution ([`EvalOptions::real_resolution`]).
#[derive(Debug, Clone, Serialize)]
pub struct LowResolutionEnd {
    pub resolution: i64,
    pub frechet: f64,
    pub kernel: f64,
    pub coverage_tv: f64,
    pub shape_follows: f64,
    pub appearance_follows: f64,
    pub pose_yaw_error_deg: f64,
    pub pose_yaw_error_in_frame_deg: f64,
    pub pose_pitch_error_deg: f64,
}

impl LowResolutionEnd {
    fn new(resolution: i64, s: &Scores) -> Self {
        Self {
            resolution,
            frechet: s.frechet,
            kernel: s.kernel,
            coverage_tv: s.coverage_tv,
            shape_follows: s.shape_follows,
            appearance_follows: s.appearance_follows,
            pose_yaw_error_deg: s.pose.yaw,
            pose_yaw_error_in_frame_deg: s.pose.yaw_in_frame,
            pose_pitch_error_deg: s.pose.pitch,
        }
    }
}

/// `imgs: (N, 3, S, S)` antialiased down to `low`² and bilinearly back up to S².
pub fn through_resolution(imgs: &Tensor, low: i64) -> Tensor {
    crate::io::resize(&crate::io::resize(imgs, low), imgs.size()[2])
}

/// The yaw rotation found for the model, the real images and the random generator (degrees).
#[derive(Debug, Clone, Serialize)]
pub struct FrameOffsets {
    pub model: f64,
    pub real: f64,
    pub random: f64,
}

#[derive(Debug, Serialize)]
pub struct ClassTable {
    pub factor: String,
    pub classes: Vec<String>,
    /// Held-out split, true classes.
    pub reference: Vec<f64>,
    pub real_predicted: Vec<f64>,
    pub model: Vec<f64>,
    pub random: Vec<f64>,
}

#[derive(Debug, Serialize)]
pub struct EvalResult {
    pub generator: String,
    pub dataset: String,
    pub features: String,
    /// The evaluation seed: codes, poses, the random generator, kernel-distance subsets.
    pub seed: u64,
    pub images: i64,
    pub resolution: i64,
    pub samples_per_ray: i64,
    /// The model's truncation ψ ([`EvalOptions::psi`]; 1 = none).
    pub psi: f64,
    pub frechet: Calibrated,
    pub kernel: Calibrated,
    /// Set when a Fréchet distance had to be regularised (few samples).
    pub warnings: Vec<String>,
    pub coverage_tv: Calibrated,
    pub classes: Vec<ClassTable>,
    pub shape_follows: Calibrated,
    pub appearance_follows: Calibrated,
    pub pose_yaw_error_deg: Calibrated,
    /// After turning each distribution's yaw by one rotation (see [`PoseErrors::yaw_in_frame`]).
    pub pose_yaw_error_in_frame_deg: Calibrated,
    /// That rotation, per distribution.
    pub yaw_frame_offset_deg: FrameOffsets,
    pub pose_pitch_error_deg: Calibrated,
    /// The real images seen at a lower resolution, when asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub real_at_resolution: Option<LowResolutionEnd>,
    pub probe_held_out_accuracy: Vec<f64>,
    pub seconds: f64,
    #[serde(skip)]
    pub samples: Tensor,
    #[serde(skip)]
    pub swap_images: Tensor,
    #[serde(skip)]
    pub swap_verdicts: Vec<Verdict>,
    #[serde(skip)]
    pub swap_side: i64,
}

/// Renders `z` at `poses` (batches of 16, no jitter, importance samples at the midpoints:
/// no random numbers) with `g`, its codes truncated by `trunc` when given. `codes`: shape
/// and appearance codes `(N, latent)` each.
fn render_codes(
    (g, trunc): (&Generator, Option<&Truncation>),
    cam: &CameraConfig,
    rc: &RenderConfig,
    codes: (&Tensor, &Tensor),
    poses: &Poses,
    res: i64,
    tick: &mut dyn FnMut(i64),
) -> Result<Tensor> {
    let (zs, za) = codes;
    let renderer = Renderer::new(g, cam, rc)?;
    let n = zs.size()[0];
    let mut out = Vec::new();
    let mut i = 0;
    while i < n {
        let b = 16.min(n - i);
        let lat = tch::no_grad(|| g.latents(&zs.narrow(0, i, b), &za.narrow(0, i, b), trunc));
        let p = Poses { pitch: poses.pitch.narrow(0, i, b), yaw: poses.yaw.narrow(0, i, b) };
        let nz = Noise::midpoints(b, res * res, rc.num_steps as i64, zs.device());
        out.push(tch::no_grad(|| renderer.render_image(&lat, &p, res, &nz))?.rgb.to_device(Device::Cpu));
        i += b;
        tick(b);
    }
    Ok(Tensor::cat(&out, 0))
}

/// A swap cell's verdicts (structure follows the row, colour follows the column); None
/// where the originals do not differ (and on the diagonal).
pub type Verdict = (Option<bool>, Option<bool>);

/// Bins per channel of the foreground colour histograms.
const HIST_BINS: i64 = 4;

/// `(N, 64)` normalised joint RGB histograms (4 bins per channel) of each image's
/// foreground — pixels at least 0.06 away from white in some channel — of `(N, 3, S, S)`
/// images in [−1, 1]. An image without foreground gets a zero histogram.
pub fn colour_histograms(images: &Tensor) -> Tensor {
    let x = ((images.to_kind(Kind::Float).to_device(Device::Cpu) + 1.0) / 2.0).clamp(0.0, 1.0);
    let (n, s) = (x.size()[0], x.size()[2] * x.size()[3]);
    let fg = x.min_dim(1, false).0.lt(0.94).view([n, s]).to_kind(Kind::Float);
    let bins = (x * HIST_BINS as f64).floor().clamp(0.0, (HIST_BINS - 1) as f64).to_kind(Kind::Int64).view([n, 3, s]);
    let idx = bins.select(1, 0) * (HIST_BINS * HIST_BINS) + bins.select(1, 1) * HIST_BINS + bins.select(1, 2);
    let hist = Tensor::zeros([n, HIST_BINS.pow(3)], (Kind::Float, Device::Cpu)).scatter_add(1, &idx, &fg);
    &hist / hist.sum_dim_intlist(1, true, Kind::Float).clamp_min(1.0)
}

/// The disentanglement rates of a k × k swap matrix (row-major: shape i, appearance j)
/// and each cell's verdict (structure follows i, colour follows j). Structure: the
/// probe's classes, over factors whose originals differ. Colour: the foreground colour
/// histograms ([`colour_histograms`], L1), over pairs whose originals differ by more than
/// 0.3 — the probe's own colour head is not used here because it reads part colours
/// partly from shape (on the dataset's own swaps its predictions followed the row).
fn swap_scores(pred: &Predictions, hist: &Tensor, k: i64) -> (f64, f64, Vec<Verdict>) {
    let classes = Vec::<i64>::try_from(pred.classes.flatten(0, -1)).unwrap();
    let cls = |i: i64, j: i64, f: usize| classes[((i * k + j) * 4) as usize + f];
    let h = |i: i64, j: i64| hist.get(i * k + j);
    let l1 = |a: &Tensor, b: &Tensor| f64::try_from((a - b).abs().sum(Kind::Double)).unwrap();
    let (mut s_hit, mut s_n, mut a_hit, mut a_n) = (0usize, 0usize, 0usize, 0usize);
    let mut verdicts = Vec::new();
    for i in 0..k {
        for j in 0..k {
            let (mut shape_ok, mut colour_ok) = (None, None);
            if i != j {
                for f in 0..4 {
                    if cls(i, i, f) != cls(j, j, f) {
                        s_n += 1;
                        let ok = cls(i, j, f) == cls(i, i, f);
                        s_hit += ok as usize;
                        shape_ok = Some(shape_ok.unwrap_or(true) && ok);
                    }
                }
                if l1(&h(i, i), &h(j, j)) > 0.3 {
                    a_n += 1;
                    let ok = l1(&h(i, j), &h(j, j)) < l1(&h(i, j), &h(i, i));
                    a_hit += ok as usize;
                    colour_ok = Some(ok);
                }
            }
            verdicts.push((shape_ok, colour_ok));
        }
    }
    let rate = |h: usize, n: usize| {
        if n == 0 {
            f64::NAN
        } else {
            h as f64 / n as f64
        }
    };
    (rate(s_hit, s_n), rate(a_hit, a_n), verdicts)
}

/// The probe's pose errors over a set of images, in degrees.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseErrors {
    /// Mean |yaw error| (wrapped to ±180°).
    pub yaw: f64,
    /// Mean |yaw error| in the generator's own frame: after the one rotation about the up
    /// axis (`yaw_offset`) that makes it smallest. It tells images that do not turn with the
    /// camera (both errors high) from images that turn but whose yaw zero is not the data's
    /// (this one low). With yaw drawn from the full circle, only the discriminator's pose
    /// head on real images with known poses ties the two zeros together; without dataset
    /// poses nothing does, and this is the fair pose score.
    pub yaw_in_frame: f64,
    /// The rotation: probe yaw − rendered yaw, wrapped to [−180°, 180°).
    pub yaw_offset: f64,
    /// Mean |pitch error| (pitch is tied to the world's up axis: not aligned).
    pub pitch: f64,
}

fn wrap_deg(x: f64) -> f64 {
    (x + 180.0).rem_euclid(360.0) - 180.0
}

/// The offset c minimising the mean of |wrap(dᵢ − c)| over yaw differences `d` (degrees),
/// and that mean. The mean is piecewise linear in c with convex kinks only at the dᵢ (at
/// dᵢ ± 180° the wrap makes concave ones), so its minimum is at one of them: trying each is
/// exact, and O(n²) is nothing at evaluation sizes.
fn best_yaw_offset(d: &[f64]) -> (f64, f64) {
    let mean_at = |c: f64| d.iter().map(|&x| wrap_deg(x - c).abs()).sum::<f64>() / d.len() as f64;
    let mut best = (0.0, mean_at(0.0));
    for &c in d {
        let m = mean_at(c);
        if m < best.1 {
            best = (wrap_deg(c), m);
        }
    }
    best
}

fn pose_errors(pred: &Predictions, truth: &Tensor) -> PoseErrors {
    let deg = 180.0 / std::f64::consts::PI;
    let t = truth.to_kind(Kind::Double).to_device(Device::Cpu);
    let p = pred.poses.to_kind(Kind::Double).to_device(Device::Cpu);
    let dy: Vec<f64> = Vec::try_from((p.select(1, 1) - t.select(1, 1)) * deg).unwrap();
    let dp = (p.select(1, 0) - t.select(1, 0)) * deg;
    let (yaw_offset, yaw_in_frame) = best_yaw_offset(&dy);
    PoseErrors {
        yaw: dy.iter().map(|&x| wrap_deg(x).abs()).sum::<f64>() / dy.len() as f64,
        yaw_in_frame,
        yaw_offset,
        pitch: f64::try_from(dp.abs().mean(Kind::Double)).unwrap(),
    }
}

fn coverage(pred: &Tensor, reference: &[Vec<f64>]) -> (f64, Vec<Vec<f64>>) {
    let h = class_histograms(pred);
    let tv = h.iter().zip(reference).map(|(a, b)| total_variation(a, b)).sum::<f64>() / FACTORS.len() as f64;
    (tv, h)
}

enum Extractor {
    Effnet,
    Inception(Box<InceptionV3>),
}

/// What one distribution of images (a generator's, or the real data's) scores.
pub struct Scores {
    pub frechet: f64,
    pub kernel: f64,
    pub warnings: Vec<String>,
    pub coverage_tv: f64,
    /// Predicted class histograms per factor.
    pub histograms: Vec<Vec<f64>>,
    pub shape_follows: f64,
    pub appearance_follows: f64,
    pub pose: PoseErrors,
    /// Up to 24 of the images `(n, 3, S, S)`.
    pub samples: Tensor,
    /// The swap matrix `(k², 3, S, S)` and its verdicts.
    pub swap_images: Tensor,
    pub swap_verdicts: Vec<Verdict>,
}

/// The real data's side of the evaluation, computed once: the reference features, the
/// held-out truth, and the real-data end of every score. [`Evaluator::score`] then scores
/// any generator (the CLI: the model and a random one; training: the EMA generator every
/// `eval.interval` steps).
pub struct Evaluator {
    effnet: EfficientNetLite0,
    extractor: Extractor,
    pub probe: Probe,
    pub opts: EvalOptions,
    pub resolution: i64,
    held_feats: Tensor,
    reference: Vec<Vec<f64>>,
    /// The real-data end.
    pub real: Scores,
    /// The real end's distance features, kept so that [`Evaluator::reseed`] can redraw its
    /// kernel distance's subsets.
    real_feats: Tensor,
    /// The real images at [`EvalOptions::real_resolution`], when set, and their features.
    pub real_low: Option<LowResolutionEnd>,
    low_feats: Option<Tensor>,
    pub device: Device,
}

impl Evaluator {
    pub fn new(
        dataset: &Path,
        probe_path: &Path,
        opts: &EvalOptions,
        device: Device,
        progress: &mut dyn FnMut(&str, i64, i64),
    ) -> Result<Self> {
        if opts.num < 2 || opts.swap < 2 || opts.steps < 2 {
            return Err(Error::Invalid(format!(
                "eval needs num ≥ 2, swap ≥ 2 and steps ≥ 2, got {}, {}, {}",
                opts.num, opts.swap, opts.steps
            )));
        }
        if !(opts.psi.is_finite() && opts.psi >= 0.0) {
            return Err(Error::Invalid(format!(
                "eval's truncation ψ is {}, expected a finite number ≥ 0 (1 = none)",
                opts.psi
            )));
        }
        let meta = Metadata::load(dataset)?;
        let res = opts.resolution.unwrap_or(meta.options.resolution as i64);
        if !(8..=512).contains(&res) {
            return Err(Error::Invalid(format!("eval resolution {res} is out of range, expected 8 to 512")));
        }
        if let Some(low) = opts.real_resolution {
            if !(2..res).contains(&low) {
                return Err(Error::Invalid(format!(
                    "--real-resolution {low} must lie between 2 and the evaluation's resolution {res} (exclusive)"
                )));
            }
        }
        let probe = Probe::load(probe_path, device)?;
        let effnet = EfficientNetLite0::load(&opts.effnet_weights, device)?;
        let extractor = match &opts.features {
            FeatureKind::Efficientnet => Extractor::Effnet,
            FeatureKind::Inception(p) => Extractor::Inception(Box::new(InceptionV3::load(p, device)?)),
        };
        progress("loading the dataset", 0, 1);
        let data = probe::load_labelled(dataset, res as usize, opts.threads, &|| {})?;
        let (held_x, held_t, held_records) = data.split(Split::HeldOut, None);
        // The real end of the distances: as many training images as generated ones.
        let (train_x, train_t, _) = data.split(Split::Train, Some(opts.num as usize));
        if held_x.size()[0] < 2 || train_x.size()[0] < 2 {
            return Err(Error::Data {
                path: dataset.to_path_buf(),
                reason: "fewer than 2 held-out or training images to compare with".into(),
            });
        }
        let k = opts.swap.min(held_x.size()[0]);
        // The dataset's own swaps of k held-out objects (shape of i, appearance of j).
        let mut real_swap = Vec::new();
        for i in 0..k as usize {
            for j in 0..k as usize {
                let r = synth::render_swap(
                    &meta,
                    held_records[i].object,
                    held_records[j].object,
                    None,
                    Some(res as usize),
                    Some(2),
                )?;
                real_swap
                    .push(Tensor::from_slice(&r.rgb).view([res, res, 3]).permute([2, 0, 1]).unsqueeze(0) * 2.0 - 1.0);
            }
            progress("rendering the dataset's swaps", (i as i64 + 1) * k, k * k);
        }
        let real_swap = Tensor::cat(&real_swap, 0).to_kind(Kind::Float);
        let mut ev = Self {
            effnet,
            extractor,
            probe,
            opts: opts.clone(),
            resolution: res,
            held_feats: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
            reference: class_histograms(&held_t.classes),
            real: Scores::empty(),
            real_feats: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
            real_low: None,
            low_feats: None,
            device,
        };
        let (held_feats, held_pred) = ev.features(&held_x, "features: held-out images", progress)?;
        ev.held_feats = held_feats;
        (ev.real, ev.real_feats) = ev.score_images(&train_x, &train_t.poses, &real_swap, k, "real images", progress)?;
        // The probe's coverage and pose ends are taken on held-out images: on the training
        // images it learned from they would be optimistic.
        let p_real = match held_pred {
            Some(p) => p,
            None => ev.predict(&held_x)?,
        };
        ev.real.coverage_tv = coverage(&p_real.classes, &ev.reference).0;
        ev.real.histograms = class_histograms(&p_real.classes);
        ev.real.pose = pose_errors(&p_real, &held_t.poses);
        if let Some(low) = opts.real_resolution {
            let blur = |x: &Tensor| through_resolution(x, low);
            let what = format!("real images at {low}²");
            let (mut s, feats) =
                ev.score_images(&blur(&train_x), &train_t.poses, &blur(&real_swap), k, &what, progress)?;
            // Coverage and pose on the held-out images, as for the real end.
            let p = ev.predict(&blur(&held_x))?;
            s.coverage_tv = coverage(&p.classes, &ev.reference).0;
            s.pose = pose_errors(&p, &held_t.poses);
            ev.real_low = Some(LowResolutionEnd::new(low, &s));
            ev.low_feats = Some(feats);
        }
        Ok(ev)
    }

    /// Makes `seed` the evaluation seed: [`Evaluator::score`] then draws its codes and poses
    /// from it, and every kernel distance (the real end's included, recomputed from its kept
    /// features) its subsets. The real images and the probe's scores of them do not depend on
    /// the seed, so one evaluator scores several seeds for the price of one real end, each
    /// exactly as a fresh evaluator with that seed would.
    pub fn reseed(&mut self, seed: u64) -> Result<()> {
        self.opts.seed = seed;
        self.real.kernel = distance::kernel(&self.real_feats, &self.held_feats, 50, 1000, seed)?.mean;
        if let (Some(low), Some(feats)) = (self.real_low.as_mut(), self.low_feats.as_ref()) {
            low.kernel = distance::kernel(feats, &self.held_feats, 50, 1000, seed)?.mean;
        }
        Ok(())
    }

    fn predict(&self, imgs: &Tensor) -> Result<Predictions> {
        let net = (self.probe.header.config.backbone == probe::Backbone::Efficientnet).then_some(&self.effnet);
        self.probe.predict(net, imgs)
    }

    /// Distance features of `imgs`, and the probe's predictions when they come from the
    /// same EfficientNet pass (the efficientnet probe with efficientnet features).
    fn features(
        &self,
        imgs: &Tensor,
        what: &str,
        progress: &mut dyn FnMut(&str, i64, i64),
    ) -> Result<(Tensor, Option<Predictions>)> {
        let n = imgs.size()[0];
        let shared = self.probe.header.config.backbone == probe::Backbone::Efficientnet;
        match &self.extractor {
            Extractor::Effnet => {
                let (pooled, tap) = self.effnet.pooled_and_last_tap(imgs, 32, &mut |d| progress(what, d, n))?;
                Ok((pooled, shared.then(|| self.probe.predict_inputs(&probe::with_colour(&tap, imgs)))))
            }
            Extractor::Inception(net) => {
                let mut out = Vec::new();
                let mut i = 0;
                while i < n {
                    let b = 16.min(n - i);
                    out.push(net.features_from_signed(&imgs.narrow(0, i, b))?.to_device(Device::Cpu));
                    i += b;
                    progress(what, i, n);
                }
                Ok((Tensor::cat(&out, 0), None))
            }
        }
    }

    /// Scores a set of images (`images` with the poses they show, a k × k swap matrix);
    /// also returns their distance features.
    #[allow(clippy::too_many_arguments)]
    fn score_images(
        &self,
        images: &Tensor,
        poses: &Tensor,
        swap: &Tensor,
        k: i64,
        what: &str,
        progress: &mut dyn FnMut(&str, i64, i64),
    ) -> Result<(Scores, Tensor)> {
        let (feats, pred) = self.features(images, &format!("features: {what}"), progress)?;
        let fd = distance::frechet(&feats, &self.held_feats)?;
        let kid = distance::kernel(&feats, &self.held_feats, 50, 1000, self.opts.seed)?;
        progress(&format!("probe: {what}"), 0, 1);
        let p = match pred {
            Some(p) => p,
            None => self.predict(images)?,
        };
        let (tv, hist) = coverage(&p.classes, &self.reference);
        let pose = pose_errors(&p, poses);
        let ps = self.predict(swap)?;
        let (shape_follows, appearance_follows, verdicts) = swap_scores(&ps, &colour_histograms(swap), k);
        let scores = Scores {
            frechet: fd.value,
            kernel: kid.mean,
            warnings: fd.warning.into_iter().collect(),
            coverage_tv: tv,
            histograms: hist,
            shape_follows,
            appearance_follows,
            pose,
            samples: images.narrow(0, 0, images.size()[0].min(24)),
            swap_images: swap.shallow_clone(),
            swap_verdicts: verdicts,
        };
        Ok((scores, feats))
    }

    /// Renders `num` images (codes and poses from the evaluation seed: the same for every
    /// generator) and a swap matrix with `g`, its codes truncated by `trunc` when given,
    /// and scores them.
    pub fn score(
        &self,
        g: &Generator,
        cam: &CameraConfig,
        trunc: Option<&Truncation>,
        what: &str,
        progress: &mut dyn FnMut(&str, i64, i64),
    ) -> Result<Scores> {
        let (num, k, res) = (self.opts.num, self.opts.swap, self.resolution);
        let device = g.kind_device().1;
        let rc = RenderConfig { num_steps: self.opts.steps as usize, jitter: false, ..RenderConfig::default() };
        let latent = g.cfg.latent_dim as i64;
        let z = StepRng::new(self.opts.seed, 0, Purpose::EvalCodes, Kind::Float, device).normal(&[num, latent]);
        let poses =
            Poses::sample_from(cam, num, &mut StepRng::new(self.opts.seed, 0, Purpose::EvalPoses, Kind::Float, device));
        let k = k.min(num);
        let zk = z.narrow(0, 0, k);
        let (swap_s, swap_a) = (zk.repeat_interleave_self_int(k, 0, None), zk.repeat([k, 1]));
        // Every swap cell at its shape code's pose, so that a row differs only in appearance.
        let rep = |t: &Tensor| t.narrow(0, 0, k).repeat_interleave_self_int(k, 0, None);
        let swap_poses = Poses { pitch: rep(&poses.pitch), yaw: rep(&poses.yaw) };
        let total = num + k * k;
        let mut done = 0;
        let label = format!("rendering: {what}");
        let mut tick = |b: i64| {
            done += b;
            progress(&label, done, total);
        };
        let imgs = render_codes((g, trunc), cam, &rc, (&z, &z), &poses, res, &mut tick)?;
        let swap = render_codes((g, trunc), cam, &rc, (&swap_s, &swap_a), &swap_poses, res, &mut tick)?;
        Ok(self.score_images(&imgs, &poses.stacked().to_device(Device::Cpu), &swap, k, what, progress)?.0)
    }
}

impl Scores {
    fn empty() -> Self {
        let none = Tensor::zeros([0], (Kind::Float, Device::Cpu));
        Self {
            frechet: f64::NAN,
            kernel: f64::NAN,
            warnings: Vec::new(),
            coverage_tv: f64::NAN,
            histograms: Vec::new(),
            shape_follows: f64::NAN,
            appearance_follows: f64::NAN,
            pose: PoseErrors { yaw: f64::NAN, yaw_in_frame: f64::NAN, yaw_offset: f64::NAN, pitch: f64::NAN },
            samples: none.shallow_clone(),
            swap_images: none,
            swap_verdicts: Vec::new(),
        }
    }
}

/// Scores `generator` against `dataset` (a procedural chairs dataset) with `probe`, beside
/// the real-data end and a random-weight generator of the same architecture.
pub fn evaluate(
    generator: &Path,
    dataset: &Path,
    probe_path: &Path,
    opts: &EvalOptions,
    device: Device,
    progress: &mut dyn FnMut(&str, i64, i64),
) -> Result<EvalResult> {
    let mut all = evaluate_seeds(generator, dataset, probe_path, opts, &[opts.seed], device, progress)?;
    Ok(all.remove(0))
}

/// [`evaluate`] once per seed in `seeds` (each seed draws the codes, the poses, the random
/// generator and the kernel distance's subsets), sharing one real end. Each result equals
/// what `evaluate` gives with that seed; its `seconds` counts its own scoring, and the first
/// one also the real end's.
pub fn evaluate_seeds(
    generator: &Path,
    dataset: &Path,
    probe_path: &Path,
    opts: &EvalOptions,
    seeds: &[u64],
    device: Device,
    progress: &mut dyn FnMut(&str, i64, i64),
) -> Result<Vec<EvalResult>> {
    let Some(&first) = seeds.first() else {
        return Err(Error::Invalid("eval needs at least one seed".into()));
    };
    let mut start = std::time::Instant::now();
    let loaded = load_generator(generator, device, Kind::Float)?;
    let mut ev = Evaluator::new(dataset, probe_path, &EvalOptions { seed: first, ..opts.clone() }, device, progress)?;
    let mut out = Vec::with_capacity(seeds.len());
    for &seed in seeds {
        ev.reseed(seed)?;
        let what = if seeds.len() > 1 { format!(" (seed {seed})") } else { String::new() };
        let names = (generator.display().to_string(), dataset);
        out.push(score_generator(&ev, &loaded.generator, &loaded.header, names, &what, start, progress)?);
        start = std::time::Instant::now();
    }
    Ok(out)
}

/// One seed's [`EvalResult`] (the seed is the evaluator's) of `generator`, whose header
/// `header` gives its camera and provenance: the model beside a random-weight generator of
/// its architecture and the evaluator's real end. `names` (the generator as shown, the
/// dataset) go into the result; `what` follows the progress labels.
pub fn score_generator(
    ev: &Evaluator,
    generator: &Generator,
    header: &crate::checkpoint::Header,
    (name, dataset): (String, &Path),
    what: &str,
    start: std::time::Instant,
    progress: &mut dyn FnMut(&str, i64, i64),
) -> Result<EvalResult> {
    let (opts, device) = (&ev.opts, ev.device);
    let cam = header.camera.clone().unwrap_or_default();
    let rvs = nn::VarStore::new(device);
    let random = crate::rng::with_global_seed(opts.seed as i64 + 1, || Generator::new(&rvs.root(), &generator.cfg))?;
    let trunc = generator.truncation_at(opts.psi);
    let model = ev.score(generator, &cam, trunc.as_ref(), &format!("model{what}"), progress)?;
    let rand = ev.score(&random, &cam, None, &format!("random generator{what}"), progress)?;
    let real = &ev.real;
    let mut warnings: Vec<String> = Vec::new();
    if matches!(opts.features, FeatureKind::Efficientnet) && trained_against_projected(header) {
        warnings.push(SHARED_FEATURES_WARNING.into());
    }
    warnings.extend(resolution_warning(header, ev.resolution));
    for w in model.warnings.iter().chain(&rand.warnings).chain(&real.warnings) {
        if !warnings.contains(w) {
            warnings.push(w.clone());
        }
    }
    let classes = FACTORS
        .iter()
        .enumerate()
        .map(|(f, (name, cls))| ClassTable {
            factor: name.to_string(),
            classes: cls.iter().map(|s| s.to_string()).collect(),
            reference: ev.reference[f].clone(),
            real_predicted: real.histograms[f].clone(),
            model: model.histograms[f].clone(),
            random: rand.histograms[f].clone(),
        })
        .collect();
    let c = |f: fn(&Scores) -> f64| Calibrated::new(f(&model), f(real), f(&rand));
    Ok(EvalResult {
        generator: name,
        dataset: dataset.display().to_string(),
        features: match &opts.features {
            FeatureKind::Efficientnet => "efficientnet-lite0 pooled (1280-d, 224², ImageNet)".into(),
            FeatureKind::Inception(p) => {
                format!("inception-v3 pool3 (2048-d, 299², {})", p.display())
            }
        },
        seed: opts.seed,
        images: opts.num,
        resolution: ev.resolution,
        samples_per_ray: 2 * opts.steps,
        psi: opts.psi,
        frechet: c(|s| s.frechet),
        kernel: c(|s| s.kernel),
        warnings,
        coverage_tv: c(|s| s.coverage_tv),
        classes,
        shape_follows: c(|s| s.shape_follows),
        appearance_follows: c(|s| s.appearance_follows),
        pose_yaw_error_deg: c(|s| s.pose.yaw),
        pose_yaw_error_in_frame_deg: c(|s| s.pose.yaw_in_frame),
        yaw_frame_offset_deg: FrameOffsets {
            model: model.pose.yaw_offset,
            real: real.pose.yaw_offset,
            random: rand.pose.yaw_offset,
        },
        pose_pitch_error_deg: c(|s| s.pose.pitch),
        real_at_resolution: ev.real_low.clone(),
        probe_held_out_accuracy: ev.probe.header.held_out.accuracy.clone(),
        seconds: start.elapsed().as_secs_f64(),
        samples: model.samples,
        swap_images: model.swap_images,
        swap_verdicts: model.swap_verdicts,
        swap_side: opts.swap.min(opts.num),
    })
}

/// `", model truncated to ψ = 0.7"` where the model's codes were truncated, else nothing.
pub(crate) fn truncation_note(psi: f64) -> String {
    if psi == 1.0 {
        String::new()
    } else {
        format!(", model truncated to ψ = {psi}")
    }
}

/// The scores as text, one line per score.
pub fn summary(r: &EvalResult) -> String {
    let mut s = format!(
        "{} images at {}² ({} samples/ray{}), features: {}\n",
        r.images,
        r.resolution,
        r.samples_per_ray,
        truncation_note(r.psi),
        r.features
    );
    s += &format!("{:<26} {:>10} {:>10} {:>10} {:>9}\n", "score", "model", "real", "random", "position");
    for (name, c) in score_rows(r) {
        s += &format!("{name:<26} {:>10.4} {:>10.4} {:>10.4} {:>9.2}\n", c.model, c.real, c.random, c.position);
    }
    let o = &r.yaw_frame_offset_deg;
    s += &format!(
        "yaw in its own frame: turned by (probe − rendered) {:.1}° model, {:.1}° real, {:.1}° random\n",
        o.model, o.real, o.random
    );
    if let Some(line) = low_resolution_line(r) {
        s += &line;
        s.push('\n');
    }
    for w in &r.warnings {
        s += &format!("warning: {w}\n");
    }
    s
}

/// What the real images score at the lower resolution, in one line, when it was asked for.
fn low_resolution_line(r: &EvalResult) -> Option<String> {
    r.real_at_resolution.as_ref().map(|l| {
        format!(
            "real images at {}² (down and back up): frechet {:.4}, kernel {:.4}, coverage tv {:.4}, shape {:.4}, \
             appearance {:.4}, yaw {:.1}° ({:.1}° in its own frame), pitch {:.1}°",
            l.resolution,
            l.frechet,
            l.kernel,
            l.coverage_tv,
            l.shape_follows,
            l.appearance_follows,
            l.pose_yaw_error_deg,
            l.pose_yaw_error_in_frame_deg,
            l.pose_pitch_error_deg
        )
    })
}

pub(crate) fn score_rows(r: &EvalResult) -> Vec<(&'static str, &Calibrated)> {
    vec![
        ("frechet distance", &r.frechet),
        ("kernel distance", &r.kernel),
        ("coverage tv", &r.coverage_tv),
        ("shape follows i", &r.shape_follows),
        ("appearance follows j", &r.appearance_follows),
        ("pose yaw error deg", &r.pose_yaw_error_deg),
        ("  in its own frame", &r.pose_yaw_error_in_frame_deg),
        ("pose pitch error deg", &r.pose_pitch_error_deg),
    ]
}

const CLASSES_CAPTION: &str = "classes: grey held-out truth, blue model, orange random generator";
const SWAP_CAPTION: &str = "swap matrix: row = shape, column = appearance";
// Apart from the line above: together they ran past the right edge of a 640-px report.
const BARS_CAPTION: &str = "bars: structure (left) and colour (right). green yes, red no, grey not counted";

/// The one-page report: scores, sample grid, class histograms (reference / model /
/// random), and the swap matrix with the probe's verdicts (a green or red bar under each
/// off-diagonal cell: left half structure follows the row, right half colour follows the
/// column).
pub fn report_image(r: &EvalResult) -> Result<image::RgbImage> {
    use crate::plot::{draw_text, fill, text_width};
    use image::Rgb;
    let s = r.resolution;
    let cols = 8;
    let grid = io::to_rgb8(&io::grid(&r.samples, cols), false)?;
    let k = r.swap_side;
    let cell = s + 6;
    // Wide enough for the grids and for every fixed caption, which would otherwise be cut.
    let captions = [CLASSES_CAPTION, SWAP_CAPTION, BARS_CAPTION];
    let text = captions.iter().map(|c| text_width(c, 1)).max().unwrap_or(0);
    let width = (grid.width() as i64).max(k * cell + 20).max(text + 10).max(620) + 20;
    let hist_h = 150;
    let low_lines = if r.real_at_resolution.is_some() { 2 } else { 0 };
    let height = 20 + 14 * (11 + low_lines) + 20 + grid.height() as i64 + 30 + hist_h + 44 + k * cell + 20;
    let mut img = image::RgbImage::from_pixel(width as u32, height as u32, Rgb([255, 255, 255]));
    let black = Rgb([0, 0, 0]);
    let mut y = 10;
    draw_text(&mut img, 10, y, &format!("gdrf eval: {} images at {}x{}", r.images, s, s), black, 1);
    y += 14;
    draw_text(
        &mut img,
        10,
        y,
        &format!("{:<24}{:>10}{:>10}{:>10}{:>10}", "score", "model", "real", "random", "position"),
        black,
        1,
    );
    for (name, c) in score_rows(r) {
        y += 14;
        draw_text(
            &mut img,
            10,
            y,
            &format!("{name:<24}{:>10.4}{:>10.4}{:>10.4}{:>10.2}", c.model, c.real, c.random, c.position),
            black,
            1,
        );
    }
    y += 14;
    let o = &r.yaw_frame_offset_deg;
    let line = format!(
        "yaw in its own frame: turned {:.1} (model) {:.1} (real) {:.1} (random) deg",
        o.model, o.real, o.random
    );
    draw_text(&mut img, 10, y, &line, black, 1);
    if let Some(l) = &r.real_at_resolution {
        let lines = [
            format!(
                "real at {}x{}: frechet {:.2} kernel {:.4} coverage {:.3} shape {:.3} appearance {:.3}",
                l.resolution, l.resolution, l.frechet, l.kernel, l.coverage_tv, l.shape_follows, l.appearance_follows
            ),
            format!(
                "  yaw {:.1} ({:.1} in its own frame) pitch {:.1} deg",
                l.pose_yaw_error_deg, l.pose_yaw_error_in_frame_deg, l.pose_pitch_error_deg
            ),
        ];
        for line in lines {
            y += 14;
            draw_text(&mut img, 10, y, &line, black, 1);
        }
    }
    y += 24;
    draw_text(&mut img, 10, y, "samples", black, 1);
    y += 12;
    image::imageops::overlay(&mut img, &grid, 10, y);
    y += grid.height() as i64 + 16;
    draw_text(&mut img, 10, y, CLASSES_CAPTION, black, 1);
    y += 14;
    let colours = [Rgb([90, 90, 90]), Rgb([40, 110, 220]), Rgb([220, 120, 40])];
    let mut x = 10;
    let bar_w = 5;
    for t in &r.classes {
        draw_text(&mut img, x, y + hist_h - 10, &t.factor, black, 1);
        for (c, _) in t.classes.iter().enumerate() {
            for (series, v) in [&t.reference, &t.model, &t.random].iter().enumerate() {
                let h = (v[c] * (hist_h - 24) as f64).round() as i64;
                fill(&mut img, x, y + hist_h - 14 - h, bar_w, h, colours[series]);
                x += bar_w;
            }
            x += 4;
        }
        x += 16;
    }
    y += hist_h + 12;
    draw_text(&mut img, 10, y, SWAP_CAPTION, black, 1);
    y += 14;
    draw_text(&mut img, 10, y, BARS_CAPTION, black, 1);
    y += 14;
    let sw = io::to_rgb8(&io::grid(&r.swap_images, k), false)?;
    for i in 0..k {
        for j in 0..k {
            let tile = image::imageops::crop_imm(&sw, (j * s) as u32, (i * s) as u32, s as u32, s as u32).to_image();
            let (tx, ty) = (10 + j * cell, y + i * cell);
            image::imageops::overlay(&mut img, &tile, tx, ty);
            if i != j {
                let (shape_ok, colour_ok) = r.swap_verdicts[(i * k + j) as usize];
                let c = |v: Option<bool>| match v {
                    Some(true) => Rgb([30, 170, 60]),
                    Some(false) => Rgb([210, 40, 40]),
                    None => Rgb([190, 190, 190]),
                };
                fill(&mut img, tx, ty + s + 1, s / 2 - 1, 3, c(shape_ok));
                fill(&mut img, tx + s / 2 + 1, ty + s + 1, s / 2 - 1, 3, c(colour_ok));
            }
        }
    }
    Ok(img)
}

/// Writes `eval.json` and `report.png` into `dir` (created; files written atomically).
pub fn write(dir: &Path, r: &EvalResult) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), source })?;
    let json = serde_json::to_string_pretty(r).map_err(|e| Error::Invalid(e.to_string()))?;
    write_atomic(&dir.join("eval.json"), json.as_bytes())?;
    io::save_png(&dir.join("report.png"), &report_image(r)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_generator_trained_against_the_projected_discriminator_is_recognised() {
        use crate::checkpoint::Header;
        let plain = Header::generator(Default::default(), None);
        assert!(!trained_against_projected(&plain), "no provenance: no warning");
        let mut h = plain.clone();
        h.info.insert(DISCRIMINATOR_INFO.into(), "release".into());
        assert!(!trained_against_projected(&h));
        h.info.insert(DISCRIMINATOR_INFO.into(), "projected".into());
        assert!(trained_against_projected(&h));
        // A training checkpoint from before the info key: its config says so.
        let mut t = plain.clone();
        t.training = Some(serde_json::json!({"config": {"discriminator": {"kind": "projected"}}}));
        assert!(trained_against_projected(&t));
        t.training = Some(serde_json::json!({"config": {"discriminator": {"kind": "release"}}}));
        assert!(!trained_against_projected(&t));
    }

    #[test]
    fn scoring_at_another_resolution_than_training_is_said() {
        use crate::checkpoint::{Header, RESOLUTION_INFO, SAMPLES_PER_RAY_INFO};
        let mut h = Header::generator(Default::default(), None);
        assert_eq!(resolution_warning(&h, 64), None, "no provenance: no warning");
        assert_eq!((h.trained_resolution(), h.trained_coarse_samples()), (None, None));
        h.info.insert(RESOLUTION_INFO.into(), "32".into());
        h.info.insert(SAMPLES_PER_RAY_INFO.into(), "24".into());
        assert_eq!((h.trained_resolution(), h.trained_coarse_samples()), (Some(32), Some(12)));
        assert_eq!(resolution_warning(&h, 32), None);
        let w = resolution_warning(&h, 64).unwrap();
        assert!(w.contains("trained at 32²") && w.contains("`--resolution 32 --steps 12`"), "{w}");
        h.info.remove(SAMPLES_PER_RAY_INFO);
        assert!(resolution_warning(&h, 64).unwrap().contains("`--resolution 32`"));
    }

    #[test]
    fn through_resolution_keeps_smooth_images_and_removes_what_the_low_grid_cannot_hold() {
        let o = (Kind::Float, Device::Cpu);
        // A constant image comes back as it was.
        let flat = Tensor::full([1, 3, 16, 16], 0.3, o);
        let back = through_resolution(&flat, 4);
        assert_eq!(back.size(), [1, 3, 16, 16]);
        assert!(back.allclose(&flat, 1e-6, 1e-6, false));
        // A ±1 checkerboard has nothing a 4² grid can hold: away from the borders (where the
        // filter is renormalised) it averages to 0, to within 1e-3 of its amplitude (libtorch's
        // antialiasing weights cancel the alternation to 7e-4, not exactly).
        let idx = Tensor::arange(16, (Kind::Int64, Device::Cpu));
        let parity = (idx.view([16, 1]) + idx.view([1, 16])).remainder(2).to_kind(Kind::Float);
        let board = (parity * 2.0 - 1.0).view([1, 1, 16, 16]).expand([1, 3, 16, 16], false).contiguous();
        let inner = through_resolution(&board, 4).narrow(2, 4, 8).narrow(3, 4, 8);
        let worst = inner.abs().max().double_value(&[]);
        assert!(worst <= 1e-3, "largest |value| inside: {worst}");
    }

    #[test]
    fn swap_scores_count_only_informative_pairs() {
        // k = 2: originals differ in legs and colour (red vs blue); cell (0, 1) keeps 0's
        // legs and takes 1's colour, cell (1, 0) takes 0's legs and keeps 1's colour (both wrong).
        let classes = Tensor::from_slice(&[
            0i64, 1, 0, 0, /* (0,1) */ 0, 1, 0, 0, /* (1,0) */ 0, 1, 0, 0, /* (1,1) */ 3, 1, 0, 0,
        ])
        .view([4, 4]);
        let pred = Predictions {
            classes,
            colours: Tensor::zeros([4, 4, 3], (Kind::Float, Device::Cpu)),
            poses: Tensor::zeros([4, 2], (Kind::Float, Device::Cpu)),
        };
        let img = |r: f64, b: f64| {
            let t = Tensor::ones([1, 3, 4, 4], (Kind::Float, Device::Cpu));
            t.narrow(2, 1, 2)
                .narrow(3, 1, 2)
                .copy_(&Tensor::from_slice(&[r as f32, -1.0, b as f32]).view([1, 3, 1, 1]).expand([1, 3, 2, 2], false));
            t
        };
        let (red, blue) = (img(0.8, -1.0), img(-1.0, 0.8));
        let swap = Tensor::cat(&[red.shallow_clone(), blue.shallow_clone(), blue.shallow_clone(), blue], 0);
        let hist = colour_histograms(&swap);
        // Four foreground pixels of one colour: one bin holds all the mass; white is background.
        assert_eq!(f64::try_from(hist.get(0).sum(Kind::Double)).unwrap(), 1.0);
        assert_eq!(f64::try_from(hist.get(0).max()).unwrap(), 1.0);
        let (shape, app, verdicts) = swap_scores(&pred, &hist, 2);
        assert_eq!(shape, 0.5);
        assert_eq!(app, 0.5);
        let (t, f) = (Some(true), Some(false));
        assert_eq!(verdicts, vec![(None, None), (t, t), (f, f), (None, None)]);
        assert_eq!(
            f64::try_from(colour_histograms(&Tensor::ones([1, 3, 4, 4], (Kind::Float, Device::Cpu))).sum(Kind::Double))
                .unwrap(),
            0.0
        );
        let c = Calibrated::new(5.0, 1.0, 9.0);
        assert_eq!(c.position, 0.5);
    }

    fn poses(pitch_yaw_deg: &[(f64, f64)]) -> Tensor {
        let flat: Vec<f64> = pitch_yaw_deg.iter().flat_map(|&(p, y)| [p.to_radians(), y.to_radians()]).collect();
        Tensor::from_slice(&flat).view([-1, 2]).to_kind(Kind::Float)
    }

    #[test]
    fn yaw_error_is_measured_in_the_generators_own_frame() {
        // Rendered yaws around the circle; the probe reads each one turned by 90° (the
        // generator's frame) and off by +4°, −2°, 0°, +6°, +1°, so the best rotation is 91°
        // (their median) and leaves errors 3, 3, 1, 5, 0 (mean 2.4°); pitch is off by
        // 1, 3, 1, 3, 2 (mean 2°).
        let truth = poses(&[(60.0, -170.0), (60.0, -45.0), (70.0, 80.0), (50.0, 175.0), (60.0, 10.0)]);
        let pred = Predictions {
            classes: Tensor::zeros([5, 4], (Kind::Int64, Device::Cpu)),
            colours: Tensor::zeros([5, 4, 3], (Kind::Float, Device::Cpu)),
            poses: poses(&[(61.0, -76.0), (63.0, 43.0), (71.0, 170.0), (53.0, -89.0), (62.0, 101.0)]),
        };
        let e = pose_errors(&pred, &truth);
        let close = |a: f64, b: f64| (a - b).abs() < 1e-4;
        assert!(close(e.yaw_offset, 91.0), "{e:?}");
        assert!(close(e.yaw_in_frame, 2.4), "{e:?}");
        // Unaligned: 94, 88, 90, 96 (−89° − 175° = −264° wraps to 96°), 91.
        assert!(close(e.yaw, (94.0 + 88.0 + 90.0 + 96.0 + 91.0) / 5.0), "{e:?}");
        assert!(close(e.pitch, 2.0), "{e:?}");
        // A probe that reads the rendered yaw exactly: no rotation, no error.
        let exact = Predictions { poses: truth.shallow_clone(), ..pred };
        let e = pose_errors(&exact, &truth);
        assert_eq!((e.yaw, e.yaw_in_frame, e.yaw_offset, e.pitch), (0.0, 0.0, 0.0, 0.0));
    }

    #[test]
    fn the_best_yaw_offset_wraps_around_the_circle() {
        // Differences straddling ±180°: the best rotation is 180°, not their plain mean 0°.
        let (c, m) = best_yaw_offset(&[178.0, -178.0, 176.0, -176.0]);
        assert!((wrap_deg(c - 180.0)).abs() <= 4.0 && (m - 3.0).abs() < 1e-12, "{c} {m}");
        // Scanning every candidate is exact: a brute-force search over 0.01° steps never wins.
        let d = [10.0, 30.0, 35.0, -120.0, 170.0, -175.0, 90.0];
        let (_, m) = best_yaw_offset(&d);
        let brute = (0..36000)
            .map(|i| {
                let c = i as f64 / 100.0 - 180.0;
                d.iter().map(|&x| wrap_deg(x - c).abs()).sum::<f64>() / d.len() as f64
            })
            .fold(f64::INFINITY, f64::min);
        assert!(m <= brute + 1e-12 && brute - m < 1e-2, "{m} {brute}");
        assert_eq!(wrap_deg(180.0), -180.0);
        assert_eq!(wrap_deg(-190.0), 170.0);
    }
}
