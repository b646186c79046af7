//! Where the camera stands and what it renders: gdrf-edit's view flags every rendering
//! subcommand shares, and what the editing subcommands add (shared noise, the release's
//! preset and path). The flags are clap's under the `cli` feature.
use crate::camera::{release_ellipse, turntable};
use crate::checkpoint::Header;
use crate::field::generator::FieldOptions;
use crate::render::{GridChoice, GridConfig, Noise};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{CameraConfig, Error, RenderConfig, Result};
use tch::Kind;

/// The resolution and coarse samples per ray of the generator's last training step (its
/// checkpoint records them), else 128² and 36: what the commands render by default.
pub struct Learned {
    pub resolution: i64,
    pub samples: usize,
}

impl Learned {
    /// Where the generator of `header` learned.
    pub fn of(header: &Header) -> Self {
        Self {
            resolution: header.trained_resolution().unwrap_or(128),
            samples: header.trained_coarse_samples().map_or(36, |n| n as usize),
        }
    }
}

/// The view flags of every rendering subcommand: image size, samples per ray, where the
/// camera stands, truncation and the template ablations.
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct ViewFlags {
    /// Image size in pixels (square). Default: where the model learned (the resolution its
    /// checkpoint records), else 128.
    #[cfg_attr(feature = "cli", arg(long))]
    pub resolution: Option<i64>,
    /// Views on a turntable (yaw spread evenly over 360° from --yaw at --pitch); --orbit is
    /// the same.
    #[cfg_attr(feature = "cli", arg(long, visible_alias = "orbit", default_value_t = 1))]
    pub views: usize,
    /// Camera pitch in degrees from the +y axis (default: the camera's mean pitch).
    #[cfg_attr(feature = "cli", arg(long))]
    pub pitch: Option<f64>,
    /// Camera yaw in degrees of the first view.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0.0))]
    pub yaw: f64,
    /// Coarse samples per ray N (the importance pass adds N more), as in gdrf-invert and
    /// gdrf-train eval. Default: where the model learned, else 36; the authors' renders use
    /// 96. `--steps` is the same flag (its older name: steps are optimisation steps
    /// everywhere else).
    #[cfg_attr(feature = "cli", arg(long, alias = "steps"))]
    pub samples: Option<usize>,
    /// Truncation ψ toward the mean mapping output (1 = none; the authors render with 0.7).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 1.0))]
    pub psi: f64,
    /// Ablations (the paper's template figure): without the deformation Δx and/or the
    /// correction Δσ.
    #[cfg_attr(feature = "cli", arg(long))]
    pub no_deformation: bool,
    #[cfg_attr(feature = "cli", arg(long))]
    pub no_correction: bool,
}

impl ViewFlags {
    /// Refuses flags out of range, naming the flag.
    pub fn check(&self) -> Result<()> {
        if let Some(r) = self.resolution {
            check_resolution(r)?;
        }
        if self.views == 0 || self.views > 3600 {
            return Err(Error::Invalid(format!("--views {}: expected 1 to 3600", self.views)));
        }
        if let Some(p) = self.pitch {
            if !(0.0..=180.0).contains(&p) {
                return Err(Error::Invalid(format!("--pitch {p}: expected degrees from the +y axis in [0, 180]")));
            }
        }
        if !self.yaw.is_finite() || !(0.0..=4.0).contains(&self.psi) {
            return Err(Error::Invalid(format!(
                "--yaw {} / --psi {}: expected a finite yaw and ψ in [0, 4]",
                self.yaw, self.psi
            )));
        }
        Ok(())
    }

    /// Renders where `learned` says the model learned unless told otherwise.
    pub fn settle(&mut self, learned: &Learned) {
        self.resolution.get_or_insert(learned.resolution);
        self.samples.get_or_insert(learned.samples);
    }

    /// The image size, once [`Self::settle`]d.
    pub fn res(&self) -> i64 {
        self.resolution.expect("ViewFlags::settle sets the resolution")
    }

    /// The coarse samples per ray, once [`Self::settle`]d.
    pub fn samples(&self) -> usize {
        self.samples.expect("ViewFlags::settle sets the samples per ray")
    }

    /// The template ablations (--no-deformation, --no-correction).
    pub fn field(&self) -> FieldOptions {
        FieldOptions { no_deformation: self.no_deformation, no_correction: self.no_correction, ..Default::default() }
    }

    /// (pitch, yaw) in radians of each view on the turntable at --pitch from --yaw.
    pub fn turntable(&self, cam: &CameraConfig) -> Vec<(f64, f64)> {
        turntable(self.pitch.map(f64::to_radians).unwrap_or(cam.v_mean), self.yaw.to_radians(), self.views)
    }
}

/// The view flags with what the editing subcommands add: seeded noise shared by every image
/// of a view, the release's preset and its elliptical path.
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct ViewArgs {
    #[cfg_attr(feature = "cli", command(flatten))]
    pub flags: ViewFlags,
    /// Seed of the renderer noise (the stratified jitter and importance uniforms); every
    /// image of a view uses the same ones, so images differ only by what was edited.
    #[cfg_attr(feature = "cli", arg(long, default_value_t = 0))]
    pub noise_seed: u64,
    /// `release`: the authors' render script — N = 96, ψ = 0.7, last sample painted white
    /// (overrides --samples and --psi).
    #[cfg_attr(feature = "cli", arg(long, value_parser = ["release"]))]
    pub preset: Option<String>,
    /// Follow the release's elliptical camera path (pitch and yaw both swing by the camera's
    /// spread) over --views instead of a turntable.
    #[cfg_attr(feature = "cli", arg(long))]
    pub ellipse: bool,
}

impl ViewArgs {
    /// Applies `--preset`, and renders where the model `learned` unless told otherwise.
    pub fn resolved(mut self, learned: &Learned) -> Self {
        if self.preset.as_deref() == Some("release") {
            self.flags.samples = Some(96);
            self.flags.psi = 0.7;
        }
        self.flags.settle(learned);
        self
    }

    /// Refuses flags out of range, naming the flag ([`ViewFlags::check`]).
    pub fn check(&self) -> Result<()> {
        self.flags.check()
    }

    /// The image size, once [`Self::resolved`].
    pub fn res(&self) -> i64 {
        self.flags.res()
    }

    /// The coarse samples per ray, once [`Self::resolved`].
    pub fn samples(&self) -> usize {
        self.flags.samples()
    }

    /// The template ablations ([`ViewFlags::field`]).
    pub fn field(&self) -> FieldOptions {
        self.flags.field()
    }

    /// (pitch, yaw) in radians of each view: the turntable, or with --ellipse the release's
    /// path ([`release_ellipse`]).
    pub fn poses(&self, cam: &CameraConfig) -> Vec<(f64, f64)> {
        if self.ellipse {
            return release_ellipse(cam, self.flags.views);
        }
        self.flags.turntable(cam)
    }

    /// The renderer's config: the samples per ray, and with `--preset release` the last
    /// sample painted white.
    pub fn render_config(&self) -> RenderConfig {
        let force_last_white = self.preset.as_deref() == Some("release");
        RenderConfig { num_steps: self.samples(), force_last_white, ..Default::default() }
    }

    /// The jitter and importance uniforms of view `k`, shared by every image of that view.
    pub fn noise(&self, k: usize, rays: i64, device: tch::Device) -> Noise {
        let n = self.samples() as i64;
        let rng = |i: u64| StepRng::new(self.noise_seed, 2 * k as u64 + i, Purpose::EditNoise, Kind::Float, device);
        Noise { jitter: Some(rng(0).uniform(&[1, rays, n])), importance: Some(rng(1).uniform(&[1, rays, n])) }
    }
}

/// The occupancy grid of the subcommands that render one shape from many views (`render`,
/// `swap`): built once per shape from its density alone and reused by all its views.
#[cfg_attr(feature = "cli", derive(clap::Args))]
pub struct GridFlags {
    /// Occupancy grid of each shape: rays that meet no occupied cell cost one sample, the
    /// others are sampled only in the occupied cells along them. `auto` builds one, coarse
    /// to fine, where it pays for itself: from 100 000 samples per shape (views × pixels ×
    /// samples per ray; two 64² views at N = 12 are 196 608) a 32³ grid, from 1 000 000 (a
    /// 64² turntable of 11 views) a 64³ one. `off` (or 0) never builds one; a number is the
    /// cells per side. See `gdrf-edit bench` for time against error.
    #[cfg_attr(feature = "cli", arg(long, default_value = "auto"))]
    pub grid: GridChoice,
    /// Density above which a grid cell counts as occupied (no denser point lies in an empty cell).
    #[cfg_attr(feature = "cli", arg(long, default_value_t = GridConfig::default().threshold))]
    pub grid_threshold: f64,
    /// With a grid size: sample only the occupied cells along each ray (empty stretches
    /// between them count as empty space), not the whole interval from the first to the
    /// last. `auto` always does.
    #[cfg_attr(feature = "cli", arg(long))]
    pub grid_cells: bool,
}

impl GridFlags {
    /// The grid to build for a shape rendered in `samples` samples in all, or none;
    /// inconsistent flags are errors that name them ([`Self::check`]).
    pub fn resolve(&self, samples: f64) -> Result<Option<GridConfig>> {
        self.check()?;
        Ok(self.grid.resolve(samples, self.grid_threshold, self.grid_cells))
    }

    /// Refuses inconsistent flags, naming them: `--grid-cells` without a grid, a threshold
    /// out of range (whether or not `auto` builds a grid this time).
    pub fn check(&self) -> Result<()> {
        if self.grid_cells && self.grid == GridChoice::Off {
            return Err(Error::Invalid(
                "--grid-cells samples inside an occupancy grid: give its size with --grid (e.g. --grid 64)".into(),
            ));
        }
        GridConfig { threshold: self.grid_threshold, ..GridConfig::default() }.validate().map_err(|e| match e {
            Error::Invalid(why) => Error::Invalid(format!("--grid-threshold {}: {why}", self.grid_threshold)),
            other => other,
        })
    }
}

/// The image sizes every subcommand renders.
fn check_resolution(r: i64) -> Result<()> {
    if !(8..=4096).contains(&r) {
        return Err(Error::Invalid(format!("--resolution {r}: expected 8 to 4096 pixels")));
    }
    Ok(())
}
