//! The four deformation regularisers (minimal correction, smoothness, rigidity, normal
//! consistency) on samples near the rendered surface, as the release computes them, and
//! the paper's variant as an option.
use crate::field::generator::Generator;
use crate::nn::film::Film;
use crate::render::RenderedRays;
use serde::{Deserialize, Serialize};
use tch::{Kind, Tensor};

/// Which formulation of the regularisers to use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RegVariant {
    /// The authors' release: 5 % of the rays (with replacement); all their samples for
    /// correction, smoothness and rigidity; the 20 % of each ray's samples closest to the
    /// expected depth for normal consistency; means; smoothness = mean of the Jacobian's
    /// row norms; rigidity = 0.5·‖JᵀJ − I‖_F.
    Release,
    /// The paper's text: the 5 % of all samples of an image closest to their ray's
    /// surface for every term; sums over those samples (averaged over images);
    /// smoothness = ‖J_Δx‖_F; rigidity = ‖JᵀJ − I‖_F.
    Paper,
}

/// Selection ratios and weights of the regularisers (defaults: CHAIR_128).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RegConfig {
    pub variant: RegVariant,
    /// Release: fraction of an image's rays drawn (with replacement).
    pub ray_ratio: f64,
    /// Release: fraction of each drawn ray's samples that count as near the surface.
    pub near_ratio: f64,
    /// Paper: fraction of an image's samples closest to the surface.
    pub sample_ratio: f64,
    pub correction: f64,
    pub smoothness: f64,
    pub rigidity: f64,
    pub normal: f64,
}

impl Default for RegConfig {
    fn default() -> Self {
        Self {
            variant: RegVariant::Release,
            ray_ratio: 0.05,
            near_ratio: 0.2,
            sample_ratio: 0.05,
            correction: 1e-2,
            smoothness: 1.0,
            rigidity: 0.1,
            normal: 5.0,
        }
    }
}

/// Sample points for the regularisers: `near: (B, Pn, 3)` (normal consistency and, in the
/// paper variant, everything) and `rest: (B, Pr, 3)` (the other samples of the drawn rays).
#[derive(Debug)]
pub struct RegSamples {
    pub near: Tensor,
    pub rest: Option<Tensor>,
}

/// Number of drawn rays per image in the release variant.
pub fn reg_ray_count(rays: i64, cfg: &RegConfig) -> i64 {
    ((cfg.ray_ratio * rays as f64).round() as i64).max(1)
}

/// Picks the regulariser samples from a render (no gradient flows through the choice).
/// `ray_idx: (B, n)` are the drawn rays (release variant); `None` draws them uniformly
/// with replacement.
pub fn select_samples(r: &RenderedRays, cfg: &RegConfig, ray_idx: Option<&Tensor>) -> RegSamples {
    tch::no_grad(|| {
        let (b, rays, s) = (r.z.size()[0], r.z.size()[1], r.z.size()[2]);
        let z = r.z.detach();
        let depth = r.depth.detach();
        match cfg.variant {
            RegVariant::Release => {
                let n = reg_ray_count(rays, cfg);
                let idx = match ray_idx {
                    Some(i) => i.shallow_clone(),
                    None => Tensor::randint(rays, [b, n], (Kind::Int64, z.device())),
                };
                let z_sel = z.gather(1, &idx.unsqueeze(-1).expand([b, n, s], false), false);
                let d_sel = depth.gather(1, &idx.unsqueeze(-1), false);
                // Points of the drawn rays only (5 % of the image).
                let ray3 = idx.unsqueeze(-1).expand([b, n, 3], false);
                let (o_sel, dir_sel) = (r.origins.gather(1, &ray3, false), r.dirs.gather(1, &ray3, false));
                let p_sel = o_sel.unsqueeze(2) + dir_sel.unsqueeze(2) * z_sel.unsqueeze(-1);
                let order = (&z_sel - d_sel).abs().argsort(-1, false);
                let k = ((cfg.near_ratio * s as f64).round() as i64).clamp(1, s);
                let take = |o: Tensor| {
                    let m = o.size()[2];
                    p_sel.gather(2, &o.unsqueeze(-1).expand([b, n, m, 3], false), false).reshape([b, n * m, 3])
                };
                let rest = (k < s).then(|| take(order.narrow(2, k, s - k)));
                RegSamples { near: take(order.narrow(2, 0, k)), rest }
            }
            RegVariant::Paper => {
                let dist = (z - depth).abs().view([b, rays * s]);
                let k = ((cfg.sample_ratio * (rays * s) as f64).round() as i64).clamp(1, rays * s);
                let idx = dist.topk(k, 1, false, true).1;
                let pts = r.points().detach().view([b, rays * s, 3]);
                let near = pts.gather(1, &idx.unsqueeze(-1).expand([b, k, 3], false), false);
                RegSamples { near, rest: None }
            }
        }
    })
}

/// Unweighted regulariser values (scalars).
#[derive(Debug)]
pub struct RegTerms {
    pub correction: Tensor,
    pub smoothness: Tensor,
    pub rigidity: Tensor,
    pub normal: Tensor,
}

impl RegTerms {
    pub fn weighted_sum(&self, cfg: &RegConfig) -> Tensor {
        &self.correction * cfg.correction
            + &self.smoothness * cfg.smoothness
            + &self.rigidity * cfg.rigidity
            + &self.normal * cfg.normal
    }
}

/// L2 norm over the last axis with a zero subgradient at the zero vector (libtorch's
/// norm backward), so the exactly-zero Jacobian at initialisation has finite gradients.
fn norm(x: &Tensor) -> Tensor {
    x.linalg_norm(2.0, [-1i64].as_slice(), false, x.kind())
}

/// The stop-gradient target ∇σ: the full target-space gradient of the raw final density
/// `sigma` w.r.t. the points `x` it was computed from (graph kept, no second order).
pub fn density_gradient(x: &Tensor, sigma: &Tensor) -> Tensor {
    Tensor::run_backward(&[sigma.sum(sigma.kind())], &[x], true, false).remove(0).detach()
}

/// Per-point 1 − cos(∇σ_t, target) with ∇σ_t = ∂σ_t/∂x_t taken w.r.t. the template-space
/// points `x_t = x + Δx` themselves, so its gradient reaches T_σ and, through x_t, the
/// deformation. Zero vectors give cos = 0 with finite gradients (libtorch clamps the norms
/// by eps = 1e-8). `x_t`, `target: (B, P, 3)`, `sigma_t: (B, P, 1)` → `(B, P)`.
pub fn normal_distance(x_t: &Tensor, sigma_t: &Tensor, target: &Tensor) -> Tensor {
    let grad_t = Tensor::run_backward(&[sigma_t.sum(sigma_t.kind())], &[x_t], true, true).remove(0);
    -Tensor::cosine_similarity(&grad_t, target, -1, 1e-8) + 1.0
}

/// Computes the four regularisers for shape modulation `shape` (one row per image) through
/// the generator's shape-side queries ([`Generator::deformation`],
/// [`Generator::template_density`]). Autograd is enabled inside (the terms are built from
/// spatial gradients), so this also works when called under `no_grad`, e.g. for finite
/// differences. [`Generator::regularisers`] is the same call.
pub fn regularisers(gen: &Generator, shape: &Film, samples: &RegSamples, variant: RegVariant) -> RegTerms {
    tch::with_grad(|| regularisers_with_grad(gen, shape, samples, variant))
}

fn regularisers_with_grad(gen: &Generator, shape: &Film, samples: &RegSamples, variant: RegVariant) -> RegTerms {
    let near = samples.near.detach();
    let pn = near.size()[1];
    let x = match &samples.rest {
        Some(rest) => Tensor::cat(&[near, rest.detach()], 1),
        None => near,
    }
    .set_requires_grad(true);
    let (b, p) = (x.size()[0], x.size()[1]);
    let (dx, dsigma) = gen.deformation(&x, shape);

    // Jacobian rows ∂Δx_i/∂x by three reverse passes, kept differentiable.
    let rows: Vec<Tensor> =
        (0..3).map(|i| Tensor::run_backward(&[dx.select(2, i).sum(dx.kind())], &[&x], true, true).remove(0)).collect();
    let jac = Tensor::stack(&rows, 2); // (B, P, 3, 3), row i = ∇Δx_i
    let eye = Tensor::eye(3, (x.kind(), x.device()));
    let j = &jac + &eye;
    let strain = j.transpose(-1, -2).matmul(&j) - &eye;

    // Normal consistency on the near samples, against the stop-gradient target.
    let x_t = x.narrow(1, 0, pn) + dx.narrow(1, 0, pn);
    let (_, sigma_t) = gen.template_density(&x_t);
    let target = density_gradient(&x, &(&sigma_t + dsigma.narrow(1, 0, pn))).narrow(1, 0, pn);
    let cos_dist = normal_distance(&x_t, &sigma_t, &target);

    match variant {
        RegVariant::Release => RegTerms {
            correction: dsigma.abs().mean(dsigma.kind()),
            smoothness: norm(&jac).mean(jac.kind()),
            rigidity: norm(&strain.view([b, p, 9])).mean(jac.kind()) * 0.5,
            normal: cos_dist.mean(cos_dist.kind()),
        },
        RegVariant::Paper => {
            let per_image = |t: Tensor| t.sum(t.kind()) / b as f64;
            RegTerms {
                correction: per_image(dsigma.abs()),
                smoothness: per_image(norm(&jac.view([b, p, 9]))),
                rigidity: per_image(norm(&strain.view([b, p, 9]))),
                normal: per_image(cos_dist),
            }
        }
    }
}
