//! The generator's objective: every term of its loss, with its weight and schedule, in one
//! place (EG3D's `training/loss.py`, where one loss object owns every term). A new term is
//! its function (in `gan`, `deform_reg` or a file of its own, as `opacity`), its weight in
//! [`LossConfig`], and a line in the method below that adds it.
// `t = t + x` on purpose: `+=` on a Tensor is an in-place add on a tensor autograd saved.
#![allow(clippy::assign_op_pattern)]
use super::coverage::{coverage_gradients, CoverageDraws};
use super::deform_reg::RegTerms;
use super::opacity::opacity_entropy;
use super::{gan, LossConfig, Losses, Schedule};
use crate::disc::DiscOutput;
use crate::render::Renderer;
use crate::{Error, Result};
use tch::Tensor;

/// The generator's objective at one step: the terms on the discriminator's verdict about
/// rendered images (adversarial, pose, latent prediction, mode seeking), the deformation
/// regularisers, and the coverage term, weighted as `cfg` schedules them at `at`.
pub struct GeneratorObjective<'a> {
    cfg: &'a LossConfig,
    at: Schedule,
}

impl<'a> GeneratorObjective<'a> {
    pub fn new(cfg: &'a LossConfig, at: Schedule) -> Self {
        Self { cfg, at }
    }

    /// The adversarial terms on the discriminator's verdict `fake` about rendered images
    /// seen from `poses: (B, 2)`: top-k adversarial loss ([`gan::g_adversarial`]), pose and
    /// (when its weight is not 0) latent prediction of the codes `z`.
    pub fn adversarial(&self, fake: &DiscOutput, poses: &Tensor, z: Option<&Tensor>) -> Result<Losses> {
        let cfg = self.cfg;
        cfg.validate()?;
        let b = fake.logit.size()[0];
        if poses.size() != [b, 2] {
            return Err(Error::Shape(format!("fake poses have shape {:?}, expected [{b}, 2]", poses.size())));
        }
        let k = gan::topk_count(self.at.step, b, cfg.topk_interval, cfg.topk_floor);
        let adv = gan::g_adversarial(cfg.adversarial, &fake.logit, k);
        let pose = gan::pose_loss_at(fake, poses, cfg.pose_min_scale);
        let mut total = &adv + &pose * cfg.pose_weight;
        let mut terms = vec![("g_adv", adv), ("g_pose", pose)];
        if cfg.latent_weight != 0.0 {
            if let Some(z) = z {
                let l = gan::latent_loss(&fake.latent, z);
                total = total + &l * cfg.latent_weight;
                terms.push(("g_latent", l));
            }
        }
        Ok(Losses { total, terms })
    }

    /// The adversarial terms plus, when the mode-seeking weight is on at this step, the
    /// mode-seeking term on the rendered images `img: (B, 3, H, W)` (consecutive pairs share
    /// a pose).
    pub fn image_terms(&self, fake: &DiscOutput, img: &Tensor, poses: &Tensor, z: Option<&Tensor>) -> Result<Losses> {
        let cfg = self.cfg;
        let mut l = self.adversarial(fake, poses, z)?;
        let weight = cfg.diversity_at(self.at.step);
        if let (true, Some(z)) = (weight != 0.0, z) {
            let b = img.size()[0];
            if b % 2 != 0 || z.size()[0] != b {
                return Err(Error::Shape(format!(
                    "the mode-seeking term needs an even batch of images with one code each, got {b} images and codes {:?}",
                    z.size()
                )));
            }
            let d = gan::mode_seeking(img, z, cfg.diversity_cap, cfg.diversity_pool);
            l.total = l.total + &d * weight;
            l.terms.push(("g_diversity", d));
        }
        Ok(l)
    }

    /// The weighted deformation regularisers (from [`Generator::regularisers`]) as a
    /// breakdown, their total scaled by the warm-up ([`LossConfig::reg_scale`]); the terms
    /// stay unweighted.
    ///
    /// [`Generator::regularisers`]: crate::Generator::regularisers
    pub fn regularisation(&self, reg: RegTerms) -> Losses {
        let scale = self.cfg.reg_scale(self.at.step);
        let total = reg.weighted_sum(&self.cfg.reg);
        let total = if scale == 1.0 { total } else { total * scale };
        Losses {
            total,
            terms: vec![
                ("reg_correction", reg.correction),
                ("reg_smoothness", reg.smoothness),
                ("reg_rigidity", reg.rigidity),
                ("reg_normal", reg.normal),
            ],
        }
    }

    /// The terms of one render: [`Self::image_terms`] + [`Self::regularisation`].
    pub fn main(
        &self,
        fake: &DiscOutput,
        img: &Tensor,
        poses: &Tensor,
        z: Option<&Tensor>,
        reg: RegTerms,
    ) -> Result<Losses> {
        let reg = self.regularisation(reg);
        Ok(self.image_terms(fake, img, poses, z)?.merge(reg))
    }

    /// Adds the opacity term to `others` when its weight is not 0: the mean binary entropy
    /// of the rendered rays' opacities `alpha()` (any shape, in [0, 1]; the object's share
    /// of each pixel, [`opacity_entropy`]), weighted into the total, unweighted in the
    /// breakdown as `g_opacity`. At weight 0 nothing is computed and `others` is returned
    /// as it is.
    pub fn add_opacity(&self, others: Losses, alpha: impl FnOnce() -> Tensor) -> Losses {
        let weight = self.cfg.opacity_weight;
        if weight == 0.0 {
            return others;
        }
        let h = opacity_entropy(&alpha());
        let Losses { total, mut terms } = others;
        let total = &total + &h * weight;
        terms.push(("g_opacity", h));
        Losses { total, terms }
    }

    /// The coverage term's weight at this step ([`LossConfig::coverage_at`]); 0: the term is
    /// not due, and nothing of it is drawn or rendered.
    pub fn coverage_weight(&self) -> f64 {
        self.cfg.coverage_at(self.at.step)
    }

    /// Adds the coverage term to `others`, the step's other terms (their gradient already
    /// taken): its gradient times its weight goes into the generator (see
    /// [`coverage_gradients`]: `renderers`, the real images `(B, 3, S, S)` seen from
    /// `real_poses: (B, 2)`, the step's `draws`, `samples` per ray, in `split` chunks), its
    /// MSE into the breakdown. An error when the real images' poses are unknown.
    pub fn add_coverage(
        &self,
        others: Losses,
        renderers: &(Renderer, Renderer),
        (real, real_poses): (&Tensor, Option<&Tensor>),
        draws: &CoverageDraws,
        (samples, split): (i64, i64),
    ) -> Result<Losses> {
        let real_poses = real_poses.ok_or_else(|| {
            Error::Config(
                "loss.coverage_weight needs the real images' poses; the dataset has none (see data.poses)".into(),
            )
        })?;
        let weight = self.coverage_weight();
        let c = coverage_gradients(renderers, real, real_poses, draws, (samples, split), self.cfg, weight)?;
        let Losses { total, mut terms } = others;
        let total = &total + &c * weight;
        terms.push(("g_coverage", c));
        Ok(Losses { total, terms })
    }
}
