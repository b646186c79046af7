//! LPIPS v0.1 (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a
//! Perceptual Metric"), computed as the `lpips` package's
//! `LPIPS(net='vgg'|'alex', version='0.1')(x, y)` does for images in [−1, 1]: both images
//! are shifted and scaled towards the backbone's ImageNet statistics, run through a frozen
//! VGG16 or AlexNet, and at five ReLU taps every feature vector is scaled to unit length;
//! the squared differences are weighted per channel by a calibrated 1×1 convolution,
//! averaged over space and summed over the taps.
//!
//! Weights come in two files. The backbone is torchvision's ImageNet `vgg16` / `alexnet`
//! state dict in torchvision's names (`features.0.weight`, …; a full model's `classifier.*`
//! tensors are checked and dropped), written by scripts/export_lpips_backbone.py. The heads
//! (`lin0.model.1.weight` … `lin4.model.1.weight`, BSD-2-Clause) ship in the lpips wheel;
//! scripts/convert_lpips_heads.py converts them.
//!
//! The distance is differentiable with respect to both images (it serves as a loss for
//! photo inversion); the weights never require a gradient.
use crate::pretrained::weights::{Conv2d, Weights};
use crate::{Error, Result};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// The backbone under the heads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LpipsNet {
    /// torchvision's `vgg16`, taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3.
    Vgg16,
    /// torchvision's `alexnet`, taps relu1 … relu5.
    Alex,
}

/// One step of torchvision's `features` sequence.
#[derive(Debug, Clone, Copy)]
enum Op {
    /// The convolution `features.{index}`, then its ReLU (`features.{index + 1}`).
    Conv { index: usize, cin: i64, cout: i64, k: i64, stride: i64, padding: i64 },
    /// Max pooling, no padding, floor mode (torchvision's `ceil_mode=False`).
    Pool { k: i64, stride: i64 },
}

const fn conv(index: usize, cin: i64, cout: i64, k: i64, stride: i64, padding: i64) -> Op {
    Op::Conv { index, cin, cout, k, stride, padding }
}

/// VGG16's `features[0..30]` cut into lpips's slices; each slice ends at a tap. The last
/// max pool (`features.30`) is not used.
const VGG16_SLICES: [&[Op]; 5] = [
    &[conv(0, 3, 64, 3, 1, 1), conv(2, 64, 64, 3, 1, 1)],
    &[Op::Pool { k: 2, stride: 2 }, conv(5, 64, 128, 3, 1, 1), conv(7, 128, 128, 3, 1, 1)],
    &[
        Op::Pool { k: 2, stride: 2 },
        conv(10, 128, 256, 3, 1, 1),
        conv(12, 256, 256, 3, 1, 1),
        conv(14, 256, 256, 3, 1, 1),
    ],
    &[
        Op::Pool { k: 2, stride: 2 },
        conv(17, 256, 512, 3, 1, 1),
        conv(19, 512, 512, 3, 1, 1),
        conv(21, 512, 512, 3, 1, 1),
    ],
    &[
        Op::Pool { k: 2, stride: 2 },
        conv(24, 512, 512, 3, 1, 1),
        conv(26, 512, 512, 3, 1, 1),
        conv(28, 512, 512, 3, 1, 1),
    ],
];

/// AlexNet's `features[0..12]` cut into lpips's slices; the last max pool (`features.12`)
/// is not used.
const ALEX_SLICES: [&[Op]; 5] = [
    &[conv(0, 3, 64, 11, 4, 2)],
    &[Op::Pool { k: 3, stride: 2 }, conv(3, 64, 192, 5, 1, 2)],
    &[Op::Pool { k: 3, stride: 2 }, conv(6, 192, 384, 3, 1, 1)],
    &[conv(8, 384, 256, 3, 1, 1)],
    &[conv(10, 256, 256, 3, 1, 1)],
];

/// torchvision's ImageNet classifier of the full model (name, shape). LPIPS does not use
/// it, but a full state dict holds it: these are read (so that `Weights::finish` accepts
/// the file) and dropped.
const VGG16_CLASSIFIER: [(&str, &[i64]); 6] = [
    ("classifier.0.weight", &[4096, 512 * 7 * 7]),
    ("classifier.0.bias", &[4096]),
    ("classifier.3.weight", &[4096, 4096]),
    ("classifier.3.bias", &[4096]),
    ("classifier.6.weight", &[1000, 4096]),
    ("classifier.6.bias", &[1000]),
];
const ALEX_CLASSIFIER: [(&str, &[i64]); 6] = [
    ("classifier.1.weight", &[4096, 256 * 6 * 6]),
    ("classifier.1.bias", &[4096]),
    ("classifier.4.weight", &[4096, 4096]),
    ("classifier.4.bias", &[4096]),
    ("classifier.6.weight", &[1000, 4096]),
    ("classifier.6.bias", &[1000]),
];

/// Side of a convolution's or pooling's output, or `None` where the input is smaller than
/// the (padded) window and libtorch would refuse it.
fn out_side(side: i64, k: i64, stride: i64, padding: i64) -> Option<i64> {
    let span = side + 2 * padding - k;
    (span >= 0).then(|| span / stride + 1)
}

impl LpipsNet {
    fn slices(self) -> &'static [&'static [Op]; 5] {
        match self {
            LpipsNet::Vgg16 => &VGG16_SLICES,
            LpipsNet::Alex => &ALEX_SLICES,
        }
    }

    fn classifier(self) -> &'static [(&'static str, &'static [i64]); 6] {
        match self {
            LpipsNet::Vgg16 => &VGG16_CLASSIFIER,
            LpipsNet::Alex => &ALEX_CLASSIFIER,
        }
    }

    /// The lpips package's name (`net='vgg'` / `net='alex'`).
    pub fn name(self) -> &'static str {
        match self {
            LpipsNet::Vgg16 => "vgg",
            LpipsNet::Alex => "alex",
        }
    }

    /// Whether an image side of `side` pixels leaves every step of the backbone at least
    /// one pixel.
    fn fits(self, side: i64) -> bool {
        let mut s = side;
        for op in self.slices().iter().flat_map(|ops| ops.iter()) {
            let next = match *op {
                Op::Conv { k, stride, padding, .. } => out_side(s, k, stride, padding),
                Op::Pool { k, stride } => out_side(s, k, stride, 0),
            };
            match next {
                Some(n) if n >= 1 => s = n,
                _ => return false,
            }
        }
        true
    }

    /// The smallest image height and width the backbone takes: 16 for VGG16, 31 for AlexNet.
    pub fn min_size(self) -> i64 {
        (1..).find(|&s| self.fits(s)).expect("some size fits")
    }
}

/// lpips's `ScalingLayer`: `(x − shift) / scale` per channel, which maps [−1, 1] images
/// near the ImageNet normalisation the backbones were trained with.
#[derive(Debug)]
struct ScalingLayer {
    /// `(1, 3, 1, 1)`.
    shift: Tensor,
    /// `(1, 3, 1, 1)`.
    scale: Tensor,
}

impl ScalingLayer {
    fn new(device: Device) -> Self {
        // The package's float32 constants, divided by (not multiplied with the reciprocal
        // of) the scale, so that the rounding matches.
        let c = |v: [f32; 3]| Tensor::from_slice(&v).view([1, 3, 1, 1]).to_device(device);
        Self { shift: c([-0.030, -0.088, -0.188]), scale: c([0.458, 0.448, 0.450]) }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        (x - &self.shift) / &self.scale
    }
}

/// One loaded step of a slice.
#[derive(Debug)]
enum Step {
    ConvRelu(Conv2d),
    MaxPool { k: i64, stride: i64 },
}

/// A run of backbone steps ending at a tap (lpips's `slice1` … `slice5`).
#[derive(Debug)]
struct Slice {
    steps: Vec<Step>,
    /// Channels of the tap.
    channels: i64,
}

impl Slice {
    fn load(w: &mut Weights, ops: &[Op]) -> Result<Self> {
        let mut channels = 0;
        let mut steps = Vec::with_capacity(ops.len());
        for op in ops {
            steps.push(match *op {
                Op::Conv { index, cin, cout, k, stride, padding } => {
                    channels = cout;
                    let conv = Conv2d::load(
                        w,
                        &format!("features.{index}"),
                        cin,
                        cout,
                        [k, k],
                        stride,
                        [padding, padding],
                        1,
                        true,
                    )?;
                    Step::ConvRelu(conv)
                }
                Op::Pool { k, stride } => Step::MaxPool { k, stride },
            });
        }
        Ok(Self { steps, channels })
    }

    /// `(B, C_in, H, W)` → `(B, C_tap, H', W')`.
    fn forward(&self, x: &Tensor) -> Tensor {
        let mut h = x.shallow_clone();
        for step in &self.steps {
            h = match step {
                Step::ConvRelu(conv) => conv.forward(&h).relu(),
                Step::MaxPool { k, stride } => h.max_pool2d([*k, *k], [*stride, *stride], [0, 0], [1, 1], false),
            };
        }
        h
    }

    fn move_to(&mut self, device: Device) {
        for step in &mut self.steps {
            if let Step::ConvRelu(conv) = step {
                conv.weight = conv.weight.to_device(device);
                conv.bias = conv.bias.as_ref().map(|b| b.to_device(device));
            }
        }
    }
}

/// lpips's `NetLinLayer` in eval mode (its dropout is the identity): a bias-free 1×1
/// convolution to one channel, the learned per-channel weight of squared differences.
#[derive(Debug)]
struct LinearHead {
    /// `(1, C, 1, 1)`.
    weight: Tensor,
}

impl LinearHead {
    fn load(w: &mut Weights, i: usize, channels: i64) -> Result<Self> {
        Ok(Self { weight: w.get(&format!("lin{i}.model.1.weight"), &[1, channels, 1, 1])? })
    }

    /// `(B, C, h, w)` → `(B, 1, h, w)`.
    fn forward(&self, d: &Tensor) -> Tensor {
        d.conv2d(&self.weight, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1)
    }
}

/// lpips's `normalize_tensor`: every feature vector divided by its length (+ 1e-10, so that
/// an all-zero vector stays zero). `(B, C, h, w)`.
fn unit_normalize(f: &Tensor) -> Tensor {
    let norm = f.square().sum_dim_intlist(1, true, None::<Kind>).sqrt();
    f / (norm + 1e-10)
}

/// LPIPS v0.1 with a frozen backbone and calibrated heads.
#[derive(Debug)]
pub struct Lpips {
    net: LpipsNet,
    scaling: ScalingLayer,
    slices: Vec<Slice>,
    heads: Vec<LinearHead>,
    device: Device,
}

impl Lpips {
    /// Reads the backbone (torchvision state dict, `features.*` or the full model) and the
    /// heads (scripts/convert_lpips_heads.py) and puts the network on `device`.
    pub fn load(net: LpipsNet, backbone: &Path, heads: &Path, device: Device) -> Result<Self> {
        // Read on the CPU and move what is kept: a full VGG16 state dict carries about 500 MB of
        // classifier that would otherwise be copied to the device just to be dropped.
        let lpips = Self::from_weights(net, Weights::open(backbone, Device::Cpu)?, Weights::open(heads, Device::Cpu)?)?;
        Ok(lpips.to_device(device))
    }

    /// Builds the network from opened weights (on their device); errors on a missing or
    /// mis-shaped tensor and on tensors of neither the backbone nor its classifier.
    pub fn from_weights(net: LpipsNet, mut backbone: Weights, mut heads: Weights) -> Result<Self> {
        let slices = net.slices().iter().map(|ops| Slice::load(&mut backbone, ops)).collect::<Result<Vec<_>>>()?;
        // Absent (a `features.*` file) is fine; present, it must be torchvision's classifier.
        for (name, shape) in net.classifier() {
            match backbone.get(name, shape) {
                Ok(_) | Err(Error::MissingTensor { .. }) => {}
                Err(e) => return Err(e),
            }
        }
        backbone.finish()?;
        let heads_list = slices
            .iter()
            .enumerate()
            .map(|(i, s)| LinearHead::load(&mut heads, i, s.channels))
            .collect::<Result<Vec<_>>>()?;
        heads.finish()?;
        let device = heads_list[0].weight.device();
        Ok(Self { net, scaling: ScalingLayer::new(device), slices, heads: heads_list, device })
    }

    pub fn net(&self) -> LpipsNet {
        self.net
    }

    pub fn device(&self) -> Device {
        self.device
    }

    /// The same network on `device`.
    pub fn to_device(mut self, device: Device) -> Self {
        for s in &mut self.slices {
            s.move_to(device);
        }
        for h in &mut self.heads {
            h.weight = h.weight.to_device(device);
        }
        Self { scaling: ScalingLayer::new(device), device, ..self }
    }

    /// The perceptual distance of `x` and `y`, both `(B, 3, H, W)` float32 images in
    /// [−1, 1] on the network's device with H, W ≥ [`LpipsNet::min_size`]; returns `(B,)`.
    /// Differentiable with respect to both images.
    pub fn distance(&self, x: &Tensor, y: &Tensor) -> Result<Tensor> {
        self.check(x, y)?;
        self.to_target(x, &self.target(y)?)
    }

    /// The unit-length taps of `y: (B, 3, H, W)`, which [`Self::to_target`] compares with:
    /// a fixed image needs them once. Differentiable with respect to `y`.
    pub fn target(&self, y: &Tensor) -> Result<Vec<Tensor>> {
        self.check(y, y)?;
        Ok(self.features(y).iter().map(unit_normalize).collect())
    }

    /// `(B,)` distances between `x: (B, 3, H, W)` and the image whose [`Self::target`]
    /// `target` is (one image broadcasts to every row of `x`).
    pub fn to_target(&self, x: &Tensor, target: &[Tensor]) -> Result<Tensor> {
        self.check(x, x)?;
        let fx = self.features(x);
        super::perceptual::check_target(&format!("LPIPS-{}", self.net.name()), &fx, target)?;
        let per_tap = fx.iter().zip(target).zip(&self.heads).map(|((a, b), head)| {
            let d = (unit_normalize(a) - b).square();
            head.forward(&d).mean_dim([2i64, 3].as_slice(), true, None::<Kind>) // (B, 1, 1, 1)
        });
        // Summed tap by tap in order, as the package does.
        let total = per_tap.reduce(|acc, t| acc + t).expect("five taps");
        Ok(total.flatten(0, -1))
    }

    /// The five taps of the scaled image. `(B, 3, H, W)` → `[(B, C_i, H_i, W_i); 5]`.
    fn features(&self, x: &Tensor) -> Vec<Tensor> {
        let mut h = self.scaling.forward(x);
        self.slices
            .iter()
            .map(|s| {
                h = s.forward(&h);
                h.shallow_clone()
            })
            .collect()
    }

    /// Refuses what libtorch would panic on or silently broadcast.
    fn check(&self, x: &Tensor, y: &Tensor) -> Result<()> {
        let what = format!("LPIPS-{}", self.net.name());
        let s = x.size();
        if s.len() != 4 || s[1] != 3 {
            return Err(Error::Shape(format!("{what} expects (B, 3, H, W) images, got {s:?}")));
        }
        if y.size() != s {
            return Err(Error::Shape(format!("{what}: the images differ in shape: {s:?} and {:?}", y.size())));
        }
        if !self.net.fits(s[2]) || !self.net.fits(s[3]) {
            let m = self.net.min_size();
            return Err(Error::Invalid(format!("{what} needs images of at least {m}×{m}, got {}×{}", s[2], s[3])));
        }
        for t in [x, y] {
            if t.kind() != Kind::Float || t.device() != self.device {
                return Err(Error::Invalid(format!(
                    "{what} expects float32 images on {:?}, got {:?} on {:?}",
                    self.device,
                    t.kind(),
                    t.device()
                )));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Named tensors, as a safetensors file holds them.
    type Named = Vec<(String, Tensor)>;

    /// Random weights of the right names and shapes (He-scaled convs, positive heads).
    fn random_weights(net: LpipsNet) -> (Named, Named) {
        let opts = (Kind::Float, Device::Cpu);
        let (mut backbone, mut heads) = (Vec::new(), Vec::new());
        for (i, ops) in net.slices().iter().enumerate() {
            let mut channels = 0;
            for op in ops.iter() {
                if let Op::Conv { index, cin, cout, k, .. } = *op {
                    let w = Tensor::randn([cout, cin, k, k], opts) * (2.0 / (cin * k * k) as f64).sqrt();
                    backbone.push((format!("features.{index}.weight"), w));
                    backbone.push((format!("features.{index}.bias"), Tensor::randn([cout], opts) * 0.1));
                    channels = cout;
                }
            }
            heads.push((format!("lin{i}.model.1.weight"), Tensor::rand([1, channels, 1, 1], opts)));
        }
        (backbone, heads)
    }

    fn build(net: LpipsNet, backbone: Named, heads: Named) -> Result<Lpips> {
        let w = |name: &str, list| Weights::from_tensors(Path::new(name), list, Device::Cpu);
        Lpips::from_weights(net, w("backbone.safetensors", backbone), w("heads.safetensors", heads))
    }

    fn copy(list: &[(String, Tensor)]) -> Named {
        list.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect()
    }

    /// `list` without `name`, plus `name` → `t` if given.
    fn swap(list: &[(String, Tensor)], name: &str, t: Option<Tensor>) -> Named {
        let mut out: Vec<_> = copy(list).into_iter().filter(|(n, _)| n != name).collect();
        out.extend(t.map(|t| (name.to_string(), t)));
        out
    }

    fn random_lpips(net: LpipsNet) -> Lpips {
        let (b, h) = random_weights(net);
        build(net, b, h).unwrap()
    }

    fn images(b: i64, h: i64, w: i64) -> Tensor {
        Tensor::rand([b, 3, h, w], (Kind::Float, Device::Cpu)) * 2.0 - 1.0
    }

    #[test]
    fn minimum_sizes_follow_the_layers() {
        assert_eq!(LpipsNet::Vgg16.min_size(), 16);
        assert_eq!(LpipsNet::Alex.min_size(), 31);
    }

    #[test]
    fn distance_is_per_image_zero_on_equal_images_and_differentiable() {
        tch::manual_seed(0);
        for net in [LpipsNet::Vgg16, LpipsNet::Alex] {
            let lpips = random_lpips(net);
            let m = net.min_size();
            // The smallest accepted size runs through libtorch: the size check is not too lax.
            let x = images(2, m, m + 3).set_requires_grad(true);
            let y = images(2, m, m + 3);
            let d = lpips.distance(&x, &y).unwrap();
            assert_eq!(d.size(), [2]);
            assert!(bool::try_from(d.gt(0.0).all()).unwrap(), "{net:?}: {d}");
            d.sum(Kind::Float).backward();
            let g = x.grad();
            assert!(bool::try_from(g.isfinite().all()).unwrap() && f64::try_from(g.abs().max()).unwrap() > 0.0);
            let zero = lpips.distance(&y, &y).unwrap();
            assert_eq!(f64::try_from(zero.abs().max()).unwrap(), 0.0, "{net:?}");
            // Each image's distance depends on that image pair only.
            let one = lpips.distance(&x.narrow(0, 1, 1), &y.narrow(0, 1, 1)).unwrap();
            assert!(f64::try_from((one - d.narrow(0, 1, 1)).abs().max()).unwrap() < 1e-6);
        }
    }

    #[test]
    fn bad_images_are_invalid_not_panics() {
        let lpips = random_lpips(LpipsNet::Alex);
        let ok = images(1, 32, 32);
        let bad = [
            (images(1, 32, 32).view([3, 32, 32]), "(B, 3, H, W)"),
            (Tensor::rand([1, 4, 32, 32], (Kind::Float, Device::Cpu)), "(B, 3, H, W)"),
            (images(1, 32, 33), "differ in shape"),
            (images(2, 32, 32), "differ in shape"),
            (images(1, 32, 32).to_kind(Kind::Double), "float32"),
        ];
        for (x, want) in bad {
            let e = lpips.distance(&x, &ok).unwrap_err();
            let shape = matches!(e, Error::Shape(_)) && want != "float32";
            let kind = matches!(e, Error::Invalid(_)) && want == "float32";
            assert!((shape || kind) && e.to_string().contains(want), "{e}");
        }
        let small = images(1, 30, 32);
        let e = lpips.distance(&small, &small).unwrap_err().to_string();
        assert!(e.contains("at least 31×31") && e.contains("30×32"), "{e}");
        let e = lpips.distance(&ok, &ok.to_kind(Kind::Double)).unwrap_err().to_string();
        assert!(e.contains("Double"), "{e}");
    }

    #[test]
    fn a_full_torchvision_state_dict_is_accepted() {
        for net in [LpipsNet::Vgg16, LpipsNet::Alex] {
            let (mut backbone, heads) = random_weights(net);
            let features = build(net, copy(&backbone), copy(&heads)).unwrap();
            // Expanded zeros: the classifier's shapes without its memory.
            for (name, shape) in net.classifier() {
                backbone.push((name.to_string(), Tensor::zeros([], (Kind::Float, Device::Cpu)).expand(*shape, false)));
            }
            let full = build(net, backbone, heads).unwrap();
            let (x, y) = (images(1, 32, 32), images(1, 32, 32));
            let (a, b) = (features.distance(&x, &y).unwrap(), full.distance(&x, &y).unwrap());
            assert_eq!(f64::try_from((a - b).abs().max()).unwrap(), 0.0);
        }
    }

    #[test]
    fn wrong_files_name_the_tensor() {
        let net = LpipsNet::Alex;
        let err = |backbone, heads| build(net, backbone, heads).unwrap_err().to_string();
        let (backbone, heads) = random_weights(net);
        let f32s = |s: &[i64]| Tensor::zeros(s, (Kind::Float, Device::Cpu));

        let e = err(swap(&backbone, "features.6.weight", Some(f32s(&[384, 192, 5, 5]))), copy(&heads));
        assert!(
            e.contains("backbone.safetensors")
                && e.contains("'features.6.weight'")
                && e.contains("[384, 192, 5, 5]")
                && e.contains("[384, 192, 3, 3]"),
            "{e}"
        );
        let e = err(swap(&backbone, "features.3.bias", None), copy(&heads));
        assert!(e.contains("'features.3.bias' is missing") && e.contains("[192]"), "{e}");
        let e = err(swap(&backbone, "classifier.4.weight", Some(f32s(&[10, 4096]))), copy(&heads));
        assert!(e.contains("'classifier.4.weight'") && e.contains("[10, 4096]") && e.contains("[4096, 4096]"), "{e}");
        let e = err(swap(&backbone, "features.1.weight", Some(f32s(&[64]))), copy(&heads));
        assert!(e.contains("unexpected tensor 'features.1.weight'"), "{e}");
        let e = err(copy(&backbone), swap(&heads, "lin2.model.1.weight", Some(f32s(&[1, 256, 1, 1]))));
        assert!(
            e.contains("heads.safetensors")
                && e.contains("'lin2.model.1.weight'")
                && e.contains("[1, 256, 1, 1]")
                && e.contains("[1, 384, 1, 1]"),
            "{e}"
        );
        // VGG heads under AlexNet: the first head that differs is named.
        let (_, vgg_heads) = random_weights(LpipsNet::Vgg16);
        let e = err(backbone, vgg_heads);
        assert!(
            e.contains("'lin1.model.1.weight'") && e.contains("[1, 128, 1, 1]") && e.contains("[1, 192, 1, 1]"),
            "{e}"
        );
    }
}
