//! The plain SIREN layer of the template density trunk.
use super::{Linear, WeightInit};
use tch::{nn, Tensor};

/// `sin(30·(W x + b))`, unmodulated.
#[derive(Debug)]
pub struct SineLayer {
    pub linear: Linear,
}

impl SineLayer {
    pub const OMEGA: f64 = 30.0;

    pub fn new(vs: nn::Path, in_dim: usize, out_dim: usize, init: WeightInit) -> Self {
        Self { linear: Linear::new(vs, in_dim, out_dim, init) }
    }

    /// `x: (…, in)` → `(…, out)`. The factor 30 is folded into W and b (one matmul and
    /// the sine per point instead of an extra pass over the activations).
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let (w, b) = (&self.linear.weight * Self::OMEGA, &self.linear.bias * Self::OMEGA);
        super::sine::sin(&x.linear(&super::like(&w, x), Some(&super::like(&b, x))))
    }
}
