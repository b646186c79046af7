//! A perceptual distance on EfficientNet-Lite0 features, in the manner of LPIPS but **not
//! LPIPS** (no learned layer weights, another backbone): at each of the five taps
//! ([`super::effnet::TAP_BLOCKS`], 112² … 7² for a 224² input) every spatial position's
//! channel vector is scaled to unit length, the squared differences are summed over
//! channels and averaged over positions, and the five layers are averaged. It is the
//! offline default of the photo inversion's perceptual term; real LPIPS
//! ([`super::lpips`]) needs a backbone file the user supplies.
use super::effnet::{EfficientNetLite0, TAP_BLOCKS};
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Name under which the distance is reported, so that nobody mistakes it for LPIPS.
pub const NAME: &str = "effnet-lite0 perceptual (LPIPS-style, not LPIPS)";

#[derive(Clone, Copy)]
pub struct EffnetPerceptual<'a> {
    pub net: &'a EfficientNetLite0,
    /// Side the images are resized to before the network (224: ImageNet's).
    pub size: i64,
}

/// Refuses a prepared `target` that does not match the taps `(B, C, H, W)` of the images
/// compared with it (another size, or another network's), which libtorch would panic on.
pub(crate) fn check_target(what: &str, taps: &[Tensor], target: &[Tensor]) -> Result<()> {
    let fits = taps.len() == target.len()
        && taps.iter().zip(target).all(|(t, u)| {
            let (a, b) = (t.size(), u.size());
            a.len() == 4 && b.len() == 4 && a[1..] == b[1..] && (b[0] == 1 || b[0] == a[0])
        });
    if !fits {
        let shapes = |v: &[Tensor]| v.iter().map(|t| t.size()).collect::<Vec<_>>();
        return Err(Error::Shape(format!(
            "{what}: a target with taps {:?} for images with taps {:?} (prepare it from an image of the same size)",
            shapes(target),
            shapes(taps)
        )));
    }
    Ok(())
}

/// Unit length along channels (LPIPS's `normalize_tensor`, eps 1e-10).
fn unit(x: &Tensor) -> Tensor {
    let n = x.square().sum_dim_intlist(1, true, Kind::Float).sqrt();
    x / (n + 1e-10)
}

impl EffnetPerceptual<'_> {
    /// `(B,)` distances between `x` and `y`, `(B, 3, H, W)` in [−1, 1]; differentiable
    /// with respect to both (the weights take no gradient).
    pub fn distance(&self, x: &Tensor, y: &Tensor) -> Result<Tensor> {
        if x.size() != y.size() {
            return Err(Error::Shape(format!("perceptual distance: shapes differ, {:?} and {:?}", x.size(), y.size())));
        }
        self.to_target(x, &self.target(y)?)
    }

    /// The unit-length taps of `y: (B, 3, H, W)` in [−1, 1], which [`Self::to_target`]
    /// compares with: a fixed image (the photo an inversion matches) needs them once, not
    /// at every step. Differentiable with respect to `y`.
    pub fn target(&self, y: &Tensor) -> Result<Vec<Tensor>> {
        let taps = self.net.taps(&self.net.prepare(y, self.size)?, TAP_BLOCKS.len() - 1);
        Ok(taps.iter().map(unit).collect())
    }

    /// `(B,)` distances between `x: (B, 3, H, W)` and the image whose [`Self::target`]
    /// `target` is (one image broadcasts to every row of `x`).
    pub fn to_target(&self, x: &Tensor, target: &[Tensor]) -> Result<Tensor> {
        let taps = self.net.taps(&self.net.prepare(x, self.size)?, TAP_BLOCKS.len() - 1);
        check_target(NAME, &taps, target)?;
        let b = x.size()[0];
        let mut total = Tensor::zeros([b], (Kind::Float, taps[0].device()));
        for (t, u) in taps.iter().zip(target) {
            let d = (unit(t) - u).square().sum_dim_intlist(1, false, Kind::Float);
            total += d.mean_dim([1i64, 2].as_slice(), false, Kind::Float);
        }
        Ok(total / taps.len() as f64)
    }
}
