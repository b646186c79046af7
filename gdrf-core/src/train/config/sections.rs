//! The tables of a training config besides the model's, the camera's, the renderer's, the
//! losses' and the data's: the curriculum's stages, the optimisers, the EMA, the intervals,
//! the learning curve's evaluation, the previews, the guard, faults for tests, precision and
//! the kind of step.
use serde::{Deserialize, Serialize};

/// One stage of the curriculum, in force from `from_step` until the next stage starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stage {
    pub from_step: i64,
    /// Image side (a power of two from 8 to 512: the discriminator's input sizes).
    pub resolution: i64,
    /// Coarse samples per ray N (the importance pass adds N more).
    pub num_steps: usize,
    /// Images per step (the global batch).
    pub batch_size: i64,
    /// The generator step renders the batch in this many chunks, accumulating gradients
    /// (bounds memory; the gradient is the batch mean whatever the split).
    #[serde(default = "one")]
    pub batch_split: i64,
    /// Horizontal bands per image: above 1, the generator step runs the release's
    /// two-pass patch step (a no-grad render, then each band re-rendered with gradients
    /// at the same sample depths).
    #[serde(default = "one")]
    pub regions: i64,
    /// Learning rates of this stage (default: `[optim]`'s). `g_lr = 0` trains the
    /// discriminator alone: the generator step is skipped (the generator and its EMA stay
    /// as they are), which warms a fresh discriminator up against a generator loaded with
    /// `init_generator` before the game resumes.
    #[serde(default)]
    pub g_lr: Option<f64>,
    #[serde(default)]
    pub d_lr: Option<f64>,
    /// The pose terms' weight in this stage (default: `[loss] pose_weight`): a stage whose
    /// patches change the share of the batch the pose terms count (`loss.pose_min_scale`)
    /// can keep a counted image's weight without changing what earlier steps ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_weight: Option<f64>,
    /// The opacity term's weight in this stage (default: `[loss] opacity_weight`), so that a
    /// run can take it up from a stage on without changing what earlier steps ran.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub opacity_weight: Option<f64>,
    /// The scaled-patch step (`[stages.patch]`): the generator renders, and the
    /// discriminator judges, one `size²` patch of each `resolution²` image instead of the
    /// whole image, so that a step costs what a `size²` step costs. Absent: whole images.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub patch: Option<PatchConfig>,
}

impl Stage {
    /// The side of the images the discriminator judges, and so of what the generator
    /// renders for it: the patch's, or the image's.
    pub fn judged_size(&self) -> i64 {
        self.patch.as_ref().map_or(self.resolution, |p| p.size)
    }
}

/// EpiGRAF's patch sampling (Skorokhodov et al. 2022, `sample_patch_params_beta`): each
/// patch's scale s = P/R + (1 − P/R)·Beta(1, β), of the image's side, its top-left offset
/// uniform in [0, 1 − s]². β rises linearly from `beta_start` to `beta_end` over
/// `anneal_images` images from the step the scaled patches began at this resolution:
/// Beta(1, 0.001) is almost always 1 (whole images, resized to P²), so training starts from
/// what the P² stage learned and drifts toward native-resolution crops (mean s at β = 0.8
/// and P/R = ½: 0.78).
///
/// `native_share` (not EpiGRAF's) mixes in native-resolution patches (s = P/R): that share
/// of the draws is native, the rest follow the Beta law. A small β shows whole chairs, which
/// the pose terms need, but few patches at R's own detail; the mixture gives both.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PatchConfig {
    /// Side P of every patch, a power of two from 8 to the stage's resolution.
    pub size: i64,
    pub beta_start: f64,
    pub beta_end: f64,
    /// Images over which β anneals (0: `beta_end` from the start).
    pub anneal_images: i64,
    /// Share of patches drawn at scale P/R, in [0, 1) (0: EpiGRAF's law alone). Written
    /// only where set, so configs from before it read and write back unchanged.
    #[serde(skip_serializing_if = "crate::config::is_zero")]
    pub native_share: f64,
}

impl Default for PatchConfig {
    fn default() -> Self {
        // EpiGRAF anneals over 10 000 kimg from scratch; a generator that already learned at
        // P² starts from whole images it knows, and a CPU sees ~1 M images a day.
        Self { size: 32, beta_start: 0.001, beta_end: 0.8, anneal_images: 200_000, native_share: 0.0 }
    }
}

fn one() -> i64 {
    1
}

/// The training-time occupancy grid (`[occupancy]`), nerfacc's `OccupancyGrid` estimator
/// shared by all shape codes: every `every` steps, `codes` shape codes from the step's own
/// stream each build their `resolution`³ grid from the generator being trained (the
/// renderer's coarse-to-fine build, density above `threshold`, dilated by a cell); their
/// union refreshes a score per cell (1 where seen, times `decay` at each refresh that did
/// not see it), and a cell counts as occupied while its score is at least ½. Every ray of
/// the step's renders that meets an occupied cell places its coarse samples between its
/// first and last one; the others keep the camera's whole interval. The scores are part of
/// the training state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OccupancyConfig {
    /// Steps between refreshes (nerfacc: 16).
    pub every: i64,
    /// Shape codes per refresh.
    pub codes: i64,
    /// Cells per side (even, so that it builds coarse to fine).
    pub resolution: i64,
    /// Density softplus(σ) a cell must reach to be marked (the renderer's grid default).
    pub threshold: f64,
    /// A cell's score is multiplied by this at each refresh that does not see it (nerfacc's
    /// `ema_decay`): at 0.95 it stays occupied 14 refreshes after it was last seen.
    pub decay: f64,
}

impl Default for OccupancyConfig {
    fn default() -> Self {
        Self { every: 16, codes: 8, resolution: 32, threshold: 0.5, decay: 0.95 }
    }
}

/// Adam (the release's betas (0, 0.9)) and gradient clipping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OptimConfig {
    pub g_lr: f64,
    pub d_lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Global L2 norm each network's gradient is clipped to (0 = off).
    pub grad_clip: f64,
}

impl Default for OptimConfig {
    fn default() -> Self {
        Self { g_lr: 2e-5, d_lr: 2e-4, beta1: 0.0, beta2: 0.9, eps: 1e-8, grad_clip: 0.3 }
    }
}

/// Exponential moving average of the generator (what samples and exports use).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EmaConfig {
    pub decay: f64,
    /// torch_ema's warm-up: decay_n = min(decay, (1 + n)/(10 + n)) at the n-th update.
    pub warmup: bool,
}

impl Default for EmaConfig {
    fn default() -> Self {
        Self { decay: 0.999, warmup: true }
    }
}

/// Length of the run and how often it logs, checkpoints and renders samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ScheduleConfig {
    /// Training stops after this many steps.
    pub total_steps: i64,
    /// Steps over which the discriminator fades in a new resolution (α: 0 → 1).
    pub fade_steps: i64,
    /// A line of metrics.jsonl every this many steps.
    pub log_interval: i64,
    pub checkpoint_interval: i64,
    /// Checkpoints kept in RUN_DIR/checkpoints (older ones are removed).
    pub keep_checkpoints: usize,
    /// Sample, swap and template grids every this many steps (0 = never).
    pub sample_interval: i64,
}

impl Default for ScheduleConfig {
    fn default() -> Self {
        Self {
            total_steps: 110_000,
            fade_steps: 10_000,
            log_interval: 10,
            checkpoint_interval: 2000,
            keep_checkpoints: 3,
            sample_interval: 2000,
        }
    }
}

/// Scores of the EMA generator during training: `gdrf-train eval --seeds`'s code, whose
/// results make the run's learning curve ([`super::curve`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainEvalConfig {
    /// Every this many steps (0 = never). Needs `probe` and a procedural dataset in `[data]`.
    pub interval: i64,
    /// Generated images per evaluation.
    pub num: i64,
    /// Side of the swap matrix.
    pub swap: i64,
    /// Coarse samples per ray (as many fine); `steps` in configs written before it was
    /// named so.
    #[serde(alias = "steps")]
    pub samples: i64,
    /// Image side the generator is scored at (0 = the dataset's).
    pub resolution: i64,
    /// Evaluation seeds (each draws other codes, poses and random end; empty = the run's
    /// `seed`).
    pub seeds: Vec<u64>,
    /// The probe from `gdrf-train eval train-probe`, relative to the config file.
    pub probe: Option<std::path::PathBuf>,
}

impl Default for TrainEvalConfig {
    fn default() -> Self {
        Self { interval: 0, num: 200, swap: 4, samples: 12, resolution: 0, seeds: Vec::new(), probe: None }
    }
}

/// The preview grids written every `sample_interval` steps.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SampleConfig {
    /// Fixed codes in the sample grid (one column each).
    pub count: i64,
    /// Side of the swap matrix (rows share shape, columns share appearance).
    pub swap: i64,
    /// Image side of the previews (0 = the stage's resolution).
    pub resolution: i64,
    /// Yaw offsets (radians) from the mean pose, one grid row each.
    pub yaws: Vec<f64>,
}

impl Default for SampleConfig {
    fn default() -> Self {
        Self { count: 8, swap: 4, resolution: 0, yaws: vec![0.0, 0.5, 1.6] }
    }
}

/// What happens on non-finite losses or gradients.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GuardConfig {
    /// After this many consecutive steps with a skipped update, roll back to the last
    /// checkpoint with the learning rates multiplied by `lr_factor`.
    pub rollback_after: i64,
    pub lr_factor: f64,
    /// Give up (stop with an error) after this many rollbacks.
    pub max_rollbacks: i64,
}

impl Default for GuardConfig {
    fn default() -> Self {
        Self { rollback_after: 3, lr_factor: 0.5, max_rollbacks: 5 }
    }
}

/// Fault injection, to test the guard: the generator loss is multiplied by NaN at these
/// steps (the first time each is reached; a replay after a rollback runs clean), on the
/// ranks `inject_nonfinite_ranks` of a data-parallel run (empty: on every rank).
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DebugConfig {
    pub inject_nonfinite_steps: Vec<i64>,
    pub inject_nonfinite_ranks: Vec<usize>,
}

/// Network arithmetic. Integration always runs in float32 or wider.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Precision {
    #[default]
    Float32,
    /// The generator's hidden SIREN/FiLM layers in bfloat16 (float32 master weights,
    /// positions, first layers, outputs, integration and discriminator). Faster on CPUs
    /// with bfloat16 instructions (AVX512-BF16, AMX): 0.77 against 1.07 s per
    /// `chairs-tiny` step on a 2-core AMD EPYC with AVX512-BF16. CPUs without them fall
    /// back to libtorch's scalar matrix product, many times slower than float32 (a
    /// campaign step took about 15 s, against 2.1 s in float32, on a 2-core EPYC without
    /// AVX-512), and training warns.
    Bfloat16,
    /// `bfloat16` on a CPU with bfloat16 instructions, `float32` elsewhere (on a GPU too,
    /// where bfloat16's casts cost more kernel launches than they save; docs/training.md,
    /// "On a GPU").
    Auto,
}

impl Precision {
    /// What this precision is on `device`: `Auto` resolved, the others as they are.
    pub fn on(self, device: tch::Device) -> Precision {
        match self {
            Precision::Auto if device == tch::Device::Cpu && cpu_has_bf16() => Precision::Bfloat16,
            Precision::Auto => Precision::Float32,
            p => p,
        }
    }

    /// The dtype of the generator's hidden layers on `device` (None: the parameters' own).
    pub fn compute_kind(self, device: tch::Device) -> Option<tch::Kind> {
        match self.on(device) {
            Precision::Bfloat16 => Some(tch::Kind::BFloat16),
            _ => None,
        }
    }
}

/// Whether this CPU has bfloat16 matrix instructions, without which libtorch computes
/// bfloat16 matrix products in scalar code. AVX512-BF16 tells: every x86 CPU with AMX-BF16
/// (whose detection is not yet stable in Rust) has it too.
pub fn cpu_has_bf16() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx512bf16")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// How a training step renders the generator's images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum StepKind {
    /// The release's: the discriminator step renders fakes of its own without gradients,
    /// then the generator step renders its batch with gradients.
    #[default]
    TwoRender,
    /// The generator's batch is rendered once, with its graph: the discriminator steps on
    /// those images (detached), then the generator's loss goes through the updated
    /// discriminator on the same graph. It drops the no-grad render, about a quarter of a
    /// step, and needs every stage's `regions` to be 1.
    OneRender,
}
