//! A per-instance occupancy grid, built from the shape side alone (Φ and T_σ at the cell
//! centres, no colour): which cells of the cube may hold density, and, along rays, the
//! interval between their first and last occupied cell or their occupied bins (what the
//! samplers of `in_grid` place samples in). The grid depends on the shape modulation
//! only, so a grid is built once per shape and reused for every view and every appearance.
use crate::camera::Rays;
use crate::config::CameraConfig;
use crate::field::generator::FieldOptions;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Lattice points mark their cells at this fraction of the threshold.
const LATTICE_MARGIN: f64 = 0.5;

/// How a grid is built.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct GridConfig {
    /// Cells per side.
    pub resolution: i64,
    /// The promise: no point whose density softplus(σ) exceeds this lies in an empty cell.
    /// Cells are marked from their centre and corners at half this density (density
    /// between lattice points can exceed what the lattice saw) and then dilated.
    pub threshold: f64,
    /// Occupied cells grow by this many cells in every direction, so that density between
    /// cell centres (and the correction field's Δσ there) is not lost.
    pub dilation: i64,
    /// Place samples only in the occupied cells along each ray (bins of half a cell),
    /// empty stretches between them counting as empty space, instead of over the whole
    /// interval between a ray's first and last occupied cell.
    pub cells_only: bool,
    /// Build coarse to fine (the default): a grid of half the resolution first
    /// (recursively, down to [`COARSEST`]³), then the density only at the lattice points
    /// inside its occupied cells; each coarser level marks at half the finer one's
    /// threshold. A trained shape fills a few per cent of the cube, so in `gdrf-edit bench`
    /// a 128³ grid of the step-95 000 model cost 0.89 M queries instead of 4.2 M (a 64³ one
    /// 0.20 M instead of 0.54 M) and rendered the same images. The price: a feature that
    /// every coarser lattice misses entirely (thinner than its spacing, in a cell it sees as
    /// empty) is missed here too. `false` evaluates every lattice point.
    pub coarse_to_fine: bool,
}

/// The coarsest grid of a coarse-to-fine build.
pub const COARSEST: i64 = 16;

impl Default for GridConfig {
    fn default() -> Self {
        Self { resolution: 32, threshold: 0.5, dilation: 1, cells_only: false, coarse_to_fine: true }
    }
}

/// Whether and which occupancy grid a renderer builds for a shape: `auto` (the default of
/// gdrf-edit), `off`, or a number of cells per side.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GridChoice {
    Auto,
    Off,
    Cells(i64),
}

impl std::str::FromStr for GridChoice {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "auto" => Ok(Self::Auto),
            "off" | "0" => Ok(Self::Off),
            n => match n.parse::<i64>() {
                Ok(g) if (4..=512).contains(&g) => Ok(Self::Cells(g)),
                _ => {
                    Err(Error::Invalid(format!("grid '{s}': expected auto, off (or 0), or cells per side in 4..=512")))
                }
            },
        }
    }
}

/// Samples per shape (views × pixels × samples per ray) from which `auto` builds a 32³
/// grid, and a 64³ one: round numbers between the break-even points of two runs of
/// `gdrf-edit bench --resolutions 64` on the step-95 000 model (2-core CPU, bench seeds 0
/// and 1). A 32³ grid (built in 63–75 ms) broke even with no grid at 84 000–167 000
/// samples, a 64³ one (223–308 ms) with the 32³ one at 0.75–1.0 M. At the same samples per
/// ray, rendering in a grid's cells was 4.6 dB (32³) and 7 dB (64³) closer to the dense
/// reference there.
pub const AUTO_GRID_SAMPLES: [f64; 2] = [100_000.0, 1_000_000.0];

impl GridChoice {
    /// The grid to build for a shape rendered in `samples` samples in all (its views ×
    /// pixels × samples per ray), sampling only its occupied cells: `auto` builds one only
    /// where its cost is paid back ([`AUTO_GRID_SAMPLES`]); an explicit size always does,
    /// `cells_only` as asked.
    pub fn resolve(self, samples: f64, threshold: f64, cells_only: bool) -> Option<GridConfig> {
        let grid = |resolution, cells_only| GridConfig { resolution, threshold, cells_only, ..GridConfig::default() };
        match self {
            Self::Off => None,
            Self::Cells(g) => Some(grid(g, cells_only)),
            Self::Auto if samples >= AUTO_GRID_SAMPLES[1] => Some(grid(64, true)),
            Self::Auto if samples >= AUTO_GRID_SAMPLES[0] => Some(grid(32, true)),
            Self::Auto => None,
        }
    }
}

impl GridConfig {
    pub fn validate(&self) -> Result<()> {
        if !(4..=512).contains(&self.resolution) {
            return Err(Error::Invalid(format!("grid resolution {} outside 4..=512", self.resolution)));
        }
        if !(self.threshold >= 0.0 && self.threshold.is_finite()) || self.dilation < 0 {
            return Err(Error::Invalid(format!(
                "grid threshold {} and dilation {}: expected a finite threshold ≥ 0 and a dilation ≥ 0",
                self.threshold, self.dilation
            )));
        }
        Ok(())
    }
}

/// Occupied cells of the cube `[−half, half]³` for one shape.
#[derive(Debug)]
pub struct OccupancyGrid {
    pub cfg: GridConfig,
    pub half: f64,
    /// `(G, G, G)` bool, indexed `[x, y, z]`.
    pub occupied: Tensor,
    /// Density queries spent building it.
    pub evaluated: i64,
}

/// Half-size of a cube holding every sample of the camera's rays: a camera on the unit
/// sphere, samples at depths [ray_start, ray_end] within the square field of view's
/// corner angle (|x|² = 1 + t² − 2t·cos θ is convex in t, so the ends bound it).
pub fn camera_half_extent(camera: &CameraConfig) -> f64 {
    let corner = (2f64.sqrt() * (camera.fov_deg.to_radians() / 2.0).tan()).atan();
    [camera.ray_start, camera.ray_end]
        .iter()
        .map(|t| (1.0 + t * t - 2.0 * t * corner.cos()).max(0.0).sqrt())
        .fold(0.0, f64::max)
}

impl OccupancyGrid {
    /// Builds the grid of shape modulation `shape` (one image) over the cube that holds
    /// every sample of `camera`'s rays.
    pub fn build<F: RadianceField>(
        generator: &F,
        shape: &Film,
        field: FieldOptions,
        camera: &CameraConfig,
        cfg: GridConfig,
        chunk: i64,
    ) -> Result<Self> {
        cfg.validate()?;
        if shape.batch_size() != 1 {
            return Err(Error::Shape(format!("an occupancy grid is built for one shape, got {}", shape.batch_size())));
        }
        let g = cfg.resolution;
        let half = camera_half_extent(camera);
        let (kind, device) = generator.kind_device();
        let cell = 2.0 * half / g as f64;
        // Density at the (G+1)³ cell corners and the G³ cell centres: a cell is occupied
        // when any of its 9 points is, so that a surface crossing a cell is seen from both
        // sides of it.
        let lattice = |n: i64, offset: f64| {
            let c = (Tensor::arange(n, (kind, device)) + offset) * cell - half;
            let axis = |shape: [i64; 3]| c.view(shape).expand([n, n, n], false);
            Tensor::stack(&[axis([n, 1, 1]), axis([1, n, 1]), axis([1, 1, n])], 3).reshape([1, n * n * n, 3])
        };
        // Coarse to fine: only the lattice points in the coarser grid's occupied cells. It
        // is dilated by at least one cell, so a point on a cell face is seen from both
        // sides, and it marks at half the threshold: its lattice points lie twice as far
        // apart, so density between them can rise further above what they saw.
        let coarse = if cfg.coarse_to_fine && g % 2 == 0 && g / 2 >= COARSEST {
            let c =
                GridConfig { resolution: g / 2, dilation: cfg.dilation.max(1), threshold: 0.5 * cfg.threshold, ..cfg };
            Some(Self::build(generator, shape, field, camera, c, chunk)?)
        } else {
            None
        };
        let mut evaluated = coarse.as_ref().map_or(0, |c| c.evaluated);
        let mut dense = |x: Tensor| -> Tensor {
            let n = x.size()[1];
            let (x, at) = match &coarse {
                Some(c) => {
                    let at = c.contains(&x).view([-1]).nonzero().view([-1]);
                    (x.index_select(1, &at), Some(at))
                }
                None => (x, None),
            };
            let m = x.size()[1];
            evaluated += m;
            let parts: Vec<Tensor> = (0..m)
                .step_by(chunk.max(1) as usize)
                .map(|start| {
                    let len = chunk.min(m - start);
                    let s = generator
                        .sigma_feature(&x.narrow(1, start, len), shape, field)
                        .0
                        .to_kind(Kind::Float)
                        .softplus();
                    // NaN densities count as occupied: the renderer then evaluates them as
                    // the reference would.
                    s.gt(cfg.threshold * LATTICE_MARGIN).logical_or(&s.isnan())
                })
                .collect();
            let marked = if parts.is_empty() {
                Tensor::zeros([1, 0], (Kind::Float, device))
            } else {
                Tensor::cat(&parts, 1).to_kind(Kind::Float).view([1, m])
            };
            match at {
                Some(at) => Tensor::zeros([1, n], (Kind::Float, device)).index_copy(1, &at, &marked),
                None => marked,
            }
        };
        let (corners, centres) = tch::no_grad(|| (dense(lattice(g + 1, 0.0)), dense(lattice(g, 0.5))));
        let corners = corners.view([1, 1, g + 1, g + 1, g + 1]).max_pool3d([2; 3], [1; 3], [0; 3], [1; 3], false);
        let occ = corners.maximum(&centres.view([1, 1, g, g, g]));
        let k = cfg.dilation;
        let occ = if k > 0 { occ.max_pool3d([2 * k + 1; 3], [1; 3], [k; 3], [1; 3], false) } else { occ };
        Ok(Self { cfg, half, occupied: occ.view([g, g, g]).gt(0.5), evaluated })
    }

    /// Whether the cells holding `x: (…, 3)` are occupied; points outside the cube count as
    /// occupied (the grid knows nothing there).
    pub fn contains(&self, x: &Tensor) -> Tensor {
        let g = self.cfg.resolution;
        let cell = ((x.to_kind(Kind::Float) + self.half) * (g as f64 / (2.0 * self.half))).floor();
        let inside = cell.ge(0.0).logical_and(&cell.lt(g as f64)).all_dim(-1, false);
        let idx = cell.clamp(0.0, (g - 1) as f64).to_kind(Kind::Int64);
        let flat = idx.select(-1, 0) * (g * g) + idx.select(-1, 1) * g + idx.select(-1, 2);
        let occ = self
            .occupied
            .to_device(x.device())
            .view([-1])
            .index_select(0, &flat.view([-1]))
            .view(flat.size().as_slice());
        occ.logical_or(&inside.logical_not())
    }

    /// Whether the P points `(B, R, P)` that walk each ray from `start` to `end` in equal
    /// steps of at most half a cell lie in occupied cells (a ray cannot cross a cell
    /// unseen), and that step.
    fn walk(&self, rays: &Rays, start: f64, end: f64) -> (Tensor, f64) {
        let cell = 2.0 * self.half / self.cfg.resolution as f64;
        let p = (((end - start) / (0.5 * cell)).ceil() as i64 + 1).max(2);
        let (kind, device) = (rays.dirs.kind(), rays.dirs.device());
        let t = Tensor::linspace(start, end, p, (kind, device));
        let x = rays.origins.unsqueeze(2) + rays.dirs.unsqueeze(2) * t.view([1, 1, p, 1]);
        (self.contains(&x), (end - start) / (p - 1) as f64)
    }

    /// Each ray's interval `(B, R, 2)` between its first and last occupied cell (widened
    /// by one step of [`Self::walk`], within [start, end]) and whether it meets any `(B, R)`.
    pub fn clip(&self, rays: &Rays, start: f64, end: f64) -> (Tensor, Tensor) {
        let (occ, step) = self.walk(rays, start, end);
        let m = occ.size()[2];
        let hit = occ.any_dim(2, false);
        let ramp = Tensor::arange(m, (Kind::Int64, occ.device())).view([1, 1, m]);
        let first = ramp.where_scalarother(&occ, m).amin(&[2i64][..], false);
        let last = ramp.where_scalarother(&occ, -1).amax(&[2i64][..], false);
        let kind = rays.dirs.kind();
        let near = (first.to_kind(kind) * step + start - step).clamp(start, end);
        let far = (last.to_kind(kind) * step + start + step).clamp(start, end);
        (Tensor::stack(&[near, far], 2), hit)
    }

    /// The occupancy `(B, R, M)` of the M bins between the points of [`Self::walk`] (a bin
    /// is occupied when either of its ends lies in an occupied cell) and whether a ray
    /// meets any `(B, R)`.
    pub fn bins(&self, rays: &Rays, start: f64, end: f64) -> (Tensor, Tensor) {
        let (edges, _) = self.walk(rays, start, end);
        let m = edges.size()[2] - 1;
        let occ = edges.narrow(2, 0, m).logical_or(&edges.narrow(2, 1, m));
        let hit = occ.any_dim(2, false);
        (occ.to_kind(Kind::Float), hit)
    }
}
