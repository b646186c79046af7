//! The training-time occupancy grid (`[occupancy]`, [`OccupancyConfig`]): nerfacc's
//! estimator made one grid for every shape code. Density depends on the shape alone, so a
//! grid is the union of shape codes' grids ([`OccupancyGrid::build`]); it is refreshed from
//! the generator being trained every `every` steps, and a cell seen once fades out over
//! the following refreshes, as nerfacc's decayed maximum does. The renders of a step clip
//! each ray to it ([`crate::render::Setup::clip`]).
use super::config::OccupancyConfig;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::render::{camera_half_extent, GridConfig, Grids, OccupancyGrid, Renderer};
use crate::{CameraConfig, Error, Result};
use tch::{Kind, Tensor};

/// The name of the scores in a training checkpoint.
pub const SCORE_TENSOR: &str = "occupancy.score";

/// A grid shared by every shape code, and the scores it is read from.
#[derive(Debug)]
pub struct SharedGrid {
    /// `(G, G, G)` float32 in [0, 1]: 1 in the cells the last refresh saw occupied, times
    /// `decay` for each refresh since one last did.
    pub score: Tensor,
    /// The cells whose score is at least ½.
    pub grid: OccupancyGrid,
}

impl SharedGrid {
    /// The grid each code builds: the renderer's, at `cfg`'s size and threshold.
    pub fn grid_config(cfg: &OccupancyConfig) -> GridConfig {
        GridConfig { resolution: cfg.resolution, threshold: cfg.threshold, ..GridConfig::default() }
    }

    /// `previous` refreshed with the grids of `shapes` (one row per code), built with
    /// `renderer`'s field, precision and camera (no gradients); a fresh grid when there is
    /// no previous one.
    pub fn refresh<F: RadianceField>(
        previous: Option<&SharedGrid>,
        renderer: &Renderer<F>,
        shapes: &Film,
        cfg: &OccupancyConfig,
    ) -> Result<Self> {
        let grid_cfg = Self::grid_config(cfg);
        let (mut seen, mut evaluated) = (None::<Tensor>, 0);
        for i in 0..shapes.batch_size() {
            let g = Grids::new(renderer).occupancy_grid(&shapes.narrow(i, 1), grid_cfg)?;
            evaluated += g.evaluated;
            seen = Some(match seen {
                None => g.occupied,
                Some(s) => s.logical_or(&g.occupied),
            });
        }
        let seen = seen.ok_or_else(|| Error::Invalid("an occupancy refresh needs at least one shape".into()))?;
        let seen = seen.to_kind(Kind::Float);
        let score = match previous {
            Some(p) => (&p.score * cfg.decay).maximum(&seen),
            None => seen,
        };
        let mut shared = Self::from_score(score, renderer.camera, cfg)?;
        shared.grid.evaluated = evaluated;
        Ok(shared)
    }

    /// The grid of stored `score`s (a checkpoint's), which must be `cfg`'s `(G, G, G)` in
    /// [0, 1].
    pub fn from_score(score: Tensor, camera: &CameraConfig, cfg: &OccupancyConfig) -> Result<Self> {
        let g = cfg.resolution;
        if score.size() != [g, g, g] {
            return Err(Error::Shape(format!(
                "{SCORE_TENSOR} has shape {:?}, expected [{g}, {g}, {g}] (occupancy.resolution)",
                score.size()
            )));
        }
        let score = score.to_kind(Kind::Float);
        let inside = score.ge(0.0).logical_and(&score.le(1.0)).all();
        if !bool::try_from(inside).unwrap_or(false) {
            return Err(Error::Invalid(format!("{SCORE_TENSOR} holds values outside [0, 1]")));
        }
        let grid = OccupancyGrid {
            cfg: Self::grid_config(cfg),
            half: camera_half_extent(camera),
            occupied: score.ge(0.5),
            evaluated: 0,
        };
        Ok(Self { score, grid })
    }

    /// The fraction of the cube's cells that count as occupied.
    pub fn occupied_fraction(&self) -> f64 {
        f64::try_from(self.grid.occupied.to_kind(Kind::Float).mean(Kind::Double)).unwrap_or(f64::NAN)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn cfg() -> OccupancyConfig {
        OccupancyConfig { resolution: 16, decay: 0.5, ..OccupancyConfig::default() }
    }

    #[test]
    fn stored_scores_are_checked_and_read_at_one_half() {
        let cam = CameraConfig::default();
        let score = Tensor::zeros([16, 16, 16], (Kind::Float, Device::Cpu));
        let _ = score.get(3).get(4).get(5).fill_(0.5);
        let _ = score.get(3).get(4).get(6).fill_(0.4999);
        let g = SharedGrid::from_score(score.shallow_clone(), &cam, &cfg()).unwrap();
        assert_eq!(i64::try_from(g.grid.occupied.sum(Kind::Int64)).unwrap(), 1);
        assert!(bool::try_from(g.grid.occupied.get(3).get(4).get(5)).unwrap());
        assert_eq!(g.occupied_fraction(), 1.0 / 4096.0);
        let e = SharedGrid::from_score(Tensor::zeros([8, 8, 8], (Kind::Float, Device::Cpu)), &cam, &cfg()).unwrap_err();
        assert!(e.to_string().contains("occupancy.score has shape [8, 8, 8], expected [16, 16, 16]"), "{e}");
        let e = SharedGrid::from_score(score + 2.0, &cam, &cfg()).unwrap_err();
        assert!(e.to_string().contains("outside [0, 1]"), "{e}");
    }
}
