//! What a training session does besides stepping, as hooks on its loop (nerfstudio's
//! `callbacks.py`): the metrics lines, the caller's progress display, checkpoints, previews,
//! and the evaluation with its learning curve. [`Trainer::run`] calls each hook at every
//! [`Point`] of the session, in the order of [`Hooks::of_session`]; a hook says itself
//! whether it is due there (its interval, or a point it always acts at).
//!
//! A new hook is one `impl Hook` here and one line in [`Hooks::of_session`]; where it goes
//! in that list is when its files are written relative to the others', which a resume that
//! replays a crashed session relies on (a checkpoint is never newer than the metrics lines
//! before it, an evaluation follows the checkpoint of its step).
use super::{curve, run, samples, Progress, StepReport, Trainer};
use crate::{Error, Result};
use std::path::PathBuf;
use std::time::Instant;

/// A point of a [`Trainer::run`] session where its hooks are called.
pub enum Point<'a> {
    /// Before the session's first step. `fresh`: the run folder holds no checkpoint yet,
    /// so the run starts here (and this process writes it).
    Start { fresh: bool },
    /// After each step, with what it did (the run's counters already moved on).
    Step(&'a StepReport),
    /// After the session's last step, whatever ended the session.
    End,
}

/// Something a training session does at the points of its loop.
pub trait Hook {
    /// Does the hook's work at `point` where it is due there, and nothing elsewhere.
    fn at(&mut self, point: &Point, trainer: &mut Trainer) -> Result<()>;
}

/// A session's hooks in the order they are called at each point.
pub(super) struct Hooks<'a>(Vec<Box<dyn Hook + 'a>>);

impl<'a> Hooks<'a> {
    /// The hooks of a session: `on_step` on every rank; the run's files only on the rank
    /// that writes them (alone, or rank 0 of a group: the ranks are identical replicas).
    pub(super) fn of_session(trainer: &Trainer, on_step: impl FnMut(&StepReport, &Progress) + 'a) -> Self {
        let on_step: Box<dyn Hook + 'a> = Box::new(OnStep(on_step));
        if !trainer.is_writer() {
            return Self(vec![on_step]);
        }
        let saved_at = trainer.progress.step;
        Self(vec![
            Box::new(Metrics),
            on_step,
            Box::new(Checkpoints { saved_at }),
            Box::new(Previews),
            Box::new(Evaluation { evaluator: None, step_seconds: Vec::new() }),
        ])
    }

    /// Calls every hook at `point`, in order.
    pub(super) fn at(&mut self, point: &Point, trainer: &mut Trainer) -> Result<()> {
        self.0.iter_mut().try_for_each(|h| h.at(point, trainer))
    }
}

/// Whether `step` is a multiple of `interval` (0: never).
fn every(interval: i64, step: i64) -> bool {
    interval > 0 && step % interval == 0
}

/// The metrics.jsonl lines: every `log_interval`-th step's, and every step that skipped an
/// update. A step that rolled back has its own line (the rollback's, written by it).
struct Metrics;

impl Hook for Metrics {
    fn at(&mut self, point: &Point, t: &mut Trainer) -> Result<()> {
        match point {
            // A fresh run in a folder a crashed fresh run left: its lines go.
            Point::Start { fresh: true } => run::truncate_metrics(&t.run_dir, t.progress.step),
            Point::Step(r) if r.rolled_back_to.is_none() => {
                if r.step % t.cfg.schedule.log_interval == 0 || r.d_skipped || r.g_skipped {
                    run::append_metrics(&t.run_dir, &r.metrics_line(&t.progress))?;
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }
}

/// The caller's view of each step (a progress bar, a test's record).
struct OnStep<F>(F);

impl<F: FnMut(&StepReport, &Progress)> Hook for OnStep<F> {
    fn at(&mut self, point: &Point, t: &mut Trainer) -> Result<()> {
        if let Point::Step(r) = point {
            (self.0)(r, &t.progress);
        }
        Ok(())
    }
}

/// The training state every `checkpoint_interval` steps, and at the points a resume may
/// start from besides: a fresh run's step 0 (with its resolved config; the rollback target
/// of early failures) and a session's last step. A checkpoint written outside the interval
/// comes with previews, so that the folder's newest previews show the state it holds.
struct Checkpoints {
    /// The step of the run's newest checkpoint: written, or rolled back to.
    saved_at: i64,
}

impl Checkpoints {
    fn with_previews(t: &Trainer) -> Result<()> {
        t.save_checkpoint()?;
        if t.cfg.schedule.sample_interval > 0 {
            samples::write_previews(t)?;
        }
        Ok(())
    }
}

impl Hook for Checkpoints {
    fn at(&mut self, point: &Point, t: &mut Trainer) -> Result<()> {
        match point {
            Point::Start { fresh: true } => {
                crate::paths::write_atomic(&t.run_dir.join(run::CONFIG), t.cfg.to_store().to_toml()?.as_bytes())?;
                Self::with_previews(t)?;
            }
            Point::Start { fresh: false } => {}
            Point::Step(r) => match r.rolled_back_to {
                Some(to) => self.saved_at = to,
                None if every(t.cfg.schedule.checkpoint_interval, t.progress.step) => {
                    t.save_checkpoint()?;
                    self.saved_at = t.progress.step;
                }
                None => {}
            },
            Point::End if self.saved_at != t.progress.step => {
                Self::with_previews(t)?;
                self.saved_at = t.progress.step;
            }
            Point::End => {}
        }
        Ok(())
    }
}

/// Preview grids (samples, swaps, templates) every `sample_interval` steps.
struct Previews;

impl Hook for Previews {
    fn at(&mut self, point: &Point, t: &mut Trainer) -> Result<()> {
        if let Point::Step(_) = point {
            if every(t.cfg.schedule.sample_interval, t.progress.step) {
                samples::write_previews(t)?;
            }
        }
        Ok(())
    }
}

/// The learning curve: the EMA generator scored every `eval.interval` steps. An evaluation
/// a session was stopped before writing (its step has a checkpoint, the curve no line) is
/// made up when the next session starts.
struct Evaluation {
    /// The evaluation's real-data side, built at its first evaluation.
    evaluator: Option<crate::eval::evaluator::Evaluator>,
    /// Seconds of each step since the last evaluation (the curve's step time).
    step_seconds: Vec<f64>,
}

impl Hook for Evaluation {
    fn at(&mut self, point: &Point, t: &mut Trainer) -> Result<()> {
        let due = |t: &Trainer| t.progress.step > 0 && every(t.cfg.eval.interval, t.progress.step);
        match point {
            Point::Start { .. } if due(t) && !curve::has(&t.run_dir, t.progress.step)? => self.evaluate(t),
            Point::Step(r) => {
                self.step_seconds.push(r.seconds);
                if due(t) {
                    self.evaluate(t)?;
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }
}

impl Evaluation {
    /// Scores the EMA generator as `gdrf-train eval --seeds` scores a generator file
    /// (`[eval]` settings, the dataset of `[data]`; each seed beside its random-weight
    /// generator), records it on the learning curve ([`curve::record`]) and keeps the
    /// generator scored.
    fn evaluate(&mut self, t: &Trainer) -> Result<()> {
        use crate::eval::evaluator::{score_generator, EvalOptions, Evaluator};
        let e = &t.cfg.eval;
        let probe = e.probe.clone().ok_or_else(|| Error::Config("eval.probe is not set".into()))?;
        let seeds = if e.seeds.is_empty() { vec![t.cfg.seed] } else { e.seeds.clone() };
        let start = Instant::now();
        if self.evaluator.is_none() {
            let opts = EvalOptions {
                num: e.num,
                swap: e.swap,
                resolution: (e.resolution > 0).then_some(e.resolution),
                samples: e.samples,
                seed: seeds[0],
                threads: t.cfg.threads,
                ..EvalOptions::default()
            };
            self.evaluator = Some(Evaluator::new(&t.cfg.data.path, &probe, &opts, t.device, &mut |_| {})?);
        }
        let header = t.header("generator");
        // As committed records show them: relative to the repository where inside it.
        let name = crate::paths::shown(&t.run_dir.join(run::GENERATOR));
        let dataset = PathBuf::from(crate::paths::shown(&t.cfg.data.path));
        let ev = self.evaluator.as_mut().expect("built above");
        let mut results = Vec::with_capacity(seeds.len());
        let mut seed_start = start;
        for &seed in &seeds {
            ev.reseed(seed)?;
            let what = format!(" (seed {seed})");
            let names = (name.clone(), dataset.as_path());
            results.push(score_generator(ev, &t.ema_generator, &header, names, &what, seed_start, &mut |_| {})?);
            seed_start = Instant::now();
        }
        let summary = crate::eval::seeds::summarise(&results)?;
        let times = std::mem::take(&mut self.step_seconds);
        let point = curve::CurvePoint {
            step: t.progress.step,
            images_seen: t.progress.images_seen,
            train_seconds: t.progress.train_seconds,
            step_seconds: (!times.is_empty()).then(|| crate::stats::median(&times)),
            eval_seconds: start.elapsed().as_secs_f64(),
            scores: &summary,
        };
        curve::record(&t.run_dir, &point, &results)?;
        // The generator scored, kept whatever checkpoints are pruned later: the curve's best
        // point can be shipped.
        t.export_generator(&curve::eval_dir(&t.run_dir, point.step).join(run::GENERATOR))
    }
}
