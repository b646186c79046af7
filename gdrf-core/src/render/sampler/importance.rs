//! Importance (PDF) samples: N more depths per ray drawn from its coarse weights, as the
//! release draws them, evaluated only where the [`ImportancePolicy`] says they are needed.
use super::{merge, Placement, Sampler, ShapeQuery};
use crate::camera::Rays;
use crate::config::RenderConfig;
use crate::render::composite::weights_from_density;
use crate::render::rays::gather_samples;
use crate::render::rays::{Noise, RaySamples};
use crate::Result;
use tch::{Kind, Tensor};

/// A placement's coarse samples and `samples` importance samples drawn from their weights.
pub struct Importance<'p> {
    pub coarse: &'p dyn Placement,
    pub samples: i64,
    pub policy: ImportancePolicy,
    /// Length of the last interval.
    pub delta_final: f64,
}

impl Sampler for Importance<'_> {
    fn sample(&self, query: &ShapeQuery, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let z_c = self.coarse.depths(rays, noise);
        let s = z_c.size();
        let (b, r, nc, n) = (s[0], s[1], s[2], self.samples);
        let (sigma_c, feature_c) = query.at(rays, &z_c);
        let mut evaluated = b * r * nc;
        // The coarse weights that place the importance samples (in occupied length when
        // the placement skips empty space).
        let w_c = tch::no_grad(|| {
            weights_from_density(&self.coarse.absorb(&sigma_c, &z_c), &z_c.unsqueeze(-1), self.delta_final)
        });
        let z_f = tch::no_grad(|| {
            let u = importance_uniforms(noise, &z_c, n);
            self.coarse.importance_depths(&w_c, &z_c, &u)
        });
        let (z_f, sigma_f, feature_f) = if self.policy.is_off() {
            let (sigma_f, feature_f) = query.at(rays, &z_f);
            evaluated += b * r * n;
            (z_f, sigma_f, feature_f)
        } else {
            let (z_f, sigma_f, feature_f, k) = tch::no_grad(|| {
                let coarse = Coarse { z: &z_c, weights: &w_c, sigma: &sigma_c, feature: &feature_c };
                self.policy.evaluate(query, rays, coarse, &z_f)
            });
            evaluated += k;
            (z_f, sigma_f, feature_f)
        };
        Ok(merge(self.coarse, vec![(z_f, sigma_f, feature_f), (z_c, sigma_c, feature_c)], evaluated))
    }
}

/// `noise.importance`, or fresh uniforms `(B, R, n)` for the rays of coarse depths `z_c`.
pub(super) fn importance_uniforms(noise: &Noise, z_c: &Tensor, n: i64) -> Tensor {
    match &noise.importance {
        Some(u) => u.shallow_clone(),
        None => Tensor::rand([z_c.size()[0], z_c.size()[1], n], (z_c.kind(), z_c.device())),
    }
}

/// Importance depths `(B, R, N)` from the coarse weights `w_c: (B, R, Nc, 1)` at depths
/// (or occupied lengths) `z_c: (B, R, Nc)` and uniforms `u: (B, R, N)`.
pub(super) fn pdf_depths(w_c: &Tensor, z_c: &Tensor, u: &Tensor) -> Tensor {
    let s = z_c.size();
    let (b, r, nc) = (s[0], s[1], s[2]);
    let n = u.size()[2];
    importance_depths(&z_c.reshape([b * r, nc]), &w_c.reshape([b * r, nc]), &u.reshape([b * r, n])).view([b, r, n])
}

/// The coarse samples of a bundle: depths `(B, R, Nc)`, integration weights, raw
/// densities `(B, R, Nc, 1)` and features `(B, R, Nc, F)`.
pub(super) struct Coarse<'a> {
    pub z: &'a Tensor,
    pub weights: &'a Tensor,
    pub sigma: &'a Tensor,
    pub feature: &'a Tensor,
}

/// Where a ray's importance samples are evaluated (inference only; the default evaluates
/// all of them). Rays whose coarse weights inside the ray (the ones the importance pdf
/// reads: all but the first and last) sum to less than `skip` get none: their importance
/// samples duplicate their first N coarse samples — depth, density and feature — so that
/// their merged integration is exactly their coarse one. Rays whose inside weight lies, to
/// the fraction `concentration`, in three neighbouring intervals get one sample in
/// `stride`: the middle one of each group of `stride` (with the bench's sorted uniforms,
/// an evenly spread subset), the others copy it. A copy sits at zero distance from its
/// original, so it absorbs nothing and carries no weight: the ray integrates as if only
/// the kept samples were there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImportancePolicy {
    /// `render.importance_skip`; 0 = off.
    pub skip: f64,
    /// `render.importance_concentration`; 0 = off.
    pub concentration: f64,
    /// `render.importance_stride`.
    pub stride: i64,
}

impl From<&RenderConfig> for ImportancePolicy {
    fn from(c: &RenderConfig) -> Self {
        Self { skip: c.importance_skip, concentration: c.importance_concentration, stride: c.importance_stride as i64 }
    }
}

impl ImportancePolicy {
    /// Whether every importance sample is evaluated.
    pub fn is_off(&self) -> bool {
        self.skip <= 0.0 && self.concentration <= 0.0
    }

    /// The importance samples `z_f: (B, R, N)` evaluated only where they are needed:
    /// depths, densities `(B, R, N, 1)`, features `(B, R, N, F)` and the queries spent.
    pub(super) fn evaluate(
        &self,
        query: &ShapeQuery,
        rays: &Rays,
        coarse: Coarse,
        z_f: &Tensor,
    ) -> (Tensor, Tensor, Tensor, i64) {
        let Coarse { z: z_c, weights: w_c, sigma: sigma_c, feature: feature_c } = coarse;
        let (nc, n, width) = (z_c.size()[2], z_f.size()[2], feature_c.size()[3]);
        let device = z_f.device();
        let w = w_c.squeeze_dim(-1);
        let interior = w.narrow(2, 1, nc - 2);
        let total = interior.sum_dim_intlist(2, true, w.kind()); // (B, R, 1)
        let need = total.ge(self.skip);
        let j = Tensor::arange(n, (Kind::Int64, device)).view([1, 1, n]);
        let rep = if self.concentration > 0.0 {
            let k = interior.size()[2];
            let width = k.min(3);
            let windows = (0..width)
                .map(|o| interior.narrow(2, o, k - width + 1))
                .reduce(|a, b| a + b)
                .expect("at least one window");
            let peak = windows.amax(&[2i64][..], true);
            let concentrated = peak.ge_tensor(&(&total * self.concentration));
            let stride = self.stride;
            let thinned = (j.divide_scalar_mode(stride, "floor") * stride + stride / 2).clamp_max(n - 1);
            thinned.expand([z_f.size()[0], z_f.size()[1], n], false).where_self(&concentrated, &j)
        } else {
            j.expand_as(z_f)
        };
        let evaluate = rep.eq_tensor(&j).logical_and(&need);
        let (sigma, feature, k) = query.at_masked(rays, z_f, &evaluate, width);
        let (z_f, sigma, feature) =
            (z_f.gather(2, &rep, false), gather_samples(&sigma, &rep), gather_samples(&feature, &rep));
        let need4 = need.unsqueeze(-1);
        (
            z_f.where_self(&need, &z_c.narrow(2, 0, n)),
            sigma.where_self(&need4, &sigma_c.narrow(2, 0, n).to_kind(sigma.kind())),
            feature.where_self(&need4, &feature_c.narrow(2, 0, n).to_kind(feature.kind())),
            k,
        )
    }
}

/// Importance depths as the release draws them. `z: (M, N)` sorted coarse depths,
/// `weights: (M, N)` coarse integration weights, `u: (M, S)` uniforms in [0, 1).
/// Weights get +1e-5, bins are the N − 1 midpoints, and the first and last weights are
/// dropped; returns `(M, S)`, not sorted, inside [mid_0, mid_{N−2}].
pub fn importance_depths(z: &Tensor, weights: &Tensor, u: &Tensor) -> Tensor {
    let n = z.size()[1];
    let w = weights + 1e-5;
    let mids = (z.narrow(1, 0, n - 1) + z.narrow(1, 1, n - 1)) * 0.5;
    sample_pdf(&mids, &w.narrow(1, 1, n - 2), u)
}

/// Inverse-CDF sampling of a piecewise-constant pdf. `bins: (M, K + 1)` edges,
/// `weights: (M, K)` (non-negative), `u: (M, S)` → `(M, S)`.
///
/// A bin whose cdf step is below 1e-5 is treated as width-less (denominator 1), as in
/// the release, so all-zero and one-hot weights stay finite.
pub fn sample_pdf(bins: &Tensor, weights: &Tensor, u: &Tensor) -> Tensor {
    let (m, k) = (weights.size()[0], weights.size()[1]);
    let s = u.size()[1];
    let w = weights + 1e-5;
    let pdf = &w / w.sum_dim_intlist(-1, true, w.kind());
    let cdf = Tensor::cat(&[pdf.narrow(1, 0, 1).zeros_like(), pdf.cumsum(-1, pdf.kind())], -1);
    let u = u.contiguous();
    let idx = u.searchsorted(&cdf, false, false, "left", None::<Tensor>);
    let below = (&idx - 1).clamp_min(0);
    let above = idx.clamp_max(k);
    let both = Tensor::stack(&[below, above], -1).view([m, 2 * s]);
    let cdf_g = cdf.gather(1, &both, false).view([m, s, 2]);
    let bins_g = bins.gather(1, &both, false).view([m, s, 2]);
    let c0 = cdf_g.select(2, 0);
    let denom = cdf_g.select(2, 1) - &c0;
    let denom = denom.ones_like().where_self(&denom.lt(1e-5), &denom);
    let b0 = bins_g.select(2, 0);
    &b0 + (u - c0) / denom * (bins_g.select(2, 1) - &b0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    fn all_finite(t: &Tensor) -> bool {
        bool::try_from(t.isfinite().all()).unwrap()
    }

    #[test]
    fn degenerate_weights_give_finite_samples_in_range() {
        let opts = (Kind::Float, Device::Cpu);
        let z = Tensor::linspace(0.6, 1.4, 16, opts).view([1, 16]).repeat([3, 1]);
        let w = Tensor::zeros([3, 16], opts);
        let _ = w.get(1).get(7).fill_(1.0); // one-hot
        let _ = w.get(2).fill_(1e30); // huge
        let u = Tensor::rand([3, 16], opts);
        let f = importance_depths(&z, &w, &u);
        assert!(all_finite(&f));
        assert!(f64::try_from(f.min()).unwrap() >= 0.6 && f64::try_from(f.max()).unwrap() <= 1.4);
        // One-hot mass concentrates the samples next to the heavy bin.
        let row = f.get(1);
        let near = row.ge(z.double_value(&[1, 6])).logical_and(&row.le(z.double_value(&[1, 8])));
        assert!(f64::try_from(near.to_kind(Kind::Float).mean(Kind::Float)).unwrap() > 0.9);
    }
}
