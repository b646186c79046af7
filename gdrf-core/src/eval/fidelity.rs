//! Per-image fidelity against a reference image: PSNR and SSIM (Wang et al. 2004, the
//! common setting: 11 × 11 Gaussian window of σ 1.5, K1 = 0.01, K2 = 0.03, data range 1,
//! population statistics, "valid" windows only, averaged over positions and channels).
//! Inputs are `(B, 3, H, W)` in [−1, 1] (the project's image convention) and are compared
//! on [0, 1].
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Side of SSIM's window; images must be at least this large.
pub const SSIM_WINDOW: i64 = 11;
const SSIM_SIGMA: f64 = 1.5;

fn check(a: &Tensor, b: &Tensor, what: &str) -> Result<()> {
    let s = a.size();
    if s.len() != 4 || s != b.size() {
        return Err(Error::Shape(format!(
            "{what}: expected two (B, C, H, W) images of one shape, got {:?} and {:?}",
            s,
            b.size()
        )));
    }
    Ok(())
}

/// The floor of every PSNR's mean squared error on [0, 1]: identical images score 100 dB.
pub const MSE_FLOOR: f64 = 1e-10;

/// `(B,)` PSNR in dB, 10·log10(1 / MSE) on [0, 1] (MSE floored at [`MSE_FLOOR`]).
pub fn psnr(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    check(a, b, "PSNR")?;
    let mse = ((a - b) / 2.0).to_kind(Kind::Double).square().mean_dim([1i64, 2, 3].as_slice(), false, Kind::Double);
    Ok(mse.clamp_min(MSE_FLOOR).log10() * -10.0)
}

/// PSNR in dB of a mean squared error on [0, 1] (floored at [`MSE_FLOOR`]).
pub fn psnr_of_mse(mse: f64) -> f64 {
    -10.0 * mse.max(MSE_FLOOR).log10()
}

/// One PSNR over every pixel of `a` against `b` (same shape, in [−1, 1], compared on [0, 1]).
pub fn psnr_all(a: &Tensor, b: &Tensor) -> Result<f64> {
    if a.size() != b.size() {
        return Err(Error::Shape(format!("PSNR of images of shapes {:?} and {:?}", a.size(), b.size())));
    }
    Ok(psnr_of_mse(f64::try_from(((a - b) * 0.5).square().mean(Kind::Double))?))
}

/// `(B,)` SSIM (see the module's documentation).
pub fn ssim(a: &Tensor, b: &Tensor) -> Result<Tensor> {
    check(a, b, "SSIM")?;
    let s = a.size();
    if s[2] < SSIM_WINDOW || s[3] < SSIM_WINDOW {
        return Err(Error::Invalid(format!(
            "SSIM needs images of at least {SSIM_WINDOW}×{SSIM_WINDOW}, got {}×{}",
            s[2], s[3]
        )));
    }
    let c = s[1];
    let opts = (Kind::Double, a.device());
    let x = (a.to_kind(Kind::Double) + 1.0) / 2.0;
    let y = (b.to_kind(Kind::Double) + 1.0) / 2.0;
    let r = Tensor::arange(SSIM_WINDOW, opts) - (SSIM_WINDOW / 2) as f64;
    let g = (-(&r * &r) / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    let g = &g / g.sum(Kind::Double);
    let gh = g.view([1, 1, 1, SSIM_WINDOW]).repeat([c, 1, 1, 1]);
    let gv = g.view([1, 1, SSIM_WINDOW, 1]).repeat([c, 1, 1, 1]);
    // Separable Gaussian filter per channel, valid positions only.
    let blur = |t: &Tensor| {
        t.conv2d(&gh, None::<Tensor>, [1, 1], [0, 0], [1, 1], c).conv2d(&gv, None::<Tensor>, [1, 1], [0, 0], [1, 1], c)
    };
    let (mx, my) = (blur(&x), blur(&y));
    let sxx = blur(&(&x * &x)) - &mx * &mx;
    let syy = blur(&(&y * &y)) - &my * &my;
    let sxy = blur(&(&x * &y)) - &mx * &my;
    let (c1, c2) = (0.01f64.powi(2), 0.03f64.powi(2));
    let map = ((&mx * &my * 2.0 + c1) * (sxy * 2.0 + c2)) / ((mx.square() + my.square() + c1) * (sxx + syy + c2));
    Ok(map.mean_dim([1i64, 2, 3].as_slice(), false, Kind::Double))
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn known_values() {
        let opts = (Kind::Float, Device::Cpu);
        let a = Tensor::rand([2, 3, 16, 16], opts) * 2.0 - 1.0;
        // Identical images: SSIM 1, PSNR at its 100 dB floor.
        assert!((f64::try_from(ssim(&a, &a).unwrap().min()).unwrap() - 1.0).abs() < 1e-12);
        assert_eq!(f64::try_from(psnr(&a, &a).unwrap().max()).unwrap(), 100.0);
        // A constant offset of 0.2 on [−1, 1] is 0.1 on [0, 1]: MSE 0.01, PSNR exactly 20 dB.
        let p = psnr(&(&a * 0.5), &(&a * 0.5 + 0.2)).unwrap();
        for v in Vec::<f64>::try_from(p).unwrap() {
            assert!((v - 20.0).abs() < 1e-5, "{v}");
        }
        // Two constant images: σ terms vanish, SSIM = (2μxμy + C1)/(μx² + μy² + C1).
        let (x, y) = (Tensor::full([1, 1, 12, 12], 0.0, opts), Tensor::full([1, 1, 12, 12], -0.5, opts));
        let want = (2.0 * 0.5 * 0.25 + 1e-4) / (0.25 + 0.0625 + 1e-4);
        assert!((f64::try_from(ssim(&x, &y).unwrap()).unwrap() - want).abs() < 1e-12);
        assert!(ssim(&a.narrow(2, 0, 10), &a.narrow(2, 0, 10)).is_err());
        assert!(psnr(&a, &a.narrow(0, 0, 1)).is_err());
    }
}
