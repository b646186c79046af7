//! Adversarial training: the discriminator step, then the generator step (the release's
//! order), with progressive resolution and fade-in, the two-pass patch step, gradient
//! clipping, Adam, EMA, and a state that checkpoints and resumes exactly.
//!
//! Every random number of step k is drawn from (run seed, k, purpose) by
//! [`StepRng`](crate::rng::StepRng); the real-image order comes from per-epoch
//! permutations of the same kind. Together with the saved state (weights, EMA, Adam
//! moments, counters), a run resumed at step k computes the same step k + 1 as the
//! uninterrupted run, bit for bit on the CPU.
pub mod config;
pub mod curve;
pub mod optim;
pub mod pass;
pub mod run;
pub mod samples;

pub use config::{Stage, StepKind, TrainConfig};
pub use pass::{discriminator_judgement, discriminator_pass, generator_judgement, generator_pass, FakeBatch};

use crate::camera::Poses;
use crate::checkpoint::{self, Header};
use crate::data::{self, Dataset};
use crate::disc::augment::AugmentedJudge;
use crate::disc::Judge;
use crate::loss::deform_reg::{reg_ray_count, regularisers, select_samples};
use crate::loss::{generator_image_terms, generator_regularisation, Losses, Schedule};
use crate::render::{Noise, RenderedRays, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{Error, Generator, Result};
use optim::{clip_grads, copy_vars, grad_norm, zero_grads, Adam, Ema};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn, Device, Kind, Tensor};

/// Counters a checkpoint carries besides its tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Steps completed: the next step to run.
    pub step: i64,
    /// Real images drawn so far (the position in the epoch permutations).
    pub images_seen: i64,
    /// Multiplies every learning rate; halved (by `guard.lr_factor`) at each rollback.
    pub lr_scale: f64,
    /// Steps whose generator or discriminator update was skipped as non-finite.
    pub skipped_steps: i64,
    pub consecutive_bad: i64,
    pub rollbacks: i64,
    /// Step counts of both Adam optimisers and the EMA (filled in when a checkpoint is
    /// written; the optimisers and the EMA own them while training).
    pub adam_g_t: i64,
    pub adam_d_t: i64,
    pub ema_updates: i64,
    /// Seconds spent in training steps, over all sessions of the run.
    pub train_seconds: f64,
}

impl Default for Progress {
    fn default() -> Self {
        Self {
            step: 0,
            images_seen: 0,
            lr_scale: 1.0,
            skipped_steps: 0,
            consecutive_bad: 0,
            rollbacks: 0,
            adam_g_t: 0,
            adam_d_t: 0,
            ema_updates: 0,
            train_seconds: 0.0,
        }
    }
}

/// The `training` header of a checkpoint.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrainingHeader {
    pub progress: Progress,
    pub stage: usize,
    pub config: TrainConfig,
}

/// What one step did.
#[derive(Debug, Clone)]
pub struct StepReport {
    /// The step that ran (0-based).
    pub step: i64,
    pub stage: usize,
    pub resolution: i64,
    pub batch_size: i64,
    pub alpha: f64,
    pub d_total: f64,
    pub g_total: f64,
    /// Unweighted terms; the generator's are batch means over its chunks.
    pub d_terms: Vec<(&'static str, f64)>,
    pub g_terms: Vec<(&'static str, f64)>,
    /// Gradient norms before clipping.
    pub grad_norm_d: f64,
    pub grad_norm_g: f64,
    pub lr_g: f64,
    pub lr_d: f64,
    pub d_skipped: bool,
    pub g_skipped: bool,
    pub seconds: f64,
    /// Set when this step's failure triggered a rollback: the step the run went back to.
    pub rolled_back_to: Option<i64>,
}

impl StepReport {
    /// The metrics.jsonl line.
    pub fn to_json(&self, p: &Progress) -> serde_json::Value {
        let terms = |t: &[(&str, f64)]| {
            t.iter().map(|(k, v)| (k.to_string(), serde_json::json!(v))).collect::<serde_json::Map<_, _>>()
        };
        serde_json::json!({
            "step": self.step,
            "stage": self.stage,
            "resolution": self.resolution,
            "batch_size": self.batch_size,
            "alpha": self.alpha,
            "d_total": finite_or_null(self.d_total),
            "g_total": finite_or_null(self.g_total),
            "d": terms(&self.d_terms),
            "g": terms(&self.g_terms),
            "grad_norm_d": finite_or_null(self.grad_norm_d),
            "grad_norm_g": finite_or_null(self.grad_norm_g),
            "lr_g": self.lr_g,
            "lr_d": self.lr_d,
            "step_seconds": self.seconds,
            "images_per_second": self.batch_size as f64 / self.seconds.max(1e-9),
            "d_skipped": self.d_skipped,
            "g_skipped": self.g_skipped,
            "skipped_steps": p.skipped_steps,
            "rollbacks": p.rollbacks,
            "images_seen": p.images_seen,
        })
    }
}

fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

/// A training run in memory: both networks, the EMA generator, optimisers and counters.
pub struct Trainer {
    pub cfg: TrainConfig,
    pub run_dir: PathBuf,
    pub device: Device,
    pub gvs: nn::VarStore,
    pub generator: Generator,
    /// The EMA generator (samples and exports).
    pub evs: nn::VarStore,
    pub ema_generator: Generator,
    pub dvs: nn::VarStore,
    pub disc: Box<dyn Judge>,
    pub adam_g: Adam,
    pub adam_d: Adam,
    pub ema: Ema,
    pub progress: Progress,
    datasets: BTreeMap<i64, Dataset>,
    permutation: Option<(i64, Vec<i64>)>,
    /// Injected faults already fired (not saved: a replay after a rollback runs clean).
    injected: BTreeSet<i64>,
    /// The evaluation's real-data side, built at the first `eval.interval` step.
    evaluator: Option<crate::eval::report::Evaluator>,
    /// Seconds of each step since the last evaluation (the curve's step time).
    step_seconds: Vec<f64>,
}

impl Trainer {
    /// A fresh run: networks initialised from the run seed, the generators then from
    /// `init_generator` if the config names one. Nothing is written yet.
    pub fn new(cfg: TrainConfig, run_dir: &Path) -> Result<Self> {
        let t = Self::seeded(cfg, run_dir)?;
        if let Some(path) = &t.cfg.init_generator {
            let loaded = checkpoint::load_generator(path, t.device, tch::Kind::Float)
                .map_err(|e| Error::Config(format!("init_generator: {e}")))?;
            if loaded.generator.cfg != t.cfg.generator {
                return Err(Error::Config(format!(
                    "init_generator {}: its [generator] ({:?}) differs from the config's ({:?}); a run starts only from a generator of the same architecture",
                    path.display(),
                    loaded.generator.cfg,
                    t.cfg.generator
                )));
            }
            copy_vars(&t.gvs, &loaded.vs);
            copy_vars(&t.evs, &loaded.vs);
        }
        Ok(t)
    }

    /// Networks initialised from the run seed alone.
    fn seeded(cfg: TrainConfig, run_dir: &Path) -> Result<Self> {
        cfg.validate()?;
        let device = crate::device::select(&cfg.device)?;
        // The initial weights come from libtorch's generator, seeded once here (as the
        // release does before building its models); training draws never touch it.
        let (gvs, generator, dvs, disc, evs, ema_generator) = crate::rng::with_global_seed(cfg.seed as i64, || {
            let gvs = nn::VarStore::new(device);
            let generator = Generator::new(&gvs.root(), &cfg.generator)?;
            let dvs = nn::VarStore::new(device);
            let disc = crate::disc::build(&dvs.root(), &cfg.discriminator)?;
            let evs = nn::VarStore::new(device);
            let ema_generator = Generator::new(&evs.root(), &cfg.generator)?;
            Ok::<_, Error>((gvs, generator, dvs, disc, evs, ema_generator))
        })?;
        copy_vars(&evs, &gvs);
        let o = &cfg.optim;
        let adam_g = Adam::new(&gvs, o.beta1, o.beta2, o.eps);
        let adam_d = Adam::new(&dvs, o.beta1, o.beta2, o.eps);
        let ema = Ema { decay: cfg.ema.decay, warmup: cfg.ema.warmup, updates: 0 };
        Ok(Self {
            cfg,
            run_dir: run_dir.to_path_buf(),
            device,
            gvs,
            generator,
            evs,
            ema_generator,
            dvs,
            disc,
            adam_g,
            adam_d,
            ema,
            progress: Progress::default(),
            datasets: BTreeMap::new(),
            permutation: None,
            injected: BTreeSet::new(),
            evaluator: None,
            step_seconds: Vec::new(),
        })
    }

    /// Continues the run in `run_dir` from its newest checkpoint. `device` overrides the
    /// saved config's device (the run continues identically elsewhere).
    pub fn resume(run_dir: &Path, device: Option<&str>) -> Result<Self> {
        let (_, path) = run::latest_checkpoint(run_dir)?;
        let mut t = Self::from_checkpoint(&path, run_dir, device)?;
        run::truncate_metrics(run_dir, t.progress.step)?;
        curve::truncate(run_dir, t.progress.step)?;
        t.injected.clear();
        Ok(t)
    }

    /// Continues the run in `run_dir` under a changed config (a longer schedule, other
    /// stages, learning rates or loss weights). The networks and the camera must be the
    /// ones the run was trained with; a difference is an error naming the table. The new
    /// config is written to RUN_DIR/config.toml and into the following checkpoints.
    pub fn resume_with(run_dir: &Path, cfg: TrainConfig) -> Result<Self> {
        let mut t = Self::resume(run_dir, Some(&cfg.device))?;
        for (table, same) in [
            ("generator", t.cfg.generator == cfg.generator),
            ("discriminator", t.cfg.discriminator == cfg.discriminator),
            ("camera", t.cfg.camera == cfg.camera),
        ] {
            if !same {
                return Err(Error::Config(format!(
                    "[{table}] differs from the run's ({}); a run continues only with the networks and camera it was trained with",
                    run_dir.display()
                )));
            }
        }
        cfg.validate()?;
        t.cfg = cfg;
        t.datasets.clear();
        t.permutation = None;
        crate::paths::write_atomic(&run_dir.join(run::CONFIG), t.cfg.to_store().to_toml()?.as_bytes())?;
        Ok(t)
    }

    fn from_checkpoint(path: &Path, run_dir: &Path, device: Option<&str>) -> Result<Self> {
        let ckpt = checkpoint::load(path)?;
        let bad = |reason: String| Error::NotACheckpoint { path: path.to_path_buf(), reason };
        if ckpt.header.model != "training_state" {
            return Err(bad(format!("it holds a '{}', not a training state", ckpt.header.model)));
        }
        let th: TrainingHeader =
            serde_json::from_value(ckpt.header.training.clone().ok_or_else(|| bad("no training header".into()))?)
                .map_err(|e| bad(format!("bad training header: {e}")))?;
        let mut cfg = th.config.from_store();
        if let Some(d) = device {
            cfg.device = d.to_string();
        }
        let mut t = Self::seeded(cfg, run_dir)?;
        let split = |prefix: &str| -> BTreeMap<String, Tensor> {
            ckpt.tensors
                .iter()
                .filter_map(|(n, v)| n.strip_prefix(prefix).map(|n| (n.to_string(), v.shallow_clone())))
                .collect()
        };
        for (prefix, vs) in [("generator.", &mut t.gvs), ("ema.", &mut t.evs), ("discriminator.", &mut t.dvs)] {
            let part = checkpoint::Checkpoint {
                path: path.to_path_buf(),
                header: ckpt.header.clone(),
                tensors: split(prefix),
            };
            part.load_into(vs).map_err(|e| bad(format!("{prefix}*: {e}")))?;
        }
        let p = th.progress;
        t.adam_g.load(&ckpt.tensors, "adam_g.", p.adam_g_t)?;
        t.adam_d.load(&ckpt.tensors, "adam_d.", p.adam_d_t)?;
        t.ema.updates = p.ema_updates;
        t.progress = p;
        Ok(t)
    }

    /// Generates the procedural dataset if the config asks for one that is not there yet.
    pub fn prepare_data(&self, progress: &(dyn Fn() + Sync)) -> Result<data::Prepared> {
        self.cfg.data.prepare(self.cfg.threads, progress)
    }

    /// The training images at `res` (loaded through the cache on first use).
    pub fn dataset(&mut self, res: i64) -> Result<&Dataset> {
        if !self.datasets.contains_key(&res) {
            let opts = self.cfg.data.load_options(res as usize, self.cfg.threads);
            let ds = data::load(&self.cfg.data.path, &opts, &|| {})?;
            if ds.is_empty() {
                return Err(Error::Data {
                    path: self.cfg.data.path.clone(),
                    reason: "the dataset holds no images".into(),
                });
            }
            self.datasets.insert(res, ds);
        }
        Ok(&self.datasets[&res])
    }

    fn rng(&self, step: i64, purpose: Purpose) -> StepRng {
        StepRng::new(self.cfg.seed, step as u64, purpose, Kind::Float, self.device)
    }

    /// Indices of the next `b` real images: consecutive positions in per-epoch random
    /// permutations of the `n` images (each epoch's permutation drawn from the seed).
    fn real_indices(&mut self, b: i64, n: i64) -> Vec<i64> {
        (0..b)
            .map(|i| {
                let pos = self.progress.images_seen + i;
                let epoch = pos / n;
                if self.permutation.as_ref().map(|p| (p.0, p.1.len() as i64)) != Some((epoch, n)) {
                    let mut perm: Vec<i64> = (0..n).collect();
                    let mut r =
                        StepRng::new(self.cfg.seed, epoch as u64, Purpose::RealIndices, Kind::Float, Device::Cpu);
                    let u = r.u64s(n as usize);
                    for k in (1..n as usize).rev() {
                        perm.swap(k, (u[k] % (k as u64 + 1)) as usize);
                    }
                    self.permutation = Some((epoch, perm));
                }
                self.permutation.as_ref().unwrap().1[(pos % n) as usize]
            })
            .collect()
    }

    /// Runs one step (D step, then G step) and returns what happened. A non-finite loss or
    /// gradient skips that network's update; `guard.rollback_after` such steps in a row
    /// roll back to the newest checkpoint with the learning rates scaled down.
    pub fn step(&mut self) -> Result<StepReport> {
        let start = Instant::now();
        let step = self.progress.step;
        let stage_index = self.cfg.stage_index(step);
        let stage = self.cfg.stages[stage_index].clone();
        let alpha = self.cfg.alpha(step);
        let (g_lr, d_lr) = self.cfg.learning_rates(step);
        let (g_lr, d_lr) = (g_lr * self.progress.lr_scale, d_lr * self.progress.lr_scale);
        let at = Schedule { step, alpha };
        let (b, res) = (stage.batch_size, stage.resolution);

        let (real, real_poses) = self.real_batch(&stage, step)?;
        let real_poses = real_poses.as_ref();
        let (d, g) = if g_lr <= 0.0 {
            // A discriminator-only stage: no generator render, no gradient, no EMA update.
            let d = self.discriminator_step(&stage, at, &real, real_poses, d_lr)?;
            (d, Update { total: f64::NAN, terms: Vec::new(), norm: f64::NAN, skipped: false })
        } else if self.cfg.step == StepKind::OneRender {
            let (d, losses) = self.one_render_gradients(&stage, at, &real, real_poses, d_lr)?;
            (d, self.generator_step(&stage, at, g_lr, &real, real_poses, Some(losses))?)
        } else {
            let d = self.discriminator_step(&stage, at, &real, real_poses, d_lr)?;
            (d, self.generator_step(&stage, at, g_lr, &real, real_poses, None)?)
        };

        let p = &mut self.progress;
        p.step += 1;
        p.images_seen += b;
        let bad = d.skipped || g.skipped;
        if bad {
            p.skipped_steps += 1;
            p.consecutive_bad += 1;
        } else {
            p.consecutive_bad = 0;
        }
        let seconds = start.elapsed().as_secs_f64();
        p.train_seconds += seconds;
        let mut report = StepReport {
            step,
            stage: stage_index,
            resolution: res,
            batch_size: b,
            alpha,
            d_total: d.total,
            g_total: g.total,
            d_terms: d.terms,
            g_terms: g.terms,
            grad_norm_d: d.norm,
            grad_norm_g: g.norm,
            lr_g: g_lr,
            lr_d: d_lr,
            d_skipped: d.skipped,
            g_skipped: g.skipped,
            seconds,
            rolled_back_to: None,
        };
        if bad && self.progress.consecutive_bad >= self.cfg.guard.rollback_after {
            report.rolled_back_to = Some(self.rollback()?);
        }
        Ok(report)
    }

    /// The real images of `step` at `stage`'s resolution, and their poses where known (the
    /// next `batch_size` positions of the epoch permutations; the counter moves on in
    /// [`Trainer::step`]).
    fn real_batch(&mut self, stage: &Stage, step: i64) -> Result<(Tensor, Option<Tensor>)> {
        let (b, res) = (stage.batch_size, stage.resolution);
        let n_real = self.dataset(res)?.len() as i64;
        let idx = self.real_indices(b, n_real);
        let ds = &self.datasets[&res];
        let flips: Option<Vec<bool>> =
            ds.flip.map(|_| self.rng(step, Purpose::RealFlips).u64s(b as usize).iter().map(|x| x & 1 == 1).collect());
        let (real, real_poses) = ds.batch(&idx, flips.as_deref())?;
        Ok((real.to_device(self.device), real_poses.map(|p| p.to_device(self.device))))
    }

    /// The live generator's renderer with sampling config `rc`, at the configured precision.
    fn live_renderer<'a>(&'a self, rc: &'a crate::RenderConfig) -> Result<Renderer<'a>> {
        let mut r = Renderer::new(&self.generator, &self.cfg.camera, rc)?;
        r.field.compute_kind = self.cfg.precision.compute_kind();
        Ok(r)
    }

    /// One player's fake batch of `stage` at `step`: codes `(B, latent)`, poses and
    /// renderer noise, from the draws `[codes, poses, jitter, importance]`.
    fn fake_draws(&self, stage: &Stage, step: i64, purposes: [Purpose; 4]) -> (Tensor, Poses, Noise) {
        let (b, res, n) = (stage.batch_size, stage.resolution, stage.num_steps as i64);
        let [codes, poses, jitter, importance] = purposes;
        let z = self.rng(step, codes).normal(&[b, self.cfg.generator.latent_dim as i64]);
        let poses = Poses::sample_from(&self.cfg.camera, b, &mut self.rng(step, poses));
        let shape = [b, res * res, n];
        let noise = Noise {
            jitter: Some(self.rng(step, jitter).uniform(&shape)),
            importance: Some(self.rng(step, importance).uniform(&shape)),
        };
        (z, poses, noise)
    }

    /// The discriminator behind the configured augmentation (`[discriminator] augment`),
    /// drawing from (seed, step, `purpose`); `None` when no augmentation is configured.
    fn augmented(&self, step: i64, purpose: Purpose) -> Option<AugmentedJudge<'_>> {
        let d = &self.cfg.discriminator;
        (!d.augment.is_empty())
            .then(|| AugmentedJudge::new(self.disc.as_ref(), &d.augment, d.augment_fill, self.rng(step, purpose)))
    }

    fn discriminator_step(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        lr: f64,
    ) -> Result<Update> {
        let purposes = [Purpose::DiscCodes, Purpose::DiscPoses, Purpose::DiscJitter, Purpose::DiscImportance];
        let (z, poses, noise) = self.fake_draws(stage, at.step, purposes);
        self.discriminator_step_on(stage, at, real, real_poses, (&z, &poses, &noise), lr)
    }

    /// The release's discriminator step on fakes of the codes, poses and noise `draws`.
    fn discriminator_step_on(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        (z, poses, noise): (&Tensor, &Poses, &Noise),
        lr: f64,
    ) -> Result<Update> {
        let rc = self.cfg.render_config(at.step);
        let renderer = self.live_renderer(&rc)?;
        // Fakes from the live generator, rendered without gradients (the release's D step).
        let lat = tch::no_grad(|| self.generator.latents(z, z, None));
        let fake =
            FakeBatch { latents: &lat, poses, z: Some(z), resolution: stage.resolution, regions: stage.regions, noise };
        let augmented = self.augmented(at.step, Purpose::DiscAugment);
        let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
        let losses = discriminator_pass(&renderer, judge, real, real_poses, &fake, at, &self.cfg.loss)?;
        // Gradients are zeroed before each backward (R1's own gradient never accumulates).
        zero_grads(&self.dvs);
        losses.total.backward();
        Ok(self.apply(Net::D, &losses, lr))
    }

    fn generator_step(
        &mut self,
        stage: &Stage,
        at: Schedule,
        lr: f64,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        rendered_once: Option<Losses>,
    ) -> Result<Update> {
        // The one-render step has already left its gradient in G.
        let mut losses = match rendered_once {
            Some(l) => l,
            None => self.generator_gradients(stage, at)?,
        };
        if self.cfg.loss.coverage_weight > 0.0 {
            let poses = real_poses.ok_or_else(|| {
                Error::Config(
                    "loss.coverage_weight needs the real images' poses; the dataset has none (see data.poses)".into(),
                )
            })?;
            let c = self.coverage_gradients(stage, at, real, poses)?;
            losses.total = &losses.total + &c * self.cfg.loss.coverage_weight;
            losses.terms.push(("g_coverage", c));
        }
        Ok(self.apply(Net::G, &losses, lr))
    }

    /// The coverage term (see [`crate::loss::LossConfig::coverage_weight`]): picks, for each
    /// real image `(B, 3, S, S)` seen from `real_poses: (B, 2)`, the nearest of
    /// `coverage_candidates` codes at low resolution, renders it at the real pose with
    /// gradients (in the stage's `batch_split` chunks, as the adversarial pass), and
    /// accumulates the weighted MSE's gradient into G. Returns the MSE.
    fn coverage_gradients(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: &Tensor,
    ) -> Result<Tensor> {
        let cfg = &self.cfg.loss;
        let (b, res, step) = (real.size()[0], stage.resolution, at.step);
        let k = cfg.coverage_candidates;
        let small = cfg.coverage_resolution.min(res);
        let latent = self.cfg.generator.latent_dim as i64;
        let z = self.rng(step, Purpose::CoverageCodes).normal(&[b * k, latent]);
        let poses = Poses::from_stacked(&real_poses.repeat_interleave_self_int(k, 0, None));
        let rc = self.cfg.render_config(step);
        // The candidates, without gradients or random draws (no jitter, mid-point importance
        // samples).
        let rc_candidates = crate::RenderConfig { jitter: false, ..rc.clone() };
        let gen = &self.generator;
        let candidates = tch::no_grad(|| {
            let renderer = self.live_renderer(&rc_candidates)?;
            let lat = gen.latents(&z, &z, None);
            let noise = Noise::midpoints(b * k, small * small, stage.num_steps as i64, z.device());
            renderer.render_image(&lat, &poses, small, &noise)
        })?
        .rgb;
        let target = crate::io::resize(real, small).repeat_interleave_self_int(k, 0, None);
        let dist = (candidates - target).square().mean_dim([1i64, 2, 3].as_slice(), false, Kind::Float).view([b, k]);
        let best = dist.argmin(1, false) + Tensor::arange(b, (Kind::Int64, dist.device())) * k;
        let z_best = z.index_select(0, &best);
        let poses = Poses::from_stacked(real_poses);
        let shape = [b, res * res, stage.num_steps as i64];
        let noise = Noise {
            jitter: Some(self.rng(step, Purpose::CoverageJitter).uniform(&shape)),
            importance: Some(self.rng(step, Purpose::CoverageImportance).uniform(&shape)),
        };
        let renderer = self.live_renderer(&rc)?;
        let split = stage.batch_split;
        let chunk = b / split;
        let mut mse = 0.0;
        for c in 0..split {
            let sl = |t: &Tensor| t.narrow(0, c * chunk, chunk);
            let noise = Noise { jitter: noise.jitter.as_ref().map(sl), importance: noise.importance.as_ref().map(sl) };
            let zc = sl(&z_best);
            let lat = self.generator.latents(&zc, &zc, None);
            let (img, _) = renderer.render_regions(&lat, &poses.narrow(c * chunk, chunk), res, 1, &noise)?;
            let m = (img - sl(real)).square().mean(Kind::Float);
            (&m * (cfg.coverage_weight / split as f64)).backward();
            mse += m.double_value(&[]) / split as f64;
        }
        Ok(Tensor::from(mse))
    }

    /// Computes the generator's gradients of the step about to run and leaves them in
    /// the generator's variables, without updating anything (diagnostics and tests:
    /// e.g. the two-pass patch step must give the single-pass gradient). Returns the
    /// loss terms.
    pub fn generator_gradients_now(&mut self) -> Result<Vec<(&'static str, f64)>> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        Ok(self.generator_gradients(&stage, at)?.values())
    }

    /// Renders the generator's batch chunk by chunk and accumulates the gradient of the
    /// batch-mean loss into the generator's variables (D frozen throughout).
    fn generator_gradients(&mut self, stage: &Stage, at: Schedule) -> Result<Losses> {
        let draws = self.generator_draws(stage, at.step);
        // The generator step leaves D's parameters alone: frozen, they get no gradient.
        self.dvs.freeze();
        zero_grads(&self.gvs);
        let split = stage.batch_split;
        let mut mean = ChunkMean::default();
        // One augmentation stream for the step: successive chunks get successive draws.
        let augmented = self.augmented(at.step, Purpose::GenAugment);
        let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
        let result = (|| -> Result<()> {
            for c in 0..split {
                let losses = self.generator_chunk(judge, stage, at, &draws.chunk(c, split), split as f64)?;
                mean.add(&losses, split);
            }
            Ok(())
        })();
        self.dvs.unfreeze();
        result?;
        Ok(mean.losses())
    }

    /// The generator's draws of `step`: codes, poses and renderer noise (in pairs sharing a
    /// pose and depths while the mode-seeking term is on, so that a pair's difference is
    /// its codes' alone), the regulariser rays, and whether a fault is injected.
    fn generator_draws(&mut self, stage: &Stage, step: i64) -> GenDraws {
        let (b, res) = (stage.batch_size, stage.resolution);
        let purposes = [Purpose::GenCodes, Purpose::GenPoses, Purpose::GenJitter, Purpose::GenImportance];
        let (z, poses, noise) = self.fake_draws(stage, step, purposes);
        let (poses, noise) = if self.cfg.loss.diversity_at(step) > 0.0 {
            let pair = |t: &Option<Tensor>| t.as_ref().map(crate::camera::rows_in_pairs);
            (poses.in_pairs(), Noise { jitter: pair(&noise.jitter), importance: pair(&noise.importance) })
        } else {
            (poses, noise)
        };
        let n_reg = reg_ray_count(res * res, &self.cfg.loss.reg);
        let reg_rays =
            Tensor::from_slice(&self.rng(step, Purpose::RegRays).below((b * n_reg) as usize, (res * res) as u64))
                .view([b, n_reg])
                .to_device(self.device);
        let inject = self.cfg.debug.inject_nonfinite_steps.contains(&step) && self.injected.insert(step);
        GenDraws { z, poses, noise, reg_rays, inject }
    }

    /// The one-render step ([`StepKind::OneRender`]) up to the generator's update: renders
    /// the generator's batch once with its graph, takes the discriminator's step on those
    /// images (detached), then leaves in G the gradient of the batch-mean loss through the
    /// updated discriminator on the same graph. Returns D's update and G's losses.
    fn one_render_gradients(
        &mut self,
        stage: &Stage,
        at: Schedule,
        real: &Tensor,
        real_poses: Option<&Tensor>,
        d_lr: f64,
    ) -> Result<(Update, Losses)> {
        let draws = self.generator_draws(stage, at.step);
        let split = stage.batch_split;
        let rc = self.cfg.render_config(at.step);
        zero_grads(&self.gvs);
        // Every chunk's graph is kept until the generator's backward.
        let rendered = {
            let renderer = self.live_renderer(&rc)?;
            (0..split)
                .map(|c| {
                    let d = draws.chunk(c, split);
                    let lat = self.generator.latents(&d.z, &d.z, None);
                    let (img, parts) = renderer.render_regions(&lat, &d.poses, stage.resolution, 1, &d.noise)?;
                    Ok((d, lat, img, parts))
                })
                .collect::<Result<Vec<_>>>()?
        };
        let fakes = Tensor::cat(&rendered.iter().map(|r| r.2.detach()).collect::<Vec<_>>(), 0);
        let d = {
            let augmented = self.augmented(at.step, Purpose::DiscAugment);
            let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
            let losses = discriminator_judgement(
                judge,
                real,
                real_poses,
                &fakes,
                &draws.poses,
                Some(&draws.z),
                at,
                &self.cfg.loss,
            )?;
            zero_grads(&self.dvs);
            losses.total.backward();
            losses
        };
        let d = self.apply(Net::D, &d, d_lr);
        self.dvs.freeze();
        let mut mean = ChunkMean::default();
        let fault = if draws.inject { f64::NAN } else { 1.0 };
        let augmented = self.augmented(at.step, Purpose::GenAugment);
        let judge = augmented.as_ref().map_or(self.disc.as_ref(), |a| a as &dyn Judge);
        let result = (|| -> Result<()> {
            for (d, lat, img, parts) in &rendered {
                let fake = FakeBatch {
                    latents: lat,
                    poses: &d.poses,
                    z: Some(&d.z),
                    resolution: stage.resolution,
                    regions: 1,
                    noise: &d.noise,
                };
                let mut losses = generator_judgement(
                    &self.generator,
                    judge,
                    img,
                    parts,
                    &fake,
                    Some(&d.reg_rays),
                    at,
                    &self.cfg.loss,
                )?;
                losses.total = losses.total.g_mul_scalar(fault);
                (&losses.total / split as f64).backward();
                mean.add(&losses, split);
            }
            Ok(())
        })();
        self.dvs.unfreeze();
        result?;
        Ok((d, mean.losses()))
    }

    /// The one-render step's discriminator update (applied) and generator gradient (left in
    /// G's variables, not applied) for the step about to run; returns G's loss terms. With
    /// [`Trainer::discriminator_step_on_generator_draws_now`] and
    /// [`Trainer::generator_gradients_now`], the same step taken the release's way (tests).
    pub fn one_render_gradients_now(&mut self) -> Result<Vec<(&'static str, f64)>> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        let (_, d_lr) = self.cfg.learning_rates(step);
        let (real, real_poses) = self.real_batch(&stage, step)?;
        let (_, losses) =
            self.one_render_gradients(&stage, at, &real, real_poses.as_ref(), d_lr * self.progress.lr_scale)?;
        Ok(losses.values())
    }

    /// The release's discriminator step (its own no-grad render) applied to the fakes of
    /// the generator's draws of the step about to run, instead of its own draws (tests).
    pub fn discriminator_step_on_generator_draws_now(&mut self) -> Result<()> {
        let step = self.progress.step;
        let stage = self.cfg.stage(step).clone();
        let at = Schedule { step, alpha: self.cfg.alpha(step) };
        let (_, d_lr) = self.cfg.learning_rates(step);
        let (real, real_poses) = self.real_batch(&stage, step)?;
        let draws = self.generator_draws(&stage, step);
        let lr = d_lr * self.progress.lr_scale;
        self.discriminator_step_on(&stage, at, &real, real_poses.as_ref(), (&draws.z, &draws.poses, &draws.noise), lr)?;
        Ok(())
    }

    /// Renders one chunk of the generator's batch, backpropagates its share of the loss
    /// (1/split of the chunk mean) into G's gradients and returns its (unscaled) losses.
    fn generator_chunk(
        &self,
        judge: &dyn Judge,
        stage: &Stage,
        at: Schedule,
        draws: &GenDraws,
        split: f64,
    ) -> Result<Losses> {
        let GenDraws { z, poses, noise, reg_rays, inject } = draws;
        let rc = self.cfg.render_config(at.step);
        let renderer = self.live_renderer(&rc)?;
        let gen = &self.generator;
        let cfg = &self.cfg.loss;
        let res = stage.resolution;
        let fault = if *inject { f64::NAN } else { 1.0 };
        let target = poses.stacked();
        if stage.regions == 1 {
            let lat = gen.latents(z, z, None);
            let fake = FakeBatch { latents: &lat, poses, z: Some(z), resolution: res, regions: 1, noise };
            let mut losses = generator_pass(&renderer, judge, &fake, Some(reg_rays), at, cfg)?;
            losses.total = losses.total.g_mul_scalar(fault);
            (&losses.total / split).backward();
            return Ok(losses);
        }
        // The release's two-pass patch step: render without gradients, take D's gradient
        // w.r.t. the image alone, then re-render each band with gradients at the very
        // sample depths of the first pass and backpropagate its slice of that gradient.
        let (img, parts) = tch::no_grad(|| {
            let lat = gen.latents(z, z, None);
            renderer.render_regions(&lat, poses, res, stage.regions, noise)
        })?;
        let img = img.detach().set_requires_grad(true);
        let d = judge.judge(&img, at.alpha)?;
        let mut adv = generator_image_terms(&d, &img, &target, Some(z), at, cfg)?;
        adv.total = adv.total.g_mul_scalar(fault);
        let g_img = Tensor::run_backward(&[&adv.total / split], &[&img], false, false).remove(0);
        // (B, 3, H, W) → (B, R, 3), the layout of per-ray pixels; pixel = (img + 1)/2.
        let b = g_img.size()[0];
        let g_rays = g_img.reshape([b, 3, res * res]).permute([0, 2, 1]) * 2.0;
        let rays = renderer.region_rays(poses, res, stage.regions)?;
        let len = res * res / stage.regions;
        for (k, (part, ray)) in parts.iter().zip(&rays).enumerate() {
            // Fresh latents per band: each backward frees its own graph.
            let lat = gen.latents(z, z, None);
            let rr = renderer.render_at_depths(&lat, ray, &part.z)?;
            (&rr.pixel * g_rays.narrow(1, k as i64 * len, len)).sum(Kind::Float).backward();
        }
        let lat = gen.latents(z, z, None);
        let samples = select_samples(&RenderedRays::concat(&parts), &cfg.reg, Some(reg_rays));
        let reg = generator_regularisation(
            regularisers(gen, &lat.shape, &samples, cfg.reg.variant),
            &cfg.reg,
            cfg.reg_scale(at.step),
        );
        (&reg.total / split).backward();
        Ok(adv.merge(reg))
    }

    /// Checks finiteness, clips and applies one network's update.
    fn apply(&mut self, net: Net, losses: &Losses, lr: f64) -> Update {
        let vs = match net {
            Net::G => &self.gvs,
            Net::D => &self.dvs,
        };
        let total = losses.total.double_value(&[]);
        let norm = grad_norm(vs);
        let ok = total.is_finite() && norm.is_finite();
        if ok {
            if self.cfg.optim.grad_clip > 0.0 {
                clip_grads(vs, norm, self.cfg.optim.grad_clip);
            }
            match net {
                Net::G => {
                    self.adam_g.step(&self.gvs, lr);
                    self.ema.update(&self.evs, &self.gvs);
                }
                Net::D => self.adam_d.step(&self.dvs, lr),
            }
        }
        Update { total, terms: losses.values(), norm, skipped: !ok }
    }

    /// Goes back to the newest checkpoint with the learning rates scaled by
    /// `guard.lr_factor`; returns the step it went back to.
    fn rollback(&mut self) -> Result<i64> {
        let p = self.progress.clone();
        if p.rollbacks >= self.cfg.guard.max_rollbacks {
            return Err(Error::Invalid(format!(
                "training diverged: {} consecutive non-finite steps at step {} after {} rollback(s) (guard.max_rollbacks)",
                p.consecutive_bad, p.step, p.rollbacks
            )));
        }
        let (_, path) = run::latest_checkpoint(&self.run_dir)?;
        let back = Self::from_checkpoint(&path, &self.run_dir, Some(&self.cfg.device))?;
        let to = back.progress.step;
        let injected = std::mem::take(&mut self.injected);
        let datasets = std::mem::take(&mut self.datasets);
        *self = back;
        self.injected = injected;
        self.datasets = datasets;
        self.progress.lr_scale = p.lr_scale * self.cfg.guard.lr_factor;
        self.progress.rollbacks = p.rollbacks + 1;
        self.progress.consecutive_bad = 0;
        self.progress.skipped_steps = p.skipped_steps;
        self.progress.train_seconds = p.train_seconds;
        run::truncate_metrics(&self.run_dir, to)?;
        curve::truncate(&self.run_dir, to)?;
        run::append_metrics(
            &self.run_dir,
            &serde_json::json!({"step": to, "event": "rollback", "from_step": p.step, "lr_scale": self.progress.lr_scale}),
        )?;
        Ok(to)
    }

    /// The checkpoint's tensors: both networks, the EMA and both optimisers' moments.
    fn state_tensors(&self) -> Vec<(String, Tensor)> {
        let mut out = Vec::new();
        for (prefix, vs) in [("generator.", &self.gvs), ("ema.", &self.evs), ("discriminator.", &self.dvs)] {
            let mut v: Vec<_> = vs.variables().into_iter().map(|(n, t)| (format!("{prefix}{n}"), t)).collect();
            v.sort_by(|a, b| a.0.cmp(&b.0));
            out.extend(v);
        }
        out.extend(self.adam_g.named_tensors("adam_g."));
        out.extend(self.adam_d.named_tensors("adam_d."));
        out
    }

    fn header(&self, model: &str) -> Header {
        let mut h = Header::generator(self.cfg.generator.clone(), Some(self.cfg.camera.clone()));
        h.model = model.into();
        let p = &self.progress;
        h.info.insert("step".into(), p.step.to_string());
        h.info.insert("images_seen".into(), p.images_seen.to_string());
        h.info.insert("train_seconds".into(), format!("{:.0}", p.train_seconds));
        // What the last step rendered at: the evaluation says when it scores the generator
        // at another resolution.
        let stage = self.cfg.stage((p.step - 1).max(0));
        h.info.insert(crate::checkpoint::RESOLUTION_INFO.into(), stage.resolution.to_string());
        h.info.insert(crate::checkpoint::SAMPLES_PER_RAY_INFO.into(), (2 * stage.num_steps).to_string());
        // Which discriminator shaped it: the evaluation warns when its distances use the
        // features a projected discriminator was built on.
        h.info.insert(crate::eval::report::DISCRIMINATOR_INFO.into(), self.cfg.discriminator.kind.name().into());
        h
    }

    /// Writes the training state after `progress.step` steps (atomically; refused if any
    /// tensor is non-finite), exports the EMA generator to RUN_DIR/generator.safetensors,
    /// and keeps the newest `schedule.keep_checkpoints` checkpoints.
    pub fn save_checkpoint(&self) -> Result<PathBuf> {
        let dir = self.run_dir.join(run::CHECKPOINTS);
        std::fs::create_dir_all(&dir).map_err(|source| Error::Io { path: dir.clone(), source })?;
        let path = dir.join(run::checkpoint_name(self.progress.step));
        let mut header = self.header("training_state");
        // The optimisers and the EMA own their step counts; the header carries them.
        let progress = Progress {
            adam_g_t: self.adam_g.t,
            adam_d_t: self.adam_d.t,
            ema_updates: self.ema.updates,
            ..self.progress.clone()
        };
        let th =
            TrainingHeader { progress, stage: self.cfg.stage_index(self.progress.step), config: self.cfg.to_store() };
        header.training = Some(serde_json::to_value(&th).map_err(|e| Error::Invalid(e.to_string()))?);
        checkpoint::save(&path, &self.state_tensors(), &header)?;
        self.export_generator(&self.run_dir.join(run::GENERATOR))?;
        run::prune_checkpoints(&self.run_dir, self.cfg.schedule.keep_checkpoints)?;
        Ok(path)
    }

    /// Saves the EMA generator as a plain generator checkpoint.
    pub fn export_generator(&self, path: &Path) -> Result<()> {
        checkpoint::save_generator(path, &self.evs, &self.header("generator"))
    }
}

/// The generator's random draws of one step ([`Trainer::generator_draws`]).
struct GenDraws {
    /// `(B, latent)`.
    z: Tensor,
    poses: Poses,
    noise: Noise,
    /// `(B, n)` rays of each image the regularisers are taken on.
    reg_rays: Tensor,
    /// A NaN is injected into this step's generator loss (`[debug]`).
    inject: bool,
}

impl GenDraws {
    /// Chunk `c` of `split` equal chunks of the batch.
    fn chunk(&self, c: i64, split: i64) -> GenDraws {
        let len = self.z.size()[0] / split;
        let sl = |t: &Tensor| t.narrow(0, c * len, len);
        GenDraws {
            z: sl(&self.z),
            poses: self.poses.narrow(c * len, len),
            noise: Noise {
                jitter: self.noise.jitter.as_ref().map(sl),
                importance: self.noise.importance.as_ref().map(sl),
            },
            reg_rays: sl(&self.reg_rays),
            inject: self.inject,
        }
    }
}

/// The batch mean of per-chunk losses (each chunk weighs 1/split).
#[derive(Default)]
struct ChunkMean {
    total: f64,
    terms: Vec<(&'static str, f64)>,
}

impl ChunkMean {
    fn add(&mut self, chunk: &Losses, split: i64) {
        self.total += chunk.total.double_value(&[]) / split as f64;
        for (i, (k, v)) in chunk.values().into_iter().enumerate() {
            if i == self.terms.len() {
                self.terms.push((k, 0.0));
            }
            self.terms[i].1 += v / split as f64;
        }
    }

    fn losses(&self) -> Losses {
        Losses {
            total: Tensor::from(self.total),
            terms: self.terms.iter().map(|(k, v)| (*k, Tensor::from(*v))).collect(),
        }
    }
}

#[derive(Clone, Copy)]
enum Net {
    G,
    D,
}

struct Update {
    total: f64,
    terms: Vec<(&'static str, f64)>,
    norm: f64,
    skipped: bool,
}

/// When a [`Trainer::run`] session stops (besides `schedule.total_steps`).
#[derive(Debug, Clone, Copy, Default)]
pub struct RunLimits {
    /// Steps to run in this session at most.
    pub steps: Option<i64>,
    /// Wall-clock seconds for this session at most (checked between steps).
    pub seconds: Option<f64>,
}

/// Why a [`Trainer::run`] session ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stopped {
    /// `schedule.total_steps` reached.
    Finished,
    /// A [`RunLimits`] bound reached.
    Limit,
    /// The stop flag was raised (Ctrl-C, SIGTERM).
    Interrupted,
}

impl Trainer {
    /// Trains until the schedule ends, a limit is reached or `stop` is raised, logging
    /// to metrics.jsonl, checkpointing every `checkpoint_interval` steps and writing
    /// previews every `sample_interval` steps. Whatever ends the session, it ends with a
    /// checkpoint of the last step. A fresh run first writes its resolved config, a
    /// step-0 checkpoint (the rollback target of early failures) and step-0 previews.
    pub fn run(
        &mut self,
        limits: RunLimits,
        stop: &std::sync::atomic::AtomicBool,
        mut on_step: impl FnMut(&StepReport, &Progress),
    ) -> Result<Stopped> {
        use std::sync::atomic::Ordering;
        std::fs::create_dir_all(&self.run_dir).map_err(|source| Error::Io { path: self.run_dir.clone(), source })?;
        if run::list_checkpoints(&self.run_dir)?.is_empty() {
            run::truncate_metrics(&self.run_dir, self.progress.step)?;
            crate::paths::write_atomic(&self.run_dir.join(run::CONFIG), self.cfg.to_store().to_toml()?.as_bytes())?;
            self.save_checkpoint()?;
            if self.cfg.schedule.sample_interval > 0 {
                samples::write_previews(self)?;
            }
        }
        let start = Instant::now();
        let first = self.progress.step;
        let s = self.cfg.schedule.clone();
        let mut saved_at = self.progress.step;
        // An evaluation interrupted before its line was written is made up on resume.
        if self.eval_due(first) && !curve::has(&self.run_dir, first)? {
            self.evaluate()?;
        }
        let stopped = loop {
            if self.progress.step >= s.total_steps {
                break Stopped::Finished;
            }
            if stop.load(Ordering::SeqCst) {
                break Stopped::Interrupted;
            }
            if limits.steps.is_some_and(|n| self.progress.step - first >= n)
                || limits.seconds.is_some_and(|t| start.elapsed().as_secs_f64() >= t)
            {
                break Stopped::Limit;
            }
            let report = self.step()?;
            self.step_seconds.push(report.seconds);
            if let Some(to) = report.rolled_back_to {
                saved_at = to;
            } else if report.step % s.log_interval == 0 || report.d_skipped || report.g_skipped {
                run::append_metrics(&self.run_dir, &report.to_json(&self.progress))?;
            }
            on_step(&report, &self.progress);
            let done = self.progress.step;
            if done % s.checkpoint_interval == 0 && report.rolled_back_to.is_none() {
                self.save_checkpoint()?;
                saved_at = done;
            }
            if s.sample_interval > 0 && done % s.sample_interval == 0 {
                samples::write_previews(self)?;
            }
            if self.eval_due(done) {
                self.evaluate()?;
            }
        };
        if saved_at != self.progress.step {
            self.save_checkpoint()?;
            if s.sample_interval > 0 {
                samples::write_previews(self)?;
            }
        }
        Ok(stopped)
    }

    /// Whether the curve has an evaluation at `step` (a positive multiple of `eval.interval`).
    fn eval_due(&self, step: i64) -> bool {
        self.cfg.eval.interval > 0 && step > 0 && step % self.cfg.eval.interval == 0
    }

    /// Scores the EMA generator as `gdrf-train eval --seeds` scores a generator file (`[eval]`
    /// settings, the dataset of `[data]`; each seed beside its random-weight generator) and
    /// records it on the learning curve ([`curve::record`]). Returns the curve's line.
    pub fn evaluate(&mut self) -> Result<serde_json::Value> {
        use crate::eval::report::{score_generator, EvalOptions, Evaluator, FeatureKind};
        let e = self.cfg.eval.clone();
        let probe = e.probe.clone().ok_or_else(|| Error::Config("eval.probe is not set".into()))?;
        let seeds = if e.seeds.is_empty() { vec![self.cfg.seed] } else { e.seeds.clone() };
        let start = Instant::now();
        if self.evaluator.is_none() {
            let opts = EvalOptions {
                num: e.num,
                swap: e.swap,
                resolution: (e.resolution > 0).then_some(e.resolution),
                steps: e.steps,
                seed: seeds[0],
                features: FeatureKind::Efficientnet,
                effnet_weights: crate::pretrained::effnet::EfficientNetLite0::default_path(),
                threads: self.cfg.threads,
                real_resolution: None,
                psi: 1.0,
            };
            self.evaluator = Some(Evaluator::new(&self.cfg.data.path, &probe, &opts, self.device, &mut |_, _, _| {})?);
        }
        let header = self.header("generator");
        // As committed records show them: relative to the repository where inside it.
        let name = crate::paths::shown(&self.run_dir.join(run::GENERATOR));
        let dataset = PathBuf::from(crate::paths::shown(&self.cfg.data.path));
        let ev = self.evaluator.as_mut().expect("built above");
        let mut results = Vec::with_capacity(seeds.len());
        let mut seed_start = start;
        for &seed in &seeds {
            ev.reseed(seed)?;
            let what = format!(" (seed {seed})");
            let names = (name.clone(), dataset.as_path());
            results.push(score_generator(
                ev,
                &self.ema_generator,
                &header,
                names,
                &what,
                seed_start,
                &mut |_, _, _| {},
            )?);
            seed_start = Instant::now();
        }
        let summary = crate::eval::seeds::summarise(&results)?;
        let mut times = std::mem::take(&mut self.step_seconds);
        times.sort_by(f64::total_cmp);
        let point = curve::CurvePoint {
            step: self.progress.step,
            images_seen: self.progress.images_seen,
            train_seconds: self.progress.train_seconds,
            step_seconds: (!times.is_empty()).then(|| {
                let m = times.len() / 2;
                if times.len() % 2 == 1 {
                    times[m]
                } else {
                    0.5 * (times[m - 1] + times[m])
                }
            }),
            eval_seconds: start.elapsed().as_secs_f64(),
            scores: &summary,
        };
        curve::record(&self.run_dir, &point, &results)?;
        // The generator scored, kept whatever checkpoints are pruned later: the curve's best
        // point can be shipped.
        self.export_generator(&curve::eval_dir(&self.run_dir, point.step).join(run::GENERATOR))?;
        serde_json::to_value(&point).map_err(|e| Error::Invalid(e.to_string()))
    }

    /// Parameter counts: (generator, discriminator in all, discriminator used at `res`).
    pub fn parameter_counts(&self, res: i64) -> (i64, i64, i64) {
        let count = |vs: &nn::VarStore| vs.variables().values().map(|t| t.numel() as i64).sum::<i64>();
        let used = self.disc.used_parameters(res).unwrap_or(0);
        (count(&self.gvs), count(&self.dvs), used)
    }
}
