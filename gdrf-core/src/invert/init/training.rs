//! The initialiser's training: its validation on held-out tuples and real images, and the
//! loop that steps, evaluates and saves it.
use crate::camera::Poses;
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::Generator;
use crate::io::resize;
use crate::nn::film::Film;
use crate::progress::Event;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, StepRng};
use crate::train::optim::{zero_grads, Adam};
use crate::{Error, Latents, Result};
use serde::Serialize;
use std::path::Path;
use tch::{Device, Kind, Tensor};

use super::data::{RealImages, Tuples};
use super::*;

/// Validation errors on held-out tuples and held-out real images.
#[derive(Debug, Clone, Serialize)]
pub struct InitEval {
    pub step: i64,
    /// Images trained on so far (rendered and real).
    pub images_seen: i64,
    /// mean (F_w(I) − w_s)² on held-out tuples.
    pub w_mse: f64,
    /// The same for the mean code's w_s (what the optimisation starts from without F).
    pub mean_code_w_mse: f64,
    /// mean (F_a(I) − a)² of the raw appearance, and the mean appearance's (the paper's
    /// start); None when F does not predict it.
    pub appearance_mse: Option<f64>,
    pub mean_appearance_mse: f64,
    /// Mean and median absolute pose errors in degrees on the held-out tuples.
    pub pitch_error_deg: f64,
    pub yaw_error_deg: f64,
    pub median_yaw_error_deg: f64,
    /// The same on the held-out real images (None without real images).
    pub real_pitch_error_deg: Option<f64>,
    pub real_yaw_error_deg: Option<f64>,
    pub real_median_yaw_error_deg: Option<f64>,
    pub train_loss: f64,
    /// The learning rate of the steps before it.
    pub lr: f64,
}

fn pose_terms(raw: &Tensor, poses: &Tensor) -> Tensor {
    let p = Poses::from_stacked(poses);
    let want = Tensor::cat(&[p.pitch, p.yaw.cos(), p.yaw.sin()], 1);
    (raw - want).square().sum_dim_intlist(1, false, Kind::Float).mean(Kind::Float)
}

/// Absolute pitch and wrapped yaw errors `(N,)` in radians of raw poses against `(N, 2)`.
fn pose_errors(raw: &Tensor, want: &Tensor) -> (Tensor, Tensor) {
    let pitch = (raw.narrow(1, 0, 1) - want.narrow(1, 0, 1)).abs().flatten(0, -1);
    let diff = raw.narrow(1, 2, 1).atan2(&raw.narrow(1, 1, 1)) - want.narrow(1, 1, 1);
    (pitch, diff.sin().atan2(&diff.cos()).abs().flatten(0, -1))
}

pub(super) fn f64_of(t: &Tensor) -> f64 {
    f64::try_from(t.to_kind(Kind::Double)).unwrap_or(f64::NAN)
}

/// What F's head reads of a set of images: its body's output, taken once for a frozen
/// backbone, or the images themselves for ResNet-34 (run with the head).
enum Inputs {
    Images(Tensor),
    Features(Tensor),
}

impl Inputs {
    /// The images, or a frozen backbone's features of them (Lite0's always, ResNet-34's
    /// with `head_only`: in inference mode, so its batch-norm statistics stay).
    fn of(init: &Initialiser, images: &Tensor, head_only: bool, progress: &mut dyn FnMut(Event)) -> Result<Self> {
        if init.lite0.is_none() && !head_only {
            return Ok(Inputs::Images(images.shallow_clone()));
        }
        let (mut out, mut done, n) = (Vec::new(), 0, images.size()[0] as u64);
        for chunk in images.split(64, 0) {
            out.push(tch::no_grad(|| init.frozen_features(&chunk))?);
            done += chunk.size()[0] as u64;
            progress(Event::new("features", done, n));
        }
        Ok(Inputs::Features(Tensor::cat(&out, 0)))
    }

    fn len(&self) -> i64 {
        match self {
            Inputs::Images(t) | Inputs::Features(t) => t.size()[0],
        }
    }

    /// F's outputs for the rows `idx`.
    fn forward(&self, init: &Initialiser, idx: &Tensor, train: bool) -> Result<(Tensor, Tensor, Tensor)> {
        match self {
            Inputs::Images(t) => init.forward_t(&t.index_select(0, idx), train),
            Inputs::Features(f) => Ok(init.head(&init.standardise(&f.index_select(0, idx)))),
        }
    }
}

/// F's outputs for every row of `x`, without gradients, 64 at a time.
fn predict_all(init: &Initialiser, x: &Inputs, rows: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
    tch::no_grad(|| {
        let m = rows.size()[0];
        let (mut w, mut p, mut a) = (Vec::new(), Vec::new(), Vec::new());
        let mut i = 0;
        while i < m {
            let b = 64.min(m - i);
            let (wi, pi, ai) = x.forward(init, &rows.narrow(0, i, b), false)?;
            w.push(wi);
            p.push(pi);
            a.push(ai);
            i += b;
        }
        Ok((Tensor::cat(&w, 0), Tensor::cat(&p, 0), Tensor::cat(&a, 0)))
    })
}

struct Validation<'a> {
    tuples: &'a Tuples,
    held: Tensor,
    mean_w: Tensor,
    mean_a: Tensor,
    reals: Option<(&'a RealImages, Tensor)>,
}

#[allow(clippy::too_many_arguments)]
fn evaluate(
    init: &Initialiser,
    x: &Inputs,
    xr: Option<&Inputs>,
    v: &Validation,
    step: i64,
    images_seen: i64,
    train_loss: f64,
    lr: f64,
) -> Result<InitEval> {
    let (w, p, a) = predict_all(init, x, &v.held)?;
    let want_w = v.tuples.w_s.index_select(0, &v.held);
    let want_a = v.tuples.appearance_raw.index_select(0, &v.held);
    let (pitch, yaw) = pose_errors(&p, &v.tuples.poses.index_select(0, &v.held));
    let mut real = (None, None, None);
    if let (Some((r, rows)), Some(xr)) = (&v.reals, xr) {
        if rows.size()[0] > 0 {
            let (_, rp, _) = predict_all(init, xr, rows)?;
            let (rpitch, ryaw) = pose_errors(&rp, &r.poses.index_select(0, rows));
            real = (
                Some(f64_of(&rpitch.mean(Kind::Float)).to_degrees()),
                Some(f64_of(&ryaw.mean(Kind::Float)).to_degrees()),
                Some(f64_of(&ryaw.median()).to_degrees()),
            );
        }
    }
    Ok(InitEval {
        step,
        images_seen,
        w_mse: f64_of(&(w - &want_w).square().mean(Kind::Float)),
        mean_code_w_mse: f64_of(&(&want_w - &v.mean_w).square().mean(Kind::Float)),
        appearance_mse: (init.appearance_dim > 0).then(|| f64_of(&(a - &want_a).square().mean(Kind::Float))),
        mean_appearance_mse: f64_of(&(&want_a - &v.mean_a).square().mean(Kind::Float)),
        pitch_error_deg: f64_of(&pitch.mean(Kind::Float)).to_degrees(),
        yaw_error_deg: f64_of(&yaw.mean(Kind::Float)).to_degrees(),
        median_yaw_error_deg: f64_of(&yaw.median()).to_degrees(),
        real_pitch_error_deg: real.0,
        real_yaw_error_deg: real.1,
        real_median_yaw_error_deg: real.2,
        train_loss,
        lr,
    })
}

/// What [`train`] reports while it runs.
pub enum TrainProgress<'a> {
    /// How far the frozen backbone's features have come.
    Features(Event<'a>),
    /// A step done, with its evaluation when one ran.
    Step(i64, Option<&'a InitEval>),
}

/// Where [`train`] starts.
#[derive(Debug, Clone, Copy)]
pub enum Start<'a> {
    /// From the seed's random weights.
    Fresh,
    /// From the weights of another initialiser file (one made for another generator, such
    /// as the one a new default generator replaces), with a new optimiser at step 0: what
    /// it learned of reading poses and images carries over, its w_s is re-learned.
    WarmFrom(&'a Path),
    /// From `out`'s saved step and Adam state.
    Resume,
}

/// Trains F on `tuples` (and `reals`, with `cfg.real_weight`) for generator `g` (identity
/// `generator_id`), writing `out` (atomically, with its Adam state) every `eval_interval`
/// steps and at the end, from `start`. `lite0` holds EfficientNet-Lite0's weights for that
/// backbone.
#[allow(clippy::too_many_arguments)]
pub fn train(
    g: &Generator,
    cam: &CameraConfig,
    generator_id: &str,
    tuples: &Tuples,
    reals: Option<&RealImages>,
    lite0: Option<Vec<(String, Tensor)>>,
    cfg: &InitConfig,
    out: &Path,
    start: Start,
    progress: &mut dyn FnMut(TrainProgress),
) -> Result<(Initialiser, Vec<InitEval>)> {
    let resume = matches!(start, Start::Resume);
    cfg.validate()?;
    let (_, device) = g.kind_device();
    let app_dim = if cfg.appearance_weight > 0.0 { tuples.appearance_raw.size()[1] } else { 0 };
    let (init, mut adam, start) = start_or_resume(g, generator_id, app_dim, lite0, cfg, out, start)?;
    let reals = reals.filter(|_| cfg.real_weight > 0.0);
    let n_train = cfg.count - cfg.held_out;
    let n_real = reals.map_or(0, |r| (r.images.size()[0] - cfg.real_held_out).max(0));
    if reals.is_some() && n_real < 1 {
        return Err(Error::Config(format!(
            "init.real_held_out is {}, but there are only {} real images: none left to train on",
            cfg.real_held_out,
            reals.map_or(0, |r| r.images.size()[0])
        )));
    }
    let x = Inputs::of(&init, &tuples.images, cfg.head_only, &mut |e| progress(TrainProgress::Features(e)))?;
    let xr = reals
        .map(|r| Inputs::of(&init, &r.images, cfg.head_only, &mut |e| progress(TrainProgress::Features(e))))
        .transpose()?;
    // The frozen features' standardisation, from the training rows alone (a resumed run keeps
    // the one it saved).
    if !resume {
        standardise(&init, &x, xr.as_ref(), n_train, n_real);
    }
    let validation = Validation {
        tuples,
        held: Tensor::arange_start(n_train, cfg.count, (Kind::Int64, device)),
        mean_w: tuples.w_s.narrow(0, 0, n_train).mean_dim(0, true, Kind::Float),
        mean_a: tuples.appearance_raw.narrow(0, 0, n_train).mean_dim(0, true, Kind::Float),
        reals: reals.map(|r| (r, Tensor::arange_start(n_real, r.images.size()[0], (Kind::Int64, device)))),
    };
    let rc = RenderConfig { num_steps: cfg.samples, ..Default::default() };
    let objective = Objective {
        g,
        renderer: Renderer::new(g, cam, &rc)?,
        tuples,
        x: &x,
        reals: reals.zip(xr.as_ref()),
        images_small: (cfg.image_weight > 0.0).then(|| resize(&tuples.images, cfg.image_resolution)),
        cfg,
        n_train,
        n_real,
        app_dim,
    };
    let per_step = cfg.batch_size + if reals.is_some() { cfg.real_batch } else { 0 };
    let mut evals = Vec::new();
    let mut last_loss = f64::NAN;
    debug_assert_eq!(x.len(), cfg.count);
    for step in start..cfg.steps {
        let loss = objective.loss(&init, step, device)?;
        last_loss = loss.double_value(&[]);
        if !last_loss.is_finite() {
            return Err(Error::Invalid(format!("the initialiser's loss is not finite at step {step}; lower init.lr")));
        }
        zero_grads(&init.vs);
        loss.backward();
        let lr = cfg.lr_at(step);
        adam.step(&init.vs, lr);
        let done = step + 1;
        let ev = if done % cfg.eval_interval == 0 || done == cfg.steps {
            let e = evaluate(&init, &x, xr.as_ref(), &validation, done, done * per_step, last_loss, lr)?;
            init.save(out, &init.header(generator_id, done, false, cfg), Some(&adam))?;
            evals.push(e.clone());
            Some(e)
        } else {
            None
        };
        progress(TrainProgress::Step(done, ev.as_ref()));
    }
    if evals.is_empty() {
        let lr = cfg.lr_at(cfg.steps - 1);
        evals.push(evaluate(&init, &x, xr.as_ref(), &validation, cfg.steps, cfg.steps * per_step, last_loss, lr)?);
    }
    Ok((init, evals))
}

/// A new F (seeded by `cfg.seed`) with a fresh Adam at step 0, or, with `resume`, the one
/// saved at `out` with its Adam state and step, if it was trained with the same settings.
fn start_or_resume(
    g: &Generator,
    generator_id: &str,
    app_dim: i64,
    lite0: Option<Vec<(String, Tensor)>>,
    cfg: &InitConfig,
    out: &Path,
    start: Start,
) -> Result<(Initialiser, Adam, i64)> {
    let (_, device) = g.kind_device();
    if let Start::Fresh | Start::WarmFrom(_) = start {
        let hidden = g.cfg.mapping_hidden_dim as i64;
        let init = Initialiser::new(cfg.backbone, device, hidden, app_dim, cfg.resolution, lite0)?;
        init.reinitialise(cfg.seed);
        if let Start::WarmFrom(from) = start {
            init.copy_weights_from(from)?;
        }
        let adam = Adam::new(&init.vs, 0.9, 0.999, 1e-8);
        return Ok((init, adam, 0));
    }
    let (init, h, state) = Initialiser::load_with_state(out, Some(generator_id), device)?;
    // A longer run, other validation points or another learning rate from here on (a
    // schedule, as the campaign's) may continue; anything else would not.
    let core = |c: &InitConfig| InitConfig { steps: 0, eval_interval: 1, lr: 1.0, lr_drops: Vec::new(), ..c.clone() };
    if core(&h.config) != core(cfg) || h.half {
        return Err(Error::Config(format!(
            "{}: saved with other initialiser settings (or shipped in half precision); resume with the same ones (only the steps and the learning rate may change)",
            out.display()
        )));
    }
    let mut adam = Adam::new(&init.vs, 0.9, 0.999, 1e-8);
    adam.load(&state, "adam.", h.step)?;
    Ok((init, adam, h.step))
}

/// Sets Lite0's feature standardisation from the training rows (the first `n_train` tuples
/// and `n_real` real images); nothing for ResNet-34.
fn standardise(init: &Initialiser, x: &Inputs, xr: Option<&Inputs>, n_train: i64, n_real: i64) {
    // ResNet-34's features, frozen for a head-only training, are what its head was trained on.
    let (Inputs::Features(f), Some(_)) = (x, &init.lite0) else { return };
    let mut rows = vec![f.narrow(0, 0, n_train)];
    if let Some(Inputs::Features(fr)) = xr {
        rows.push(fr.narrow(0, 0, n_real));
    }
    let all = Tensor::cat(&rows, 0);
    tch::no_grad(|| {
        init.feat_mean.as_ref().expect("Lite0").shallow_clone().copy_(&all.mean_dim(0, false, Kind::Float));
        // A floor of a tenth of the mean deviation: a feature (nearly) constant over the
        // training images must not turn small differences into large inputs.
        let std = all.std_dim(0, true, false);
        let floor = std.mean(Kind::Float) * 0.1;
        init.feat_std.as_ref().expect("Lite0").shallow_clone().copy_(&(std + floor));
    });
}

/// What one step's loss is made of: the training tuples and real images with F's inputs,
/// the renderer of the image term, and the weights.
struct Objective<'a> {
    g: &'a Generator,
    renderer: Renderer<'a>,
    tuples: &'a Tuples,
    x: &'a Inputs,
    reals: Option<(&'a RealImages, &'a Inputs)>,
    /// The tuples' images at the image term's resolution (with `image_weight`).
    images_small: Option<Tensor>,
    cfg: &'a InitConfig,
    n_train: i64,
    n_real: i64,
    app_dim: i64,
}

impl Objective<'_> {
    /// Step `step`'s loss, on its batches drawn from (seed, step): w_s, pose and appearance
    /// on tuples, pose on real images, the re-rendered image.
    fn loss(&self, init: &Initialiser, step: i64, device: Device) -> Result<Tensor> {
        let (cfg, tuples) = (self.cfg, self.tuples);
        let mut rng = StepRng::new(cfg.seed, step as u64, Purpose::InitBatches, Kind::Float, device);
        let idx = Tensor::from_slice(&rng.below(cfg.batch_size as usize, self.n_train as u64)).to_device(device);
        let (w, p, a) = self.x.forward(init, &idx, true)?;
        let mut loss = (&w - tuples.w_s.index_select(0, &idx)).square().mean(Kind::Float)
            + pose_terms(&p, &tuples.poses.index_select(0, &idx)) * cfg.pose_weight;
        if self.app_dim > 0 {
            loss +=
                (a - tuples.appearance_raw.index_select(0, &idx)).square().mean(Kind::Float) * cfg.appearance_weight;
        }
        if let Some((r, xr)) = self.reals {
            let ridx = Tensor::from_slice(&rng.below(cfg.real_batch as usize, self.n_real as u64)).to_device(device);
            let (_, rp, _) = xr.forward(init, &ridx, true)?;
            loss += pose_terms(&rp, &r.poses.index_select(0, &ridx)) * cfg.real_weight;
        }
        if let Some(small) = &self.images_small {
            let poses = Poses::from_stacked(&tuples.poses.index_select(0, &idx));
            let lat = Latents {
                shape: self.g.shape_from_w(&w, None),
                appearance: Film::from_raw(&tuples.appearance_raw.index_select(0, &idx)),
            };
            let (r2, n) = (cfg.image_resolution * cfg.image_resolution, cfg.samples as i64);
            let noise = Noise::midpoints(cfg.batch_size, r2, n, device);
            let (re, _) = self.renderer.render_regions(&lat, &poses, cfg.image_resolution, 1, &noise)?;
            loss += (re - small.index_select(0, &idx)).square().mean(Kind::Float) * cfg.image_weight;
        }
        Ok(loss)
    }
}
