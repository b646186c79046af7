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
pub mod hooks;
pub mod occupancy;
pub mod optim;
mod parallel;
pub mod pass;
pub mod plateau;
mod reals;
pub mod run;
pub mod samples;
mod scaled;
pub mod snapshot;
mod state;
mod step;

pub use config::{PatchConfig, Stage, StepKind, TrainConfig};
pub use pass::{
    discriminator_judgement, discriminator_pass, generator_judgement, generator_pass, patch_gradients, FakeBatch,
    Judged,
};

use crate::data::Dataset;
use crate::disc::Judge;
use crate::{Error, Generator, Result};
use optim::{Adam, Ema};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{nn, Device};

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
    /// The fraction of the training-time occupancy grid's cells this step's renders counted
    /// as occupied (with `[occupancy]`).
    pub occupancy: Option<f64>,
}

impl StepReport {
    /// The metrics.jsonl line, with the run's counters after this step.
    pub fn metrics_line(&self, p: &Progress) -> MetricsLine<'_> {
        MetricsLine {
            alpha: self.alpha,
            batch_size: self.batch_size,
            d: self.d_terms.iter().copied().collect(),
            d_skipped: self.d_skipped,
            d_total: self.d_total,
            g: self.g_terms.iter().copied().collect(),
            g_skipped: self.g_skipped,
            g_total: self.g_total,
            grad_norm_d: self.grad_norm_d,
            grad_norm_g: self.grad_norm_g,
            images_per_second: self.batch_size as f64 / self.seconds.max(1e-9),
            images_seen: p.images_seen,
            lr_d: self.lr_d,
            lr_g: self.lr_g,
            occupancy: self.occupancy,
            resolution: self.resolution,
            rollbacks: p.rollbacks,
            skipped_steps: p.skipped_steps,
            stage: self.stage,
            step: self.step,
            step_seconds: self.seconds,
        }
    }
}

/// One line of metrics.jsonl: a step's losses, gradient norms, learning rates and time,
/// and the run's counters. Keys in alphabetical order, as the file has always had them;
/// a non-finite number is written as `null`.
#[derive(Debug, Serialize)]
pub struct MetricsLine<'a> {
    pub alpha: f64,
    pub batch_size: i64,
    /// The discriminator's unweighted terms by name.
    pub d: BTreeMap<&'a str, f64>,
    pub d_skipped: bool,
    pub d_total: f64,
    /// The generator's unweighted terms by name (batch means over its chunks).
    pub g: BTreeMap<&'a str, f64>,
    pub g_skipped: bool,
    pub g_total: f64,
    pub grad_norm_d: f64,
    pub grad_norm_g: f64,
    pub images_per_second: f64,
    pub images_seen: i64,
    pub lr_d: f64,
    pub lr_g: f64,
    /// The fraction of the training-time occupancy grid's cells occupied (with `[occupancy]`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub occupancy: Option<f64>,
    pub resolution: i64,
    pub rollbacks: i64,
    pub skipped_steps: i64,
    pub stage: usize,
    pub step: i64,
    pub step_seconds: f64,
}

/// A training run in memory: both networks, the EMA generator, optimisers and counters.
/// Its state changes only through its own steps, resumes and rollbacks; callers read it
/// through the accessors below.
pub struct Trainer {
    pub(crate) cfg: TrainConfig,
    pub(crate) run_dir: PathBuf,
    pub(crate) device: Device,
    pub(crate) gvs: nn::VarStore,
    pub(crate) generator: Generator,
    /// The EMA generator (samples and exports).
    pub(crate) evs: nn::VarStore,
    pub(crate) ema_generator: Generator,
    pub(crate) dvs: nn::VarStore,
    pub(crate) disc: Box<dyn Judge>,
    pub(crate) adam_g: Adam,
    pub(crate) adam_d: Adam,
    pub(crate) ema: Ema,
    pub(crate) progress: Progress,
    datasets: BTreeMap<i64, Dataset>,
    permutation: Option<(i64, Vec<i64>)>,
    /// Injected faults already fired (not saved: a replay after a rollback runs clean).
    injected: BTreeSet<i64>,
    /// Checkpoints a resume passed over as damaged, newest first, with why.
    skipped: Vec<(PathBuf, String)>,
    /// The data-parallel group this trainer is a rank of ([`Trainer::join_group`]).
    group: Option<crate::dist::ProcessGroup>,
    /// The training-time occupancy grid (`[occupancy]`), saved with the state; `None` until
    /// the first step builds it.
    pub(crate) grid: Option<occupancy::SharedGrid>,
}

impl Trainer {
    /// The run's config (as resolved when it started or resumed).
    pub fn cfg(&self) -> &TrainConfig {
        &self.cfg
    }

    pub fn run_dir(&self) -> &Path {
        &self.run_dir
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// Steps, images seen, skips and rollbacks so far.
    pub fn progress(&self) -> &Progress {
        &self.progress
    }

    /// The EMA's schedule and update count.
    pub fn ema(&self) -> &Ema {
        &self.ema
    }

    /// The live generator's, the EMA generator's and the discriminator's parameters.
    pub fn generator_vars(&self) -> &nn::VarStore {
        &self.gvs
    }

    pub fn ema_vars(&self) -> &nn::VarStore {
        &self.evs
    }

    /// The training-time occupancy grid as the last step used it (`[occupancy]`).
    pub fn occupancy_grid(&self) -> Option<&occupancy::SharedGrid> {
        self.grid.as_ref()
    }

    pub fn disc_vars(&self) -> &nn::VarStore {
        &self.dvs
    }

    /// The newer checkpoints [`Trainer::resume`] found damaged and passed over, newest
    /// first, with why (empty when it resumed from the newest).
    pub fn skipped_checkpoints(&self) -> &[(PathBuf, String)] {
        &self.skipped
    }

    /// Threads for the steps from now on (`--threads` on resume); 0 means all cores.
    pub fn set_threads(&mut self, threads: usize) {
        self.cfg.threads = threads;
    }
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
    /// Trains until the schedule ends, a limit is reached or `stop` is raised, calling the
    /// session's hooks ([`hooks`]: metrics.jsonl, `on_step`, checkpoints, previews, the
    /// learning curve) before the first step, after each step and after the last. Whatever
    /// ends the session, it ends with a checkpoint of the last step. A fresh run first
    /// writes its resolved config, a step-0 checkpoint (the rollback target of early
    /// failures) and step-0 previews.
    pub fn run(
        &mut self,
        limits: RunLimits,
        stop: &std::sync::atomic::AtomicBool,
        on_step: impl FnMut(&StepReport, &Progress),
    ) -> Result<Stopped> {
        use std::sync::atomic::Ordering;
        std::fs::create_dir_all(&self.run_dir)
            .map_err(|source| Error::Io { path: self.run_dir.clone(), err: source })?;
        let mut hooks = hooks::Hooks::of_session(self, on_step);
        let fresh = self.is_writer() && run::list_checkpoints(&self.run_dir)?.is_empty();
        hooks.at(&hooks::Point::Start { fresh }, self)?;
        let start = Instant::now();
        let first = self.progress.step;
        let stopped = loop {
            if self.progress.step >= self.cfg.schedule.total_steps {
                break Stopped::Finished;
            }
            // Every rank stops at the same step: a stop or limit on any stops all.
            if self.any_rank(stop.load(Ordering::SeqCst))? {
                break Stopped::Interrupted;
            }
            if self.any_rank(
                limits.steps.is_some_and(|n| self.progress.step - first >= n)
                    || limits.seconds.is_some_and(|t| start.elapsed().as_secs_f64() >= t),
            )? {
                break Stopped::Limit;
            }
            let report = self.step()?;
            hooks.at(&hooks::Point::Step(&report), self)?;
        };
        hooks.at(&hooks::Point::End, self)?;
        Ok(stopped)
    }

    /// Parameter counts: (generator, discriminator in all, discriminator used at `res`).
    pub fn parameter_counts(&self, res: i64) -> (i64, i64, i64) {
        let count = |vs: &nn::VarStore| vs.variables().values().map(|t| t.numel() as i64).sum::<i64>();
        let used = self.disc.used_parameters(res).unwrap_or(0);
        (count(&self.gvs), count(&self.dvs), used)
    }
}
