//! The GDRF renderer: coarse pass, importance pass, merge, integrate — for training
//! batches (with gradients), patches, and chunked inference in bounded memory.
use super::composite::{composite, transmittance, weights_from_density, CompositeOptions};
use super::rays::{assemble_image, DensitySamples, Image, Noise, RayColours, RenderedRays};
use super::samplers::{
    gather_samples, importance_depths, sort_depths, stratified_depths, stratified_in, OccupiedLength,
};
use crate::camera::{Poses, Rays};
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::{FieldOptions, Generator, Latents};
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

/// Renders a radiance field (the generator by default) with a camera and sampling
/// configuration.
pub struct Renderer<'a, F: RadianceField = Generator> {
    pub generator: &'a F,
    pub camera: &'a CameraConfig,
    pub config: &'a RenderConfig,
    pub field: FieldOptions,
}

impl<'a, F: RadianceField> Renderer<'a, F> {
    pub fn new(generator: &'a F, camera: &'a CameraConfig, config: &'a RenderConfig) -> Result<Self> {
        camera.validate()?;
        config.validate()?;
        Ok(Self { generator, camera, config, field: FieldOptions::default() })
    }

    pub(crate) fn composite_options(&self) -> CompositeOptions {
        self.config.into()
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

    /// The density pass (the shape side): coarse stratified depths, importance depths drawn
    /// from the coarse weights, Φ and T_σ at both — no colour — merged and sorted.
    /// Missing noise is drawn from libtorch's generator.
    pub fn density_pass(&self, shape: &Film, rays: &Rays, noise: &Noise) -> Result<DensitySamples> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        if shape.batch_size() != b {
            return Err(Error::Invalid(format!("{} latents for a batch of {b} ray sets", shape.batch_size())));
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
            return tch::no_grad(|| self.density_pass_terminating(shape, rays, noise, &z_c));
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
        Ok(DensitySamples { sigma, features, z, order, skipped: None, evaluated })
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
    fn density_pass_terminating(
        &self,
        shape: &Film,
        rays: &Rays,
        noise: &Noise,
        z_c: &Tensor,
    ) -> Result<DensitySamples> {
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
        Ok(DensitySamples {
            sigma: gather_samples(&sigma, &order),
            features,
            z: zs,
            order,
            skipped: Some(skipped),
            evaluated,
        })
    }

    /// Renders rays `(B, R, 3)` of the batch driven by `latents` (gradients flow where
    /// autograd is enabled): the density pass, then colour on every sample (the reference
    /// sampler). Missing noise is drawn from libtorch's generator.
    pub fn render_rays(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RenderedRays> {
        if latents.batch_size() != rays.dirs.size()[0] {
            return Err(Error::Invalid(format!(
                "{} latents for a batch of {} ray sets",
                latents.batch_size(),
                rays.dirs.size()[0]
            )));
        }
        let d = self.density_pass(&latents.shape, rays, noise)?;
        let rgb: Vec<Tensor> = d
            .features
            .iter()
            .map(|f| {
                let s = f.size();
                let (b, r, n) = (s[0], s[1], s[2]);
                let dirs = self.sample_dirs(&rays.dirs, n);
                self.generator.radiance(&f.reshape([b, r * n, -1]), &dirs, &latents.appearance).view([b, r, n, 3])
            })
            .collect();
        let rgb = gather_samples(&Tensor::cat(&rgb, 2), &d.order);
        let c = composite(&rgb, &d.sigma, &d.z.unsqueeze(-1), &self.composite_options());
        Ok(RenderedRays {
            pixel: c.pixel,
            depth: c.depth,
            opacity: c.opacity,
            z: d.z,
            weights: c.weights,
            origins: rays.origins.shallow_clone(),
            dirs: rays.dirs.shallow_clone(),
        })
    }

    /// Renders `res × res` images without gradients, `chunk_points` samples at a time, so
    /// any resolution fits in bounded memory.
    pub fn render_image(&self, latents: &Latents, poses: &Poses, res: i64, noise: &Noise) -> Result<Image> {
        Ok(self
            .render_image_with(latents, poses, res, noise, |_, lat, rays, noise| self.render_bundle(lat, rays, noise))?
            .0)
    }

    /// Renders `res × res` images without gradients one image at a time, each image's rays
    /// by `per_image(i, latents, rays, noise)`. Also returns the density and colour queries
    /// spent.
    pub(crate) fn render_image_with(
        &self,
        latents: &Latents,
        poses: &Poses,
        res: i64,
        noise: &Noise,
        per_image: impl Fn(usize, &Latents, &Rays, &Noise) -> Result<RayColours>,
    ) -> Result<(Image, (i64, i64))> {
        let rays = Rays::from_poses(poses, res, self.camera.fov_deg);
        let (b, r) = (poses.len(), res * res);
        let mut parts = Vec::new();
        tch::no_grad(|| -> Result<()> {
            for i in 0..b {
                let (lat, rays, noise) = (latents.narrow(i, 1), rays.narrow_batch(i, 1), noise.slice(i, 1, 0, r));
                parts.push(per_image(i as usize, &lat, &rays, &noise)?);
            }
            Ok(())
        })?;
        let evals = (parts.iter().map(|p| p.density_evals).sum(), parts.iter().map(|p| p.colour_evals).sum());
        let to_image = |f: &dyn Fn(&RayColours) -> &Tensor, c: i64| {
            Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 0).permute([0, 2, 1]).reshape([b, c, res, res])
        };
        let image = Image {
            rgb: to_image(&|p| &p.pixel, 3) * 2.0 - 1.0,
            depth: to_image(&|p| &p.depth, 1),
            opacity: to_image(&|p| &p.opacity, 1),
        };
        Ok((image, evals))
    }

    /// Renders rays `(B, R, 3)` without gradients in chunks: the staged path when the
    /// config skips queries ([`RenderConfig::skips_samples`]), else the reference sampler;
    /// with the queries spent.
    pub fn render_bundle(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RayColours> {
        if self.config.skips_samples() {
            return self.render_staged_chunked(latents, rays, noise);
        }
        let out = tch::no_grad(|| self.render_rays_chunked(latents, rays, noise))?;
        let evals = out.z.size()[0] * out.z.size()[1] * out.z.size()[2];
        Ok(RayColours {
            pixel: out.pixel,
            depth: out.depth,
            opacity: out.opacity,
            density_evals: evals,
            colour_evals: evals,
        })
    }

    /// Renders rays `(B, R, 3)` in chunks of about `chunk_points` samples (gradients flow
    /// where autograd is enabled); the result equals one [`Self::render_rays`] call.
    pub fn render_rays_chunked(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RenderedRays> {
        let b = rays.dirs.size()[0];
        self.in_chunks(rays, self.config.samples_per_ray() as i64, |start, len| {
            self.render_rays(latents, &rays.narrow(start, len), &noise.slice(0, b, start, len))
        })
    }

    /// Renders rays `(B, R, 3)` at the given sorted sample depths `z: (B, R, S)`, without
    /// placing samples: the field is evaluated at exactly those points and integrated.
    /// The two-pass patch step uses it to re-render with gradients the samples that a
    /// no-grad pass placed, so both passes see the same points.
    pub fn render_at_depths(&self, latents: &Latents, rays: &Rays, z: &Tensor) -> Result<RenderedRays> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        if z.dim() != 3 || z.size()[0] != b || z.size()[1] != r {
            return Err(Error::Invalid(format!("sample depths have shape {:?}, expected [{b}, {r}, S]", z.size())));
        }
        if latents.batch_size() != b {
            return Err(Error::Invalid(format!("{} latents for a batch of {b} ray sets", latents.batch_size())));
        }
        let s = z.size()[2];
        self.in_chunks(rays, s, |start, len| {
            let (rays, z) = (rays.narrow(start, len), z.narrow(1, start, len));
            let x = (rays.origins.unsqueeze(2) + rays.dirs.unsqueeze(2) * z.unsqueeze(-1)).reshape([b, len * s, 3]);
            let (sigma, feature) = self.generator.sigma_feature(&x, &latents.shape, self.field);
            let dirs = self.sample_dirs(&rays.dirs, s);
            let rgb = self.generator.radiance(&feature, &dirs, &latents.appearance).view([b, len, s, 3]);
            let c = composite(&rgb, &sigma.view([b, len, s, 1]), &z.unsqueeze(-1), &self.composite_options());
            Ok(RenderedRays {
                pixel: c.pixel,
                depth: c.depth,
                opacity: c.opacity,
                z: z.shallow_clone(),
                weights: c.weights,
                origins: rays.origins,
                dirs: rays.dirs,
            })
        })
    }

    /// Ray chunk length for `per_ray` samples per ray over `b` images.
    pub(crate) fn chunk_rays(&self, per_ray: i64, b: i64, device: tch::Device) -> i64 {
        (self.config.chunk_points_on(device) / (per_ray * b).max(1)).max(1)
    }

    /// Runs `f(start, len)` over consecutive ray ranges of about `chunk_points` samples
    /// (`per_ray` samples per ray, all images of the batch) and joins the results.
    fn in_chunks(
        &self,
        rays: &Rays,
        per_ray: i64,
        f: impl Fn(i64, i64) -> Result<RenderedRays>,
    ) -> Result<RenderedRays> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        let chunk = self.chunk_rays(per_ray, b, rays.dirs.device());
        if chunk >= r {
            return f(0, r);
        }
        let mut parts = Vec::new();
        let mut start = 0;
        while start < r {
            let len = chunk.min(r - start);
            parts.push(f(start, len)?);
            start += len;
        }
        Ok(RenderedRays::concat(&parts))
    }

    /// Training render of `res × res` images split into `regions` horizontal bands rendered
    /// one after the other (the release's patch mode; with gradients). Returns the images
    /// `(B, 3, H, W)` in [−1, 1] and each band's per-ray results.
    pub fn render_regions(
        &self,
        latents: &Latents,
        poses: &Poses,
        res: i64,
        regions: i64,
        noise: &Noise,
    ) -> Result<(Tensor, Vec<RenderedRays>)> {
        let b = poses.len();
        let len = res * res / regions.max(1);
        let parts = self
            .region_rays(poses, res, regions)?
            .iter()
            .enumerate()
            .map(|(k, rays)| self.render_rays_chunked(latents, rays, &noise.slice(0, b, k as i64 * len, len)))
            .collect::<Result<Vec<_>>>()?;
        Ok((assemble_image(&parts, res), parts))
    }

    /// Rays of the `regions` horizontal bands of `res × res` images seen from `poses`,
    /// in image order (the bands [`Self::render_regions`] renders).
    pub fn region_rays(&self, poses: &Poses, res: i64, regions: i64) -> Result<Vec<Rays>> {
        let r = res * res;
        if regions < 1 || r % regions != 0 {
            return Err(Error::Invalid(format!("{regions} regions do not split {res}×{res} rays into equal bands")));
        }
        let rays = Rays::from_poses(poses, res, self.camera.fov_deg);
        let len = r / regions;
        Ok((0..regions).map(|k| rays.narrow(k * len, len)).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Poses, Rays};
    use crate::GeneratorConfig;
    use tch::{nn, Device, Kind};

    /// Re-rendering at the depths a render placed gives the same image (the premise of
    /// the two-pass patch step), chunked or not.
    #[test]
    fn render_at_depths_reproduces_the_render() {
        tch::manual_seed(3);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        vs.double();
        let cam = CameraConfig::chair();
        let rc = RenderConfig { num_steps: 6, chunk_points: 100, ..Default::default() };
        let r = Renderer::new(&g, &cam, &rc).unwrap();
        let z = Tensor::randn([2, 8], (Kind::Double, Device::Cpu));
        let lat = g.latents(&z, &z, None);
        let poses = Poses::from_angles(&[(1.0, 0.2), (1.3, -2.0)], Kind::Double, Device::Cpu);
        let (img, parts) = r.render_regions(&lat, &poses, 6, 3, &Noise::default()).unwrap();
        let rays = r.region_rays(&poses, 6, 3).unwrap();
        let again: Vec<_> =
            parts.iter().zip(&rays).map(|(p, ray)| r.render_at_depths(&lat, ray, &p.z).unwrap()).collect();
        let img2 = assemble_image(&again, 6);
        assert!(img.allclose(&img2, 1e-12, 1e-12, false));
        assert!(r.render_at_depths(&lat, &rays[0], &parts[0].z.narrow(1, 0, 2)).is_err());
    }

    /// bfloat16 hidden layers change the image by a few bf16 ulps of colour, never to
    /// NaN, and the integration stays float32.
    #[test]
    fn bfloat16_networks_render_close_to_float32() {
        tch::manual_seed(4);
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig { hidden_dim: 32, ..GeneratorConfig::tiny() };
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        let cam = CameraConfig::chair();
        let rc = RenderConfig { num_steps: 8, jitter: false, ..Default::default() };
        let mut r = Renderer::new(&g, &cam, &rc).unwrap();
        let z = Tensor::randn([2, 8], (Kind::Float, Device::Cpu));
        let lat = g.latents(&z, &z, None);
        let poses = Poses::from_angles(&[(1.0, 0.2), (1.3, -2.0)], Kind::Float, Device::Cpu);
        let rays = Rays::from_poses(&poses, 8, cam.fov_deg);
        let noise = Noise { jitter: None, importance: Some(Tensor::rand([2, 64, 8], (Kind::Float, Device::Cpu))) };
        let full = r.render_rays(&lat, &rays, &noise).unwrap();
        r.field.compute_kind = Some(Kind::BFloat16);
        let half = r.render_rays(&lat, &rays, &noise).unwrap();
        assert_eq!((half.pixel.kind(), half.weights.kind(), half.z.kind()), (Kind::Float, Kind::Float, Kind::Float));
        assert!(bool::try_from(half.pixel.isfinite().all()).unwrap());
        let err = f64::try_from((&half.pixel - &full.pixel).abs().max()).unwrap();
        println!("bf16 vs f32: max colour error {err:.2e}");
        assert!(err > 0.0 && err < 1e-2, "bf16 colour error {err}");
    }
}
