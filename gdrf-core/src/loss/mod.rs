//! Training losses: the generator's objective (adversarial, pose, latent prediction, mode
//! seeking, the deformation regularisers and the coverage term: [`GeneratorObjective`]) and
//! the discriminator's loss (logistic, R1, pose), each with a named breakdown.
//!
//! Losses take what was rendered and judged — discriminator outputs, poses, regulariser
//! terms — and never render: the training loop renders once and decides what carries
//! gradients (the two-pass patch step differentiates the image, then each band).
// `t = t + x` on purpose: `+=` on a Tensor is an in-place add on a tensor autograd saved.
#![allow(clippy::assign_op_pattern)]
pub mod coverage;
pub mod deform_reg;
pub mod gan;
mod objective;
pub mod opacity;

use crate::disc::DiscOutput;
use crate::error::require;
use crate::{Error, Result};
use deform_reg::RegConfig;
pub use objective::GeneratorObjective;
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
    /// Whether the discriminator's pose head also learns the poses of generated images
    /// (true, the release). With `false` it learns from real images alone (their poses must
    /// be known), so the generator's pose loss asks for images whose pose reads as a real
    /// image's does, not as the discriminator has learned to read the generator's own.
    pub d_pose_fakes: bool,
    /// Under the scaled-patch step, the pose terms (the discriminator's on reals and fakes,
    /// the generator's) count only the images judged through patches of at least this scale
    /// of the image's side ([`gan::pose_loss_at`]): a small patch shows too little of the
    /// object for its pose to be read, and the discriminator's pose head then learns noise
    /// that its gradient passes on to the generator. 0 (the default) counts every patch, 1
    /// only whole images. Whole-image stages are not affected.
    pub pose_min_scale: f64,
    /// Weight of the latent-prediction loss (0 in the release).
    pub latent_weight: f64,
    /// Weight of the capped mode-seeking term on the generator (0 in the release; see
    /// [`gan::mode_seeking`]). When on, the generator's batch is rendered in pairs of codes
    /// sharing a pose.
    pub diversity_weight: f64,
    /// Image difference per unit of code distance above which the mode-seeking term is 0.
    pub diversity_cap: f64,
    /// The mode-seeking term compares images averaged over blocks of this many pixels
    /// per side (1 = every pixel).
    pub diversity_pool: i64,
    /// The mode-seeking weight falls linearly from `diversity_weight` at step 0 to 0 at this
    /// step, after which the term is off and the generator's batch is no longer rendered in
    /// pairs (0 = a constant weight). The term breaks the symmetry of a fresh generator; late
    /// in a run it only rewards codes for differing, also by an object turned per code.
    pub diversity_decay: i64,
    /// The deformation regularisers' weights ramp linearly from 0 over this many steps
    /// (0 = full weight from step 0, as in the release), so that shapes can first vary with
    /// the code before smoothness, rigidity and normal consistency pull them together.
    pub reg_warmup: i64,
    /// Weight of the coverage term (0 = off, as in the release): implicit maximum likelihood
    /// (IMLE, Li & Malik 2018) on the generator. For each real image of the step,
    /// `coverage_candidates` random codes are rendered at the real image's pose at
    /// `coverage_resolution` without gradients; the nearest (pixel MSE) is rendered again at
    /// the stage's resolution with gradients and pulled toward the real image by MSE. Every
    /// real image thus claims a code, so the generator cannot cover the data with one
    /// object. Needs the real images' poses.
    pub coverage_weight: f64,
    pub coverage_candidates: i64,
    pub coverage_resolution: i64,
    /// Apply the coverage term every k steps only, scaled by k (lazily, as `r1_interval`
    /// does for R1); 1 = every step. Its renders cost about as much as the rest of a
    /// 32² step, so a long run takes it lazily.
    pub coverage_interval: i64,
    /// Top-k schedule: p = max(0.99^(step/interval), floor).
    pub topk_interval: f64,
    pub topk_floor: f64,
    /// The adversarial loss: `"logistic"` (the release's non-saturating logistic loss) or
    /// `"hinge"` (the projected GAN's).
    pub adversarial: gan::Adversarial,
    /// Weight of the opacity term (0 = off, the release): the mean binary entropy of each
    /// generated ray's opacity, the share of its pixel the object covers
    /// ([`opacity::opacity_entropy`]). One ray through each pixel's centre cannot antialias a
    /// silhouette as the real images are antialiased, so the adversarial loss alone rewards
    /// a fringe of low density that softens the edge; the term asks each ray to be object or
    /// background (docs/campaign-log.md, "The curve at 64²"). Whole-image and scaled-patch
    /// steps only (not the two-pass `regions` step).
    #[serde(skip_serializing_if = "crate::config::is_zero")]
    pub opacity_weight: f64,
    pub reg: RegConfig,
}

impl Default for LossConfig {
    fn default() -> Self {
        Self {
            r1_gamma: 1.0,
            r1_interval: 1,
            pose_weight: 15.0,
            d_pose_fakes: true,
            pose_min_scale: 0.0,
            latent_weight: 0.0,
            diversity_weight: 0.0,
            diversity_cap: 0.1,
            diversity_pool: 4,
            diversity_decay: 0,
            reg_warmup: 0,
            coverage_weight: 0.0,
            coverage_candidates: 16,
            coverage_resolution: 16,
            coverage_interval: 1,
            topk_interval: 2000.0,
            topk_floor: 0.6,
            adversarial: gan::Adversarial::Logistic,
            opacity_weight: 0.0,
            reg: RegConfig::default(),
        }
    }
}

impl LossConfig {
    pub fn validate(&self) -> Result<()> {
        require(self.r1_interval >= 1, "loss.r1_interval", self.r1_interval, "at least 1")?;
        if !(self.topk_interval > 0.0 && (0.0..=1.0).contains(&self.topk_floor)) {
            return Err(Error::Config(format!(
                "loss.topk_interval {} must be positive and loss.topk_floor {} in [0, 1]",
                self.topk_interval, self.topk_floor
            )));
        }
        require(
            self.diversity_weight >= 0.0 && self.diversity_weight.is_finite(),
            "loss.diversity_weight",
            self.diversity_weight,
            "0 (off) or a positive weight",
        )?;
        require(
            self.coverage_weight >= 0.0 && self.coverage_weight.is_finite(),
            "loss.coverage_weight",
            self.coverage_weight,
            "0 (off) or a positive weight",
        )?;
        require(
            self.opacity_weight >= 0.0 && self.opacity_weight.is_finite(),
            "loss.opacity_weight",
            self.opacity_weight,
            "0 (off) or a positive weight",
        )?;
        require(self.coverage_candidates >= 1, "loss.coverage_candidates", self.coverage_candidates, "at least 1")?;
        require(
            (2..=512).contains(&self.coverage_resolution),
            "loss.coverage_resolution",
            self.coverage_resolution,
            "2 to 512 pixels",
        )?;
        require(
            (0.0..=1.0).contains(&self.pose_min_scale),
            "loss.pose_min_scale",
            self.pose_min_scale,
            "a scale in [0, 1] (0 every patch, 1 whole images only)",
        )?;
        require(self.coverage_interval >= 1, "loss.coverage_interval", self.coverage_interval, "at least 1")?;
        require(
            self.diversity_decay >= 0,
            "loss.diversity_decay",
            self.diversity_decay,
            "0 (a constant weight) or a number of steps",
        )?;
        require(self.reg_warmup >= 0, "loss.reg_warmup", self.reg_warmup, "0 (off) or a number of steps")?;
        require(self.diversity_pool >= 1, "loss.diversity_pool", self.diversity_pool, "at least 1")?;
        require(
            self.diversity_cap > 0.0 && self.diversity_cap.is_finite(),
            "loss.diversity_cap",
            self.diversity_cap,
            "a positive number",
        )?;
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

impl Losses {
    /// Joins two breakdowns: totals added, terms concatenated.
    pub fn merge(self, other: Losses) -> Losses {
        let mut terms = self.terms;
        terms.extend(other.terms);
        Losses { total: self.total + other.total, terms }
    }
}

impl LossConfig {
    /// The regularisers' weight factor at `step`: min(1, step / reg_warmup).
    pub fn reg_scale(&self, step: i64) -> f64 {
        if self.reg_warmup <= 0 {
            1.0
        } else {
            (step.max(0) as f64 / self.reg_warmup as f64).min(1.0)
        }
    }

    /// The mode-seeking weight at `step`: `diversity_weight`, falling linearly to 0 at
    /// `diversity_decay` when that is set.
    pub fn diversity_at(&self, step: i64) -> f64 {
        if self.diversity_decay <= 0 {
            self.diversity_weight
        } else {
            self.diversity_weight * (1.0 - step.max(0) as f64 / self.diversity_decay as f64).max(0.0)
        }
    }

    /// Whether R1 is applied at `step` (lazy R1 applies it every `r1_interval` steps).
    /// The caller makes the real images require grad on those steps.
    pub fn r1_due(&self, step: i64) -> bool {
        self.r1_gamma != 0.0 && step % self.r1_interval == 0
    }

    /// The coverage term's weight at `step`: `coverage_weight · coverage_interval` on the
    /// steps where the lazy term is due, else 0 (and the term is not rendered).
    pub fn coverage_at(&self, step: i64) -> f64 {
        if self.coverage_weight > 0.0 && step % self.coverage_interval == 0 {
            self.coverage_weight * self.coverage_interval as f64
        } else {
            0.0
        }
    }
}

/// Training state the losses depend on.
#[derive(Debug, Clone, Copy)]
pub struct Schedule {
    pub step: i64,
    /// Discriminator fade-in α.
    pub alpha: f64,
}

/// The discriminator's loss from its verdicts on real images and on (detached) fakes:
/// adversarial terms ([`gan::d_adversarial`]), R1 on the reals when due ([`LossConfig::r1_due`]; lazily every
/// `r1_interval` steps, scaled by it — `real_images` must then be the tensor `real` was
/// computed from, with requires_grad), pose on fakes (`fake_poses: (B, 2)`; logged but not
/// trained on with `d_pose_fakes = false`) and on reals (when `real_poses` are known).
/// An error when the pose head would learn from nothing: `d_pose_fakes = false`, a pose
/// weight and no real poses.
#[allow(clippy::too_many_arguments)]
pub fn discriminator_loss(
    real: &DiscOutput,
    real_images: &Tensor,
    real_poses: Option<&Tensor>,
    fake: &DiscOutput,
    fake_poses: &Tensor,
    z: Option<&Tensor>,
    at: Schedule,
    cfg: &LossConfig,
) -> Result<Losses> {
    cfg.validate()?;
    let (d_real, d_fake) = gan::d_adversarial(cfg.adversarial, &real.logit, &fake.logit);
    if !cfg.d_pose_fakes && cfg.pose_weight != 0.0 && real_poses.is_none() {
        return Err(Error::Config(
            "loss.d_pose_fakes = false trains the discriminator's pose head on real images only, \
             and these real images have no poses (see data.poses)"
                .into(),
        ));
    }
    let pose_fake = gan::pose_loss_at(fake, fake_poses, cfg.pose_min_scale);
    let mut total = &d_real + &d_fake;
    if cfg.d_pose_fakes {
        total = total + &pose_fake * cfg.pose_weight;
    }
    let mut terms = vec![("d_real", d_real), ("d_fake", d_fake)];
    if cfg.r1_due(at.step) {
        let r1 = gan::r1_penalty(&real.logit, real_images)?;
        total = total + &r1 * (cfg.r1_gamma * cfg.r1_interval as f64);
        terms.push(("d_r1", r1));
    }
    terms.push(("d_pose_fake", pose_fake));
    if let Some(rp) = real_poses {
        let pose_real = gan::pose_loss_at(real, rp, cfg.pose_min_scale);
        total = total + &pose_real * cfg.pose_weight;
        terms.push(("d_pose_real", pose_real));
    }
    if cfg.latent_weight != 0.0 {
        if let Some(z) = z {
            let l = gan::latent_loss(&fake.latent, z);
            total = total + &l * cfg.latent_weight;
            terms.push(("d_latent", l));
        }
    }
    Ok(Losses { total, terms })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::disc::Discriminator;
    use deform_reg::RegTerms;
    use tch::{nn, Device, Kind};

    #[test]
    fn bad_loss_settings_are_named() {
        let e = LossConfig { r1_interval: 0, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("r1_interval"), "{e}");
        assert!(LossConfig { topk_floor: 1.5, ..Default::default() }.validate().is_err());
        let e = LossConfig { coverage_interval: 0, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("loss.coverage_interval is 0"), "{e}");
        LossConfig::default().validate().unwrap();
    }

    #[test]
    fn the_lazy_coverage_term_weighs_k_times_on_every_kth_step() {
        let off = LossConfig { coverage_interval: 3, ..Default::default() };
        assert!((0..7).all(|s| off.coverage_at(s) == 0.0));
        let every = LossConfig { coverage_weight: 0.5, ..Default::default() };
        assert!((0..7).all(|s| every.coverage_at(s) == 0.5));
        let lazy = LossConfig { coverage_interval: 3, ..every };
        let w: Vec<f64> = (0..7).map(|s| lazy.coverage_at(s)).collect();
        assert_eq!(w, [1.5, 0.0, 0.0, 1.5, 0.0, 0.0, 1.5]);
    }

    #[test]
    fn lazy_r1_applies_every_k_steps_scaled_by_k() {
        tch::manual_seed(0);
        let dvs = nn::VarStore::new(Device::Cpu);
        let disc = Discriminator::new(&dvs.root());
        let fake_img = Tensor::rand([2, 3, 8, 8], (Kind::Float, Device::Cpu));
        let real = Tensor::rand([2, 3, 8, 8], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let poses = Tensor::from_slice(&[1.0f32, 0.0, 1.2, 2.0]).view([2, 2]);
        let (dr, df) = (disc.forward(&real, 1.0).unwrap(), disc.forward(&fake_img, 1.0).unwrap());
        let lazy = LossConfig { r1_interval: 4, r1_gamma: 2.0, ..Default::default() };
        let every = LossConfig { r1_gamma: 2.0, ..Default::default() };
        assert!(!lazy.r1_due(3) && lazy.r1_due(8) && every.r1_due(3));
        let at = |step| Schedule { step, alpha: 1.0 };
        let loss = |step, cfg: &LossConfig| {
            discriminator_loss(&dr, &real, Some(&poses), &df, &poses, None, at(step), cfg).unwrap()
        };
        let off = loss(3, &lazy);
        assert!(off.get("d_r1").is_none());
        let on = loss(8, &lazy);
        let base = loss(8, &every);
        let r1 = on.get("d_r1").unwrap().double_value(&[]);
        assert!(r1 > 0.0);
        let extra = on.total.double_value(&[]) - off.total.double_value(&[]);
        assert!((extra - 4.0 * 2.0 * r1).abs() < 1e-5 * (1.0 + extra.abs()), "{extra} vs {}", 8.0 * r1);
        let extra_every = base.total.double_value(&[]) - off.total.double_value(&[]);
        assert!((extra_every - 2.0 * r1).abs() < 1e-5 * (1.0 + extra.abs()));
        // R1 due on images that do not require grad is an error, not a silent zero.
        let plain = real.detach();
        let dp = disc.forward(&plain, 1.0).unwrap();
        assert!(discriminator_loss(&dp, &plain, None, &df, &poses, None, at(8), &lazy).is_err());
    }

    #[test]
    fn the_pose_head_can_learn_from_real_images_alone() {
        let out = |logit: [f64; 2], pose: [f64; 4]| DiscOutput {
            logit: Tensor::from_slice(&logit).view([2, 1]),
            latent: Tensor::zeros([2, 256], (Kind::Double, Device::Cpu)),
            pose: Tensor::from_slice(&pose).view([2, 2]),
            scale: None,
        };
        let (real, fake) = (out([0.5, -0.2], [1.0, 0.0, 1.0, 0.5]), out([-0.4, 0.1], [0.0, 0.0, 0.5, 0.0]));
        let real_poses = Tensor::from_slice(&[1.0f64, 0.25, 1.0, 0.5]).view([2, 2]);
        let fake_poses = Tensor::from_slice(&[1.0f64, 0.0, 1.0, 0.0]).view([2, 2]);
        let img = Tensor::zeros([2, 3, 4, 4], (Kind::Double, Device::Cpu));
        let at = Schedule { step: 1, alpha: 1.0 };
        let release = LossConfig { r1_interval: 2, ..Default::default() };
        let real_only = LossConfig { d_pose_fakes: false, ..release.clone() };
        let loss = |cfg: &LossConfig| {
            discriminator_loss(&real, &img, Some(&real_poses), &fake, &fake_poses, None, at, cfg).unwrap()
        };
        let adv = Tensor::from_slice(&[-0.5f64, 0.2]).softplus().mean(Kind::Double).double_value(&[])
            + Tensor::from_slice(&[-0.4f64, 0.1]).softplus().mean(Kind::Double).double_value(&[]);
        // Mean of 1 − cos over both angles: the reals miss by 0.25 in one yaw, the fakes by
        // 1 in one pitch and 0.5 in the other.
        let pose_real = (1.0 - 0.25f64.cos()) / 4.0;
        let pose_fake = ((1.0 - 1.0f64.cos()) + (1.0 - 0.5f64.cos())) / 4.0;
        let (with, without) = (loss(&release), loss(&real_only));
        assert!((with.total.double_value(&[]) - (adv + 15.0 * (pose_real + pose_fake))).abs() < 1e-12);
        assert!((without.total.double_value(&[]) - (adv + 15.0 * pose_real)).abs() < 1e-12);
        // The fakes' pose error is still logged.
        assert!((without.get("d_pose_fake").unwrap().double_value(&[]) - pose_fake).abs() < 1e-12);
        let e = discriminator_loss(&real, &img, None, &fake, &fake_poses, None, at, &real_only).unwrap_err();
        assert!(e.to_string().contains("loss.d_pose_fakes") && e.to_string().contains("data.poses"), "{e}");
        // Without the pose loss there is nothing to learn, and no real poses are needed.
        let no_pose = LossConfig { pose_weight: 0.0, ..real_only };
        discriminator_loss(&real, &img, None, &fake, &fake_poses, None, at, &no_pose).unwrap();
    }

    #[test]
    fn the_pose_terms_count_only_patches_above_the_bound() {
        let out = |scale: Option<[f64; 2]>| DiscOutput {
            logit: Tensor::from_slice(&[0.5f64, -0.2]).view([2, 1]),
            latent: Tensor::zeros([2, 256], (Kind::Double, Device::Cpu)),
            pose: Tensor::from_slice(&[1.0f64, 0.0, 0.0, 0.5]).view([2, 2]),
            scale: scale.map(|s| Tensor::from_slice(&s)),
        };
        let poses = Tensor::zeros([2, 2], (Kind::Double, Device::Cpu));
        // Per image, 1 − cos over both angles: image 0 misses by 1, image 1 by 0.5.
        let (p0, p1) = (1.0 - 1.0f64.cos(), 1.0 - 0.5f64.cos());
        let every = LossConfig { r1_gamma: 0.0, ..Default::default() };
        let bounded = LossConfig { pose_min_scale: 0.9, ..every.clone() };
        let at = Schedule { step: 1, alpha: 1.0 };
        let img = Tensor::zeros([2, 3, 4, 4], (Kind::Double, Device::Cpu));
        let d_pose = |o: &DiscOutput, cfg: &LossConfig| {
            let l = discriminator_loss(o, &img, Some(&poses), o, &poses, None, at, cfg).unwrap();
            let g = GeneratorObjective::new(cfg, at).adversarial(o, &poses, None).unwrap();
            let v = |l: &Losses, k: &str| l.get(k).unwrap().double_value(&[]);
            (v(&l, "d_pose_real"), v(&l, "d_pose_fake"), v(&g, "g_pose"))
        };
        // Image 1's patch (scale 0.5) is below the bound: its term is 0, the mean over both.
        let patches = out(Some([0.95, 0.5]));
        for v in <[f64; 3]>::from(d_pose(&patches, &bounded)) {
            assert!((v - p0 / 4.0).abs() < 1e-15, "{v}");
        }
        // The bound itself counts; no bound, or whole images, count every image.
        let at_bound = d_pose(&out(Some([0.9, 0.9])), &bounded);
        for v in [at_bound, d_pose(&patches, &every), d_pose(&out(None), &bounded)] {
            for x in <[f64; 3]>::from(v) {
                assert!((x - (p0 + p1) / 4.0).abs() < 1e-15, "{x}");
            }
        }
        let e = LossConfig { pose_min_scale: 1.5, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("loss.pose_min_scale"), "{e}");
    }

    #[test]
    fn generator_total_is_adversarial_plus_weighted_regularisers() {
        let logit = Tensor::from_slice(&[0.3f64, -1.0]).view([2, 1]);
        let d = DiscOutput {
            logit,
            latent: Tensor::zeros([2, 256], (Kind::Double, Device::Cpu)),
            pose: Tensor::zeros([2, 2], (Kind::Double, Device::Cpu)),
            scale: None,
        };
        let poses = Tensor::from_slice(&[0.5f64, 0.0, 1.0, 0.0]).view([2, 2]);
        let c = |v: f64| Tensor::from(v);
        let reg = RegTerms { correction: c(2.0), smoothness: c(3.0), rigidity: c(4.0), normal: c(0.5) };
        let cfg = LossConfig::default();
        let img = Tensor::zeros([2, 3, 4, 4], (Kind::Double, Device::Cpu));
        let l =
            GeneratorObjective::new(&cfg, Schedule { step: 0, alpha: 1.0 }).main(&d, &img, &poses, None, reg).unwrap();
        let adv = (Tensor::from_slice(&[-0.3f64, 1.0])).softplus().mean(Kind::Double).double_value(&[]);
        let pose = ((1.0 - 0.5f64.cos()) + (1.0 - 1.0f64.cos())) / 4.0;
        let want = adv + 15.0 * pose + 0.01 * 2.0 + 3.0 + 0.1 * 4.0 + 5.0 * 0.5;
        assert!((l.total.double_value(&[]) - want).abs() < 1e-12);
        let names: Vec<_> = l.terms.iter().map(|t| t.0).collect();
        assert_eq!(names, ["g_adv", "g_pose", "reg_correction", "reg_smoothness", "reg_rigidity", "reg_normal"]);
        assert!(GeneratorObjective::new(&cfg, Schedule { step: 0, alpha: 1.0 })
            .adversarial(&d, &poses.narrow(0, 0, 1), None)
            .is_err());

        // With the mode-seeking term on: two equal images of codes 2 apart in every entry
        // add weight × cap (ratio 0).
        let z = Tensor::from_slice(&[1.0f64, 1.0, -1.0, -1.0]).view([2, 2]);
        let on = LossConfig { diversity_weight: 3.0, diversity_cap: 0.2, ..Default::default() };
        let terms = |cfg: &LossConfig, img: &Tensor| {
            GeneratorObjective::new(cfg, Schedule { step: 0, alpha: 1.0 })
                .image_terms(&d, img, &poses, Some(&z))
                .unwrap()
        };
        let (with, without) = (terms(&on, &img), terms(&cfg, &img));
        assert_eq!(f64::try_from(with.get("g_diversity").unwrap()).unwrap(), 0.2);
        assert!((with.total.double_value(&[]) - without.total.double_value(&[]) - 0.6).abs() < 1e-12);
        assert!(without.get("g_diversity").is_none());
        let odd = Tensor::zeros([3, 3, 4, 4], (Kind::Double, Device::Cpu));
        assert!(GeneratorObjective::new(&on, Schedule { step: 0, alpha: 1.0 })
            .image_terms(&d, &odd, &poses, Some(&z))
            .is_err());
        let e = LossConfig { diversity_weight: -1.0, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("loss.diversity_weight"), "{e}");
        assert!(LossConfig { diversity_cap: 0.0, ..Default::default() }.validate().is_err());
        assert!(LossConfig { diversity_pool: 0, ..Default::default() }.validate().is_err());
        // The mode-seeking decay: 40 → 30 at a quarter, 0 from the decay step on, where the
        // term is no longer added.
        let decaying = LossConfig { diversity_weight: 40.0, diversity_decay: 1000, ..on.clone() };
        let w: Vec<f64> = [0, 250, 1000, 5000].iter().map(|&s| decaying.diversity_at(s)).collect();
        assert_eq!(w, [40.0, 30.0, 0.0, 0.0]);
        assert_eq!(on.diversity_at(1_000_000), 3.0);
        let late = GeneratorObjective::new(&decaying, Schedule { step: 1000, alpha: 1.0 }).image_terms(
            &d,
            &img,
            &poses,
            Some(&z),
        );
        assert!(late.unwrap().get("g_diversity").is_none());
        let e = LossConfig { diversity_decay: -1, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("loss.diversity_decay"), "{e}");
        // The regularisers' warm-up: none at step 0, half way at 50, full from 100 on.
        let warm = LossConfig { reg_warmup: 100, ..Default::default() };
        assert_eq!(
            (warm.reg_scale(0), warm.reg_scale(50), warm.reg_scale(100), warm.reg_scale(400)),
            (0.0, 0.5, 1.0, 1.0)
        );
        assert_eq!(LossConfig::default().reg_scale(0), 1.0);
        let c = |v: f64| Tensor::from(v);
        let terms = || RegTerms { correction: c(2.0), smoothness: c(3.0), rigidity: c(4.0), normal: c(0.5) };
        let at = |step| Schedule { step, alpha: 1.0 };
        let early = GeneratorObjective::new(&warm, at(25)).main(&d, &img, &poses, None, terms()).unwrap();
        let late = GeneratorObjective::new(&warm, at(200)).main(&d, &img, &poses, None, terms()).unwrap();
        let reg_full = 0.01 * 2.0 + 3.0 + 0.1 * 4.0 + 5.0 * 0.5;
        let gap = late.total.double_value(&[]) - early.total.double_value(&[]);
        assert!((gap - 0.75 * reg_full).abs() < 1e-12, "{gap}");
        assert_eq!(early.get("reg_smoothness").unwrap().double_value(&[]), 3.0);
        assert!(LossConfig { reg_warmup: -1, ..Default::default() }.validate().is_err());
    }
}
