//! Building blocks: a Linear layer with the release's initialisation schemes, the plain
//! SIREN layer, the FiLM-SIREN layer and its modulation, the mapping network, and their sine.
pub mod film;
pub mod mapping;
pub mod sine;
pub mod siren;

use tch::{nn, Tensor};

/// How a Linear layer's weight is initialised. Biases always keep PyTorch's default
/// U(±1/√fan_in), which the release never overwrites.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WeightInit {
    /// U(±√(6/fan_in)/f) ("frequency_init"; f = 30 is "sine_init").
    Frequency(f64),
    /// U(±1/fan_in), the first-layer rule of SIREN.
    FirstLayer,
    /// N(0, (gain/√fan_in)²) with gain = √(2/(1+0.2²)), times `scale`.
    KaimingLeaky { scale: f64 },
    /// All zeros (the deformation head).
    Zeros,
}

/// `y = x Wᵀ + b` with `W: (out, in)`, `b: (out)` — the layout of PyTorch's nn.Linear.
#[derive(Debug)]
pub struct Linear {
    pub weight: Tensor,
    pub bias: Tensor,
}

impl Linear {
    pub fn new(vs: nn::Path, in_dim: usize, out_dim: usize, init: WeightInit) -> Self {
        let fan_in = in_dim as f64;
        let w_init = match init {
            WeightInit::Frequency(f) => {
                let b = (6.0 / fan_in).sqrt() / f;
                nn::Init::Uniform { lo: -b, up: b }
            }
            WeightInit::FirstLayer => nn::Init::Uniform { lo: -1.0 / fan_in, up: 1.0 / fan_in },
            WeightInit::KaimingLeaky { scale } => {
                let gain = (2.0 / (1.0 + 0.2f64 * 0.2)).sqrt();
                nn::Init::Randn { mean: 0.0, stdev: scale * gain / fan_in.sqrt() }
            }
            WeightInit::Zeros => nn::Init::Const(0.0),
        };
        let bound = 1.0 / fan_in.sqrt();
        let dims = [out_dim as i64, in_dim as i64];
        let weight = vs.var("weight", &dims, w_init);
        let bias = vs.var("bias", &[out_dim as i64], nn::Init::Uniform { lo: -bound, up: bound });
        Self { weight, bias }
    }

    /// `x: (…, in)` → `(…, out)`, computed in `x`'s dtype (the float32 parameters are
    /// cast when the input is reduced precision).
    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.linear(&like(&self.weight, x), Some(&like(&self.bias, x)))
    }
}

/// `t` in the dtype of `x` (no copy when they already agree): reduced-precision network
/// evaluation keeps float32 master weights and casts them per call.
pub fn like(t: &Tensor, x: &Tensor) -> Tensor {
    if t.kind() == x.kind() {
        t.shallow_clone()
    } else {
        t.to_kind(x.kind())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    fn bounds(t: &Tensor) -> (f64, f64) {
        (t.min().double_value(&[]), t.max().double_value(&[]))
    }

    #[test]
    fn inits_follow_the_release() {
        tch::manual_seed(0);
        let vs = nn::VarStore::new(Device::Cpu);
        let f = Linear::new(vs.root() / "f", 256, 256, WeightInit::Frequency(25.0));
        let (lo, hi) = bounds(&f.weight);
        let b = (6.0f64 / 256.0).sqrt() / 25.0;
        assert!(lo >= -b && hi <= b && hi > 0.9 * b && lo < -0.9 * b, "{lo} {hi} {b}");
        let (lo, hi) = bounds(&f.bias);
        assert!(lo >= -1.0 / 16.0 && hi <= 1.0 / 16.0 && hi > 0.05, "{lo} {hi}");

        let first = Linear::new(vs.root() / "first", 3, 256, WeightInit::FirstLayer);
        let (lo, hi) = bounds(&first.weight);
        assert!(lo >= -1.0 / 3.0 && hi <= 1.0 / 3.0 && hi > 0.3);

        let k = Linear::new(vs.root() / "k", 256, 2048, WeightInit::KaimingLeaky { scale: 0.25 });
        let std = k.weight.std(true).double_value(&[]);
        let want = 0.25 * 0.08667;
        assert!((std - want).abs() < 0.02 * want, "{std} vs {want}");

        let z = Linear::new(vs.root() / "z", 256, 4, WeightInit::Zeros);
        assert_eq!(z.weight.abs().sum(Kind::Float).double_value(&[]), 0.0);
        assert!(z.bias.abs().sum(Kind::Float).double_value(&[]) > 0.0);
    }
}
