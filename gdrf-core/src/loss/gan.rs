//! Adversarial terms: non-saturating logistic or hinge losses, R1, the pose loss and top-k.
use crate::disc::DiscOutput;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use tch::Tensor;

/// D's loss on fakes, mean softplus(logit). `logit: (B, 1)`.
pub fn d_fake(logit: &Tensor) -> Tensor {
    logit.softplus().mean(logit.kind())
}

/// D's loss on reals, mean softplus(−logit).
pub fn d_real(logit: &Tensor) -> Tensor {
    (-logit).softplus().mean(logit.kind())
}

/// G's non-saturating loss over the `k` largest logits: mean softplus(−logit).
pub fn g_nonsaturating(logit: &Tensor, k: i64) -> Tensor {
    (-top(logit, k)).softplus().mean(logit.kind())
}

/// Which adversarial loss both players use.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Adversarial {
    /// The release's: D softplus(−real) + softplus(fake), G softplus(−fake).
    #[default]
    Logistic,
    /// The projected GAN's (and BigGAN's): D relu(1 − real) + relu(1 + fake), G −fake.
    /// D stops pushing a logit once it is past the margin, so a discriminator that
    /// separates the two sets early cannot drive its logits, and G's loss, without bound.
    Hinge,
}

/// D's loss on reals with mean relu(1 − logit).
pub fn d_real_hinge(logit: &Tensor) -> Tensor {
    (-logit + 1.0).relu().mean(logit.kind())
}

/// D's loss on fakes with mean relu(1 + logit).
pub fn d_fake_hinge(logit: &Tensor) -> Tensor {
    (logit + 1.0).relu().mean(logit.kind())
}

/// G's hinge loss over the `k` largest logits: −mean(logit).
pub fn g_hinge(logit: &Tensor, k: i64) -> Tensor {
    -top(logit, k).mean(logit.kind())
}

/// D's (real, fake) terms under `loss`.
pub fn d_adversarial(loss: Adversarial, real: &Tensor, fake: &Tensor) -> (Tensor, Tensor) {
    match loss {
        Adversarial::Logistic => (d_real(real), d_fake(fake)),
        Adversarial::Hinge => (d_real_hinge(real), d_fake_hinge(fake)),
    }
}

/// G's term under `loss` over the `k` largest logits.
pub fn g_adversarial(loss: Adversarial, fake: &Tensor, k: i64) -> Tensor {
    match loss {
        Adversarial::Logistic => g_nonsaturating(fake, k),
        Adversarial::Hinge => g_hinge(fake, k),
    }
}

/// The `k` largest of a `(B, 1)` batch of logits, flattened (all of them when k ≥ B).
fn top(logit: &Tensor, k: i64) -> Tensor {
    let l = logit.view([-1]);
    if k < l.size()[0] {
        l.topk(k, 0, true, true).0
    } else {
        l
    }
}

/// The release's top-k schedule: p = max(0.99^(step/interval), v), k = ⌈p·n⌉.
pub fn topk_count(step: i64, n: i64, interval: f64, v: f64) -> i64 {
    let p = 0.99f64.powf(step as f64 / interval).max(v);
    ((p * n as f64).ceil() as i64).clamp(1, n)
}

/// R1: 0.5 · mean_b ‖∂Σlogit/∂x_b‖² on real images `x: (B, 3, H, W)` that require grad.
/// The gradient is taken with `create_graph` so that the penalty trains D.
pub fn r1_penalty(real_logit: &Tensor, real: &Tensor) -> Result<Tensor> {
    if !real.requires_grad() || !real_logit.requires_grad() {
        return Err(Error::Invalid(
            "R1 needs real images that require grad and logits computed from them with autograd on".into(),
        ));
    }
    let g = Tensor::run_backward(&[real_logit.sum(real_logit.kind())], &[real], true, true).remove(0);
    // Σx² rather than ‖x‖²: same value, and a plain polynomial has no kink at 0.
    Ok(g.square().flatten(1, -1).sum_dim_intlist(1, false, g.kind()).mean(g.kind()) * 0.5)
}

/// Pose loss: mean over the batch and both angles of 1 − cos(pred − target); periodic,
/// so ±π wrap-around costs nothing. `pred`, `target: (B, 2)`.
pub fn pose_loss(pred: &Tensor, target: &Tensor) -> Tensor {
    pose_terms(pred, target).mean(pred.kind())
}

/// Each entry's 1 − cos(pred − target), `(B, 2)`.
fn pose_terms(pred: &Tensor, target: &Tensor) -> Tensor {
    -(pred - target).cos() + 1.0
}

/// [`pose_loss`] on a verdict, counting only the images judged through patches of scale
/// ≥ `min_scale` ([`DiscOutput::scale`]): the others' terms are 0, the mean still over the
/// whole batch, so that an image that counts weighs what it weighs on whole images. With
/// `min_scale` 0, or on whole images, it is [`pose_loss`] itself (the same operations, so
/// that a run resumed without the bound stays bit-exact).
pub fn pose_loss_at(out: &DiscOutput, target: &Tensor, min_scale: f64) -> Tensor {
    match &out.scale {
        Some(scale) if min_scale > 0.0 => {
            let counts = scale.ge(min_scale).to_kind(out.pose.kind()).unsqueeze(1);
            (pose_terms(&out.pose, target) * counts).mean(out.pose.kind())
        }
        _ => pose_loss(&out.pose, target),
    }
}

/// The latent-prediction loss MSE(pred, z) (weight 0 in the release configs).
pub fn latent_loss(pred: &Tensor, z: &Tensor) -> Tensor {
    // The head is 256 wide (the release's latent size); a smaller code is predicted by
    // its first entries (the configuration refuses codes wider than the head).
    pred.narrow(1, 0, z.size()[1]).mse_loss(z, tch::Reduction::Mean)
}

/// A capped mode-seeking term (MSGAN, Mao et al. 2019, in DSGAN's clamped form): for the
/// pairs of consecutive images (2k, 2k+1), which the caller renders at the same pose,
/// `relu(cap − mean|P(I_2k) − P(I_2k+1)| / mean|z_2k − z_2k+1|)`, averaged over the pairs,
/// where P averages `pool × pool` pixel blocks. Zero once two codes' images differ by `cap`
/// per unit of code distance, so it pushes a collapsed generator apart without rewarding
/// difference beyond that; the pooling makes silhouettes and colours count, not speckle.
/// `img: (B, 3, H, W)`, `z: (B, Z)`, B even.
pub fn mode_seeking(img: &Tensor, z: &Tensor, cap: f64, pool: i64) -> Tensor {
    let b = img.size()[0];
    let img = if pool > 1 {
        img.avg_pool2d([pool, pool], [pool, pool], [0, 0], false, true, None)
    } else {
        img.shallow_clone()
    };
    let img = &img;
    let pairs = |t: &Tensor| t.reshape([b / 2, 2, -1]);
    let (i, c) = (pairs(img), pairs(&z.to_kind(img.kind())));
    let d = |t: &Tensor| (t.select(1, 0) - t.select(1, 1)).abs().mean_dim(1, false, t.kind());
    // A code distance of 0 (two equal codes) has no direction to push: its pair is skipped.
    let ratio = d(&i) / d(&c).clamp_min(1e-8);
    (-ratio + cap).relu().mean(img.kind())
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Kind;

    #[test]
    fn hinge_terms_on_known_logits() {
        let o = (Kind::Double, tch::Device::Cpu);
        let real = Tensor::from_slice(&[2.0f64, 0.5, -1.0]).view([3, 1]).to_kind(o.0);
        let fake = Tensor::from_slice(&[-3.0f64, -0.5, 1.5]).view([3, 1]).to_kind(o.0);
        let (r, f) = d_adversarial(Adversarial::Hinge, &real, &fake);
        // relu(1 − r): 0, 0.5, 2 → 2.5/3; relu(1 + f): 0, 0.5, 2.5 → 3/3.
        assert!((r.double_value(&[]) - 2.5 / 3.0).abs() < 1e-15);
        assert!((f.double_value(&[]) - 1.0).abs() < 1e-15);
        // G: −mean over the 2 largest fake logits (1.5, −0.5) = −0.5; over all 3: 2/3.
        assert!((g_adversarial(Adversarial::Hinge, &fake, 2).double_value(&[]) + 0.5).abs() < 1e-15);
        assert!((g_adversarial(Adversarial::Hinge, &fake, 3).double_value(&[]) - 2.0 / 3.0).abs() < 1e-15);
        // The logistic choice is the release's terms.
        let (r, f) = d_adversarial(Adversarial::Logistic, &real, &fake);
        let sp = |x: f64| (1.0 + x.exp()).ln();
        assert!((r.double_value(&[]) - (sp(-2.0) + sp(-0.5) + sp(1.0)) / 3.0).abs() < 1e-15);
        assert!((f.double_value(&[]) - (sp(-3.0) + sp(-0.5) + sp(1.5)) / 3.0).abs() < 1e-15);
        let g = g_adversarial(Adversarial::Logistic, &fake, 2).double_value(&[]);
        assert!((g - (sp(-1.5) + sp(0.5)) / 2.0).abs() < 1e-15);
    }

    #[test]
    fn mode_seeking_on_known_pairs() {
        let o = (Kind::Double, tch::Device::Cpu);
        // Pair 0: images differ by 0.1 everywhere, codes by 1 → ratio 0.1, below the cap 0.25.
        // Pair 1: images differ by 0.5, codes by 1 → ratio 0.5, above the cap: no loss.
        let img = Tensor::zeros([4, 3, 2, 2], o);
        let _ = img.get(1).fill_(0.1);
        let _ = img.get(3).fill_(-0.5);
        let z = Tensor::zeros([4, 3], o);
        let _ = z.get(1).fill_(1.0);
        let _ = z.get(3).fill_(-1.0);
        let l = f64::try_from(mode_seeking(&img, &z, 0.25, 1)).unwrap();
        assert!((l - 0.15 / 2.0).abs() < 1e-12, "{l}");
        // The gradient pushes the collapsed pair apart and leaves the other alone.
        let img = img.set_requires_grad(true);
        let g = Tensor::run_backward(&[mode_seeking(&img, &z, 0.25, 1)], &[&img], false, false).remove(0);
        assert!(f64::try_from(g.get(1).sum(Kind::Double)).unwrap() < 0.0);
        assert_eq!(f64::try_from(g.narrow(0, 2, 2).abs().sum(Kind::Double)).unwrap(), 0.0);
    }

    #[test]
    fn latent_loss_reads_the_first_entries_of_the_head() {
        let pred = Tensor::zeros([2, 256], (Kind::Double, tch::Device::Cpu));
        let _ = pred.narrow(1, 8, 248).fill_(5.0);
        let z = Tensor::ones([2, 8], (Kind::Double, tch::Device::Cpu));
        // Only the first 8 entries (all 0) are compared with z (all 1): MSE exactly 1.
        assert_eq!(f64::try_from(latent_loss(&pred, &z)).unwrap(), 1.0);
    }

    #[test]
    fn topk_follows_the_release_schedule() {
        assert_eq!(topk_count(0, 4, 2000.0, 0.6), 4);
        assert_eq!(topk_count(57_000, 4, 2000.0, 0.6), 4);
        assert_eq!(topk_count(58_000, 4, 2000.0, 0.6), 3);
        assert_eq!(topk_count(1_000_000, 4, 2000.0, 0.6), 3); // the 0.6 floor
        assert_eq!(topk_count(1_000_000, 1, 2000.0, 0.6), 1);
    }

    #[test]
    fn g_loss_keeps_the_largest_logits() {
        let l = Tensor::from_slice(&[-3.0f64, 5.0, 1.0, 0.0]).view([4, 1]);
        let want = (Tensor::from_slice(&[-5.0f64, -1.0])).softplus().mean(Kind::Double);
        assert!(g_nonsaturating(&l, 2).allclose(&want, 1e-12, 1e-12, false));
    }
}
