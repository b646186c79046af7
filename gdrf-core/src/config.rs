//! Model, camera and rendering configuration. Defaults are the authors' release values
//! (CHAIR_128 where a value depends on the dataset).
use crate::error::require;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// `skip_serializing_if` for a weight or share added after configs were written: left at 0,
/// it is not written, so that configs and checkpoints from before the key keep their bytes.
pub(crate) fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// Sizes of the generator's networks, and which template they have.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeneratorConfig {
    /// Dimension of the latent codes z_s and z_a.
    pub latent_dim: usize,
    /// Width of every SIREN / FiLM layer (template and deformation).
    pub hidden_dim: usize,
    /// Width of the mapping networks' hidden layers (and of w_s).
    pub mapping_hidden_dim: usize,
    /// Plain SIREN layers in the template density trunk T_σ.
    pub trunk_layers: usize,
    /// FiLM layers in the colour branch T_c; the view direction enters the last one. Its
    /// key in configs and checkpoint headers is the release's `color_layers` (a generator's
    /// identity hashes the header, so the key stays as files have it).
    #[serde(rename = "color_layers")]
    pub colour_layers: usize,
    /// FiLM layers in the deformation/correction field Φ.
    pub deform_layers: usize,
    /// Scale of the density correction: Δσ = correct_scale · raw.
    pub correct_scale: f64,
    /// Scale of the displacement: Δx = deform_scale · raw.
    pub deform_scale: f64,
    /// Initial deformation head. 0 (the release): zero weights, so every code starts with
    /// the same shape and the adversarial game alone has to break that symmetry; f > 0:
    /// frequency_init(f) weights, U(±√(6/H)/f), for the Δx rows (the Δσ row stays zero),
    /// so shapes differ with the code from the first step (an option for small budgets,
    /// see docs/training.md).
    pub deform_head_frequency: f64,
    /// The deformation head's initial bias. `uniform` (the release): U(±1/√H), so that
    /// every code starts with the same Δx offset and Δσ = `correct_scale` · bias is added to
    /// every density, up to ±12.5 at H = 64 (an empty volume, where softplus′ stalls the
    /// density, or fog, by the draw); `zero`: no offset at any width, so every density
    /// starts as the template's.
    pub deform_head_bias: HeadBias,
    /// What colours each ray's last sample, the one behind the far plane that fills the
    /// background. `learned` (the release): the template's colour there, which training
    /// teaches to match the data's background. `random`: trained on real and generated
    /// images composited on random colours (`gdrf_core::train`), so the generator never
    /// paints its background: every render paints the last sample white. `corners`: the
    /// same on colours drawn from the RGB cube's eight corners, where fog shows.
    #[serde(skip_serializing_if = "Background::is_learned")]
    pub background: Background,
    /// The template T (`field::template`), recorded in every header written since the key
    /// exists. Headers written before have none and load as `siren`, the only template
    /// there was.
    #[serde(deserialize_with = "TemplateKind::deserialize_keyed")]
    pub template: TemplateKind,
}

/// Which template a generator has ([`GeneratorConfig::template`]); each variant is one
/// implementation of `field::template::Template`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TemplateKind {
    /// The release's: a SIREN density trunk of `trunk_layers` and a FiLM-SIREN colour
    /// branch of `color_layers`, all of width `hidden_dim`.
    #[default]
    Siren,
}

impl TemplateKind {
    /// Reads the `template` key; a name no template has (or a value that is no name) is an
    /// error naming the key, which serde's own message for an enum leaves out.
    fn deserialize_keyed<'de, D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::{value::StrDeserializer, Error as _};
        let keyed = |e: &dyn std::fmt::Display| D::Error::custom(format!("generator.template: {e}"));
        let name = String::deserialize(d).map_err(|e| keyed(&e))?;
        Self::deserialize(StrDeserializer::<serde::de::value::Error>::new(&name)).map_err(|e| keyed(&e))
    }
}

/// What colours the background ([`GeneratorConfig::background`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Background {
    /// The template field's colour at each ray's last sample (the release).
    #[default]
    Learned,
    /// Uniform random colours in training; white in every render.
    Random,
    /// Random colours from the RGB cube's eight corners (each channel 0 or 1) in training;
    /// white in every render. A uniform fog of opacity f and colour q turns a uniform
    /// colour c into (1 − f)·c + f·q, another uniform colour, which the discriminator cannot
    /// tell from a real background when c is uniform in the cube; it lies off the corners
    /// for every corner but q itself, so here it shows.
    Corners,
}

impl Background {
    /// Headers of generators with the release's background stay as they were written before
    /// the key existed (a generator's identity hashes its header).
    pub(crate) fn is_learned(&self) -> bool {
        *self == Background::Learned
    }

    /// The key's value as written in a config (its serde name).
    pub fn name(&self) -> String {
        serde_json::to_value(self).ok().and_then(|v| v.as_str().map(str::to_owned)).unwrap_or_default()
    }
}

/// How the deformation head's bias starts ([`GeneratorConfig::deform_head_bias`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HeadBias {
    /// U(±1/√H), PyTorch's nn.Linear default (the release).
    #[default]
    Uniform,
    /// Zero.
    Zero,
}

impl Default for GeneratorConfig {
    fn default() -> Self {
        Self {
            latent_dim: 256,
            hidden_dim: 256,
            mapping_hidden_dim: 256,
            trunk_layers: 5,
            colour_layers: 4,
            deform_layers: 4,
            correct_scale: 100.0,
            deform_scale: 1.0,
            deform_head_frequency: 0.0,
            deform_head_bias: HeadBias::Uniform,
            background: Background::Learned,
            template: TemplateKind::Siren,
        }
    }
}

impl GeneratorConfig {
    /// A generator small enough to build and render in milliseconds (8-d codes, 16 hidden
    /// units everywhere): the fixture of the tests.
    pub fn tiny() -> Self {
        Self { latent_dim: 8, hidden_dim: 16, mapping_hidden_dim: 16, ..Default::default() }
    }

    /// How many values the generator of this config holds (every weight and bias), without
    /// building it: a checkpoint whose header promises more than its file stores is refused
    /// before anything is allocated. Saturates instead of overflowing.
    pub fn parameter_count(&self) -> u128 {
        let n = |v: usize| v as u128;
        let linear = |a: u128, b: u128| a.saturating_mul(b).saturating_add(b);
        let (z, h, m) = (n(self.latent_dim), n(self.hidden_dim), n(self.mapping_hidden_dim));
        let mapping = |out: u128| [linear(z, m), linear(m, m), linear(m, m), linear(m, out)];
        // Layers of width H whose first takes `first` inputs and the rest H.
        let stack = |layers: usize, first: u128| match layers {
            0 => 0,
            l => linear(first, h).saturating_add(linear(h, h).saturating_mul(n(l) - 1)),
        };
        // The template's share (`field::template::build` builds what it counts).
        let template = match self.template {
            TemplateKind::Siren => {
                // The colour layers: H → H, except the last, which takes the view direction too.
                let colour = match self.colour_layers {
                    0 => 0,
                    l => linear(h, h).saturating_mul(n(l) - 1).saturating_add(linear(h + 3, h)),
                };
                [stack(self.trunk_layers, 3), linear(h, 1), colour, linear(h, 3)]
                    .into_iter()
                    .fold(0, u128::saturating_add)
            }
        };
        let parts = [template, stack(self.deform_layers, 3), linear(h, 4)];
        let modulations = [self.colour_layers, self.deform_layers].map(|l| n(l).saturating_mul(2).saturating_mul(h));
        parts.into_iter().chain(modulations.into_iter().flat_map(mapping)).fold(0, u128::saturating_add)
    }

    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("latent_dim", self.latent_dim),
            ("hidden_dim", self.hidden_dim),
            ("mapping_hidden_dim", self.mapping_hidden_dim),
            ("trunk_layers", self.trunk_layers),
            ("deform_layers", self.deform_layers),
        ];
        for (key, v) in positive {
            require(v >= 1, &format!("generator.{key}"), v, "at least 1")?;
        }
        require(
            self.deform_head_frequency >= 0.0 && self.deform_head_frequency.is_finite(),
            "generator.deform_head_frequency",
            self.deform_head_frequency,
            "0 (zero head, the release) or a positive frequency",
        )?;
        require(
            self.colour_layers >= 2,
            "generator.color_layers",
            self.colour_layers,
            "at least 2 (the view direction enters the last one)",
        )?;
        Ok(())
    }
}

/// How training poses are drawn (yaw θ from `h_*`, pitch φ from `v_*`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseDistribution {
    /// θ = h_mean + h_std·U(−1,1); φ = v_mean + v_std·U(−1,1).
    Uniform,
    /// θ = h_mean + h_std·N(0,1); φ likewise.
    Normal,
    /// Area-uniform on a sphere cap: v = v_mean/π + (v_std/π)·U(−1,1), φ = arccos(1−2v).
    SphericalUniform,
    /// Always the mean pose.
    Fixed,
}

/// Camera intrinsics, ray range and pose distribution.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// Full field of view in degrees (both axes, square images).
    pub fov_deg: f64,
    pub ray_start: f64,
    pub ray_end: f64,
    pub distribution: PoseDistribution,
    pub h_mean: f64,
    pub h_std: f64,
    pub v_mean: f64,
    pub v_std: f64,
    /// Feed the constant direction (0, 0, −1) to the colour branch.
    pub lock_view_dependence: bool,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self::chair()
    }
}

/// The cameras of the release's dataset configs, by name: what `--camera` takes in every
/// binary.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum CameraPreset {
    Chair,
    Car,
    Carla,
}

impl CameraPreset {
    pub fn camera(self) -> CameraConfig {
        match self {
            Self::Chair => CameraConfig::chair(),
            Self::Car => CameraConfig::car(),
            Self::Carla => CameraConfig::carla(),
        }
    }
}

impl std::str::FromStr for CameraPreset {
    type Err = Error;
    fn from_str(name: &str) -> Result<Self> {
        match name {
            "chair" => Ok(Self::Chair),
            "car" => Ok(Self::Car),
            "carla" => Ok(Self::Carla),
            other => Err(Error::Config(format!("camera preset '{other}': expected chair, car or carla"))),
        }
    }
}

impl CameraConfig {
    pub fn chair() -> Self {
        Self {
            fov_deg: 50.0,
            ray_start: 0.6,
            ray_end: 1.4,
            distribution: PoseDistribution::Uniform,
            h_mean: 0.0,
            h_std: std::f64::consts::PI,
            v_mean: 1.070796,
            v_std: 0.2618,
            lock_view_dependence: false,
        }
    }
    pub fn car() -> Self {
        Self { fov_deg: 30.0, ray_start: 0.75, ray_end: 1.25, v_mean: 1.2217, ..Self::chair() }
    }
    pub fn carla() -> Self {
        Self {
            fov_deg: 30.0,
            ray_start: 0.7,
            ray_end: 1.3,
            distribution: PoseDistribution::SphericalUniform,
            h_mean: std::f64::consts::FRAC_PI_2,
            h_std: std::f64::consts::PI,
            v_mean: 0.7418,
            v_std: 0.7418,
            lock_view_dependence: true,
        }
    }
    pub fn validate(&self) -> Result<()> {
        require(self.fov_deg > 0.0 && self.fov_deg < 180.0, "camera.fov_deg", self.fov_deg, "a value in (0, 180)")?;
        if !(self.ray_start >= 0.0 && self.ray_end > self.ray_start && self.ray_end.is_finite()) {
            return Err(Error::Config(format!(
                "camera ray range [{}, {}] is invalid, expected 0 <= ray_start < ray_end",
                self.ray_start, self.ray_end
            )));
        }
        Ok(())
    }
}

/// How rays are sampled and integrated. Under the `cli` feature its options are clap's
/// flags (`gdrf-edit render`), named as their config keys (`render.shade_min_weight` is
/// `--shade-min-weight`); the samples per ray come from the view flags, where the
/// checkpoint's header gives their default, and the integration's constants are no flags.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::Args))]
#[serde(default, deny_unknown_fields)]
pub struct RenderConfig {
    /// Coarse samples per ray N (the importance pass adds N more).
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().num_steps))]
    pub num_steps: usize,
    /// Add N importance samples drawn from the coarse weights.
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().hierarchical))]
    pub hierarchical: bool,
    /// Stratified jitter of the coarse depths (the release always jitters).
    #[cfg_attr(
        feature = "cli",
        arg(
            long = "no-jitter",
            action = clap::ArgAction::SetFalse,
            help = "Turn off the stratified jitter of the coarse samples (deterministic renders)"
        )
    )]
    pub jitter: bool,
    /// Composite on white: pixel += 1 − Σw.
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().white_back))]
    pub white_back: bool,
    /// Add the leftover transmittance to the last sample's weight.
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().last_back))]
    pub last_back: bool,
    /// Paint the last sample white before integration (the authors' render and FID scripts
    /// do).
    #[cfg_attr(feature = "cli", arg(long))]
    pub force_last_white: bool,
    /// Length of the last interval.
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().delta_final))]
    pub delta_final: f64,
    /// Colour widening ε: c' = c(1 + 2ε) − ε.
    #[cfg_attr(feature = "cli", arg(skip = RenderConfig::default().widen_eps))]
    pub widen_eps: f64,
    /// Samples evaluated at once (`render.chunk_points`; rays are rendered in chunks of this
    /// many samples); bounds memory. 0 = by device: 16 384 on the CPU (small chunks are
    /// faster there), 1 048 576 on a GPU (fewer kernel launches).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = RenderConfig::default().chunk_points))]
    pub chunk_points: usize,
    /// Density-first (`render.shade_min_weight`; `--min-weight` is the same flag): inference
    /// shades only samples whose weight exceeds this (the pixel moves by at most this ×
    /// samples per ray); 0 shades every sample (the reference
    /// sampler).
    #[cfg_attr(
        feature = "cli",
        arg(long, alias = "min-weight", default_value_t = RenderConfig::default().shade_min_weight)
    )]
    pub shade_min_weight: f64,
    /// Early ray termination (`render.termination`; inference only): coarse samples are
    /// evaluated front to back in four segments and a ray stops once its transmittance
    /// falls below this; samples behind are not evaluated unless the final integration
    /// finds more light left there than this, so no pixel moves by more than it. 0 = off.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = RenderConfig::default().termination))]
    pub termination: f64,
    /// Rays whose coarse samples find less than this much light inside the ray (their
    /// coarse weights but the first and last) get no importance samples: nothing there for
    /// them to resolve, their image is their coarse render (inference only). 0 = off: every
    /// ray gets N. Config key `render.importance_skip`; `--skip-empty` is the same flag.
    #[cfg_attr(
        feature = "cli",
        arg(long, alias = "skip-empty", default_value_t = RenderConfig::default().importance_skip)
    )]
    pub importance_skip: f64,
    /// Rays whose coarse weights lie, to at least this fraction, in three neighbouring
    /// intervals (a single sharp surface: a few samples resolve it) evaluate only one
    /// importance sample in `--importance-stride`; the samples dropped are copies of the kept
    /// ones at zero distance, which add no light (inference only). 0 = off. Config key
    /// `render.importance_concentration`; `--thin-concentrated` is the same flag.
    #[cfg_attr(
        feature = "cli",
        arg(long, alias = "thin-concentrated", default_value_t = RenderConfig::default().importance_concentration)
    )]
    pub importance_concentration: f64,
    /// One importance sample in this many is kept on concentrated rays
    /// (`render.importance_stride`; `--thin-stride` is the same flag).
    #[cfg_attr(
        feature = "cli",
        arg(long, alias = "thin-stride", default_value_t = RenderConfig::default().importance_stride)
    )]
    pub importance_stride: usize,
}

impl Default for RenderConfig {
    fn default() -> Self {
        Self {
            num_steps: 36,
            hierarchical: true,
            jitter: true,
            white_back: true,
            last_back: false,
            force_last_white: false,
            delta_final: 1e10,
            widen_eps: 1e-3,
            chunk_points: 0,
            shade_min_weight: 0.0,
            termination: 0.0,
            importance_skip: 0.0,
            importance_concentration: 0.0,
            importance_stride: 4,
        }
    }
}

impl RenderConfig {
    /// Samples per chunk on `device`: `chunk_points`, or for 0 the device's default
    /// (16 384 on the CPU, 1 048 576 on a GPU). On the CPU each activation tensor then
    /// stays small enough (16 MB at 16 384 × 256 floats) for the allocator to reuse instead
    /// of mapping fresh pages (40 % faster than 131 072 on a 2-core CPU); on a GPU every
    /// chunk costs kernel launches (a `chairs-tiny` training step on an H100 took 0.317 s in
    /// chunks of 16 384 and 0.108 s in one chunk). A training render keeps every chunk's
    /// graph until the backward pass, so there only `batch_split` bounds memory.
    pub fn chunk_points_on(&self, device: tch::Device) -> i64 {
        match (self.chunk_points, device) {
            (0, tch::Device::Cpu) => 1 << 14,
            (0, _) => 1 << 20,
            (n, _) => n as i64,
        }
    }

    /// Whether inference renders skip queries (density-first shading, early termination,
    /// skipped or thinned importance samples): they then take the staged path.
    pub fn skips_samples(&self) -> bool {
        self.shade_min_weight > 0.0
            || self.termination > 0.0
            || self.importance_skip > 0.0
            || self.importance_concentration > 0.0
    }

    pub fn validate(&self) -> Result<()> {
        require(
            !(self.num_steps < 3 && self.hierarchical),
            "render.num_steps",
            self.num_steps,
            "at least 3 with hierarchical sampling",
        )?;
        require(self.num_steps >= 1, "render.num_steps", self.num_steps, "at least 1")?;
        if self.last_back && self.white_back {
            return Err(Error::Config(
                "render.last_back and render.white_back both fill the leftover transmittance; enable at most one"
                    .into(),
            ));
        }
        require(
            self.importance_skip >= 0.0 && self.importance_skip < 1.0,
            "render.importance_skip",
            self.importance_skip,
            "a weight in [0, 1) (0 = off)",
        )?;
        require(
            self.importance_concentration >= 0.0 && self.importance_concentration <= 1.0,
            "render.importance_concentration",
            self.importance_concentration,
            "a fraction in [0, 1] (0 = off)",
        )?;
        require(self.importance_stride >= 1, "render.importance_stride", self.importance_stride, "at least 1")?;
        require(
            self.termination >= 0.0 && self.termination < 1.0,
            "render.termination",
            self.termination,
            "a transmittance in [0, 1) (0 = off)",
        )?;
        require(
            self.shade_min_weight >= 0.0 && self.shade_min_weight < 1.0,
            "render.shade_min_weight",
            self.shade_min_weight,
            "a weight in [0, 1) (0 = shade every sample)",
        )?;
        Ok(())
    }
    /// Samples per ray after merging coarse and fine samples.
    pub fn samples_per_ray(&self) -> usize {
        if self.hierarchical {
            2 * self.num_steps
        } else {
            self.num_steps
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_keys_are_rejected_by_name() {
        let err = toml::from_str::<CameraConfig>("fov = 30.0").unwrap_err().to_string();
        assert!(err.contains("fov"), "{err}");
    }

    #[test]
    fn chunk_points_zero_picks_the_device_default() {
        let auto = RenderConfig::default();
        assert_eq!(auto.chunk_points, 0);
        assert_eq!(auto.chunk_points_on(tch::Device::Cpu), 16_384);
        assert_eq!(auto.chunk_points_on(tch::Device::Cuda(0)), 1_048_576);
        let fixed = RenderConfig { chunk_points: 500, ..Default::default() };
        assert_eq!(fixed.chunk_points_on(tch::Device::Cpu), 500);
        assert_eq!(fixed.chunk_points_on(tch::Device::Cuda(1)), 500);
        assert!(auto.validate().is_ok());
    }

    #[test]
    fn presets_validate() {
        assert_eq!("car".parse::<CameraPreset>().unwrap().camera(), CameraConfig::car());
        assert!("plane".parse::<CameraPreset>().unwrap_err().to_string().contains("'plane'"));
        for c in [CameraConfig::chair(), CameraConfig::car(), CameraConfig::carla()] {
            c.validate().unwrap();
        }
        GeneratorConfig::default().validate().unwrap();
        RenderConfig::default().validate().unwrap();
        assert!(CameraConfig { fov_deg: 180.0, ..CameraConfig::chair() }.validate().is_err());
    }

    /// `[generator] template` is optional (SIREN), and a name no template has is an error
    /// naming the key.
    #[test]
    fn template_keys_default_to_siren_and_unknown_ones_are_named() {
        assert_eq!(toml::from_str::<GeneratorConfig>("").unwrap().template, TemplateKind::Siren);
        assert_eq!(toml::from_str::<GeneratorConfig>("template = \"siren\"").unwrap().template, TemplateKind::Siren);
        for bad in ["template = \"grid\"", "template = 1"] {
            let e = toml::from_str::<GeneratorConfig>(bad).unwrap_err().to_string();
            assert!(e.contains("generator.template"), "{bad}: {e}");
        }
    }

    #[test]
    fn background_names_are_the_config_values() {
        #[derive(Deserialize)]
        struct Key {
            background: Background,
        }
        for (b, name) in
            [(Background::Learned, "learned"), (Background::Random, "random"), (Background::Corners, "corners")]
        {
            assert_eq!(b.name(), name);
            assert_eq!(toml::from_str::<Key>(&format!("background = \"{name}\"")).unwrap().background, b);
        }
    }
}
