//! Training losses: the generator's total (adversarial, pose, deformation regularisers)
//! and the discriminator's (logistic, R1, pose), each with a named breakdown.
// `t = t + x` on purpose: `+=` on a Tensor is an in-place add on a tensor autograd saved.
#![allow(clippy::assign_op_pattern)]
pub mod deform_reg;
pub mod gan;

use crate::camera::Poses;
use crate::disc::Discriminator;
use crate::render::{Noise, RenderedRays, Renderer};
use crate::{Error, Latents, Result};
use deform_reg::{regularisers, select_samples, RegConfig};
use serde::{Deserialize, Serialize};
use tch::Tensor;

/// Loss weights and schedules (defaults: the release's CHAIR_128).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LossConfig {
    /// R1 weight γ (the penalty is 0.5·γ·E‖∇D‖²).
    pub r1_gamma: f64,
    /// Apply R1 every k steps only, scaled by k (StyleGAN2's lazy regularisation); 1 = every step.
    pub r1_interval: i64,
    /// Weight of the pose loss (on fakes for D and G, on reals for D).
    pub pose_weight: f64,
    /// Weight of the latent-prediction loss (0 in the release).
    pub latent_weight: f64,
    /// Top-k schedule: p = max(0.99^(step/interval), floor).
    pub topk_interval: f64,
    pub topk_floor: f64,
    pub reg: RegConfig,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            r1_gamma: 1.0,
            r1_interval: 1,
            pose_weight: 15.0,
            latent_weight: 0.0,
            topk_interval: 2000.0,
            topk_floor: 0.6,
            reg: RegConfig::default(),
        }
    }
}

impl LossConfig {
    pub fn validate(&self) -> Result<()> {
        if self.r1_interval < 1 {
            return Err(Error::Config(format!("loss.r1_interval is {}, expected at least 1", self.r1_interval)));
        }
        if !(self.topk_interval > 0.0 && (0.0..=1.0).contains(&self.topk_floor)) {
            return Err(Error::Config(format!(
                "loss.topk_interval {} must be positive and loss.topk_floor {} in [0, 1]",
                self.topk_interval, self.topk_floor
            )));
        }
        Ok(())
    }
}

/// A total loss and its unweighted terms by name (scalars).
#[derive(Debug)]
pub struct Losses {
    pub total: Tensor,
    pub terms: Vec<(&'static str, Tensor)>,
}

impl Losses {
    pub fn get(&self, name: &str) -> Option<&Tensor> {
        self.terms.iter().find(|(n, _)| *n == name).map(|(_, t)| t)
    }
    /// Terms as plain numbers, for logs.
    pub fn values(&self) -> Vec<(&'static str, f64)> {
        self.terms.iter().map(|(n, t)| (*n, t.double_value(&[]))).collect()
    }
}

/// A batch of generated images: what drives it and how it is seen.
pub struct FakeBatch<'a> {
    pub latents: &'a Latents,
    pub poses: &'a Poses,
    /// The codes, for the latent-prediction loss (only read when its weight is not 0).
    pub z: Option<&'a Tensor>,
    /// Image size and number of horizontal patches it is rendered in.
    pub resolution: i64,
    pub regions: i64,
    /// Renderer noise (drawn when absent).
    pub noise: &'a Noise,
}

/// Training state the losses depend on.
#[derive(Debug, Clone, Copy)]
pub struct Schedule {
    pub step: i64,
    /// Discriminator fade-in α.
    pub alpha: f64,
}

/// The generator's loss: top-k non-saturating GAN + pose + the four regularisers on the
/// rendered batch. `reg_rays: (B, n)` fixes the regulariser's ray draw (tests).
pub fn generator_loss(
    renderer: &Renderer,
    disc: &Discriminator,
    fake: &FakeBatch,
    at: Schedule,
    cfg: &LossConfig,
    reg_rays: Option<&Tensor>,
) -> Result<Losses> {
    cfg.validate()?;
    let (img, parts) = renderer.render_regions(fake.latents, fake.poses, fake.resolution, fake.regions, fake.noise)?;
    let d = disc.forward(&img, at.alpha)?;
    let b = img.size()[0];
    let k = gan::topk_count(at.step, b, cfg.topk_interval, cfg.topk_floor);
    let adv = gan::g_nonsaturating(&d.logit, k);
    let pose = gan::pose_loss(&d.pose, &fake.poses.stacked());
    let rendered = RenderedRays::concat(&parts);
    let samples = select_samples(&rendered, &cfg.reg, reg_rays);
    let reg = regularisers(renderer.generator, &fake.latents.shape, &samples, cfg.reg.variant);
    let mut total = &adv + &pose * cfg.pose_weight + reg.weighted_sum(&cfg.reg);
    let mut terms = vec![("g_adv", adv), ("g_pose", pose)];
    if cfg.latent_weight != 0.0 {
        if let Some(z) = fake.z {
            let l = gan::latent_loss(&d.latent, z);
            total = total + &l * cfg.latent_weight;
            terms.push(("g_latent", l));
        }
    }
    terms.extend([
        ("reg_correction", reg.correction),
        ("reg_smoothness", reg.smoothness),
        ("reg_rigidity", reg.rigidity),
        ("reg_normal", reg.normal),
    ]);
    Ok(Losses { total, terms })
}

/// The discriminator's loss on real images `(B, 3, H, W)` with poses `(B, 2)` and on fakes
/// rendered without gradients: logistic terms, R1 on reals (lazily every
/// `r1_interval` steps, scaled by it), pose on fakes and reals. Real images that already
/// require grad are used as they are (so callers can differentiate w.r.t. them).
pub fn discriminator_loss(
    renderer: &Renderer,
    disc: &Discriminator,
    real: &Tensor,
    real_poses: &Tensor,
    fake: &FakeBatch,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    cfg.validate()?;
    let fakes = tch::no_grad(|| renderer.render_regions(fake.latents, fake.poses, fake.resolution, fake.regions, fake.noise))?.0;
    let r1_now = cfg.r1_gamma != 0.0 && at.step % cfg.r1_interval == 0;
    let real = if real.requires_grad() { real.shallow_clone() } else { real.detach().set_requires_grad(r1_now) };
    let dr = disc.forward(&real, at.alpha)?;
    let df = disc.forward(&fakes.detach(), at.alpha)?;
    let d_real = gan::d_real(&dr.logit);
    let d_fake = gan::d_fake(&df.logit);
    let pose_fake = gan::pose_loss(&df.pose, &fake.poses.stacked());
    let pose_real = gan::pose_loss(&dr.pose, real_poses);
    let mut total = &d_real + &d_fake + (&pose_fake + &pose_real) * cfg.pose_weight;
    let mut terms = vec![("d_real", d_real), ("d_fake", d_fake)];
    if r1_now {
        let r1 = gan::r1_penalty(&dr.logit, &real)?;
        total = total + &r1 * (cfg.r1_gamma * cfg.r1_interval as f64);
        terms.push(("d_r1", r1));
    }
    terms.extend([("d_pose_fake", pose_fake), ("d_pose_real", pose_real)]);
    if cfg.latent_weight != 0.0 {
        if let Some(z) = fake.z {
            let l = gan::latent_loss(&df.latent, z);
            total = total + &l * cfg.latent_weight;
            terms.push(("d_latent", l));
        }
    }
    Ok(Losses { total, terms })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{CameraConfig, Generator, GeneratorConfig, RenderConfig};
    use tch::{nn, Device, Kind};

    #[test]
    fn bad_loss_settings_are_named() {
        let e = LossConfig { r1_interval: 0, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("r1_interval"), "{e}");
        assert!(LossConfig { topk_floor: 1.5, ..Default::default() }.validate().is_err());
        LossConfig::default().validate().unwrap();
    }

    #[test]
    fn lazy_r1_applies_every_k_steps_scaled_by_k() {
        tch::manual_seed(0);
        let gvs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig { latent_dim: 4, hidden_dim: 8, mapping_hidden_dim: 8, ..Default::default() };
        let gen = Generator::new(&gvs.root(), &cfg).unwrap();
        let dvs = nn::VarStore::new(Device::Cpu);
        let disc = Discriminator::new(&dvs.root());
        let (cam, rc) = (CameraConfig::chair(), RenderConfig { num_steps: 4, ..Default::default() });
        let r = Renderer::new(&gen, &cam, &rc).unwrap();
        let z = Tensor::randn([2, 4], (Kind::Float, Device::Cpu));
        let lat = gen.latents(&z, &z, None);
        let poses = Poses::from_angles(&[(1.0, 0.0), (1.2, 2.0)], Kind::Float, Device::Cpu);
        let noise = Noise {
            jitter: Some(Tensor::rand([2, 64, 4], (Kind::Float, Device::Cpu))),
            importance: Some(Tensor::rand([2, 64, 4], (Kind::Float, Device::Cpu))),
        };
        let fake = FakeBatch { latents: &lat, poses: &poses, z: None, resolution: 8, regions: 1, noise: &noise };
        let real = Tensor::rand([2, 3, 8, 8], (Kind::Float, Device::Cpu));
        let rp = poses.stacked();
        let lazy = LossConfig { r1_interval: 4, r1_gamma: 2.0, ..Default::default() };
        let every = LossConfig { r1_gamma: 2.0, ..Default::default() };
        let at = |step| Schedule { step, alpha: 1.0 };
        let off = discriminator_loss(&r, &disc, &real, &rp, &fake, at(3), &lazy).unwrap();
        assert!(off.get("d_r1").is_none());
        let on = discriminator_loss(&r, &disc, &real, &rp, &fake, at(8), &lazy).unwrap();
        let base = discriminator_loss(&r, &disc, &real, &rp, &fake, at(8), &every).unwrap();
        let r1 = on.get("d_r1").unwrap().double_value(&[]);
        assert!(r1 > 0.0);
        let extra = on.total.double_value(&[]) - off.total.double_value(&[]);
        assert!((extra - 4.0 * 2.0 * r1).abs() < 1e-5 * (1.0 + extra.abs()), "{extra} vs {}", 8.0 * r1);
        let extra_every = base.total.double_value(&[]) - off.total.double_value(&[]);
        assert!((extra_every - 2.0 * r1).abs() < 1e-5 * (1.0 + extra.abs()));
    }
}
