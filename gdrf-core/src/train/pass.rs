//! One forward pass of each player: render, judge, and hand the judgement to the losses
//! (which never render themselves).
use crate::camera::Poses;
use crate::disc::Judge;
use crate::loss::deform_reg::{regularisers, select_samples};
use crate::loss::{discriminator_loss, GeneratorObjective, LossConfig, Losses, Schedule};
use crate::render::{Noise, RenderedRays, Renderer};
use crate::{Generator, Latents, Result};
use tch::{Kind, Tensor};

/// A batch of generated images: what drives it and how it is seen.
pub struct FakeBatch<'a> {
    pub latents: &'a Latents,
    pub poses: &'a Poses,
    /// The codes, for the latent-prediction loss (only read when its weight is not 0).
    pub z: Option<&'a Tensor>,
    /// Image side and the number of horizontal bands it is rendered in.
    pub resolution: i64,
    pub regions: i64,
    /// Renderer noise (drawn from libtorch's generator when absent).
    pub noise: &'a Noise,
}

/// The generator's loss in one pass with gradients: render (all bands), let `disc` judge
/// the images, pick the regulariser samples (`reg_rays: (B, n)` fixes the ray draw) and
/// compute the regularisers through the generator. Freeze D's variables first if its
/// parameters must not receive gradients.
pub fn generator_pass(
    renderer: &Renderer,
    disc: &dyn Judge,
    fake: &FakeBatch,
    reg_rays: Option<&Tensor>,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    let (img, parts) = renderer.render_regions(fake.latents, fake.poses, fake.resolution, fake.regions, fake.noise)?;
    let judged = Judged { img: &img, poses: fake.poses, z: fake.z };
    generator_judgement(renderer.generator, disc, &judged, (fake.latents, &parts), reg_rays, at, cfg)
}

/// The images the discriminator judges, with the poses they are seen from and their codes
/// (for the latent-prediction and mode-seeking terms): the images just rendered, or, on
/// ranks that judge the global batch, that batch holding them (`Trainer::judged_rows`).
pub struct Judged<'a> {
    /// `(B, 3, S, S)`.
    pub img: &'a Tensor,
    pub poses: &'a Poses,
    pub z: Option<&'a Tensor>,
}

/// The generator's loss on images already rendered with their graph: `disc`'s verdict on
/// `judged` and the image terms, the regularisers through `generator` on `own`, the
/// latents and the rays (`parts`) of the images this process rendered, and the opacity
/// term on those rays where its weight is not 0.
pub fn generator_judgement(
    generator: &Generator,
    disc: &dyn Judge,
    judged: &Judged,
    (latents, parts): (&Latents, &[RenderedRays]),
    reg_rays: Option<&Tensor>,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    let d = disc.judge(judged.img, at.alpha)?;
    let rays = RenderedRays::concat(parts);
    let samples = select_samples(&rays, &cfg.reg, reg_rays);
    let reg = regularisers(generator, &latents.shape, &samples, cfg.reg.variant);
    let objective = GeneratorObjective::new(cfg, at);
    let losses = objective.main(&d, judged.img, &judged.poses.stacked(), judged.z, reg)?;
    Ok(objective.add_opacity(losses, || rays.object_share()))
}

/// The discriminator's loss: fakes rendered without gradients, then
/// [`discriminator_judgement`].
pub fn discriminator_pass(
    renderer: &Renderer,
    disc: &dyn Judge,
    real: &Tensor,
    real_poses: Option<&Tensor>,
    fake: &FakeBatch,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    let fakes =
        tch::no_grad(|| renderer.render_regions(fake.latents, fake.poses, fake.resolution, fake.regions, fake.noise))?
            .0;
    discriminator_judgement(disc, real, real_poses, &fakes, fake.poses, fake.z, at, cfg)
}

/// The discriminator's loss on rendered `fakes: (B, 3, S, S)` seen from `fake_poses`
/// (detached here: no gradient reaches the generator): D on the reals (made to require
/// grad when R1 is due, unless they already do) and on the fakes.
#[allow(clippy::too_many_arguments)]
pub fn discriminator_judgement(
    disc: &dyn Judge,
    real: &Tensor,
    real_poses: Option<&Tensor>,
    fakes: &Tensor,
    fake_poses: &Poses,
    z: Option<&Tensor>,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    let real =
        if real.requires_grad() { real.shallow_clone() } else { real.detach().set_requires_grad(cfg.r1_due(at.step)) };
    let dr = disc.judge(&real, at.alpha)?;
    let df = disc.judge(&fakes.detach(), at.alpha)?;
    discriminator_loss(&dr, &real, real_poses, &df, &fake_poses.stacked(), z, at, cfg)
}

/// Puts a rank's images into the batch the discriminator judges (`Trainer::judged_rows`).
pub type JudgedView<'a> = &'a dyn Fn(&Tensor) -> Result<Tensor>;

/// The release's two-pass patch step for one chunk of the generator's batch (codes `z`,
/// drawn at `poses` with `noise`): render without gradients, take the judge's gradient with
/// respect to the image alone, then re-render each of `regions` bands with gradients at the
/// very sample depths of the first pass and backpropagate its slice of that gradient; the
/// regularisers likewise. The judge sees `view` of the images (the images themselves, or
/// the global batch holding them: `Trainer::judged_rows`), seen from `judged_poses` with
/// codes `judged_z`. Leaves `1/split` of the chunk's gradient (times `fault`: NaN to
/// inject a non-finite step) in the generator and returns the chunk's losses.
#[allow(clippy::too_many_arguments)]
pub fn patch_gradients(
    renderer: &Renderer,
    judge: &dyn Judge,
    (z, poses, noise): (&Tensor, &Poses, &Noise),
    (view, judged_poses, judged_z): (JudgedView, &Poses, &Tensor),
    (res, regions): (i64, i64),
    reg_rays: &Tensor,
    at: Schedule,
    cfg: &LossConfig,
    (split, fault): (f64, f64),
) -> Result<Losses> {
    let gen = renderer.generator;
    let objective = GeneratorObjective::new(cfg, at);
    // The release's two-pass patch step: render without gradients, take D's gradient
    // w.r.t. the image alone, then re-render each band with gradients at the very
    // sample depths of the first pass and backpropagate its slice of that gradient.
    let (img, parts) = tch::no_grad(|| {
        let lat = gen.latents(z, z, None)?;
        renderer.render_regions(&lat, poses, res, regions, noise)
    })?;
    let img = img.detach().set_requires_grad(true);
    let seen = view(&img)?;
    let d = judge.judge(&seen, at.alpha)?;
    let mut adv = objective.image_terms(&d, &seen, &judged_poses.stacked(), Some(judged_z))?;
    adv.total = adv.total.g_mul_scalar(fault);
    let g_img = Tensor::run_backward(&[&adv.total / split], &[&img], false, false).remove(0);
    // (B, 3, H, W) → (B, R, 3), the layout of per-ray pixels; pixel = (img + 1)/2.
    let b = g_img.size()[0];
    let g_rays = g_img.reshape([b, 3, res * res]).permute([0, 2, 1]) * 2.0;
    let rays = renderer.region_rays(poses, res, regions)?;
    let len = res * res / regions;
    for (k, (part, ray)) in parts.iter().zip(&rays).enumerate() {
        // Fresh latents per band: each backward frees its own graph.
        let lat = gen.latents(z, z, None)?;
        let rr = renderer.render_at_depths(&lat, ray, &part.z)?;
        (&rr.pixel * g_rays.narrow(1, k as i64 * len, len)).sum(Kind::Float).backward();
    }
    let lat = gen.latents(z, z, None)?;
    let samples = select_samples(&RenderedRays::concat(&parts), &cfg.reg, Some(reg_rays));
    let reg = objective.regularisation(regularisers(gen, &lat.shape, &samples, cfg.reg.variant));
    (&reg.total / split).backward();
    Ok(adv.merge(reg))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disc::Discriminator;
    use crate::loss::opacity::opacity_entropy;
    use crate::render::background_share;
    use crate::{Background, CameraConfig, GeneratorConfig, RenderConfig};
    use tch::{nn, Device};

    /// The opacity term through the generator's pass: absent at weight 0; at a weight, the
    /// mean binary entropy of each rendered ray's object share, added to the total at that
    /// weight, with a gradient that reaches the generator. Both ways the background can
    /// show: painted by the generator at the last sample (the release), and composited on
    /// colours, where the object's share is one minus the compositor's background share.
    #[test]
    fn opacity_term_is_the_entropy_of_the_rays_object_share() {
        for background in [Background::Learned, Background::Corners] {
            let vs = nn::VarStore::new(Device::Cpu);
            let gcfg = GeneratorConfig { hidden_dim: 32, background, ..GeneratorConfig::tiny() };
            let g = crate::rng::with_global_seed(3, || Generator::new(&vs.root(), &gcfg).unwrap());
            let dvs = nn::VarStore::new(Device::Cpu);
            let d = crate::rng::with_global_seed(4, || Discriminator::new(&dvs.root()));
            let cam = CameraConfig::chair();
            let rc = RenderConfig { num_steps: 8, ..Default::default() };
            let r = Renderer::new(&g, &cam, &rc).unwrap();
            let (b, res, n) = (2i64, 8i64, 8i64);
            let cpu = (Kind::Float, Device::Cpu);
            let draw = |seed| crate::rng::with_global_seed(seed, || Tensor::rand([b, res * res, n], cpu));
            let noise = Noise { jitter: Some(draw(5)), importance: Some(draw(6)) };
            let z = crate::rng::with_global_seed(7, || Tensor::randn([b, gcfg.latent_dim as i64], cpu));
            let poses = Poses::from_angles(&[(1.0, 0.5), (1.2, -2.5)], Kind::Float, Device::Cpu);
            let at = Schedule { step: 0, alpha: 1.0 };
            let pass = |weight: f64| {
                let lat = g.latents(&z, &z, None).unwrap();
                let fake =
                    FakeBatch { latents: &lat, poses: &poses, z: None, resolution: res, regions: 1, noise: &noise };
                let cfg = LossConfig { opacity_weight: weight, ..Default::default() };
                generator_pass(&r, &d, &fake, None, at, &cfg).unwrap()
            };
            let off = pass(0.0);
            assert!(off.get("g_opacity").is_none(), "{background:?}: the term is computed at weight 0");
            let weight = 0.7;
            let on = pass(weight);
            let h = on.get("g_opacity").expect("the opacity term at weight 0.7").double_value(&[]);
            // The same rays rendered again: every sample's weight but the last's.
            let lat = g.latents(&z, &z, None).unwrap();
            let (_, parts) = tch::no_grad(|| r.render_regions(&lat, &poses, res, 1, &noise)).unwrap();
            let w = &parts[0].weights;
            assert_eq!(w.size(), [b, res * res, 2 * n, 1]);
            let share = w.narrow(2, 0, 2 * n - 1).sum_dim_intlist(2, false, Kind::Float);
            if background == Background::Corners {
                // Composited on colours: the compositor's own background share is the rest.
                let o = r.composite_options();
                let back = background_share(w, &parts[0].opacity, &o);
                let gap = f64::try_from((&share + &back - 1.0).abs().max()).unwrap();
                assert!(gap < 1e-6, "object share + background share − 1 reaches {gap}");
            }
            let want = opacity_entropy(&share).double_value(&[]);
            assert!((h - want).abs() <= 1e-7 + 1e-6 * want, "{background:?}: g_opacity {h}, the rays' entropy {want}");
            assert!(h > 1e-3 && h < std::f64::consts::LN_2, "{background:?}: {h}");
            let (t_on, t_off) = (on.total.double_value(&[]), off.total.double_value(&[]));
            assert!(
                (t_on - t_off - weight * h).abs() <= 1e-5 * (1.0 + t_off.abs()),
                "{background:?}: total {t_on} against {t_off} + {weight}·{h}"
            );
            // Its gradient alone reaches the generator.
            on.get("g_opacity").unwrap().backward();
            let reached = vs.trainable_variables().iter().any(|v| {
                let gr = v.grad();
                gr.defined() && f64::try_from(gr.abs().sum(Kind::Double)).unwrap() > 0.0
            });
            assert!(reached, "{background:?}: no gradient from the opacity term");
        }
    }
}
