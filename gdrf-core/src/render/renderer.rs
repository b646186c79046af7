//! The GDRF renderer, a composition of three parts as in nerfstudio: the sampler places a
//! bundle's samples and answers their density from the shape alone ([`Renderer::sample`],
//! `sampler.rs`, giving one [`RaySamples`]); the field colours them from the appearance
//! ([`Renderer::colour`]); the compositor integrates along each ray (`composite.rs`). Around
//! it: training batches and patches with gradients, chunked inference in bounded memory,
//! the staged shape-side / re-shade path (`staged.rs`) and occupancy grids
//! (`occupancy.rs`).
use super::composite::composite;
use super::rays::gather_samples;
use super::rays::{assemble_image, Image, Noise, RayColours, RaySamples, RenderedRays};
use super::setup::Setup;
use super::staged::Staged;
use crate::camera::{Poses, Rays};
use crate::config::{CameraConfig, RenderConfig};
use crate::field::generator::{FieldOptions, Generator, Latents};
use crate::field::RadianceField;
use crate::nn::film::Film;
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Renders a radiance field (the generator by default) with a camera and sampling
/// configuration: samples, colours and composites, for training and in bounded memory.
/// Its [`Setup`] (field, camera, config, field options) is reached through it
/// (`renderer.field = …`).
pub struct Renderer<'a, F: RadianceField = Generator> {
    setup: Setup<'a, F>,
}

impl<'a, F: RadianceField> std::ops::Deref for Renderer<'a, F> {
    type Target = Setup<'a, F>;
    fn deref(&self) -> &Setup<'a, F> {
        &self.setup
    }
}

impl<F: RadianceField> std::ops::DerefMut for Renderer<'_, F> {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.setup
    }
}

impl<'a, F: RadianceField> Renderer<'a, F> {
    /// The staged shape-side / re-shade path of this renderer.
    pub fn staged(&self) -> Staged<'a, F> {
        Staged { setup: self.setup }
    }

    pub fn new(generator: &'a F, camera: &'a CameraConfig, config: &'a RenderConfig) -> Result<Self> {
        camera.validate()?;
        config.validate()?;
        Ok(Self { setup: Setup { generator, camera, config, field: FieldOptions::default(), clip: None } })
    }

    /// The field's second answer: colours `(B, R, S, 3)` of every sample, sorted by depth,
    /// under `appearance` seen along `dirs: (B, R, 3)`. Colour is pointwise, so each pass
    /// is coloured in merge order and the 3 channels sorted instead of the F features.
    pub fn colour(&self, samples: &RaySamples, dirs: &Tensor, appearance: &Film) -> Tensor {
        let rgb: Vec<Tensor> = samples
            .features
            .iter()
            .map(|f| {
                let s = f.size();
                let (b, r, n) = (s[0], s[1], s[2]);
                let dirs = self.sample_dirs(dirs, n);
                self.generator.radiance(&f.reshape([b, r * n, -1]), &dirs, appearance).view([b, r, n, 3])
            })
            .collect();
        gather_samples(&Tensor::cat(&rgb, 2), &samples.order)
    }

    /// Colours and composites `samples` of `rays` under `appearance`.
    fn integrate(&self, samples: RaySamples, rays: &Rays, appearance: &Film) -> RenderedRays {
        let rgb = self.colour(&samples, &rays.dirs, appearance);
        let c = composite(&rgb, &samples.sigma, &samples.z.unsqueeze(-1), &self.composite_options());
        RenderedRays {
            pixel: c.pixel,
            depth: c.depth,
            opacity: c.opacity,
            z: samples.z,
            weights: c.weights,
            origins: rays.origins.shallow_clone(),
            dirs: rays.dirs.shallow_clone(),
        }
    }

    /// Renders rays `(B, R, 3)` of the batch driven by `latents` (gradients flow where
    /// autograd is enabled): sample, colour, composite. Missing noise is drawn from
    /// libtorch's generator.
    pub fn render_rays(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RenderedRays> {
        if latents.batch_size() != rays.dirs.size()[0] {
            return Err(Error::Shape(format!(
                "{} latents for a batch of {} ray sets",
                latents.batch_size(),
                rays.dirs.size()[0]
            )));
        }
        let samples = self.sample(&latents.shape, rays, noise)?;
        Ok(self.integrate(samples, rays, &latents.appearance))
    }

    /// Renders `res × res` images without gradients, `chunk_points` samples at a time, so
    /// any resolution fits in bounded memory. The reference sampler renders as many whole
    /// images together as fit in one chunk: on a GPU, where every chunk costs the same few
    /// hundred kernel launches, the coverage term's 512 candidates at 16² took 1.4–1.9 s one
    /// image at a time, against 0.09 s for the rest of a campaign step. The skipping paths
    /// keep one image at a time.
    pub fn render_image(&self, latents: &Latents, poses: &Poses, res: i64, noise: &Noise) -> Result<Image> {
        let group = if self.config.skips_samples() {
            1
        } else {
            let rays = self.chunk_rays(self.config.samples_per_ray() as i64, 1, latents.shape.gamma.device());
            (rays / (res * res).max(1)).max(1)
        };
        Ok(self
            .render_image_with(latents, poses, res, noise, group, |_, lat, rays, noise| {
                self.render_bundle(lat, rays, noise)
            })?
            .0)
    }

    /// Renders `res × res` images without gradients, `group` images at a time, each group's
    /// rays by `per_group(first image, latents, rays, noise)`. Also returns the density and
    /// colour queries spent.
    pub(crate) fn render_image_with(
        &self,
        latents: &Latents,
        poses: &Poses,
        res: i64,
        noise: &Noise,
        group: i64,
        per_group: impl Fn(usize, &Latents, &Rays, &Noise) -> Result<RayColours>,
    ) -> Result<(Image, (i64, i64))> {
        let rays = Rays::from_poses(poses, res, self.camera.fov_deg);
        let (b, r) = (poses.len(), res * res);
        let mut parts = Vec::new();
        tch::no_grad(|| -> Result<()> {
            for i in (0..b).step_by(group.max(1) as usize) {
                let n = group.max(1).min(b - i);
                let (lat, rays, noise) = (latents.narrow(i, n), rays.narrow_batch(i, n), noise.slice(i, n, 0, r));
                parts.push(per_group(i as usize, &lat, &rays, &noise)?);
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
            return self.staged().render_chunked(latents, rays, noise);
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
    pub(crate) fn render_rays_chunked(&self, latents: &Latents, rays: &Rays, noise: &Noise) -> Result<RenderedRays> {
        let b = rays.dirs.size()[0];
        let parts = self.in_chunks(rays, self.config.samples_per_ray() as i64, |start, len| {
            self.render_rays(latents, &rays.narrow(start, len), &noise.slice(0, b, start, len))
        })?;
        Ok(RenderedRays::join(parts))
    }

    /// Renders rays `(B, R, 3)` at the given sorted sample depths `z: (B, R, S)`, without
    /// placing samples: the field is evaluated at exactly those points and integrated.
    /// The two-pass patch step uses it to re-render with gradients the samples that a
    /// no-grad pass placed, so both passes see the same points.
    pub fn render_at_depths(&self, latents: &Latents, rays: &Rays, z: &Tensor) -> Result<RenderedRays> {
        let (b, r) = (rays.dirs.size()[0], rays.num_rays());
        if z.dim() != 3 || z.size()[0] != b || z.size()[1] != r {
            return Err(Error::Shape(format!("sample depths have shape {:?}, expected [{b}, {r}, S]", z.size())));
        }
        if latents.batch_size() != b {
            return Err(Error::Shape(format!("{} latents for a batch of {b} ray sets", latents.batch_size())));
        }
        let s = z.size()[2];
        let order = Tensor::arange(s, (Kind::Int64, z.device())).view([1, 1, s]);
        let query = self.shape_query(&latents.shape);
        let parts = self.in_chunks(rays, s, |start, len| {
            let (rays, z) = (rays.narrow(start, len), z.narrow(1, start, len));
            let (sigma, feature) = query.at(&rays, &z);
            // The samples as given: already sorted, so their order is the identity.
            let samples = RaySamples {
                z: z.shallow_clone(),
                sigma,
                features: vec![feature],
                order: order.expand([b, len, s], false),
                skipped: None,
                evaluated: b * len * s,
            };
            Ok(self.integrate(samples, &rays, &latents.appearance))
        })?;
        Ok(RenderedRays::join(parts))
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
        let lat = g.latents(&z, &z, None).unwrap();
        let poses = Poses::from_angles(&[(1.0, 0.2), (1.3, -2.0)], Kind::Double, Device::Cpu);
        let (img, parts) = r.render_regions(&lat, &poses, 6, 3, &Noise::default()).unwrap();
        let rays = r.region_rays(&poses, 6, 3).unwrap();
        let again: Vec<_> =
            parts.iter().zip(&rays).map(|(p, ray)| r.render_at_depths(&lat, ray, &p.z).unwrap()).collect();
        let img2 = assemble_image(&again, 6);
        assert!(img.allclose(&img2, 1e-12, 1e-12, false));
        assert!(r.render_at_depths(&lat, &rays[0], &parts[0].z.narrow(1, 0, 2)).is_err());
    }

    /// `render_image` renders as many whole images together as fit in a chunk, and
    /// its images, depths and opacities equal those rendered one image at a time (each
    /// image keeps its rows of the noise), whether the last group is full or not.
    #[test]
    fn render_image_groups_whole_images_per_chunk() {
        tch::manual_seed(5);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        vs.double();
        let cam = CameraConfig::chair();
        let z = Tensor::randn([5, 8], (Kind::Double, Device::Cpu));
        let lat = g.latents(&z, &z, None).unwrap();
        let angles: Vec<(f64, f64)> = (0..5).map(|i| (1.0 + 0.1 * i as f64, -2.0 + 0.9 * i as f64)).collect();
        let poses = Poses::from_angles(&angles, Kind::Double, Device::Cpu);
        let noise = Noise {
            jitter: Some(Tensor::rand([5, 36, 6], (Kind::Double, Device::Cpu))),
            importance: Some(Tensor::rand([5, 36, 6], (Kind::Double, Device::Cpu))),
        };
        // 12 samples a ray, 36 rays an image: 432 points per image.
        let render = |chunk_points: usize| {
            let rc = RenderConfig { num_steps: 6, chunk_points, ..Default::default() };
            Renderer::new(&g, &cam, &rc).unwrap().render_image(&lat, &poses, 6, &noise).unwrap()
        };
        let one = render(432);
        for (chunk_points, group) in
            [(100, "rays of one image a chunk"), (864, "2 images"), (1296, "3 images, then 2"), (1 << 20, "all 5")]
        {
            let grouped = render(chunk_points);
            for (what, a, b) in [
                ("rgb", &grouped.rgb, &one.rgb),
                ("depth", &grouped.depth, &one.depth),
                ("opacity", &grouped.opacity, &one.opacity),
            ] {
                assert_eq!(a.size(), b.size(), "{group}: {what}");
                assert!(
                    a.allclose(b, 1e-12, 1e-12, false),
                    "{group}: {what} differs by {}",
                    f64::try_from((a - b).abs().max()).unwrap()
                );
            }
        }
    }

    /// A generator that does not paint its background ([`crate::Background::Random`],
    /// [`crate::Background::Corners`]) renders as the same weights with the last sample
    /// forced white, and not as they render with the field's colour there.
    #[test]
    fn a_generator_trained_on_random_backgrounds_renders_its_background_white() {
        tch::manual_seed(5);
        let vs = nn::VarStore::new(Device::Cpu);
        let mut g = Generator::new(&vs.root(), &GeneratorConfig::tiny()).unwrap();
        let cam = CameraConfig::chair();
        let z = Tensor::randn([2, 8], (Kind::Float, Device::Cpu));
        let lat = g.latents(&z, &z, None).unwrap();
        let poses = Poses::from_angles(&[(1.0, 0.2), (1.3, -2.0)], Kind::Float, Device::Cpu);
        let noise = Noise::midpoints(2, 36, 6, Device::Cpu);
        let render = |g: &Generator, force_last_white: bool| {
            let rc = RenderConfig { num_steps: 6, jitter: false, force_last_white, ..Default::default() };
            Renderer::new(g, &cam, &rc).unwrap().render_image(&lat, &poses, 6, &noise).unwrap().rgb
        };
        let (learned, forced) = (render(&g, false), render(&g, true));
        assert!(f64::try_from((&learned - &forced).abs().max()).unwrap() > 1e-3);
        for background in [crate::Background::Random, crate::Background::Corners] {
            g.cfg.background = background;
            assert!(render(&g, false).equal(&forced), "{background:?}");
        }
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
        let lat = g.latents(&z, &z, None).unwrap();
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
