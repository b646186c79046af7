//! The mapping network: z → (raw frequencies, raw phases) for one FiLM-modulated net.
use super::{Linear, WeightInit};
use crate::rng::{Purpose, RandomSource, StepRng};
use tch::{nn, Device, Kind, Tensor};

/// Four Linear layers `z → h → h → h → out` with LeakyReLU(0.2) after the first three.
/// The activation after the third LeakyReLU is the paper's `w` (w_s for the shape net).
#[derive(Debug)]
pub struct MappingNetwork {
    pub layers: Vec<Linear>,
}

impl MappingNetwork {
    pub fn new(vs: nn::Path, z_dim: usize, hidden: usize, out_dim: usize) -> Self {
        let dims = [(z_dim, hidden), (hidden, hidden), (hidden, hidden), (hidden, out_dim)];
        let layers = dims
            .iter()
            .enumerate()
            .map(|(i, &(a, b))| {
                let scale = if i == 3 { 0.25 } else { 1.0 };
                Linear::new(vs.clone() / i, a, b, WeightInit::KaimingLeaky { scale })
            })
            .collect();
        Self { layers }
    }

    /// `z: (B, z_dim)` → `w: (B, hidden)`.
    pub fn features(&self, z: &Tensor) -> Tensor {
        self.layers[..3].iter().fold(z.shallow_clone(), |x, l| leaky_relu(&l.forward(&x)))
    }

    /// `w: (B, hidden)` → raw `(B, out_dim)` = `[frequencies | phases]`.
    pub fn head(&self, w: &Tensor) -> Tensor {
        self.layers[3].forward(w)
    }

    /// `z: (B, z_dim)` → raw `(B, out_dim)`.
    pub fn forward(&self, z: &Tensor) -> Tensor {
        self.head(&self.features(z))
    }

    /// Mean raw output over `n` codes z ~ N(0, I) drawn from `seed` (the truncation
    /// centre). The release redraws 10 000 codes on every call; a fixed seed makes
    /// renders reproducible at no cost in accuracy. The codes come from the project's
    /// counter-based generator, so libtorch's global generator is neither read nor reseeded.
    pub fn mean_output(&self, n: i64, seed: i64, kind: Kind, device: Device) -> Tensor {
        let z_dim = self.layers[0].weight.size()[1];
        tch::no_grad(|| {
            let z = StepRng::new(seed as u64, 0, Purpose::Truncation, kind, device).normal(&[n, z_dim]);
            self.forward(&z).mean_dim(0, true, kind)
        })
    }
}

/// LeakyReLU with slope 0.2 (tch's `leaky_relu` has the fixed slope 0.01).
pub fn leaky_relu(x: &Tensor) -> Tensor {
    x.maximum(&(x * 0.2))
}

/// `randn(shape)` after `manual_seed(seed)` on the CPU generator: the same numbers as
/// PyTorch's `torch.manual_seed(seed); torch.randn(shape)`, so seeds name the same codes
/// as in the authors' scripts. Reseeds libtorch's global generator (under
/// [`with_global_seed`](crate::rng::with_global_seed)'s lock).
pub fn seeded_randn(shape: &[i64], seed: i64) -> Tensor {
    crate::rng::with_global_seed(seed, || Tensor::randn(shape, (Kind::Float, Device::Cpu)))
}
