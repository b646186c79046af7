//! The discriminators. The release's ([`Discriminator`]): pi-GAN's progressive CoordConv
//! residual encoder with anti-aliased fade-in, heads for the real/fake logit, a latent
//! prediction and the pose (pitch, yaw). An option for small budgets
//! ([`projected::ProjectedDiscriminator`]): learned heads on a frozen pretrained network's
//! features, with the same outputs. The training loop sees either through [`Judge`].
pub mod augment;
pub mod projected;

use crate::error::require;
use crate::nn::mapping::leaky_relu;
use crate::{Error, Result};
use projected::{ProjectedConfig, ProjectedDiscriminator};
use serde::{Deserialize, Serialize};
use tch::{nn, Tensor};

/// Channels of fromRGB[i] (the input of layers[i]) in the release.
pub const CHANNELS: [i64; 9] = [16, 32, 64, 128, 256, 400, 400, 400, 400];
/// Width of the latent-prediction head.
pub const LATENT_DIM: i64 = 256;

/// Widths of the discriminator (default: the release's). A narrower D is what makes
/// small CPU runs affordable: at 32² the release's D (12.5 M parameters, R1's double
/// backward) costs a third of a training step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DiscConfig {
    /// Channels of fromRGB[i] and of the input of layers[i], i = 0..8 (9 values; the
    /// last is the head's input). Layer i maps channels[i] → channels[i + 1].
    pub channels: Vec<i64>,
    /// Group size of a minibatch standard-deviation channel appended before the head
    /// (StyleGAN's remedy for mode collapse: D sees how much a group of images varies);
    /// 0 = off, as in the release. Groups shrink to divide the batch.
    pub minibatch_std_group: i64,
    /// Which discriminator: `"release"` (default) or `"projected"`.
    pub kind: DiscKind,
    /// Settings of the projected discriminator (read when `kind = "projected"`).
    pub projected: ProjectedConfig,
    /// DiffAugment's transforms applied to every image the discriminator judges, real or
    /// generated, in both players' steps: any of `"color"`, `"translation"`, `"cutout"`
    /// ([`augment`]); empty (the release) = none. The projected GAN trains with all three.
    pub augment: Vec<augment::Augmentation>,
    /// What translation uncovers and cutout removes, in [−1, 1]: 0 (DiffAugment's, the
    /// default) is mid-grey, 1 white, the procedural datasets' background.
    pub augment_fill: f64,
}

/// Which discriminator a run trains.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum DiscKind {
    /// The release's progressive CoordConv encoder, trained from scratch.
    #[default]
    Release,
    /// Heads on frozen EfficientNet-Lite0 features ([`projected`]).
    Projected,
}

impl DiscKind {
    /// The config's spelling.
    pub fn name(self) -> &'static str {
        match self {
            DiscKind::Release => "release",
            DiscKind::Projected => "projected",
        }
    }
}

impl Default for DiscConfig {
    fn default() -> Self {
        Self {
            channels: CHANNELS.to_vec(),
            minibatch_std_group: 0,
            kind: DiscKind::Release,
            projected: ProjectedConfig::default(),
            augment: Vec::new(),
            augment_fill: 0.0,
        }
    }
}

/// What the training loop needs of a discriminator.
pub trait Judge {
    /// `img: (B, 3, S, S)` in [−1, 1] → logit `(B, 1)`, latent `(B, 256)`, pose `(B, 2)`;
    /// `alpha` is the fade-in of a resolution switch (1 = none).
    fn judge(&self, img: &Tensor, alpha: f64) -> Result<DiscOutput>;
    /// The same verdict on scaled patches of images (the scaled-patch step), each seen
    /// where it lies: `at: (B, 3)` holds each patch's scale and top-left offset
    /// `[s, ox, oy]` as fractions of its image ([`crate::camera::patch::Patch::coords`]).
    /// A discriminator that cannot be told refuses.
    fn judge_patches(&self, _img: &Tensor, _alpha: f64, _at: &Tensor) -> Result<DiscOutput> {
        Err(Error::Config(
            "this discriminator cannot be told where a scaled patch lies; stages.patch needs \
             discriminator.kind = \"release\""
                .into(),
        ))
    }
    /// Trained parameters a `size × size` input uses.
    fn used_parameters(&self, size: i64) -> Result<i64>;
}

/// The configured discriminator, its variables under `vs`.
pub fn build(vs: &nn::Path, cfg: &DiscConfig) -> Result<Box<dyn Judge>> {
    cfg.validate()?;
    Ok(match cfg.kind {
        DiscKind::Release => Box::new(Discriminator::with_config(vs, cfg)?),
        DiscKind::Projected => Box::new(ProjectedDiscriminator::new(vs, &cfg.projected)?),
    })
}

impl DiscConfig {
    pub fn validate(&self) -> Result<()> {
        self.projected.validate()?;
        if self.channels.len() != CHANNELS.len() || self.channels.iter().any(|&c| c < 1) {
            return Err(Error::Config(format!(
                "discriminator.channels is {:?}, expected {} positive widths (one per resolution 512² … 2²)",
                self.channels,
                CHANNELS.len()
            )));
        }
        require(
            (-1.0..=1.0).contains(&self.augment_fill),
            "discriminator.augment_fill",
            self.augment_fill,
            "a pixel value in [-1, 1] (0 grey, 1 white)",
        )?;
        require(
            self.minibatch_std_group >= 0,
            "discriminator.minibatch_std_group",
            self.minibatch_std_group,
            "0 (off) or a group size ≥ 1",
        )?;
        Ok(())
    }
}

/// Appends StyleGAN's minibatch standard-deviation channel: images are split into groups
/// of `group` (shrunk to the largest divisor of the batch), the standard deviation of every
/// feature over each group is averaged to one number per group and broadcast as an extra
/// channel. `x: (B, C, H, W)` → `(B, C + 1, H, W)`.
pub fn minibatch_std(x: &Tensor, group: i64) -> Tensor {
    let s = x.size();
    let (b, c, h, w) = (s[0], s[1], s[2], s[3]);
    let g = (1..=group.min(b)).rev().find(|g| b % g == 0).unwrap_or(1);
    let y = x.view([g, b / g, c, h, w]);
    // Variance + ε before the square root: a group of identical images has a finite gradient.
    let sd = ((&y - y.mean_dim(0, true, x.kind())).square().mean_dim(0, false, x.kind()) + 1e-8).sqrt();
    let per_group = sd.mean_dim([1i64, 2, 3].as_slice(), false, x.kind()); // (B/g,)
    let ch = per_group.view([1, b / g, 1, 1, 1]).expand([g, b / g, 1, h, w], false).reshape([b, 1, h, w]);
    Tensor::cat(&[x.shallow_clone(), ch], 1)
}

/// A 2-D convolution with PyTorch's default initialisation (weight and bias
/// U(±1/√fan_in), fan_in = in·k·k), which the release keeps for every conv of D.
#[derive(Debug)]
pub struct Conv {
    pub weight: Tensor,
    pub bias: Tensor,
    padding: i64,
}

impl Conv {
    pub fn new(vs: nn::Path, cin: i64, cout: i64, k: i64, padding: i64) -> Self {
        let b = 1.0 / ((cin * k * k) as f64).sqrt();
        let init = nn::Init::Uniform { lo: -b, up: b };
        Self { weight: vs.var("weight", &[cout, cin, k, k], init), bias: vs.var("bias", &[cout], init), padding }
    }
    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.conv2d(&self.weight, Some(&self.bias), [1, 1], [self.padding, self.padding], [1, 1], 1)
    }
}

/// Appends the coordinate channels: first the row coordinate (varies along H), then the
/// column coordinate (varies along W), each idx/(size − 1)·2 − 1. `x: (B, C, H, W)`.
pub fn add_coords(x: &Tensor) -> Tensor {
    add_coords_at(x, None)
}

/// [`add_coords`] of a scaled patch of the image: with `at: (B, 3)` = `[s, ox, oy]`
/// (scale and top-left offset as fractions of the image, y down), each coordinate is
/// EpiGRAF's `(c + 1)·s − 1 + 2·o` of the patch's own c = idx/(size − 1)·2 − 1: where the
/// patch lies in the whole image's [−1, 1], its spacing carrying the scale. The whole image
/// (`[1, 0, 0]`) gets `add_coords`' channels bit for bit, so a discriminator trained on
/// whole images sees whole-image patches exactly as before, and no parameter is added.
pub fn add_coords_at(x: &Tensor, at: Option<&Tensor>) -> Tensor {
    let s = x.size();
    let (b, h, w) = (s[0], s[2], s[3]);
    let opts = (x.kind(), x.device());
    let coord = |n: i64| Tensor::arange(n, opts) / ((n - 1).max(1) as f64) * 2.0 - 1.0;
    let (rows, cols) = match at {
        None => (coord(h).view([1, 1, h, 1]), coord(w).view([1, 1, 1, w])),
        Some(at) => {
            let at = at.to_kind(x.kind()).view([b, 3, 1, 1]);
            let (scale, ox, oy) = (at.narrow(1, 0, 1), at.narrow(1, 1, 1), at.narrow(1, 2, 1));
            let place = |c: Tensor, o: &Tensor| (c + 1.0) * &scale - 1.0 + o * 2.0;
            (place(coord(h).view([1, 1, h, 1]), &oy), place(coord(w).view([1, 1, 1, w]), &ox))
        }
    };
    let rows = rows.expand([b, 1, h, w], false);
    let cols = cols.expand([b, 1, h, w], false);
    Tensor::cat(&[x.shallow_clone(), rows, cols], 1)
}

/// CoordConv 3×3 → LeakyReLU → CoordConv 3×3 → LeakyReLU → avg-pool 2, plus a pooled
/// (and, when widths differ, 1×1-projected) skip; the sum is scaled by 1/√2.
#[derive(Debug)]
pub struct ResidualBlock {
    pub conv1: Conv,
    pub conv2: Conv,
    pub proj: Option<Conv>,
}

impl ResidualBlock {
    pub fn new(vs: nn::Path, cin: i64, cout: i64) -> Self {
        Self {
            conv1: Conv::new(&vs / "conv1", cin + 2, cout, 3, 1),
            conv2: Conv::new(&vs / "conv2", cout + 2, cout, 3, 1),
            proj: (cin != cout).then(|| Conv::new(&vs / "proj", cin, cout, 1, 0)),
        }
    }
    /// `x: (B, C, H, W)`, the coordinate channels those of the patches `at` where given
    /// ([`add_coords_at`]).
    pub fn forward(&self, x: &Tensor, at: Option<&Tensor>) -> Tensor {
        let y = leaky_relu(&self.conv1.forward(&add_coords_at(x, at)));
        let y = leaky_relu(&self.conv2.forward(&add_coords_at(&y, at)));
        let y = y.avg_pool2d([2, 2], [2, 2], [0, 0], false, true, None);
        let skip = x.avg_pool2d([2, 2], [2, 2], [0, 0], false, true, None);
        let skip = match &self.proj {
            Some(p) => p.forward(&skip),
            None => skip,
        };
        (y + skip) / std::f64::consts::SQRT_2
    }
}

/// Anti-aliased ×2 downsampling: replicate-pad 1 px, then a depthwise stride-2 conv with
/// the separable kernel [1, 3, 3, 1]/8 ⊗ [1, 3, 3, 1]/8. `(B, C, H, W)` → `(B, C, H/2, W/2)`.
pub fn downsample_aa(x: &Tensor) -> Tensor {
    let c = x.size()[1];
    let k1 = Tensor::from_slice(&[1.0f64, 3.0, 3.0, 1.0]).to_kind(x.kind()).to_device(x.device()) / 8.0;
    let k = k1.view([4, 1]).matmul(&k1.view([1, 4])).view([1, 1, 4, 4]).repeat([c, 1, 1, 1]);
    x.pad([1, 1, 1, 1], "replicate", None).conv2d(&k, None::<Tensor>, [2, 2], [0, 0], [1, 1], c)
}

/// What the discriminator says about a batch.
#[derive(Debug)]
pub struct DiscOutput {
    /// `(B, 1)` real/fake logit.
    pub logit: Tensor,
    /// `(B, 256)` latent prediction (weight 0 in every release config).
    pub latent: Tensor,
    /// `(B, 2)` predicted (pitch, yaw).
    pub pose: Tensor,
    /// `(B,)` the scale of the patch each image was judged through ([`Judge::judge_patches`]),
    /// `None` for whole images: what the pose loss may count ([`crate::loss::gan::pose_loss_at`]).
    pub scale: Option<Tensor>,
}

#[derive(Debug)]
pub struct Discriminator {
    pub from_rgb: Vec<Conv>,
    pub layers: Vec<ResidualBlock>,
    pub head: Conv,
    minibatch_std_group: i64,
}

impl Judge for Discriminator {
    fn judge(&self, img: &Tensor, alpha: f64) -> Result<DiscOutput> {
        self.forward(img, alpha)
    }
    fn judge_patches(&self, img: &Tensor, alpha: f64, at: &Tensor) -> Result<DiscOutput> {
        if at.size() != [img.size()[0], 3] {
            return Err(Error::Shape(format!(
                "patch coordinates of shape {:?} for {} images, expected [{}, 3]",
                at.size(),
                img.size()[0],
                img.size()[0]
            )));
        }
        self.forward_at(img, alpha, Some(at))
    }
    fn used_parameters(&self, size: i64) -> Result<i64> {
        used_parameters(self, size)
    }
}

impl Discriminator {
    /// The release's discriminator.
    pub fn new(vs: &nn::Path) -> Self {
        Self::with_config(vs, &DiscConfig::default()).expect("the release's widths are valid")
    }

    /// A discriminator of the configured widths (PyTorch's default conv init, drawn under
    /// [`crate::rng::with_global_generator`]).
    pub fn with_config(vs: &nn::Path, cfg: &DiscConfig) -> Result<Self> {
        crate::rng::with_global_generator(|| Self::create(vs, cfg))
    }

    fn create(vs: &nn::Path, cfg: &DiscConfig) -> Result<Self> {
        cfg.validate()?;
        let c = &cfg.channels;
        let from_rgb = c.iter().enumerate().map(|(i, &c)| Conv::new(vs / "from_rgb" / i, 3, c, 1, 0)).collect();
        let layers = (0..8).map(|i| ResidualBlock::new(vs / "layers" / i, c[i], c[i + 1])).collect();
        let head_in = c[8] + (cfg.minibatch_std_group > 0) as i64;
        let head = Conv::new(vs / "head", head_in, 1 + LATENT_DIM + 2, 2, 0);
        Ok(Self { from_rgb, layers, head, minibatch_std_group: cfg.minibatch_std_group })
    }

    /// Index of the first block for a `size × size` input (512 → 0, …, 64 → 3, 2 → 8).
    pub fn start_index(size: i64) -> Result<usize> {
        match size {
            2 | 4 | 8 | 16 | 32 | 64 | 128 | 256 | 512 => Ok(9 - size.trailing_zeros() as usize),
            _ => Err(Error::Invalid(format!(
                "discriminator input is {size}×{size}; expected a power of two from 2 to 512"
            ))),
        }
    }

    /// `img: (B, 3, S, S)` in [−1, 1]; `alpha` ∈ [0, 1] fades in the first block (1 = fully in).
    pub fn forward(&self, img: &Tensor, alpha: f64) -> Result<DiscOutput> {
        self.forward_at(img, alpha, None)
    }

    /// [`Self::forward`] on scaled patches `img` lying at `at: (B, 3)` in their images
    /// ([`add_coords_at`]; `None`: whole images).
    pub fn forward_at(&self, img: &Tensor, alpha: f64, at: Option<&Tensor>) -> Result<DiscOutput> {
        let size = img.size()[3];
        if img.size()[2] != size || img.size()[1] != 3 {
            return Err(Error::Shape(format!("discriminator expects (B, 3, S, S) images, got {:?}", img.size())));
        }
        let start = Self::start_index(size)?;
        let mut x = leaky_relu(&self.from_rgb[start].forward(img));
        for (i, layer) in self.layers[start..].iter().enumerate() {
            if i == 1 && alpha < 1.0 {
                let skip = leaky_relu(&self.from_rgb[start + 1].forward(&downsample_aa(img)));
                x = x * alpha + skip * (1.0 - alpha);
            }
            x = layer.forward(&x, at);
        }
        if self.minibatch_std_group > 0 {
            x = minibatch_std(&x, self.minibatch_std_group);
        }
        let out = self.head.forward(&x).flatten(1, -1);
        Ok(DiscOutput {
            logit: out.narrow(1, 0, 1),
            latent: out.narrow(1, 1, LATENT_DIM),
            pose: out.narrow(1, 1 + LATENT_DIM, 2),
            scale: at.map(|a| a.select(1, 0)),
        })
    }
}

/// The release's fade-in: α = 1 until the first resolution switch, then rises linearly
/// from 0 to 1 over `fade_steps` steps after it.
pub fn fade_alpha(step: i64, switch_step: Option<i64>, fade_steps: i64) -> f64 {
    match switch_step {
        Some(s) if step >= s => ((step - s) as f64 / fade_steps.max(1) as f64).min(1.0),
        _ => 1.0,
    }
}

/// Number of parameters a `size × size` input actually uses.
pub fn used_parameters(d: &Discriminator, size: i64) -> Result<i64> {
    let start = Discriminator::start_index(size)?;
    let n = |c: &Conv| (c.weight.numel() + c.bias.numel()) as i64;
    let mut total = n(&d.from_rgb[start]) + n(&d.head);
    if start + 1 < 9 {
        total += n(&d.from_rgb[start + 1]);
    }
    for l in &d.layers[start..] {
        total += n(&l.conv1) + n(&l.conv2) + l.proj.as_ref().map(n).unwrap_or(0);
    }
    Ok(total)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn parameter_counts_match_the_release() {
        let vs = nn::VarStore::new(Device::Cpu);
        let d = Discriminator::new(&vs.root());
        let total: i64 = vs.trainable_variables().iter().map(|t| t.numel() as i64).sum();
        assert_eq!(total, 12_825_523);
        assert_eq!(used_parameters(&d, 64).unwrap(), 12_508_883);
        assert_eq!(used_parameters(&d, 128).unwrap(), 12_742_483);
    }

    #[test]
    fn outputs_have_the_head_layout_at_every_size() {
        let vs = nn::VarStore::new(Device::Cpu);
        let d = Discriminator::new(&vs.root());
        for s in [8, 32, 64] {
            let img = Tensor::rand([2, 3, s, s], (Kind::Float, Device::Cpu));
            let o = d.forward(&img, 0.5).unwrap();
            assert_eq!(o.logit.size(), [2, 1]);
            assert_eq!(o.latent.size(), [2, 256]);
            assert_eq!(o.pose.size(), [2, 2]);
        }
        assert!(d.forward(&Tensor::rand([1, 3, 48, 48], (Kind::Float, Device::Cpu)), 1.0).is_err());
    }

    #[test]
    fn narrow_widths_work_and_bad_ones_are_named() {
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = DiscConfig { channels: vec![8, 16, 16, 32, 32, 64, 64, 64, 64], ..Default::default() };
        let d = Discriminator::with_config(&vs.root(), &cfg).unwrap();
        let o = d.forward(&Tensor::rand([3, 3, 32, 32], (Kind::Float, Device::Cpu)), 0.3).unwrap();
        assert_eq!(o.pose.size(), [3, 2]);
        let e =
            Discriminator::with_config(&(&vs.root() / "x"), &DiscConfig { channels: vec![4; 8], ..Default::default() })
                .unwrap_err()
                .to_string();
        assert!(e.contains("discriminator.channels"), "{e}");
    }

    #[test]
    fn minibatch_std_sees_the_spread_of_each_group() {
        let opts = (Kind::Double, Device::Cpu);
        // Two groups of two (group 2, batch 4): images 0 and 2 form one group, 1 and 3 the other.
        let x = Tensor::cat(
            &[
                Tensor::zeros([1, 2, 2, 2], opts),
                Tensor::ones([1, 2, 2, 2], opts),
                Tensor::full([1, 2, 2, 2], 2.0, opts),
                Tensor::ones([1, 2, 2, 2], opts),
            ],
            0,
        );
        let y = minibatch_std(&x, 2);
        assert_eq!(y.size(), [4, 3, 2, 2]);
        let ch: Vec<f64> = Vec::try_from(y.select(1, 2).mean_dim([1i64, 2].as_slice(), false, Kind::Double)).unwrap();
        // Group {0, 2}: values 0 and 2 → population sd 1; group {1, 3}: identical → √1e-8.
        for (got, want) in ch.iter().zip([1.0, 1e-4, 1.0, 1e-4]) {
            assert!((got - want).abs() <= 1e-9 + 1e-6 * want, "{ch:?}");
        }
        // A batch of 3 with group 4 falls back to one group of 3; gradients stay finite for identical images.
        let z = Tensor::ones([3, 2, 2, 2], opts).set_requires_grad(true);
        minibatch_std(&z, 4).sum(Kind::Double).backward();
        assert!(bool::try_from(z.grad().isfinite().all()).unwrap());
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = DiscConfig {
            channels: vec![8, 16, 16, 32, 32, 64, 64, 64, 64],
            minibatch_std_group: 4,
            ..Default::default()
        };
        let d = Discriminator::with_config(&vs.root(), &cfg).unwrap();
        assert_eq!(d.head.weight.size()[1], 65);
        assert_eq!(
            d.forward(&Tensor::rand([6, 3, 32, 32], (Kind::Float, Device::Cpu)), 1.0).unwrap().logit.size(),
            [6, 1]
        );
    }

    /// Under the scaled-patch step the coordinate channels say where each patch lies: the
    /// whole image's bit for bit at `[1, 0, 0]`, EpiGRAF's `(c + 1)·s − 1 + 2·o` elsewhere.
    #[test]
    fn patch_coordinates_place_each_patch_in_its_image() {
        let opts = (Kind::Float, Device::Cpu);
        let x = Tensor::rand([2, 1, 5, 5], opts);
        let whole = Tensor::from_slice(&[1.0f32, 0.0, 0.0, 1.0, 0.0, 0.0]).view([2, 3]);
        assert!(add_coords_at(&x, Some(&whole)).equal(&add_coords(&x)));
        // Image 0: a quarter-size patch at (0.5, 0.25); image 1: half size at (0.1, 0.5).
        let at = Tensor::from_slice(&[0.25f64, 0.5, 0.25, 0.5, 0.1, 0.5]).view([2, 3]);
        let y = add_coords_at(&x.to_kind(Kind::Double), Some(&at));
        for (b, (s, ox, oy)) in [(0i64, (0.25, 0.5, 0.25)), (1, (0.5, 0.1, 0.5))] {
            for k in 0..5i64 {
                let c = k as f64 / 4.0 * 2.0 - 1.0;
                let (row, col) = ((c + 1.0) * s - 1.0 + 2.0 * oy, (c + 1.0) * s - 1.0 + 2.0 * ox);
                // Rows vary along H, columns along W.
                assert!((y.double_value(&[b, 1, k, 3]) - row).abs() < 1e-15, "image {b} row {k}");
                assert!((y.double_value(&[b, 2, 2, k]) - col).abs() < 1e-15, "image {b} column {k}");
            }
        }
        // A patch's first row and column start at its offset: −1 + 2·o.
        assert_eq!(y.double_value(&[0, 2, 0, 0]), 0.0);
        assert_eq!(y.double_value(&[1, 1, 0, 0]), 0.0);
        // The discriminator: whole-image patches judge as whole images, exactly; other
        // patches differently; a wrong shape of coordinates is refused.
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = DiscConfig { channels: vec![8, 8, 8, 8, 8, 8, 8, 8, 8], ..Default::default() };
        let d = Discriminator::with_config(&vs.root(), &cfg).unwrap();
        let img = Tensor::rand([2, 3, 16, 16], opts);
        let plain = d.judge(&img, 1.0).unwrap();
        assert!(d.judge_patches(&img, 1.0, &whole).unwrap().logit.equal(&plain.logit));
        let placed = d.judge_patches(&img, 1.0, &at.to_kind(Kind::Float)).unwrap();
        assert!(!placed.logit.allclose(&plain.logit, 1e-6, 1e-6, false));
        assert!(d.judge_patches(&img, 1.0, &whole.narrow(0, 0, 1)).is_err());
        // The verdict carries each patch's scale, for the pose loss; whole images none.
        assert_eq!(Vec::<f32>::try_from(placed.scale.unwrap()).unwrap(), vec![0.25, 0.5]);
        assert!(plain.scale.is_none());
    }

    #[test]
    fn aa_downsample_keeps_constants_and_halves_size() {
        let x = Tensor::full([1, 2, 8, 8], 0.7, (Kind::Double, Device::Cpu));
        let y = downsample_aa(&x);
        assert_eq!(y.size(), [1, 2, 4, 4]);
        assert!(f64::try_from((y - 0.7).abs().max()).unwrap() < 1e-12);
    }

    #[test]
    fn fade_schedule() {
        assert_eq!(fade_alpha(50, None, 10_000), 1.0);
        assert_eq!(fade_alpha(95_100, Some(95_100), 10_000), 0.0);
        assert_eq!(fade_alpha(100_100, Some(95_100), 10_000), 0.5);
        assert_eq!(fade_alpha(200_000, Some(95_100), 10_000), 1.0);
    }
}
