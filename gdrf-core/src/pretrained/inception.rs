//! FID's Inception-v3: the 2048-d pool3 features of pytorch-fid's `InceptionV3([3])` with
//! `use_fid_inception=True`, i.e. the PyTorch port of TensorFlow's 2015-12-05 Inception
//! graph that the original FID code used. Fréchet distances are only comparable with
//! published numbers when computed on exactly these features, so every detail of that port
//! is kept: bias-free convolutions with BatchNorm (ε = 0.001), TensorFlow-style average
//! pooling that leaves padding out of the mean inside the FID blocks, and a max pool in the
//! last block's pooling branch (where the paper's network has an average pool).
//!
//! Tensor names are those of the pytorch-fid module's state dict (`blocks.0.0.conv.weight`,
//! `blocks.2.0.branch1x1.bn.running_mean` …), so a file written from that module by
//! `scripts/export_inception_weights.py` loads directly.
use super::weights::{BatchNorm, Conv2d, Weights};
use crate::{Error, Result};
use std::path::Path;
use tch::{Device, Kind, Tensor};

/// Width of the pool3 features.
pub const FEATURE_DIM: i64 = 2048;
/// Side of the square the images are resized to, as pytorch-fid does.
pub const INPUT_SIZE: i64 = 299;
/// BatchNorm ε of the TensorFlow graph (torchvision's `BasicConv2d`).
const BN_EPS: f64 = 1e-3;

/// Convolution without bias → eval-mode BatchNorm → ReLU (torchvision's `BasicConv2d`;
/// names `{prefix}.conv.weight`, `{prefix}.bn.*`).
struct BasicConv {
    conv: Conv2d,
    bn: BatchNorm,
}

impl BasicConv {
    fn load(
        w: &mut Weights,
        prefix: &str,
        cin: i64,
        cout: i64,
        k: [i64; 2],
        stride: i64,
        padding: [i64; 2],
    ) -> Result<Self> {
        Ok(Self {
            conv: Conv2d::load(w, &format!("{prefix}.conv"), cin, cout, k, stride, padding, 1, false)?,
            bn: BatchNorm::load(w, &format!("{prefix}.bn"), cout, BN_EPS)?,
        })
    }

    /// A 1×1 convolution, stride 1.
    fn pointwise(w: &mut Weights, prefix: &str, cin: i64, cout: i64) -> Result<Self> {
        Self::load(w, prefix, cin, cout, [1, 1], 1, [0, 0])
    }

    /// `(B, cin, H, W)` → `(B, cout, H', W')`.
    fn forward(&self, x: &Tensor) -> Tensor {
        self.bn.forward(&self.conv.forward(x)).relu()
    }
}

/// 3×3 stride-1 average pool over the valid pixels only: TensorFlow's 'SAME' average pool
/// divides by the number of pixels inside the image, not by 9 (PyTorch's
/// `count_include_pad=False`). Shape-preserving.
fn tf_avg_pool_3x3(x: &Tensor) -> Tensor {
    x.avg_pool2d([3, 3], [1, 1], [1, 1], false, false, None)
}

/// 3×3 stride-2 max pool without padding: `(B, C, H, W)` → `(B, C, (H−3)/2+1, (W−3)/2+1)`.
fn max_pool_3x3_s2(x: &Tensor) -> Tensor {
    x.max_pool2d([3, 3], [2, 2], [0, 0], [1, 1], false)
}

/// Mixed_5b/5c/5d (pytorch-fid's `FIDInceptionA`): branches 1×1 (64), 1×1→5×5 (64),
/// 1×1→3×3→3×3 (96) and TF-avg-pool→1×1 (`pool_features`).
/// `(B, cin, 35, 35)` → `(B, 224 + pool_features, 35, 35)`.
struct InceptionA {
    branch1x1: BasicConv,
    branch5x5: [BasicConv; 2],
    branch3x3dbl: [BasicConv; 3],
    branch_pool: BasicConv,
}

impl InceptionA {
    fn load(w: &mut Weights, prefix: &str, cin: i64, pool_features: i64) -> Result<Self> {
        let p = |name: &str| format!("{prefix}.{name}");
        Ok(Self {
            branch1x1: BasicConv::pointwise(w, &p("branch1x1"), cin, 64)?,
            branch5x5: [
                BasicConv::pointwise(w, &p("branch5x5_1"), cin, 48)?,
                BasicConv::load(w, &p("branch5x5_2"), 48, 64, [5, 5], 1, [2, 2])?,
            ],
            branch3x3dbl: [
                BasicConv::pointwise(w, &p("branch3x3dbl_1"), cin, 64)?,
                BasicConv::load(w, &p("branch3x3dbl_2"), 64, 96, [3, 3], 1, [1, 1])?,
                BasicConv::load(w, &p("branch3x3dbl_3"), 96, 96, [3, 3], 1, [1, 1])?,
            ],
            branch_pool: BasicConv::pointwise(w, &p("branch_pool"), cin, pool_features)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        Tensor::cat(
            &[
                self.branch1x1.forward(x),
                chain(&self.branch5x5, x),
                chain(&self.branch3x3dbl, x),
                self.branch_pool.forward(&tf_avg_pool_3x3(x)),
            ],
            1,
        )
    }
}

/// Mixed_6a (torchvision's `InceptionB`, unchanged by the port): stride-2 reduction with
/// branches 3×3/2 (384), 1×1→3×3→3×3/2 (96) and max-pool 3×3/2.
/// `(B, 288, 35, 35)` → `(B, 768, 17, 17)`.
struct InceptionB {
    branch3x3: BasicConv,
    branch3x3dbl: [BasicConv; 3],
}

impl InceptionB {
    fn load(w: &mut Weights, prefix: &str, cin: i64) -> Result<Self> {
        let p = |name: &str| format!("{prefix}.{name}");
        Ok(Self {
            branch3x3: BasicConv::load(w, &p("branch3x3"), cin, 384, [3, 3], 2, [0, 0])?,
            branch3x3dbl: [
                BasicConv::pointwise(w, &p("branch3x3dbl_1"), cin, 64)?,
                BasicConv::load(w, &p("branch3x3dbl_2"), 64, 96, [3, 3], 1, [1, 1])?,
                BasicConv::load(w, &p("branch3x3dbl_3"), 96, 96, [3, 3], 2, [0, 0])?,
            ],
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        Tensor::cat(&[self.branch3x3.forward(x), chain(&self.branch3x3dbl, x), max_pool_3x3_s2(x)], 1)
    }
}

/// Mixed_6b–6e (pytorch-fid's `FIDInceptionC`): factorised 7×7 convolutions of width `c7`;
/// branches 1×1 (192), 1×1→1×7→7×1 (192), 1×1→7×1→1×7→7×1→1×7 (192) and TF-avg-pool→1×1
/// (192). `(B, 768, 17, 17)` → `(B, 768, 17, 17)`.
struct InceptionC {
    branch1x1: BasicConv,
    branch7x7: [BasicConv; 3],
    branch7x7dbl: [BasicConv; 5],
    branch_pool: BasicConv,
}

impl InceptionC {
    fn load(w: &mut Weights, prefix: &str, cin: i64, c7: i64) -> Result<Self> {
        let p = |name: &str| format!("{prefix}.{name}");
        let (row, col) = ([1, 7], [7, 1]);
        let (row_pad, col_pad) = ([0, 3], [3, 0]);
        Ok(Self {
            branch1x1: BasicConv::pointwise(w, &p("branch1x1"), cin, 192)?,
            branch7x7: [
                BasicConv::pointwise(w, &p("branch7x7_1"), cin, c7)?,
                BasicConv::load(w, &p("branch7x7_2"), c7, c7, row, 1, row_pad)?,
                BasicConv::load(w, &p("branch7x7_3"), c7, 192, col, 1, col_pad)?,
            ],
            branch7x7dbl: [
                BasicConv::pointwise(w, &p("branch7x7dbl_1"), cin, c7)?,
                BasicConv::load(w, &p("branch7x7dbl_2"), c7, c7, col, 1, col_pad)?,
                BasicConv::load(w, &p("branch7x7dbl_3"), c7, c7, row, 1, row_pad)?,
                BasicConv::load(w, &p("branch7x7dbl_4"), c7, c7, col, 1, col_pad)?,
                BasicConv::load(w, &p("branch7x7dbl_5"), c7, 192, row, 1, row_pad)?,
            ],
            branch_pool: BasicConv::pointwise(w, &p("branch_pool"), cin, 192)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        Tensor::cat(
            &[
                self.branch1x1.forward(x),
                chain(&self.branch7x7, x),
                chain(&self.branch7x7dbl, x),
                self.branch_pool.forward(&tf_avg_pool_3x3(x)),
            ],
            1,
        )
    }
}

/// Mixed_7a (torchvision's `InceptionD`, unchanged by the port): stride-2 reduction with
/// branches 1×1→3×3/2 (320), 1×1→1×7→7×1→3×3/2 (192) and max-pool 3×3/2.
/// `(B, 768, 17, 17)` → `(B, 1280, 8, 8)`.
struct InceptionD {
    branch3x3: [BasicConv; 2],
    branch7x7x3: [BasicConv; 4],
}

impl InceptionD {
    fn load(w: &mut Weights, prefix: &str, cin: i64) -> Result<Self> {
        let p = |name: &str| format!("{prefix}.{name}");
        Ok(Self {
            branch3x3: [
                BasicConv::pointwise(w, &p("branch3x3_1"), cin, 192)?,
                BasicConv::load(w, &p("branch3x3_2"), 192, 320, [3, 3], 2, [0, 0])?,
            ],
            branch7x7x3: [
                BasicConv::pointwise(w, &p("branch7x7x3_1"), cin, 192)?,
                BasicConv::load(w, &p("branch7x7x3_2"), 192, 192, [1, 7], 1, [0, 3])?,
                BasicConv::load(w, &p("branch7x7x3_3"), 192, 192, [7, 1], 1, [3, 0])?,
                BasicConv::load(w, &p("branch7x7x3_4"), 192, 192, [3, 3], 2, [0, 0])?,
            ],
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        Tensor::cat(&[chain(&self.branch3x3, x), chain(&self.branch7x7x3, x), max_pool_3x3_s2(x)], 1)
    }
}

/// What the pooling branch of an `InceptionE` block pools with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EPool {
    /// Mixed_7b (`FIDInceptionE_1`): TF average pool, padding left out of the mean.
    TfAverage,
    /// Mixed_7c (`FIDInceptionE_2`): 3×3 stride-1 max pool with padding 1 — the TF graph
    /// has a max pool here (the paper an average pool), and FID is defined by the graph.
    Max,
}

/// Mixed_7b/7c (pytorch-fid's `FIDInceptionE_1`/`_2`): branches 1×1 (320),
/// 1×1→{1×3, 3×1} (2·384), 1×1→3×3→{1×3, 3×1} (2·384) and pool→1×1 (192).
/// `(B, cin, 8, 8)` → `(B, 2048, 8, 8)`.
struct InceptionE {
    branch1x1: BasicConv,
    branch3x3_1: BasicConv,
    branch3x3_2: [BasicConv; 2],
    branch3x3dbl_12: [BasicConv; 2],
    branch3x3dbl_3: [BasicConv; 2],
    branch_pool: BasicConv,
    pool: EPool,
}

impl InceptionE {
    fn load(w: &mut Weights, prefix: &str, cin: i64, pool: EPool) -> Result<Self> {
        let p = |name: &str| format!("{prefix}.{name}");
        // The 1×3 / 3×1 pair that splits a branch in two.
        let split = |w: &mut Weights, a: &str, b: &str| -> Result<[BasicConv; 2]> {
            Ok([
                BasicConv::load(w, &p(a), 384, 384, [1, 3], 1, [0, 1])?,
                BasicConv::load(w, &p(b), 384, 384, [3, 1], 1, [1, 0])?,
            ])
        };
        Ok(Self {
            branch1x1: BasicConv::pointwise(w, &p("branch1x1"), cin, 320)?,
            branch3x3_1: BasicConv::pointwise(w, &p("branch3x3_1"), cin, 384)?,
            branch3x3_2: split(w, "branch3x3_2a", "branch3x3_2b")?,
            branch3x3dbl_12: [
                BasicConv::pointwise(w, &p("branch3x3dbl_1"), cin, 448)?,
                BasicConv::load(w, &p("branch3x3dbl_2"), 448, 384, [3, 3], 1, [1, 1])?,
            ],
            branch3x3dbl_3: split(w, "branch3x3dbl_3a", "branch3x3dbl_3b")?,
            branch_pool: BasicConv::pointwise(w, &p("branch_pool"), cin, 192)?,
            pool,
        })
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let b3 = self.branch3x3_1.forward(x);
        let b3dbl = chain(&self.branch3x3dbl_12, x);
        let pooled = match self.pool {
            EPool::TfAverage => tf_avg_pool_3x3(x),
            EPool::Max => x.max_pool2d([3, 3], [1, 1], [1, 1], [1, 1], false),
        };
        Tensor::cat(
            &[
                self.branch1x1.forward(x),
                self.branch3x3_2[0].forward(&b3),
                self.branch3x3_2[1].forward(&b3),
                self.branch3x3dbl_3[0].forward(&b3dbl),
                self.branch3x3dbl_3[1].forward(&b3dbl),
                self.branch_pool.forward(&pooled),
            ],
            1,
        )
    }
}

/// Applies `convs` one after the other.
fn chain(convs: &[BasicConv], x: &Tensor) -> Tensor {
    convs.iter().fold(x.shallow_clone(), |y, c| c.forward(&y))
}

/// FID's Inception-v3 up to the final average pool, frozen, in eval mode.
pub struct InceptionV3 {
    /// `blocks.0.{0,1,2}` (Conv2d_1a/2a/2b) and `blocks.1.{0,1}` (Conv2d_3b/4a); a 3×3/2
    /// max pool follows each group. `(B, 3, 299, 299)` → `(B, 192, 35, 35)`.
    stem: [BasicConv; 5],
    /// `blocks.2.{0,1,2}`: Mixed_5b/5c/5d.
    mixed_5: [InceptionA; 3],
    /// `blocks.2.3`: Mixed_6a.
    mixed_6a: InceptionB,
    /// `blocks.2.{4..7}`: Mixed_6b–6e.
    mixed_6: [InceptionC; 4],
    /// `blocks.3.0`: Mixed_7a.
    mixed_7a: InceptionD,
    /// `blocks.3.{1,2}`: Mixed_7b (average-pool branch), Mixed_7c (max-pool branch).
    mixed_7: [InceptionE; 2],
    device: Device,
}

impl InceptionV3 {
    /// Reads the weights from a safetensors file holding pytorch-fid's state dict (see
    /// `scripts/export_inception_weights.py`), onto `device`.
    pub fn load(path: &Path, device: Device) -> Result<Self> {
        Self::from_weights(Weights::open(path, device)?)
    }

    /// Builds the network from `w`; errors name any missing, mis-shaped or unexpected tensor.
    pub fn from_weights(mut w: Weights) -> Result<Self> {
        let net = Self::build(&mut w)?;
        w.finish()?;
        Ok(net)
    }

    fn build(w: &mut Weights) -> Result<Self> {
        let stem = [
            BasicConv::load(w, "blocks.0.0", 3, 32, [3, 3], 2, [0, 0])?,
            BasicConv::load(w, "blocks.0.1", 32, 32, [3, 3], 1, [0, 0])?,
            BasicConv::load(w, "blocks.0.2", 32, 64, [3, 3], 1, [1, 1])?,
            BasicConv::pointwise(w, "blocks.1.0", 64, 80)?,
            BasicConv::load(w, "blocks.1.1", 80, 192, [3, 3], 1, [0, 0])?,
        ];
        let mixed_5 = [
            InceptionA::load(w, "blocks.2.0", 192, 32)?,
            InceptionA::load(w, "blocks.2.1", 256, 64)?,
            InceptionA::load(w, "blocks.2.2", 288, 64)?,
        ];
        let mixed_6a = InceptionB::load(w, "blocks.2.3", 288)?;
        let mixed_6 = [
            InceptionC::load(w, "blocks.2.4", 768, 128)?,
            InceptionC::load(w, "blocks.2.5", 768, 160)?,
            InceptionC::load(w, "blocks.2.6", 768, 160)?,
            InceptionC::load(w, "blocks.2.7", 768, 192)?,
        ];
        let mixed_7a = InceptionD::load(w, "blocks.3.0", 768)?;
        let mixed_7 = [
            InceptionE::load(w, "blocks.3.1", 1280, EPool::TfAverage)?,
            InceptionE::load(w, "blocks.3.2", 2048, EPool::Max)?,
        ];
        let device = stem[0].conv.weight.device();
        Ok(Self { stem, mixed_5, mixed_6a, mixed_6, mixed_7a, mixed_7, device })
    }

    /// The device the weights live on; inputs are moved there and features returned there.
    pub fn device(&self) -> Device {
        self.device
    }

    /// Pool3 features of images in [-1, 1] (the range of this project's generators and
    /// datasets): `(B, 3, H, W)` of any float kind and size → `(B, 2048)` float32. The images
    /// are mapped to [0, 1] by (x + 1)/2 and then treated exactly as
    /// [`features_from_unit`](Self::features_from_unit) does.
    pub fn features_from_signed(&self, images: &Tensor) -> Result<Tensor> {
        check_images(images)?;
        self.features_from_unit(&((self.prepare(images) + 1.0) / 2.0))
    }

    /// Pool3 features of images in [0, 1], what pytorch-fid's `InceptionV3` takes:
    /// `(B, 3, H, W)` of any float kind and size → `(B, 2048)` float32. The images are
    /// resized to 299×299 bilinearly (half-pixel centres, no antialiasing, as
    /// `F.interpolate(mode='bilinear', align_corners=False)`) and mapped to [-1, 1].
    /// Memory grows with B: chunk large image sets.
    pub fn features_from_unit(&self, images: &Tensor) -> Result<Tensor> {
        check_images(images)?;
        let x = self.prepare(images);
        Ok(tch::no_grad(|| {
            let x = x.upsample_bilinear2d([INPUT_SIZE, INPUT_SIZE], false, None, None) * 2.0 - 1.0;
            self.forward_normalised(&x)
        }))
    }

    /// Float32 on the weights' device, cut from any graph.
    fn prepare(&self, images: &Tensor) -> Tensor {
        images.detach().to_device(self.device).to_kind(Kind::Float)
    }

    /// `(B, 3, 299, 299)` in [-1, 1] → `(B, 2048)`.
    fn forward_normalised(&self, x: &Tensor) -> Tensor {
        let [c1a, c2a, c2b, c3b, c4a] = &self.stem;
        let x = max_pool_3x3_s2(&c2b.forward(&c2a.forward(&c1a.forward(x))));
        let mut x = max_pool_3x3_s2(&c4a.forward(&c3b.forward(&x)));
        for m in &self.mixed_5 {
            x = m.forward(&x);
        }
        x = self.mixed_6a.forward(&x);
        for m in &self.mixed_6 {
            x = m.forward(&x);
        }
        x = self.mixed_7a.forward(&x);
        for m in &self.mixed_7 {
            x = m.forward(&x);
        }
        x.adaptive_avg_pool2d([1, 1]).flatten(1, -1)
    }
}

/// A batch the extractor accepts: `(B, 3, H, W)`, B, H, W ≥ 1, floating point.
fn check_images(x: &Tensor) -> Result<()> {
    let s = x.size();
    if s.len() != 4 || s[1] != 3 || s.iter().any(|&d| d < 1) {
        return Err(Error::Shape(format!("Inception-v3 takes a (B, 3, H, W) batch of RGB images, got shape {s:?}")));
    }
    if !x.is_floating_point() {
        return Err(Error::Invalid(format!("Inception-v3 takes float images, got {:?}", x.kind())));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_wrong_shapes_and_kinds() {
        for shape in [vec![3, 8, 8], vec![2, 1, 8, 8], vec![2, 4, 8, 8], vec![0, 3, 8, 8], vec![1, 3, 0, 8]] {
            let e = check_images(&Tensor::zeros(shape.as_slice(), (Kind::Float, Device::Cpu))).unwrap_err();
            assert!(matches!(e, Error::Shape(_)) && e.to_string().contains(&format!("{shape:?}")), "{e}");
        }
        let e = check_images(&Tensor::zeros([1, 3, 8, 8], (Kind::Uint8, Device::Cpu))).unwrap_err();
        assert!(matches!(e, Error::Invalid(_)), "{e}");
        check_images(&Tensor::zeros([1, 3, 5, 9], (Kind::Double, Device::Cpu))).unwrap();
    }

    #[test]
    fn tf_average_pool_leaves_padding_out() {
        // A constant map stays constant at the borders only if the padding is not averaged in.
        let x = Tensor::ones([1, 1, 4, 5], (Kind::Float, Device::Cpu));
        let y = tf_avg_pool_3x3(&x);
        assert_eq!(y.size(), [1, 1, 4, 5]);
        assert_eq!(f64::try_from((y - 1.0).abs().max()).unwrap(), 0.0);
    }
}
