//! The settings of an inversion, and its defaults where the generator learned.
use crate::render::GridChoice;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};

/// Settings of the optimisation (stage 2).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InvertConfig {
    /// Adam steps at most (the paper: 2 000).
    pub steps: usize,
    /// Adam's learning rate (betas 0.9, 0.999).
    pub lr: f64,
    /// Side of the renders compared with the photo.
    pub resolution: i64,
    /// Samples per ray, coarse (the importance pass adds as many); `num_steps` in files
    /// written before it was named so.
    #[serde(alias = "num_steps")]
    pub samples: usize,
    pub mse_weight: f64,
    pub perceptual_weight: f64,
    /// Weight of mean (opacity − silhouette)² where the photo has a silhouette (alpha,
    /// mask or a uniform background); 0 = off, as in the paper.
    pub silhouette_weight: f64,
    /// Weight of mean (w_s − w_s⁰)².
    pub prior_shape: f64,
    /// Weight of mean (a − a⁰)² over the raw appearance (f, β).
    pub prior_appearance: f64,
    /// Fraction of rays whose gradients are taken each step (1 = all).
    pub ray_fraction: f64,
    /// Fraction of the steps, from the start, compared at half resolution.
    pub coarse_fraction: f64,
    /// Early stop after this many steps without improvement (0 = never).
    pub patience: usize,
    /// Relative improvement of the best loss that counts for `patience`.
    pub min_improvement: f64,
    /// Seed of the renderer noise and the ray subsets.
    pub seed: u64,
    /// The generator's hidden layers in bfloat16 (integration and the optimised features
    /// stay float32): faster on GPUs and on CPUs with bfloat16 instructions.
    pub bf16: bool,
    /// Optimise the camera pose (pitch, yaw) along with the features, from the given or
    /// predicted pose.
    pub refine_pose: bool,
    /// Adam's learning rate of the pose, in radians.
    pub pose_lr: f64,
    /// Cells per side of an occupancy grid of the current shape (0 = none): each ray is
    /// sampled only between its first and last occupied cell (or, with `grid_cells`, only
    /// in the occupied cells along it), and rays that meet none from the far end alone.
    /// The grid is rebuilt from the current w_s every `grid_refresh` steps, so the shape
    /// can grow by its dilation per rebuild.
    pub grid: i64,
    /// Sample only the grid's occupied cells along each ray, empty stretches between them
    /// counting as empty space ([`crate::render::GridConfig::cells_only`]).
    pub grid_cells: bool,
    /// Steps between rebuilds of the grid.
    pub grid_refresh: usize,
    /// The grid's density threshold: cells where softplus(σ) stays below it count as
    /// empty (see [`crate::render::GridConfig::threshold`]). Higher skips more and loses faint density.
    pub grid_threshold: f64,
}

impl Default for InvertConfig {
    fn default() -> Self {
        Self {
            steps: 50,
            lr: Self::PAPER_LR,
            resolution: 64,
            samples: 24,
            mse_weight: 1.0,
            perceptual_weight: 1.0,
            silhouette_weight: Self::SILHOUETTE_WEIGHT,
            prior_shape: 0.01,
            prior_appearance: 0.01,
            ray_fraction: 1.0,
            coarse_fraction: 0.0,
            patience: 0,
            min_improvement: 1e-3,
            seed: 0,
            bf16: false,
            refine_pose: false,
            pose_lr: 0.005,
            grid: 0,
            grid_cells: false,
            grid_refresh: 10,
            grid_threshold: 0.5,
        }
    }
}

impl InvertConfig {
    /// The paper's optimisation's learning rate (with all rays, for 2 000 steps): the
    /// reference of `gdrf-invert bench`. The defaults are that optimisation cut short:
    /// from the initialiser's start, its first 50 steps keep nearly all of the 2 000 steps'
    /// novel-view gain (docs/inversion.md), where a quarter of the rays at lr 0.03 (the
    /// defaults before an initialiser shipped) gained less per second.
    pub const PAPER_LR: f64 = 0.01;

    /// The silhouette term's default weight (docs/inversion.md, "The photo's silhouette").
    pub const SILHOUETTE_WEIGHT: f64 = 4.0;

    /// The defaults, rendered where the generator learned: the resolution and samples per
    /// ray of its last training step when its header records them (a model trained at 32²
    /// draws its best there, and a larger render only costs time), else 64² and 24 + 24.
    pub fn where_learned(header: &crate::checkpoint::Header) -> Self {
        let d = Self::default();
        Self {
            resolution: header.trained_resolution().unwrap_or(d.resolution),
            samples: header.trained_coarse_samples().map_or(d.samples, |n| n as usize),
            ..d
        }
    }

    /// With the occupancy grid `choice` resolved as gdrf-edit resolves it
    /// ([`GridChoice::resolve`]) for the samples one grid serves: `grid_refresh` steps of
    /// `resolution²` rays, each with `samples` coarse and as many importance samples.
    pub fn with_grid(self, choice: GridChoice, cells_only: bool) -> Self {
        let rays = (self.resolution * self.resolution) as f64;
        let samples = self.grid_refresh as f64 * rays * 2.0 * self.samples as f64;
        let g = choice.resolve(samples, self.grid_threshold, cells_only);
        Self { grid: g.map_or(0, |g| g.resolution), grid_cells: g.is_some_and(|g| g.cells_only), ..self }
    }

    pub fn validate(&self) -> Result<()> {
        let bad =
            |key: &str, v: String, want: &str| Err(Error::Config(format!("invert.{key} is {v}, expected {want}")));
        if self.lr <= 0.0 || !self.lr.is_finite() {
            return bad("lr", self.lr.to_string(), "a positive number");
        }
        if !(4..=1024).contains(&self.resolution) {
            return bad("resolution", self.resolution.to_string(), "4 to 1024");
        }
        if self.samples < 3 {
            return bad("samples", self.samples.to_string(), "at least 3");
        }
        for (k, v) in [
            ("mse_weight", self.mse_weight),
            ("perceptual_weight", self.perceptual_weight),
            ("silhouette_weight", self.silhouette_weight),
            ("prior_shape", self.prior_shape),
            ("prior_appearance", self.prior_appearance),
        ] {
            if v < 0.0 || !v.is_finite() {
                return bad(k, v.to_string(), "a weight ≥ 0");
            }
        }
        if !(self.ray_fraction > 0.0 && self.ray_fraction <= 1.0) {
            return bad("ray_fraction", self.ray_fraction.to_string(), "in (0, 1]");
        }
        if !(0.0..1.0).contains(&self.coarse_fraction) {
            return bad("coarse_fraction", self.coarse_fraction.to_string(), "in [0, 1)");
        }
        if !(self.pose_lr > 0.0 && self.pose_lr.is_finite()) {
            return bad("pose_lr", self.pose_lr.to_string(), "a positive number of radians");
        }
        if self.grid != 0 && !(4..=512).contains(&self.grid) {
            return bad("grid", self.grid.to_string(), "0 (none) or 4 to 512 cells per side");
        }
        if self.grid_refresh == 0 {
            return bad("grid_refresh", "0".into(), "at least 1 step");
        }
        if !(self.grid_threshold >= 0.0 && self.grid_threshold.is_finite()) {
            return bad("grid_threshold", self.grid_threshold.to_string(), "a finite density ≥ 0");
        }
        if self.min_improvement.is_nan() || self.min_improvement < 0.0 {
            return bad("min_improvement", self.min_improvement.to_string(), "≥ 0");
        }
        Ok(())
    }

    /// Side of the renders at `step`.
    pub fn resolution_at(&self, step: usize) -> i64 {
        if (step as f64) < self.coarse_fraction * self.steps as f64 {
            (self.resolution / 2).max(4)
        } else {
            self.resolution
        }
    }
}
