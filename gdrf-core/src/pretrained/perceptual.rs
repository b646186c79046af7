//! A perceptual distance on EfficientNet-Lite0 features, in the manner of LPIPS but **not
//! LPIPS** (no learned layer weights, another backbone): at each of the five taps
//! ([`super::effnet::TAP_BLOCKS`], 112² … 7² for a 224² input) every spatial position's
//! channel vector is scaled to unit length, the squared differences are summed over
//! channels and averaged over positions, and the five layers are averaged. It is the
//! offline default of the photo inversion's perceptual term; real LPIPS
//! ([`super::lpips`]) needs a backbone file the user supplies.
use super::effnet::EfficientNetLite0;
use crate::{Error, Result};
use tch::{Kind, Tensor};

/// Name under which the distance is reported, so that nobody mistakes it for LPIPS.
pub const NAME: &str = "effnet-lite0 perceptual (LPIPS-style, not LPIPS)";

pub struct EffnetPerceptual<'a> {
    pub net: &'a EfficientNetLite0,
    /// Side the images are resized to before the network (224: ImageNet's).
    pub size: i64,
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
        let b = x.size()[0];
        let both = Tensor::cat(&[x, y], 0);
        let f = self.net.forward(&self.net.prepare(&both, self.size)?);
        let mut total = Tensor::zeros([b], (Kind::Float, both.device()));
        for t in &f.taps {
            let u = unit(t);
            let d = (u.narrow(0, 0, b) - u.narrow(0, b, b)).square().sum_dim_intlist(1, false, Kind::Float);
            total += d.mean_dim([1i64, 2].as_slice(), false, Kind::Float);
        }
        Ok(total / f.taps.len() as f64)
    }
}
