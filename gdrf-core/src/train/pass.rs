//! One forward pass of each player: render, judge, and hand the judgement to the losses
//! (which never render themselves).
use crate::camera::Poses;
use crate::disc::Judge;
use crate::loss::deform_reg::{regularisers, select_samples};
use crate::loss::{discriminator_loss, generator_loss, LossConfig, Losses, Schedule};
use crate::render::{Noise, RenderedRays, Renderer};
use crate::{Generator, Latents, Result};
use tch::Tensor;

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
    generator_judgement(renderer.generator, disc, &img, &parts, fake, reg_rays, at, cfg)
}

/// The generator's loss on images already rendered with their graph (`img: (B, 3, S, S)`
/// and the rays `parts` it was composited from, drawn from `fake`): `disc`'s verdict, the
/// image terms and the regularisers through `generator`.
#[allow(clippy::too_many_arguments)]
pub fn generator_judgement(
    generator: &Generator,
    disc: &dyn Judge,
    img: &Tensor,
    parts: &[RenderedRays],
    fake: &FakeBatch,
    reg_rays: Option<&Tensor>,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    let d = disc.judge(img, at.alpha)?;
    let samples = select_samples(&RenderedRays::concat(parts), &cfg.reg, reg_rays);
    let reg = regularisers(generator, &fake.latents.shape, &samples, cfg.reg.variant);
    generator_loss(&d, img, &fake.poses.stacked(), fake.z, reg, at, cfg)
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
