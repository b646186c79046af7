//! FiLM modulation: per-image frequencies γ and phases β for a stack of FiLM-SIREN layers.
use super::{Linear, WeightInit};
use tch::{nn, Tensor};

/// Modulation of `L` FiLM layers of width `H` for `B` images.
///
/// `gamma`, `beta`: `(B, L·H)`; layer `i` uses columns `[i·H, (i+1)·H)`. `gamma` is the
/// actual frequency (the release's `15·f_raw + 30`), `beta` the phase shift.
#[derive(Debug)]
pub struct Film {
    pub gamma: Tensor,
    pub beta: Tensor,
}

impl Film {
    /// From a mapping network's raw output `(B, 2·L·H)`: first half raw frequencies,
    /// second half phases; γ = 15·f_raw + 30.
    pub fn from_raw(raw: &Tensor) -> Self {
        let half = raw.size()[1] / 2;
        let f_raw = raw.narrow(1, 0, half);
        let beta = raw.narrow(1, half, half);
        Self { gamma: f_raw * 15.0 + 30.0, beta }
    }

    /// `(γ_i, β_i)` of layer `i`, shaped `(B, 1, H)` to broadcast over points.
    pub fn layer(&self, i: usize, width: usize) -> (Tensor, Tensor) {
        let (s, w) = ((i * width) as i64, width as i64);
        (self.gamma.narrow(1, s, w).unsqueeze(1), self.beta.narrow(1, s, w).unsqueeze(1))
    }

    /// Images `[start, start+len)` of the batch.
    pub fn narrow(&self, start: i64, len: i64) -> Self {
        Self { gamma: self.gamma.narrow(0, start, len), beta: self.beta.narrow(0, start, len) }
    }

    pub fn batch_size(&self) -> i64 {
        self.gamma.size()[0]
    }

    pub fn detach(&self) -> Self {
        Self { gamma: self.gamma.detach(), beta: self.beta.detach() }
    }
}

/// `sin(γ ⊙ (W x + b) + β)` — the frequency multiplies the whole pre-activation.
#[derive(Debug)]
pub struct FilmLayer {
    pub linear: Linear,
}

impl FilmLayer {
    pub fn new(vs: nn::Path, in_dim: usize, out_dim: usize, init: WeightInit) -> Self {
        Self { linear: Linear::new(vs, in_dim, out_dim, init) }
    }

    /// `x: (B, P, in)`, `gamma`, `beta: (B, 1, out)` → `(B, P, out)`.
    ///
    /// γ ⊙ (W x + b) + β is evaluated as (diag(γ) W) x + (γ ⊙ b + β): the modulation is
    /// folded into a per-image weight (out × in, cheap) so the per-point work is one
    /// batched matmul and the sine, and autograd keeps one activation less per layer.
    pub fn forward(&self, x: &Tensor, gamma: &Tensor, beta: &Tensor) -> Tensor {
        let w = gamma.transpose(1, 2) * &self.linear.weight; // (B, out, in)
        let b = gamma * &self.linear.bias + beta; // (B, 1, out)
                                                  // Folded in float32, then cast to the points' dtype (reduced-precision evaluation).
        super::sine::sin(&super::like(&b, x).baddbmm(x, &super::like(&w, x).transpose(1, 2), 1, 1))
    }
}
