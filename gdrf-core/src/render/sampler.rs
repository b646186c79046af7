//! The sampler: where a bundle's samples go and what the shape side says there. Coarse
//! depths (stratified over the camera's interval, within a ray's occupied interval, or
//! only in its occupied cells), importance depths drawn from the coarse weights, Φ and
//! T_σ at both (density first, no colour), merged and sorted into one [`RaySamples`].
//! Optional shortcuts evaluate fewer samples: importance only where a ray carries weight
//! (`importance_skip`), thinned where it is concentrated (`importance_concentration`),
//! and early ray termination (`termination`).
use super::composite::{transmittance, weights_from_density};
use super::rays::{Noise, RaySamples};
use super::renderer::Renderer;
use super::samplers::{
    gather_samples, importance_depths, sort_depths, stratified_depths, stratified_in, OccupiedLength,
};
use crate::camera::Rays;
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// The coarse samples of a bundle: depths `(B, R, Nc)`, integration weights, raw
/// densities `(B, R, Nc, 1)` and features `(B, R, Nc, F)`.
struct Coarse<'a> {
    z: &'a Tensor,
    weights: &'a Tensor,
    sigma: &'a Tensor,
    feature: &'a Tensor,
}

/// The raw density of a sample that early termination did not evaluate: softplus gives
/// about 1e-35, no light.
pub const SKIPPED_SIGMA: f64 = -80.0;

/// Segments of the coarse samples evaluated one after the other under early termination.
const TERMINATION_SEGMENTS: i64 = 4;

impl<F: RadianceField> Renderer<'_, F> {
    /// The samples of rays `(B, R, 3)` and their density (the shape side): coarse stratified depths, importance depths drawn
    /// from the coarse weights, Φ and T_σ at both — no colour — merged and sorted.
    /// Missing noise is drawn from libtorch's generator.
    pub fn sample(&self, shape: &Film, rays: &Rays, noise: &Noise) -> Result<RaySamples> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        if shape.batch_size() != b {
            return Err(Error::Shape(format!("{} latents for a batch of {b} ray sets", shape.batch_size())));
        }
        let cfg = self.config;
        let n = cfg.num_steps as i64;
        let opts = (rays.dirs.kind(), rays.dirs.device());
        let gen = self.generator;
        let at = |z: &Tensor| {
            let s = z.size()[2];
            (rays.origins.unsqueeze(2) + rays.dirs.unsqueeze(2) * z.unsqueeze(-1)).reshape([b, r * s, 3])
        };

        let drawn;
        let jitter = match (&noise.jitter, cfg.jitter) {
            (_, false) => None,
            (Some(u), true) => Some(u),
            (None, true) => {
                drawn = Tensor::rand([b, r, n], opts);
                Some(&drawn)
            }
        };
        let occupied =
            rays.occupied.as_ref().map(|o| OccupiedLength::new(o, (self.camera.ray_start, self.camera.ray_end)));
        let z_c = match (&occupied, &rays.bounds) {
            (Some(o), _) => {
                if cfg.termination > 0.0 {
                    return Err(Error::Invalid(
                        "early termination does not combine with sampling only in occupied cells".into(),
                    ));
                }
                // As with bounds: the far-end sample ends every ray as the reference's do.
                let end = Tensor::full([b, r, 1], self.camera.ray_end, opts);
                Tensor::cat(&[o.stratified(n, jitter).to_kind(opts.0), end], 2)
            }
            (None, None) => stratified_depths((b, r), n, (self.camera.ray_start, self.camera.ray_end), jitter, opts),
            (None, Some(nf)) => {
                // The release's last interval is infinite (delta_final): whatever density a
                // ray meets at the camera's far end absorbs its remaining light. Rays with
                // their own bounds keep that sample, so that they end as the reference's do.
                let end = nf.narrow(2, 1, 1).clamp_min(self.camera.ray_end);
                Tensor::cat(&[stratified_in(nf, n, jitter), end], 2)
            }
        };
        let nc = z_c.size()[2];
        if cfg.termination > 0.0 {
            return tch::no_grad(|| self.sample_terminating(shape, rays, noise, &z_c));
        }
        let (sigma_c, feature_c) = gen.sigma_feature(&at(&z_c), shape, self.field);
        let sigma_c = sigma_c.view([b, r, nc, 1]);
        let feature_c = feature_c.view([b, r, nc, -1]);
        let mut evaluated = b * r * nc;
        let (z, sigma, features) = if cfg.hierarchical {
            // The coarse weights that place the importance samples (in occupied length
            // when the rays carry occupied bins).
            let w_c = tch::no_grad(|| {
                let sigma = match &occupied {
                    Some(o) => o.absorb_only_where_occupied(&sigma_c, &z_c),
                    None => sigma_c.shallow_clone(),
                };
                weights_from_density(&sigma, &z_c.unsqueeze(-1), cfg.delta_final)
            });
            let z_f = tch::no_grad(|| self.importance(&w_c, &z_c, noise, occupied.as_ref()));
            let (z_f, sigma_f, feature_f) = if cfg.importance_skip > 0.0 || cfg.importance_concentration > 0.0 {
                let (z_f, sigma_f, feature_f, k) = tch::no_grad(|| {
                    let coarse = Coarse { z: &z_c, weights: &w_c, sigma: &sigma_c, feature: &feature_c };
                    self.importance_where_needed(shape, rays, coarse, &z_f)
                });
                evaluated += k;
                (z_f, sigma_f, feature_f)
            } else {
                let (sigma_f, feature_f) = gen.sigma_feature(&at(&z_f), shape, self.field);
                evaluated += b * r * n;
                (z_f, sigma_f.view([b, r, n, 1]), feature_f.view([b, r, n, -1]))
            };
            (Tensor::cat(&[z_f, z_c], 2), Tensor::cat(&[sigma_f, sigma_c], 2), vec![feature_f, feature_c])
        } else {
            (z_c, sigma_c, vec![feature_c])
        };
        let (z, order) = sort_depths(&z);
        let sigma = gather_samples(&sigma, &order);
        let sigma = match &occupied {
            Some(o) => o.absorb_only_where_occupied(&sigma, &z),
            None => sigma,
        };
        Ok(RaySamples { sigma, features, z, order, skipped: None, evaluated })
    }

    /// The importance samples `z_f: (B, R, N)` evaluated only where they are needed.
    /// Rays whose coarse weights inside the ray (the ones the importance pdf reads: all but
    /// the first and last) sum to less than `importance_skip` get none: their importance
    /// samples duplicate their first N coarse samples — depth, density and feature — so
    /// that their merged integration is exactly their coarse one. Rays whose inside weight
    /// lies, to the fraction `importance_concentration`, in three neighbouring intervals
    /// get one sample in `importance_stride`: the middle one of each group of `stride`
    /// (with the bench's sorted uniforms, an evenly spread subset), the others copy it. A
    /// copy sits at zero distance from its original, so it absorbs nothing and carries no
    /// weight: the ray integrates as if only the kept samples were there. Returns depths,
    /// densities `(B, R, N, 1)`, features `(B, R, N, F)` and the queries spent.
    fn importance_where_needed(
        &self,
        shape: &Film,
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
        let need = total.ge(self.config.importance_skip);
        let j = Tensor::arange(n, (Kind::Int64, device)).view([1, 1, n]);
        let rep = if self.config.importance_concentration > 0.0 {
            let k = interior.size()[2];
            let width = k.min(3);
            let windows = (0..width)
                .map(|o| interior.narrow(2, o, k - width + 1))
                .reduce(|a, b| a + b)
                .expect("at least one window");
            let peak = windows.amax(&[2i64][..], true);
            let concentrated = peak.ge_tensor(&(&total * self.config.importance_concentration));
            let stride = self.config.importance_stride as i64;
            let thinned = (j.divide_scalar_mode(stride, "floor") * stride + stride / 2).clamp_max(n - 1);
            thinned.expand([z_f.size()[0], z_f.size()[1], n], false).where_self(&concentrated, &j)
        } else {
            j.expand_as(z_f)
        };
        let evaluate = rep.eq_tensor(&j).logical_and(&need);
        let (sigma, feature, k) = self.query_where(shape, rays, z_f, &evaluate, width);
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

    /// N importance depths `(B, R, N)` from the coarse weights `w_c: (B, R, Nc, 1)` at
    /// `z_c`; drawn in occupied length when `occupied` is given, so that none falls in
    /// an empty bin.
    fn importance(&self, w_c: &Tensor, z_c: &Tensor, noise: &Noise, occupied: Option<&OccupiedLength>) -> Tensor {
        let s = z_c.size();
        let (b, r, nc) = (s[0], s[1], s[2]);
        let n = self.config.num_steps as i64;
        let u = match &noise.importance {
            Some(u) => u.shallow_clone(),
            None => Tensor::rand([b, r, n], (z_c.kind(), z_c.device())),
        };
        let coords = match occupied {
            Some(o) => o.length_at(z_c).to_kind(z_c.kind()),
            None => z_c.shallow_clone(),
        };
        let f = importance_depths(&coords.reshape([b * r, nc]), &w_c.reshape([b * r, nc]), &u.reshape([b * r, n]))
            .view([b, r, n]);
        match occupied {
            Some(o) => o.depth_at(&f).to_kind(z_c.kind()),
            None => f,
        }
    }

    /// The field at the samples `mask: (B, R, S)` of depths `z: (B, R, S)` only: raw
    /// densities `(B, R, S, 1)` ([`SKIPPED_SIGMA`] elsewhere), features `(B, R, S, F)`
    /// (0 elsewhere) and the number of queries.
    fn query_where(&self, shape: &Film, rays: &Rays, z: &Tensor, mask: &Tensor, width: i64) -> (Tensor, Tensor, i64) {
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
            let (sg, ft) = self.generator.sigma_feature(&x.unsqueeze(0), &shape.narrow(i, 1), self.field);
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
    fn feature_width(&self, shape: &Film) -> i64 {
        let (kind, device) = self.generator.kind_device();
        let x = Tensor::zeros([1, 1, 3], (kind, device));
        self.generator.sigma_feature(&x, &shape.narrow(0, 1), self.field).1.size()[2]
    }

    /// The density pass with early ray termination (no gradients): coarse samples front to
    /// back in [`TERMINATION_SEGMENTS`] segments, each ray stopping once its transmittance
    /// is below `termination`; importance samples only in front of where a ray stopped; a
    /// last check on the merged samples evaluates whatever a ray skipped where the merged
    /// transmittance is still above `termination`, so the skipped samples carry at most
    /// that much light.
    fn sample_terminating(&self, shape: &Film, rays: &Rays, noise: &Noise, z_c: &Tensor) -> Result<RaySamples> {
        let s = z_c.size();
        let (b, r, nc) = (s[0], s[1], s[2]);
        let (eps, df) = (self.config.termination, self.config.delta_final);
        let device = z_c.device();
        let width = self.feature_width(shape);
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
            let (sg, ft, k) = self.query_where(shape, rays, z_c, &mask, width);
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
        if self.config.hierarchical {
            let w_c = weights_from_density(&sigma, &z_c.unsqueeze(-1), df);
            let z_f = self.importance(&w_c, z_c, noise, None);
            // A ray that stopped skips the importance samples behind its first skipped
            // coarse sample.
            let stop = z_c.where_self(&done.logical_not(), &z_c.full_like(f64::INFINITY)).amin(&[2i64][..], true);
            let mask = z_f.lt_tensor(&stop);
            let (sigma_f, feature_f, k) = self.query_where(shape, rays, &z_f, &mask, width);
            evaluated += k;
            z = Tensor::cat(&[z_f, z], 2);
            sigma = Tensor::cat(&[sigma_f, sigma], 2);
            features = vec![feature_f, features.remove(0)];
            done = Tensor::cat(&[mask, done], 2);
        }
        // The merged integration's light in front of the first skipped sample of each ray:
        // rays that still have more than `termination` left are evaluated in full.
        let (zs, order) = sort_depths(&z);
        let skipped_sorted = done.logical_not().gather(2, &order, false);
        let t = transmittance(&gather_samples(&sigma, &order), &zs.unsqueeze(-1), df).squeeze_dim(-1);
        let left = t.where_self(&skipped_sorted, &t.zeros_like()).amax(&[2i64][..], true);
        let redo = done.logical_not().logical_and(&left.ge(eps));
        if bool::try_from(redo.any())? {
            let (sg, ft, k) = self.query_where(shape, rays, &z, &redo, width);
            evaluated += k;
            let m4 = redo.unsqueeze(-1);
            sigma = sg.where_self(&m4, &sigma);
            let joined = Tensor::cat(&features, 2);
            let joined = ft.where_self(&m4, &joined);
            let n_f = if self.config.hierarchical { self.config.num_steps as i64 } else { 0 };
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
