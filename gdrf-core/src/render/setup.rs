//! What every render of a field needs: the field, the camera, the render config and the
//! field options, and from them the samplers, the chunk loop, the view directions and the
//! integration options. The renderer and its staged path are both built on it.
use super::composite::CompositeOptions;
use super::occupancy::OccupancyGrid;
use super::rays::{Noise, RaySamples};
use super::sampler::{SamplerSpec, ShapeQuery};
use crate::camera::Rays;
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::{FieldOptions, Generator};
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::Result;
use tch::Tensor;

/// A radiance field (the generator by default) with a camera and sampling configuration.
pub struct Setup<'a, F: RadianceField = Generator> {
    pub generator: &'a F,
    pub camera: &'a CameraConfig,
    pub config: &'a RenderConfig,
    pub field: FieldOptions,
    /// A grid shared by every image (training's, [`crate::train::config::OccupancyConfig`]):
    /// each ray that meets one of its occupied cells and has no bounds of its own places its
    /// samples between its first and last one; a ray that meets none keeps the camera's
    /// whole interval, so that a grid which missed a shape never blanks it.
    pub clip: Option<&'a OccupancyGrid>,
}

// By hand: a derive would ask `F: Copy`, and only references to F are held.
impl<F: RadianceField> Clone for Setup<'_, F> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<F: RadianceField> Copy for Setup<'_, F> {}

impl<F: RadianceField> Setup<'_, F> {
    /// The samples of rays `(B, R, 3)` and their density (the shape side), placed by the
    /// samplers the config and the rays call for ([`SamplerSpec::sample`]). Missing noise
    /// is drawn from libtorch's generator.
    pub fn sample(&self, shape: &Film, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let spec = SamplerSpec::new(self.config, self.camera);
        match self.clip {
            Some(grid) if rays.bounds.is_none() && rays.occupied.is_none() => {
                spec.sample(&self.shape_query(shape), &clipped(rays, grid, spec.range), noise)
            }
            _ => spec.sample(&self.shape_query(shape), rays, noise),
        }
    }

    /// What samplers ask of the field: its shape side under `shape`.
    pub fn shape_query<'s>(&'s self, shape: &'s Film) -> ShapeQuery<'s> {
        ShapeQuery { field: self.generator, shape, options: self.field }
    }

    /// The config's integration, with the last sample painted white where the field does
    /// not paint the background.
    pub(crate) fn composite_options(&self) -> CompositeOptions {
        let o: CompositeOptions = self.config.into();
        CompositeOptions { force_last_white: o.force_last_white || !self.generator.paints_background(), ..o }
    }

    /// View directions fed to the colour branch for every sample: `(B, R·S, 3)`.
    pub(crate) fn sample_dirs(&self, dirs: &Tensor, s: i64) -> Tensor {
        let (b, r) = (dirs.size()[0], dirs.size()[1]);
        let d = if self.camera.lock_view_dependence {
            let locked = dirs.zeros_like();
            let _ = locked.narrow(2, 2, 1).fill_(-1.0);
            locked
        } else {
            dirs.shallow_clone()
        };
        d.unsqueeze(2).expand([b, r, s, 3], false).reshape([b, r * s, 3])
    }

    /// Ray chunk length for `per_ray` samples per ray over `b` images.
    pub(crate) fn chunk_rays(&self, per_ray: i64, b: i64, device: tch::Device) -> i64 {
        (self.config.chunk_points_on(device) / (per_ray * b).max(1)).max(1)
    }

    /// Runs `f(start, len)` over consecutive ray ranges of about `chunk_points` samples
    /// (`per_ray` samples per ray, all images of the batch), in ray order: the one chunk
    /// loop of every bounded-memory render.
    pub(crate) fn in_chunks<T>(
        &self,
        rays: &Rays,
        per_ray: i64,
        mut f: impl FnMut(i64, i64) -> Result<T>,
    ) -> Result<Vec<T>> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        let chunk = self.chunk_rays(per_ray, b, rays.dirs.device());
        let mut parts = Vec::new();
        let mut start = 0;
        while start < r {
            let len = chunk.min(r - start);
            parts.push(f(start, len)?);
            start += len;
        }
        Ok(parts)
    }
}

/// `rays` with bounds: their occupied interval in `grid` where they meet it, the camera's
/// `range` where they do not.
fn clipped(rays: &Rays, grid: &OccupancyGrid, range: (f64, f64)) -> Rays {
    let (near_far, hit) = tch::no_grad(|| grid.clip(rays, range.0, range.1));
    let whole = Tensor::from_slice(&[range.0, range.1]).to_kind(near_far.kind()).to_device(near_far.device());
    let bounds = near_far.where_self(&hit.unsqueeze(-1), &whole.view([1, 1, 2]));
    Rays {
        origins: rays.origins.shallow_clone(),
        dirs: rays.dirs.shallow_clone(),
        bounds: Some(bounds),
        occupied: None,
    }
}
