//! A run's state: a fresh or resumed trainer, its checkpoints (both networks, the EMA,
//! both optimisers' moments and the counters), the exported EMA generator, and the
//! rollback to the last good checkpoint.
use super::optim::{copy_vars, Adam, Ema};
use super::{curve, occupancy, run, Progress, TrainConfig, Trainer, TrainingHeader};
use crate::checkpoint::{self, Header};
use crate::{Error, Generator, GeneratorConfig, Result};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use tch::{nn, Tensor};

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
            skipped: Vec::new(),
            group: None,
            grid: None,
        })
    }

    /// Continues the run in `run_dir` from its newest checkpoint that loads. `device`
    /// overrides the saved config's device (the run continues identically elsewhere). A
    /// damaged checkpoint (truncated, a checksum that does not match, a non-finite or
    /// missing tensor) is passed over for the next older one, and named in
    /// [`Trainer::skipped_checkpoints`]; when none loads, the error lists every one tried.
    pub fn resume(run_dir: &Path, device: Option<&str>) -> Result<Self> {
        let all = run::list_checkpoints(run_dir)?;
        if all.is_empty() {
            // The error that says what a run folder should hold.
            run::latest_checkpoint(run_dir)?;
        }
        let mut skipped = Vec::new();
        for (_, path) in all.iter().rev() {
            match Self::from_checkpoint(path, run_dir, device) {
                Ok(mut t) => {
                    run::truncate_metrics(run_dir, t.progress.step)?;
                    curve::truncate(run_dir, t.progress.step)?;
                    t.injected.clear();
                    t.skipped = skipped;
                    return Ok(t);
                }
                Err(e) if damaged(&e) => skipped.push((path.clone(), e.to_string())),
                Err(e) => return Err(e),
            }
        }
        let tried: Vec<String> = skipped.iter().map(|(_, why)| format!("  {why}")).collect();
        Err(Error::Data {
            path: run_dir.join(run::CHECKPOINTS),
            reason: format!("no checkpoint loads; tried, newest first:\n{}", tried.join("\n")),
        })
    }

    /// Continues the run in `run_dir` under a changed config (a longer schedule, other
    /// stages, learning rates or loss weights, the background the images are judged on).
    /// The networks and the camera must be the ones the run was trained with; a difference
    /// is an error naming the table. The new config is written to RUN_DIR/config.toml and
    /// into the following checkpoints.
    pub fn resume_with(run_dir: &Path, cfg: TrainConfig) -> Result<Self> {
        let mut t = Self::resume(run_dir, Some(&cfg.device))?;
        // `generator.background` is how the networks are trained and rendered, not what they are.
        let background = cfg.generator.background;
        let networks = GeneratorConfig { background, ..t.cfg.generator.clone() };
        for (table, same) in [
            ("generator", networks == cfg.generator),
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
        if t.cfg.occupancy != cfg.occupancy {
            // Another grid (or none): the next step builds it afresh.
            t.grid = None;
        }
        t.cfg = cfg;
        t.generator.cfg.background = background;
        t.ema_generator.cfg.background = background;
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
        // A damaged header (outside the checksum) is refused here, naming the file, before
        // the networks it describes are built.
        cfg.validate().map_err(|e| bad(format!("its config: {e}")))?;
        let ema = ckpt.tensors.iter().filter(|(n, _)| n.starts_with("ema.")).map(|(_, t)| t);
        checkpoint::check_generator_size(path, &cfg.generator, ema)?;
        // Every discriminator width is some stored tensor's dimension: a wider one is a
        // damaged header, and building it would allocate what it claims.
        let widest = ckpt
            .tensors
            .iter()
            .filter(|(n, _)| n.starts_with("discriminator."))
            .flat_map(|(_, t)| t.size())
            .max()
            .unwrap_or(0);
        if let Some(c) = cfg.discriminator.channels.iter().find(|&&c| c > widest) {
            return Err(bad(format!(
                "its header's discriminator has {c} channels, more than any tensor it stores holds ({widest})"
            )));
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
        // The training-time grid as the run left it; a state saved before its first step
        // (or without `[occupancy]`) has none, and the next step builds it.
        if let (Some(oc), Some(score)) = (&t.cfg.occupancy, ckpt.tensors.get(occupancy::SCORE_TENSOR)) {
            let score = score.to_device(t.device);
            t.grid = Some(occupancy::SharedGrid::from_score(score, &t.cfg.camera, oc).map_err(|e| bad(e.to_string()))?);
        }
        Ok(t)
    }

    /// Goes back to the newest checkpoint with the learning rates scaled by
    /// `guard.lr_factor`; returns the step it went back to.
    pub(super) fn rollback(&mut self) -> Result<i64> {
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
        // A rank stays in its group: every rank rolls back at the same step, to the same
        // checkpoint (rank 0's), so the replicas stay identical.
        let group = self.group.take();
        *self = back;
        self.injected = injected;
        self.datasets = datasets;
        self.group = group;
        self.progress.lr_scale = p.lr_scale * self.cfg.guard.lr_factor;
        self.progress.rollbacks = p.rollbacks + 1;
        self.progress.consecutive_bad = 0;
        self.progress.skipped_steps = p.skipped_steps;
        self.progress.train_seconds = p.train_seconds;
        if self.is_writer() {
            run::truncate_metrics(&self.run_dir, to)?;
            curve::truncate(&self.run_dir, to)?;
            run::append_metrics(
                &self.run_dir,
                &RollbackLine { event: "rollback", from_step: p.step, lr_scale: self.progress.lr_scale, step: to },
            )?;
        }
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
        if let Some(g) = &self.grid {
            out.push((occupancy::SCORE_TENSOR.to_string(), g.score.shallow_clone()));
        }
        out
    }

    pub(super) fn header(&self, model: &str) -> Header {
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
        h.info.insert(crate::eval::provenance::DISCRIMINATOR_INFO.into(), self.cfg.discriminator.kind.name().into());
        h
    }

    /// Writes the training state after `progress.step` steps (atomically; refused if any
    /// tensor is non-finite), exports the EMA generator to RUN_DIR/generator.safetensors,
    /// and keeps the newest `schedule.keep_checkpoints` checkpoints.
    pub fn save_checkpoint(&self) -> Result<PathBuf> {
        let dir = self.run_dir.join(run::CHECKPOINTS);
        std::fs::create_dir_all(&dir).map_err(|source| Error::Io { path: dir.clone(), err: source })?;
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
        header.training = Some(serde_json::to_value(&th)?);
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

/// The metrics.jsonl line of a rollback (keys in alphabetical order, as every line's).
#[derive(serde::Serialize)]
struct RollbackLine {
    event: &'static str,
    /// The step whose failure triggered it.
    from_step: i64,
    /// The learning rates' scale from now on.
    lr_scale: f64,
    /// The step the run went back to.
    step: i64,
}

/// Whether `e` says a checkpoint file is damaged (what a crash, a full disk or a flipped bit
/// leaves), so that resuming may fall back to an older one, rather than that the run
/// cannot continue at all (another device, another config).
fn damaged(e: &Error) -> bool {
    matches!(
        e,
        Error::Io { .. }
            | Error::NotACheckpoint { .. }
            | Error::ShapeMismatch { .. }
            | Error::MissingTensor { .. }
            | Error::UnexpectedTensor { .. }
            | Error::DType { .. }
    )
}
