//! Early ray termination (inference only): a placement's samples evaluated front to back,
//! each ray stopping once little light is left for what lies behind.
use super::importance::importance_uniforms;
use super::{Placement, Sampler, ShapeQuery};
use crate::camera::Rays;
use crate::render::composite::{transmittance, weights_from_density};
use crate::render::rays::{gather_samples, sort_depths};
use crate::render::rays::{Noise, RaySamples};
use crate::Result;
use tch::{Kind, Tensor};

/// The raw density of a sample that early termination did not evaluate: softplus gives
/// about 1e-35, no light.
pub const SKIPPED_SIGMA: f64 = -80.0;

/// Segments of the coarse samples evaluated one after the other under early termination.
const TERMINATION_SEGMENTS: i64 = 4;

/// A placement's coarse samples evaluated front to back in [`TERMINATION_SEGMENTS`]
/// segments, each ray stopping once its transmittance is below `threshold`; importance
/// samples (`importance` per ray, when given) only in front of where a ray stopped; a last
/// check on the merged samples evaluates whatever a ray skipped where the merged
/// transmittance is still above `threshold`, so the skipped samples carry at most that
/// much light. No gradients.
pub struct Terminating<'p> {
    pub coarse: &'p dyn Placement,
    pub importance: Option<i64>,
    pub threshold: f64,
    /// Length of the last interval.
    pub delta_final: f64,
}

impl Sampler for Terminating<'_> {
    fn sample(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        tch::no_grad(|| self.sample_front_to_back(query, rays, noise))
    }
}

impl Terminating<'_> {
    fn sample_front_to_back(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let z_c = &self.coarse.depths(rays, noise);
        let s = z_c.size();
        let (b, r, nc) = (s[0], s[1], s[2]);
        let (eps, df) = (self.threshold, self.delta_final);
        let device = z_c.device();
        let width = query.feature_width();
        let (mut sigma_c, mut feature_c) = (
            Tensor::full([b, r, nc, 1], SKIPPED_SIGMA, (z_c.kind(), device)),
            Tensor::zeros([b, r, nc, width], (z_c.kind(), device)),
        );
        let mut evaluated = 0;
        let mut done_c = Tensor::zeros([b, r, nc], (Kind::Bool, device));
        let mut active = Tensor::ones([b, r, 1], (Kind::Bool, device));
        let seg = (nc + TERMINATION_SEGMENTS - 1) / TERMINATION_SEGMENTS;
        let pos = Tensor::arange(nc, (Kind::Int64, device)).view([1, 1, nc]);
        let mut start = 0;
        while start < nc {
            let end = (start + seg).min(nc);
            let mask = pos.ge(start).logical_and(&pos.lt(end)).logical_and(&active);
            let (sg, ft, k) = query.at_masked(rays, z_c, &mask, width);
            let m4 = mask.unsqueeze(-1);
            sigma_c = sg.where_self(&m4, &sigma_c);
            feature_c = ft.where_self(&m4, &feature_c);
            done_c = done_c.logical_or(&mask);
            evaluated += k;
            if end < nc {
                let t = transmittance(&sigma_c, &z_c.unsqueeze(-1), df).squeeze_dim(-1).narrow(2, end, 1);
                active = active.logical_and(&t.ge(eps));
            }
            start = end;
        }
        let (mut z, mut sigma, mut features, mut done) = (z_c.shallow_clone(), sigma_c, vec![feature_c], done_c);
        if let Some(n) = self.importance {
            let w_c = weights_from_density(&sigma, &z_c.unsqueeze(-1), df);
            let z_f = self.coarse.importance_depths(&w_c, z_c, &importance_uniforms(noise, z_c, n));
            // A ray that stopped skips the importance samples behind its first skipped
            // coarse sample.
            let stop = z_c.where_self(&done.logical_not(), &z_c.full_like(f64::INFINITY)).amin(&[2i64][..], true);
            let mask = z_f.lt_tensor(&stop);
            let (sigma_f, feature_f, k) = query.at_masked(rays, &z_f, &mask, width);
            evaluated += k;
            z = Tensor::cat(&[z_f, z], 2);
            sigma = Tensor::cat(&[sigma_f, sigma], 2);
            features = vec![feature_f, features.remove(0)];
            done = Tensor::cat(&[mask, done], 2);
        }
        // The merged integration's light in front of the first skipped sample of each ray:
        // rays that still have more than `threshold` left are evaluated in full.
        let (zs, order) = sort_depths(&z);
        let skipped_sorted = done.logical_not().gather(2, &order, false);
        let t = transmittance(&gather_samples(&sigma, &order), &zs.unsqueeze(-1), df).squeeze_dim(-1);
        let left = t.where_self(&skipped_sorted, &t.zeros_like()).amax(&[2i64][..], true);
        let redo = done.logical_not().logical_and(&left.ge(eps));
        if bool::try_from(redo.any())? {
            let (sg, ft, k) = query.at_masked(rays, &z, &redo, width);
            evaluated += k;
            let m4 = redo.unsqueeze(-1);
            sigma = sg.where_self(&m4, &sigma);
            let joined = Tensor::cat(&features, 2);
            let joined = ft.where_self(&m4, &joined);
            let n_f = self.importance.unwrap_or(0);
            features = if n_f > 0 { vec![joined.narrow(2, 0, n_f), joined.narrow(2, n_f, nc)] } else { vec![joined] };
            done = done.logical_or(&redo);
        }
        let skipped = done.logical_not().gather(2, &order, false);
        Ok(RaySamples {
            sigma: gather_samples(&sigma, &order),
            features,
            z: zs,
            order,
            skipped: Some(skipped),
            evaluated,
        })
    }
}
