//! Samplers, as nerfstudio's `ray_samplers.py`: each one places a bundle's samples and asks
//! the shape side (Φ and T_σ, density first, no colour) about them, giving one
//! [`RaySamples`]. The coarse placements ([`Placement`]: [`Stratified`] over the camera's
//! interval, [`OccupiedBounds`] within each ray's occupied interval, [`OccupiedCells`] only
//! in its occupied cells) are samplers by themselves; [`Importance`] adds the release's
//! importance (PDF) samples to a placement, where its [`ImportancePolicy`] says they are
//! needed, and [`Terminating`] evaluates a placement front to back with early ray
//! termination. [`SamplerSpec`] is the render config read as which of them to build.
//!
//! A new sampler goes in a file of its own here, implementing [`Sampler`] (or
//! [`Placement`], for a new place to put the first samples), and [`SamplerSpec::sample`]
//! chooses it.
mod cells;
mod importance;
mod stratified;
mod termination;

pub use cells::{OccupiedCells, OccupiedLength};
pub use importance::{importance_depths, sample_pdf, Importance, ImportancePolicy};
pub use stratified::{stratified_depths, stratified_in, OccupiedBounds, Stratified};
pub use termination::{Terminating, SKIPPED_SIGMA};

use super::rays::{gather_samples, sort_depths, Noise, RaySamples};
use crate::camera::Rays;
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::FieldOptions;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Error, Result};
use tch::Tensor;

/// Places the samples of a bundle of rays `(B, R, 3)` and evaluates the shape side there.
/// Missing noise is drawn from libtorch's generator.
pub trait Sampler {
    fn sample(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples>;
}

/// Where the first (coarse) samples of each ray go, before anything is known of the
/// field; evaluated as they are, a placement is a sampler.
pub trait Placement {
    /// Sorted depths `(B, R, Nc)` of `rays`, jittered by `noise.jitter` (drawn when missing
    /// and the placement jitters).
    fn depths(&self, rays: &Rays, noise: &Noise) -> Tensor;

    /// Raw densities `sigma: (B, R, S, 1)` at sorted depths `z: (B, R, S)` as they are to
    /// be integrated (a placement that skips empty space rescales them so that it absorbs
    /// nothing).
    fn absorb(&self, sigma: &Tensor, _z: &Tensor) -> Tensor {
        sigma.shallow_clone()
    }

    /// Importance depths `(B, R, N)` drawn with uniforms `u: (B, R, N)` from the coarse
    /// weights `w_c: (B, R, Nc, 1)` at `z_c`.
    fn importance_depths(&self, w_c: &Tensor, z_c: &Tensor, u: &Tensor) -> Tensor {
        importance::pdf_depths(w_c, z_c, u)
    }

    /// Whether early termination may walk these samples front to back.
    fn terminates(&self) -> bool {
        true
    }
}

/// A placement evaluated as it is: the coarse samples alone.
impl<P: Placement + ?Sized> Sampler for P {
    fn sample(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let z_c = self.depths(rays, noise);
        let (sigma, feature) = query.at(rays, &z_c);
        let evaluated = z_c.numel() as i64;
        Ok(merge(self, vec![(z_c, sigma, feature)], evaluated))
    }
}

/// Sorts the passes `(depths (B, R, N), densities (B, R, N, 1), features (B, R, N, F))`,
/// in merge order, into one [`RaySamples`], with the densities as `placement` integrates them.
fn merge<P: Placement + ?Sized>(placement: &P, passes: Vec<(Tensor, Tensor, Tensor)>, evaluated: i64) -> RaySamples {
    let (z, sigma, features) = if passes.len() == 1 {
        let (z, sigma, feature) = passes.into_iter().next().expect("one pass");
        (z, sigma, vec![feature])
    } else {
        let z = Tensor::cat(&passes.iter().map(|p| p.0.shallow_clone()).collect::<Vec<_>>(), 2);
        let sigma = Tensor::cat(&passes.iter().map(|p| p.1.shallow_clone()).collect::<Vec<_>>(), 2);
        (z, sigma, passes.into_iter().map(|p| p.2).collect())
    };
    let (z, order) = sort_depths(&z);
    let sigma = placement.absorb(&gather_samples(&sigma, &order), &z);
    RaySamples { sigma, features, z, order, skipped: None, evaluated }
}

/// The shape side of a field for one batch of shape modulations: what samplers query.
pub struct ShapeQuery<'a> {
    pub field: &'a dyn RadianceField,
    /// One row per image of the bundle.
    pub shape: &'a Film,
    pub options: FieldOptions,
}

impl ShapeQuery<'_> {
    /// Raw densities `(B, R, S, 1)` and features `(B, R, S, F)` at depths `z: (B, R, S)`
    /// along `rays`.
    pub fn at(&self, rays: &Rays, z: &Tensor) -> (Tensor, Tensor) {
        let s = z.size();
        let (b, r, n) = (s[0], s[1], s[2]);
        let x = (rays.origins.unsqueeze(2) + rays.dirs.unsqueeze(2) * z.unsqueeze(-1)).reshape([b, r * n, 3]);
        let (sigma, feature) = self.field.sigma_feature(&x, self.shape, self.options);
        (sigma.view([b, r, n, 1]), feature.view([b, r, n, -1]))
    }

    /// The field at the samples `mask: (B, R, S)` of depths `z: (B, R, S)` only: raw
    /// densities `(B, R, S, 1)` ([`SKIPPED_SIGMA`] elsewhere), features `(B, R, S, F)`
    /// (0 elsewhere) and the number of queries.
    pub fn at_masked(&self, rays: &Rays, z: &Tensor, mask: &Tensor, width: i64) -> (Tensor, Tensor, i64) {
        let s = z.size();
        let (b, r, n) = (s[0], s[1], s[2]);
        let (kind, device) = (z.kind(), z.device());
        let mut sigma = Tensor::full([b, r * n, 1], SKIPPED_SIGMA, (kind, device));
        let mut feature = Tensor::zeros([b, r * n, width], (kind, device));
        let mut count = 0;
        for i in 0..b {
            let idx = mask.get(i).reshape([-1]).nonzero().view([-1]);
            let k = idx.size()[0];
            if k == 0 {
                continue;
            }
            let zi = z.get(i).reshape([-1]).index_select(0, &idx).unsqueeze(-1);
            let ray = idx.divide_scalar_mode(n, "floor");
            let x = rays.origins.get(i).index_select(0, &ray) + rays.dirs.get(i).index_select(0, &ray) * zi;
            let (sg, ft) = self.field.sigma_feature(&x.unsqueeze(0), &self.shape.narrow(i, 1), self.options);
            let row = Tensor::from(i).to_device(device);
            sigma = sigma.index_put(
                &[Some(row.shallow_clone()), Some(idx.shallow_clone())],
                &sg.get(0).to_kind(kind),
                false,
            );
            feature = feature.index_put(&[Some(row), Some(idx)], &ft.get(0).to_kind(kind), false);
            count += k;
        }
        (sigma.view([b, r, n, 1]), feature.view([b, r, n, width]), count)
    }

    /// Width of the colour feature (one query at the origin).
    pub fn feature_width(&self) -> i64 {
        let (kind, device) = self.field.kind_device();
        let x = Tensor::zeros([1, 1, 3], (kind, device));
        self.field.sigma_feature(&x, &self.shape.narrow(0, 1), self.options).1.size()[2]
    }
}

/// The render config read as a choice of samplers: how many samples, jittered or not,
/// importance samples and where they are needed, early termination.
#[derive(Debug, Clone, Copy)]
pub struct SamplerSpec {
    /// Coarse samples per ray N (importance sampling adds N more).
    pub samples: i64,
    pub hierarchical: bool,
    pub jitter: bool,
    pub importance: ImportancePolicy,
    /// Early ray termination's transmittance threshold; 0 = off.
    pub termination: f64,
    /// The camera's ray interval [start, end].
    pub range: (f64, f64),
    /// Length of the last interval.
    pub delta_final: f64,
}

impl SamplerSpec {
    pub fn new(config: &RenderConfig, camera: &CameraConfig) -> Self {
        Self {
            samples: config.num_steps as i64,
            hierarchical: config.hierarchical,
            jitter: config.jitter,
            importance: ImportancePolicy::from(config),
            termination: config.termination,
            range: (camera.ray_start, camera.ray_end),
            delta_final: config.delta_final,
        }
    }

    /// The samples of `rays` for `query`: the placement their own bounds or occupied bins
    /// call for ([`Rays::bounds`], [`Rays::occupied`]; else stratified over the camera's
    /// interval), then early termination or importance samples as the spec asks.
    pub fn sample(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let b = rays.dirs.size()[0];
        if query.shape.batch_size() != b {
            return Err(Error::Shape(format!("{} latents for a batch of {b} ray sets", query.shape.batch_size())));
        }
        let (samples, jitter, end) = (self.samples, self.jitter, self.range.1);
        let placement: Box<dyn Placement> = match (&rays.occupied, &rays.bounds) {
            (Some(o), _) => {
                Box::new(OccupiedCells { length: OccupiedLength::new(o, self.range), samples, jitter, end })
            }
            (None, None) => Box::new(Stratified { range: self.range, samples, jitter }),
            (None, Some(nf)) => Box::new(OccupiedBounds { bounds: nf.shallow_clone(), samples, jitter, end }),
        };
        if self.termination > 0.0 {
            if !placement.terminates() {
                return Err(Error::Invalid(
                    "early termination does not combine with sampling only in occupied cells".into(),
                ));
            }
            let sampler = Terminating {
                coarse: placement.as_ref(),
                importance: self.hierarchical.then_some(samples),
                threshold: self.termination,
                delta_final: self.delta_final,
            };
            return sampler.sample(query, rays, noise);
        }
        if self.hierarchical {
            let sampler = Importance {
                coarse: placement.as_ref(),
                samples,
                policy: self.importance,
                delta_final: self.delta_final,
            };
            return sampler.sample(query, rays, noise);
        }
        placement.sample(query, rays, noise)
    }
}

/// `noise.jitter`, or for `samples` per ray of `rays` fresh uniforms, when `jitter` is on.
fn jitter_noise(noise: &Noise, jitter: bool, rays: &Rays, samples: i64) -> Option<Tensor> {
    match (&noise.jitter, jitter) {
        (_, false) => None,
        (Some(u), true) => Some(u.shallow_clone()),
        (None, true) => {
            let (b, r) = (rays.dirs.size()[0], rays.num_rays());
            Some(Tensor::rand([b, r, samples], (rays.dirs.kind(), rays.dirs.device())))
        }
    }
}
