//! The training configuration (TOML): models, camera, sampling, the curriculum, losses,
//! optimisers, EMA, intervals, data, seed, device, precision. Every table rejects unknown
//! keys; [`TrainConfig::validate`] names each out-of-range value and what was expected.
//! The resolved config is saved in the run directory and inside every checkpoint.
use crate::data::DataConfig;
use crate::disc::DiscConfig;
use crate::error::require;
use crate::loss::LossConfig;
use crate::{CameraConfig, Error, GeneratorConfig, RenderConfig, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

mod sections;
pub use sections::{
    cpu_has_bf16, DebugConfig, EmaConfig, GuardConfig, OccupancyConfig, OptimConfig, PatchConfig, Precision,
    SampleConfig, ScheduleConfig, Stage, StepKind, TrainEvalConfig,
};

/// A whole training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Seeds the initial weights and every random draw of every step.
    #[serde(default)]
    pub seed: u64,
    /// auto, cpu, cuda or cuda:N.
    #[serde(default = "auto")]
    pub device: String,
    #[serde(default)]
    pub precision: Precision,
    /// `two-render` (the release) or `one-render` ([`StepKind`]).
    #[serde(default)]
    pub step: StepKind,
    /// libtorch threads (0 = all cores).
    #[serde(default)]
    pub threads: usize,
    /// A generator file (a run's `generator.safetensors` export or a shipped model's) whose
    /// weights start both the live and the EMA generator of a new run, e.g. to go on
    /// training a shipped model under another schedule; the discriminator and the
    /// optimisers start fresh. Its `[generator]` must equal this config's. Relative to the
    /// config file's folder; not read on resume (the checkpoint holds the weights).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init_generator: Option<std::path::PathBuf>,
    #[serde(default)]
    pub generator: GeneratorConfig,
    #[serde(default)]
    pub discriminator: DiscConfig,
    #[serde(default)]
    pub camera: CameraConfig,
    /// Sampling and integration; `num_steps` is set by each stage.
    #[serde(default)]
    pub render: RenderConfig,
    #[serde(default)]
    pub loss: LossConfig,
    #[serde(default)]
    pub optim: OptimConfig,
    #[serde(default)]
    pub ema: EmaConfig,
    #[serde(default)]
    pub schedule: ScheduleConfig,
    #[serde(default)]
    pub samples: SampleConfig,
    #[serde(default)]
    pub eval: TrainEvalConfig,
    #[serde(default)]
    pub guard: GuardConfig,
    #[serde(default)]
    pub debug: DebugConfig,
    /// The training-time occupancy grid ([`OccupancyConfig`]); absent: every ray samples the
    /// camera's whole interval.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub occupancy: Option<OccupancyConfig>,
    pub stages: Vec<Stage>,
    pub data: DataConfig,
}

fn auto() -> String {
    "auto".into()
}

/// `base.join(p)` with `.` and `..` resolved lexically (`configs/../data` → `data`).
fn lexical_join(base: &Path, p: &Path) -> std::path::PathBuf {
    let mut out = std::path::PathBuf::new();
    for c in base.join(p).components() {
        match c {
            std::path::Component::CurDir => {}
            std::path::Component::ParentDir
                if matches!(out.components().next_back(), Some(std::path::Component::Normal(_))) =>
            {
                out.pop();
            }
            c => out.push(c),
        }
    }
    out
}

fn cfg_err(msg: String) -> Error {
    Error::Config(msg)
}

impl TrainConfig {
    /// Parses and validates TOML. `base` resolves the data paths (the config file's folder).
    pub fn from_toml(text: &str, base: &Path) -> Result<Self> {
        let mut cfg: TrainConfig = toml::from_str(text).map_err(|e| cfg_err(e.to_string()))?;
        cfg.data.path = lexical_join(base, &cfg.data.path);
        cfg.data.poses = cfg.data.poses.map(|p| lexical_join(base, &p));
        cfg.data.cache_dir = cfg.data.cache_dir.map(|p| lexical_join(base, &p));
        cfg.eval.probe = cfg.eval.probe.map(|p| lexical_join(base, &p));
        cfg.init_generator = cfg.init_generator.map(|p| lexical_join(base, &p));
        cfg.validate()?;
        Ok(cfg)
    }

    /// Reads, parses and validates a config file; errors name the file.
    pub fn load(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io { path: path.into(), err: source })?;
        // Absolute, so that a run resumes from any working directory. The file's path is made
        // absolute before taking its folder: a bare `x.toml` has the empty path as parent.
        let file = std::path::absolute(path).map_err(|source| Error::Io { path: path.into(), err: source })?;
        let base = file.parent().unwrap_or(Path::new("/")).to_path_buf();
        Self::from_toml(&text, &base).map_err(|e| match e {
            Error::Config(m) => Error::Config(format!("{}: {m}", path.display())),
            e => e,
        })
    }

    /// The config as a run stores it (its config.toml, every checkpoint): paths inside the
    /// repository ([`crate::paths::repo_root`]) relative to it, so that the stored run names no
    /// machine's folder and a copy of it resumes in another clone. Paths elsewhere stay
    /// absolute. [`TrainConfig::from_store`] undoes it.
    pub fn to_store(&self) -> Self {
        let root = crate::paths::repo_root();
        let rel = |p: &Path| p.strip_prefix(&root).map(Path::to_path_buf).unwrap_or_else(|_| p.to_path_buf());
        self.map_paths(&rel)
    }

    /// A stored config ([`TrainConfig::to_store`]) with its relative paths resolved against
    /// the repository root. Absolute paths (older runs, folders outside the repository) are
    /// kept.
    pub fn from_store(&self) -> Self {
        let root = crate::paths::repo_root();
        self.map_paths(&|p: &Path| if p.is_relative() { root.join(p) } else { p.to_path_buf() })
    }

    fn map_paths(&self, f: &dyn Fn(&Path) -> std::path::PathBuf) -> Self {
        let mut c = self.clone();
        c.data.path = f(&c.data.path);
        c.data.poses = c.data.poses.as_deref().map(f);
        c.data.cache_dir = c.data.cache_dir.as_deref().map(f);
        c.eval.probe = c.eval.probe.as_deref().map(f);
        c.init_generator = c.init_generator.as_deref().map(f);
        c
    }

    /// The resolved config as TOML (every default written out).
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self).map_err(|e| cfg_err(format!("cannot write the config as TOML: {e}")))
    }

    pub fn validate(&self) -> Result<()> {
        self.generator.validate()?;
        self.discriminator.validate()?;
        self.camera.validate()?;
        self.render.validate()?;
        self.loss.validate()?;
        crate::device::select_syntax(&self.device).map_err(|e| cfg_err(format!("device: {e}")))?;
        self.validate_optimisation()?;
        self.validate_schedule()?;
        self.validate_latent_weight()?;
        self.validate_eval()?;
        self.validate_previews()?;
        self.validate_occupancy()?;
        let g = &self.guard;
        if g.rollback_after < 1 || !(g.lr_factor > 0.0 && g.lr_factor <= 1.0) || g.max_rollbacks < 0 {
            return Err(cfg_err(format!(
                "guard: rollback_after {} must be at least 1, lr_factor {} in (0, 1], max_rollbacks {} at least 0",
                g.rollback_after, g.lr_factor, g.max_rollbacks
            )));
        }
        if self.stages.is_empty() {
            return Err(cfg_err("stages: at least one [[stages]] table is needed".into()));
        }
        if self.stages[0].from_step != 0 {
            return Err(cfg_err(format!("stages[0].from_step is {}, expected 0", self.stages[0].from_step)));
        }
        for (i, st) in self.stages.iter().enumerate() {
            self.validate_stage(i, st)?;
        }
        if let Some(synth) = &self.data.synth {
            synth.validate().map_err(|e| cfg_err(format!("data.synth: {e}")))?;
        }
        Ok(())
    }

    /// `[optim]` and `[ema]`: positive rates, betas and decay in [0, 1).
    fn validate_optimisation(&self) -> Result<()> {
        let o = &self.optim;
        for (k, v) in [("optim.g_lr", o.g_lr), ("optim.d_lr", o.d_lr), ("optim.eps", o.eps)] {
            if !(v > 0.0 && v.is_finite()) {
                return Err(cfg_err(format!("{k} is {v}, expected a positive number")));
            }
        }
        for (k, v) in [("optim.beta1", o.beta1), ("optim.beta2", o.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return Err(cfg_err(format!("{k} is {v}, expected a value in [0, 1)")));
            }
        }
        if !(o.grad_clip >= 0.0 && o.grad_clip.is_finite()) {
            return Err(cfg_err(format!("optim.grad_clip is {}, expected 0 (off) or a positive norm", o.grad_clip)));
        }
        if !(0.0..1.0).contains(&self.ema.decay) {
            return Err(cfg_err(format!("ema.decay is {}, expected a value in [0, 1)", self.ema.decay)));
        }
        Ok(())
    }

    /// `[occupancy]`: a refresh interval and codes of at least 1, an even grid the renderer
    /// can build, a finite threshold ≥ 0 and a decay in [0, 1).
    fn validate_occupancy(&self) -> Result<()> {
        let Some(o) = &self.occupancy else { return Ok(()) };
        for (k, v) in [("occupancy.every", o.every), ("occupancy.codes", o.codes)] {
            if v < 1 {
                return Err(cfg_err(format!("{k} is {v}, expected at least 1")));
            }
        }
        if !(crate::render::COARSEST..=512).contains(&o.resolution) || o.resolution % 2 != 0 {
            return Err(cfg_err(format!(
                "occupancy.resolution is {}, expected an even number of cells per side in {}..=512",
                o.resolution,
                crate::render::COARSEST
            )));
        }
        if !(o.threshold >= 0.0 && o.threshold.is_finite()) {
            return Err(cfg_err(format!("occupancy.threshold is {}, expected a finite density ≥ 0", o.threshold)));
        }
        if !(0.0..1.0).contains(&o.decay) {
            return Err(cfg_err(format!("occupancy.decay is {}, expected a value in [0, 1)", o.decay)));
        }
        Ok(())
    }

    /// `[schedule]`'s step counts and intervals.
    fn validate_schedule(&self) -> Result<()> {
        let s = &self.schedule;
        for (k, v) in [
            ("schedule.total_steps", s.total_steps),
            ("schedule.fade_steps", s.fade_steps),
            ("schedule.log_interval", s.log_interval),
            ("schedule.checkpoint_interval", s.checkpoint_interval),
        ] {
            if v < 1 {
                return Err(cfg_err(format!("{k} is {v}, expected at least 1")));
            }
        }
        if s.keep_checkpoints < 1 {
            return Err(cfg_err("schedule.keep_checkpoints is 0, expected at least 1".into()));
        }
        Ok(())
    }

    /// The latent-prediction weight, which needs a code no wider than the discriminator's head.
    fn validate_latent_weight(&self) -> Result<()> {
        let lw = self.loss.latent_weight;
        if !(lw >= 0.0 && lw.is_finite()) {
            return Err(cfg_err(format!("loss.latent_weight is {lw}, expected 0 (off) or a positive weight")));
        }
        if lw > 0.0 && self.generator.latent_dim as i64 > crate::disc::LATENT_DIM {
            return Err(cfg_err(format!(
                "loss.latent_weight is {lw} but generator.latent_dim {} is wider than the discriminator's latent head ({})",
                self.generator.latent_dim,
                crate::disc::LATENT_DIM
            )));
        }
        Ok(())
    }

    /// `[eval]`: sizes, seeds, and the probe an evaluation during training needs.
    fn validate_eval(&self) -> Result<()> {
        let e = &self.eval;
        if e.interval < 0 || e.num < 2 || e.swap < 2 || e.samples < 2 {
            return Err(cfg_err(format!(
                "eval: interval {}, num {}, swap {}, samples {}: expected interval ≥ 0 (0 = never) and num, swap, samples ≥ 2",
                e.interval, e.num, e.swap, e.samples
            )));
        }
        if e.resolution != 0 && !(8..=512).contains(&e.resolution) {
            return Err(cfg_err(format!(
                "eval.resolution is {}, expected 0 (the dataset's) or 8 to 512 pixels",
                e.resolution
            )));
        }
        if let Some(k) = e.seeds.iter().enumerate().position(|(i, s)| e.seeds[..i].contains(s)) {
            return Err(cfg_err(format!("eval.seeds lists seed {} twice", e.seeds[k])));
        }
        if e.interval > 0 && e.probe.is_none() {
            return Err(cfg_err(format!(
                "eval.interval is {} but eval.probe is not set: scores need a probe (make one with `gdrf-train eval train-probe --dataset DIR`)",
                e.interval
            )));
        }
        Ok(())
    }

    /// The previews: `schedule.sample_interval` and `[samples]`.
    fn validate_previews(&self) -> Result<()> {
        let s = &self.schedule;
        if s.sample_interval < 0 {
            return Err(cfg_err(format!(
                "schedule.sample_interval is {}, expected 0 (never) or more",
                s.sample_interval
            )));
        }
        let sm = &self.samples;
        if sm.count < 1 || sm.swap < 1 || sm.yaws.is_empty() || sm.resolution < 0 {
            return Err(cfg_err(format!(
                "samples: count {} and swap {} must be at least 1, yaws non-empty, resolution 0 (the stage's) or more",
                sm.count, sm.swap
            )));
        }
        Ok(())
    }

    /// A stage's `[stages.patch]` (under `key`): a patch size the discriminator takes, no
    /// larger than the image; β in (0, ∞); whole-image bands only; a discriminator that can be
    /// told where each patch lies.
    fn validate_patch(&self, key: &str, st: &Stage, p: &PatchConfig) -> Result<()> {
        if !(8..=st.resolution).contains(&p.size) || p.size.count_ones() != 1 {
            return Err(cfg_err(format!(
                "{key}.size is {}, expected a power of two from 8 to the stage's resolution ({})",
                p.size, st.resolution
            )));
        }
        for (k, v) in [("beta_start", p.beta_start), ("beta_end", p.beta_end)] {
            require(v > 0.0 && v.is_finite(), &format!("{key}.{k}"), v, "a positive number")?;
        }
        require(p.anneal_images >= 0, &format!("{key}.anneal_images"), p.anneal_images, "0 or more")?;
        let q = p.native_share;
        require((0.0..1.0).contains(&q), &format!("{key}.native_share"), q, "a share in [0, 1)")?;
        if st.regions != 1 {
            return Err(cfg_err(format!(
                "{key} renders one patch per image, but the stage's regions is {}: expected 1",
                st.regions
            )));
        }
        if self.discriminator.kind != crate::disc::DiscKind::Release {
            return Err(cfg_err(format!(
                "{key} tells the discriminator where each patch lies through its coordinate channels, \
                 which discriminator.kind = \"{}\" has not: expected \"release\"",
                self.discriminator.kind.name()
            )));
        }
        Ok(())
    }

    /// Stage `i` (`stages[i]`), after the one before it: its resolution, samples, batch and
    /// split, bands, and learning rates, against the step kind, background and loss.
    fn validate_stage(&self, i: usize, st: &Stage) -> Result<()> {
        let key = |k: &str| format!("stages[{i}].{k}");
        if i > 0 && st.from_step <= self.stages[i - 1].from_step {
            return Err(cfg_err(format!(
                "{} is {}, expected more than stages[{}].from_step ({})",
                key("from_step"),
                st.from_step,
                i - 1,
                self.stages[i - 1].from_step
            )));
        }
        if !(8..=512).contains(&st.resolution) || st.resolution.count_ones() != 1 {
            return Err(cfg_err(format!(
                "{} is {}, expected a power of two from 8 to 512",
                key("resolution"),
                st.resolution
            )));
        }
        if st.num_steps < 3 {
            return Err(cfg_err(format!("{} is {}, expected at least 3", key("num_steps"), st.num_steps)));
        }
        if st.batch_size < 1 || st.batch_split < 1 || st.batch_size % st.batch_split != 0 {
            return Err(cfg_err(format!(
                "{} is {} and {} is {}: expected positive values, the split dividing the batch",
                key("batch_size"),
                st.batch_size,
                key("batch_split"),
                st.batch_split
            )));
        }
        if self.loss.diversity_weight > 0.0 && (st.batch_size / st.batch_split) % 2 != 0 {
            return Err(cfg_err(format!(
                "loss.diversity_weight is on but {} / {} is {}: the mode-seeking term needs an even number of images per chunk (pairs of codes)",
                key("batch_size"),
                key("batch_split"),
                st.batch_size / st.batch_split
            )));
        }
        if self.step == StepKind::OneRender && st.regions != 1 {
            return Err(cfg_err(format!(
                "step = \"one-render\" renders each image once with its graph, but {} is {}: the patch step needs step = \"two-render\"",
                key("regions"),
                st.regions
            )));
        }
        if !self.generator.background.is_learned() && st.regions != 1 {
            return Err(cfg_err(format!(
                "generator.background = \"{}\" composites whole rendered images on random colours, but {} is {}: expected 1",
                self.generator.background.name(),
                key("regions"),
                st.regions
            )));
        }
        if st.regions < 1 || (st.resolution * st.resolution) % st.regions != 0 {
            return Err(cfg_err(format!(
                "{} is {}, expected a positive divisor of the {}² rays",
                key("regions"),
                st.regions,
                st.resolution
            )));
        }
        if let Some(p) = &st.patch {
            self.validate_patch(&key("patch"), st, p)?;
        }
        if let Some(v) = st.g_lr {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(cfg_err(format!(
                    "{} is {v}, expected a positive number (or 0: the discriminator trains alone)",
                    key("g_lr")
                )));
            }
        }
        if let Some(v) = st.d_lr {
            if !(v > 0.0 && v.is_finite()) {
                return Err(cfg_err(format!("{} is {v}, expected a positive number", key("d_lr"))));
            }
        }
        if let Some(v) = st.pose_weight {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(cfg_err(format!("{} is {v}, expected 0 (off) or a positive weight", key("pose_weight"))));
            }
        }
        if let Some(v) = st.opacity_weight {
            if !(v >= 0.0 && v.is_finite()) {
                return Err(cfg_err(format!(
                    "{} is {v}, expected 0 (off) or a positive weight",
                    key("opacity_weight")
                )));
            }
        }
        // The two-pass `regions` step differentiates the image, then each band's colours:
        // the opacity term has no place in it.
        if st.regions > 1 && st.opacity_weight.unwrap_or(self.loss.opacity_weight) > 0.0 {
            return Err(cfg_err(format!(
                "{} is {} with the opacity term on (loss.opacity_weight or {}); the term needs whole-image or scaled-patch steps (regions = 1)",
                key("regions"),
                st.regions,
                key("opacity_weight")
            )));
        }
        Ok(())
    }

    /// Index of the stage in force at `step`.
    pub fn stage_index(&self, step: i64) -> usize {
        self.stages.iter().rposition(|s| s.from_step <= step).unwrap_or(0)
    }

    pub fn stage(&self, step: i64) -> &Stage {
        &self.stages[self.stage_index(step)]
    }

    /// The step of the last change of the discriminator's input size at or before `step`
    /// (None before the first). Only a change of resolution counts (the release's rule): a
    /// stage that changes only N or the batch does not restart the fade-in. Under scaled
    /// patches the discriminator's input is the patch ([`Stage::judged_size`]): EpiGRAF's one
    /// fixed-size discriminator, so a patch stage after a stage judging that size fades
    /// nothing in, and one after a larger size returns to a path trained before.
    pub fn switch_step(&self, step: i64) -> Option<i64> {
        self.stages
            .windows(2)
            .filter(|w| w[1].judged_size() > w[0].judged_size() && w[1].from_step <= step)
            .map(|w| w[1].from_step)
            .next_back()
    }

    /// The discriminator's fade-in α at `step`.
    pub fn alpha(&self, step: i64) -> f64 {
        crate::disc::fade_alpha(step, self.switch_step(step), self.schedule.fade_steps)
    }

    /// Learning rates (G, D) of the stage at `step`, before any rollback scaling.
    pub fn learning_rates(&self, step: i64) -> (f64, f64) {
        let st = self.stage(step);
        (st.g_lr.unwrap_or(self.optim.g_lr), st.d_lr.unwrap_or(self.optim.d_lr))
    }

    /// The losses' settings at `step`: `[loss]` with the stage's `pose_weight` and
    /// `opacity_weight` where it sets them.
    pub fn loss_at(&self, step: i64) -> LossConfig {
        let st = self.stage(step);
        let pose_weight = st.pose_weight.unwrap_or(self.loss.pose_weight);
        let opacity_weight = st.opacity_weight.unwrap_or(self.loss.opacity_weight);
        LossConfig { pose_weight, opacity_weight, ..self.loss.clone() }
    }

    /// The render config of the stage at `step` for the training renders. Early
    /// termination and skipped or thinned importance samples are inference shortcuts (they evaluate
    /// without gradients), so training renders never use them; the preview grids do when
    /// `[render]` asks for them.
    pub fn render_config(&self, step: i64) -> RenderConfig {
        RenderConfig {
            num_steps: self.stage(step).num_steps,
            termination: 0.0,
            importance_skip: 0.0,
            importance_concentration: 0.0,
            ..self.render.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: &str = r#"
[[stages]]
from_step = 0
resolution = 32
num_steps = 12
batch_size = 8

[[stages]]
from_step = 100
resolution = 32
num_steps = 16
batch_size = 8

[[stages]]
from_step = 200
resolution = 64
num_steps = 16
batch_size = 4
batch_split = 2
g_lr = 1e-4

[data]
path = "data/x"
"#;

    fn parse(extra: &str) -> Result<TrainConfig> {
        TrainConfig::from_toml(&format!("{extra}\n{MIN}"), Path::new("/base"))
    }

    #[test]
    fn auto_precision_is_bfloat16_only_on_a_cpu_with_bfloat16_instructions() {
        use tch::{Device, Kind};
        assert_eq!(parse("precision = \"auto\"").unwrap().precision, Precision::Auto);
        let cpu = if cpu_has_bf16() { Precision::Bfloat16 } else { Precision::Float32 };
        assert_eq!(Precision::Auto.on(Device::Cpu), cpu);
        assert_eq!(Precision::Auto.on(Device::Cuda(0)), Precision::Float32);
        assert_eq!(Precision::Auto.compute_kind(Device::Cuda(0)), None);
        // Named precisions are what they say on every device.
        for d in [Device::Cpu, Device::Cuda(0)] {
            assert_eq!(Precision::Bfloat16.compute_kind(d), Some(Kind::BFloat16));
            assert_eq!(Precision::Float32.compute_kind(d), None);
        }
        let err = parse("precision = \"half\"").unwrap_err().to_string();
        assert!(err.contains("precision") && err.contains("auto"), "{err}");
    }

    #[test]
    fn defaults_stages_fade_and_rates() {
        let c = parse("").unwrap();
        assert_eq!(c.data.path, Path::new("/base/data/x"));
        assert_eq!(lexical_join(Path::new("/a/configs"), Path::new("../data/./x")), Path::new("/a/data/x"));
        assert_eq!(lexical_join(Path::new("configs"), Path::new("../../x")), Path::new("../x"));
        assert_eq!(c.optim, OptimConfig::default());
        assert_eq!(c.stage_index(99), 0);
        assert_eq!(c.stage_index(100), 1);
        assert_eq!(c.stage_index(10_000), 2);
        // Only the resolution change at 200 starts a fade.
        assert_eq!(c.switch_step(150), None);
        assert_eq!(c.alpha(150), 1.0);
        assert_eq!(c.switch_step(250), Some(200));
        assert_eq!(c.alpha(200), 0.0);
        assert_eq!(c.alpha(200 + 5_000), 0.5);
        assert_eq!(c.learning_rates(0), (2e-5, 2e-4));
        assert_eq!(c.learning_rates(200), (1e-4, 2e-4));
        assert_eq!(c.render_config(150).num_steps, 16);
        let with_termination =
            TrainConfig { render: RenderConfig { termination: 1e-3, ..c.render.clone() }, ..c.clone() };
        assert_eq!(with_termination.render_config(150).termination, 0.0);
        // The resolved config round-trips through TOML.
        let back = TrainConfig::from_toml(&c.to_toml().unwrap(), Path::new("")).unwrap();
        assert_eq!(back, c);
    }

    #[test]
    fn a_stored_config_names_repository_paths_relative_to_it() {
        let root = crate::paths::repo_root();
        let cfg = TrainConfig::load(&root.join("configs/chairs-campaign.toml")).unwrap();
        assert_eq!(cfg.data.path, root.join("data/chairs-64"));
        let stored = cfg.to_store();
        assert_eq!(stored.data.path, Path::new("data/chairs-64"));
        assert_eq!(stored.eval.probe.as_deref(), Some(Path::new("models/chairs-probe/probe.safetensors")));
        assert!(!stored.to_toml().unwrap().contains(&*root.to_string_lossy()));
        assert_eq!(stored.from_store(), cfg);
        // A folder outside the repository, and an older run's absolute path, stay as they are.
        let mut outside = cfg.clone();
        outside.data.path = "/elsewhere/chairs".into();
        assert_eq!(outside.to_store().data.path, Path::new("/elsewhere/chairs"));
        assert_eq!(cfg.from_store(), cfg);
    }

    #[test]
    fn errors_name_the_key() {
        let cases = [
            ("bogus = 1", "bogus"),
            ("[optim]\ng_lrr = 1.0", "g_lrr"),
            ("[optim]\ng_lr = \"fast\"", "g_lr"),
            ("[optim]\ng_lr = -1.0", "optim.g_lr"),
            ("[optim]\nbeta2 = 1.0", "optim.beta2"),
            ("[ema]\ndecay = 1.5", "ema.decay"),
            ("[schedule]\ncheckpoint_interval = 0", "schedule.checkpoint_interval"),
            ("[generator]\nhidden_dim = 0", "generator.hidden_dim"),
            ("[discriminator]\nchannels = [1, 2]", "discriminator.channels"),
            ("[camera]\nfov_deg = 200.0", "camera.fov_deg"),
            ("[loss]\nr1_interval = 0", "loss.r1_interval"),
            ("device = \"tpu\"", "device"),
            ("precision = \"float8\"", "precision"),
            ("[discriminator]\nminibatch_std_group = -1", "discriminator.minibatch_std_group"),
            ("[discriminator]\naugment_fill = 2.0", "discriminator.augment_fill"),
            ("[loss]\nlatent_weight = -1.0", "loss.latent_weight"),
            ("[generator]\nlatent_dim = 300\n[loss]\nlatent_weight = 1.0", "generator.latent_dim"),
            ("[loss]\ndiversity_weight = -2.0", "loss.diversity_weight"),
            ("[eval]\ninterval = 100", "eval.probe"),
            ("[eval]\nresolution = 4", "eval.resolution"),
            ("[eval]\nseeds = [0, 1, 0]", "eval.seeds"),
            ("[eval]\nnum = 1", "eval"),
            ("step = \"three-render\"", "step"),
            ("[generator]\ndeform_head_bias = \"random\"", "deform_head_bias"),
            ("[loss]\ndiversity_decay = -5", "loss.diversity_decay"),
            ("[occupancy]\nevery = 0", "occupancy.every"),
            ("[occupancy]\ncodes = 0", "occupancy.codes"),
            ("[occupancy]\nresolution = 33", "occupancy.resolution"),
            ("[occupancy]\nresolution = 8", "occupancy.resolution"),
            ("[occupancy]\nthreshold = -1.0", "occupancy.threshold"),
            ("[occupancy]\ndecay = 1.0", "occupancy.decay"),
            ("[occupancy]\nrefresh = 4", "refresh"),
        ];
        for (extra, key) in cases {
            let e = parse(extra).unwrap_err().to_string();
            assert!(e.contains(key), "{extra:?}: {e}");
        }
        // An empty [occupancy] table is the grid with its defaults; no table, no grid.
        assert_eq!(parse("[occupancy]").unwrap().occupancy, Some(OccupancyConfig::default()));
        assert_eq!(parse("").unwrap().occupancy, None);
        assert!(!parse("").unwrap().to_toml().unwrap().contains("occupancy"), "a config without it stores none");
        let bad_stage = MIN.replace("resolution = 64", "resolution = 48");
        let e = TrainConfig::from_toml(&bad_stage, Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].resolution") && e.contains("power of two"), "{e}");
        let bad_split = MIN.replace("batch_split = 2", "batch_split = 3");
        let e = TrainConfig::from_toml(&bad_split, Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].batch_split"), "{e}");
        // Stage 2 renders chunks of 4 / 2 = 2 images: pairs for the mode-seeking term; 4 / 4 is 1.
        parse("[loss]\ndiversity_weight = 1.0").unwrap();
        let odd = MIN.replace("batch_split = 2", "batch_split = 4") + "[loss]\ndiversity_weight = 1.0\n";
        let e = TrainConfig::from_toml(&odd, Path::new("")).unwrap_err().to_string();
        assert!(e.contains("loss.diversity_weight") && e.contains("stages[2].batch_split"), "{e}");
        // A stage's g_lr may be 0 (the discriminator trains alone), never negative; its d_lr not 0.
        let d_only = TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "g_lr = 0.0"), Path::new("")).unwrap();
        assert_eq!(d_only.learning_rates(200), (0.0, 2e-4));
        let e =
            TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "g_lr = -1e-4"), Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].g_lr") && e.contains("or 0"), "{e}");
        let e =
            TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "d_lr = 0.0"), Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].d_lr") && e.contains("positive"), "{e}");
        // A stage's pose weight holds from its first step on, [loss]'s before it; it is never
        // negative, and a stage without one stores none.
        let posed = TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "pose_weight = 28.6"), Path::new("")).unwrap();
        assert_eq!([199, 200].map(|s| posed.loss_at(s).pose_weight), [15.0, 28.6]);
        assert_eq!(LossConfig { pose_weight: 15.0, ..posed.loss_at(200) }, posed.loss);
        assert_eq!(posed.to_toml().unwrap().matches("pose_weight").count(), 2);
        let e = TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "pose_weight = -1.0"), Path::new(""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("stages[2].pose_weight"), "{e}");
        // The opacity term's weight likewise: [loss]'s (0, not written), a stage's from its
        // first step on; never negative; refused with the two-pass `regions` step.
        let opaque =
            TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "opacity_weight = 0.5"), Path::new("")).unwrap();
        assert_eq!([199, 200].map(|s| opaque.loss_at(s).opacity_weight), [0.0, 0.5]);
        assert_eq!(opaque.to_toml().unwrap().matches("opacity_weight").count(), 1);
        assert_eq!(posed.to_toml().unwrap().matches("opacity_weight").count(), 0);
        let everywhere = parse("[loss]\nopacity_weight = 0.25").unwrap();
        assert_eq!([0, 200].map(|s| everywhere.loss_at(s).opacity_weight), [0.25, 0.25]);
        assert_eq!(everywhere.to_toml().unwrap().matches("opacity_weight").count(), 1);
        let e = parse("[loss]\nopacity_weight = -0.5").unwrap_err().to_string();
        assert!(e.contains("loss.opacity_weight") && e.contains("-0.5"), "{e}");
        let e = TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "opacity_weight = -1.0"), Path::new(""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("stages[2].opacity_weight"), "{e}");
        TrainConfig::from_toml(&MIN.replace("g_lr = 1e-4", "regions = 2"), Path::new("")).unwrap();
        let banded = MIN.replace("g_lr = 1e-4", "regions = 2\nopacity_weight = 0.5");
        let e = TrainConfig::from_toml(&banded, Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].regions") && e.contains("stages[2].opacity_weight"), "{e}");
        let unordered = MIN.replace("from_step = 200", "from_step = 50");
        let e = TrainConfig::from_toml(&unordered, Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages[2].from_step"), "{e}");
        let e = TrainConfig::from_toml("[data]\npath = \"x\"", Path::new("")).unwrap_err().to_string();
        assert!(e.contains("stages"), "{e}");
    }
}
