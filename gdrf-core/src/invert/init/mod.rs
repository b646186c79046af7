//! Stage 1 of the inversion (paper §5.2): a network F that reads a photo's shape feature
//! w_s and camera pose (and, optionally, its raw appearance), trained on images the
//! generator renders from random codes and poses, and on real images of a dataset's
//! training split whose poses are known. Its w_s starts the optimisation, and its pose
//! stands in for a pose the user does not know.
//!
//! Two backbones ([`Backbone`]): the paper's ResNet-34 (tch's architecture, trained from
//! scratch with its head), and the ImageNet-pretrained EfficientNet-Lite0, frozen, under a
//! trained two-layer head. The frozen backbone's features of every training image are taken
//! once, so the head's steps cost next to nothing on a CPU.
//!
//! Loss per batch: on rendered images `mean (F_w(I) − w_s)² + pose_weight · pose error +
//! appearance_weight · mean (F_a(I) − a)² + image_weight · MSE(I(F_w(I), a, θ), I)`; on
//! real images `real_weight · pose error`. The pose error is (pitch − pitch*)² + (cos yaw −
//! cos yaw*)² + (sin yaw − sin yaw*)² (the yaw is predicted as a unit vector, so ±π is no
//! edge). The image term is the paper's re-rendering loss without its LPIPS part; it renders
//! every training image again with gradients, so it is off by default on CPUs.
use crate::checkpoint::{load_tensors_with, tensors_to_bytes};
use crate::io::resize;
use crate::paths::write_atomic;
use crate::pretrained::effnet::{EfficientNetLite0, FEATURE_DIM};
use crate::pretrained::weights::Weights;
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::train::optim::Adam;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;
use tch::nn::{self, Module, ModuleT};
use tch::{Device, Kind, Tensor};

mod data;
mod training;
pub use data::{generate, load_real_images, RealImages, Tuples};
pub use training::{train, InitEval, Start, TrainProgress};

/// Metadata key of an initialiser file's JSON header.
pub const INIT_KEY: &str = "gdrf_initialiser";

/// The file name of a generator's initialiser, in the generator's folder.
pub const INIT_FILE: &str = "initialiser.safetensors";

/// Side EfficientNet-Lite0 reads the photo at (upsampled from `resolution`): its last
/// feature map is then 4 × 4.
pub const EFFNET_INPUT: i64 = 128;
const EFFNET_TAP: i64 = 320 * (EFFNET_INPUT / 32) * (EFFNET_INPUT / 32);
const EFFNET_HIDDEN: i64 = 512;

/// The network that reads the photo.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Backbone {
    /// ResNet-34 trained from scratch with its head (the paper's).
    Resnet34,
    /// ImageNet-pretrained EfficientNet-Lite0 (weights/efficientnet-lite0.safetensors),
    /// frozen; only a two-layer head on its pooled feature and last feature map is trained.
    EffnetLite0,
}

impl Backbone {
    pub fn name(self) -> &'static str {
        match self {
            Backbone::Resnet34 => "ResNet-34 (from scratch)",
            Backbone::EffnetLite0 => "EfficientNet-Lite0 (ImageNet-pretrained, frozen)",
        }
    }
}

/// Settings of the initialiser's training.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitConfig {
    pub backbone: Backbone,
    /// Side of the generated training images (and of F's input).
    pub resolution: i64,
    /// Samples per ray of the training renders (coarse; as many importance samples);
    /// `num_steps` in files written before it was named so.
    #[serde(alias = "num_steps")]
    pub samples: usize,
    /// Generated (image, pose, w_s, γ_a, β_a) tuples; the last `held_out` are validation.
    pub count: i64,
    pub held_out: i64,
    pub batch_size: i64,
    pub steps: i64,
    /// Adam's learning rate, until the first of `lr_drops`.
    pub lr: f64,
    /// (step, learning rate) from that step on, in increasing steps.
    pub lr_drops: Vec<(i64, f64)>,
    pub pose_weight: f64,
    /// Weight of the raw appearance's error (0 = F does not predict the appearance).
    pub appearance_weight: f64,
    /// Weight of the re-rendering term (0 = off).
    pub image_weight: f64,
    /// Side of the re-rendering term's renders.
    pub image_resolution: i64,
    /// Weight of the pose error on real images (0 = none are used).
    pub real_weight: f64,
    /// Real images in each batch.
    pub real_batch: i64,
    /// The last this many of the real images are validation, never trained on.
    pub real_held_out: i64,
    /// Validation every this many steps (and at the end).
    pub eval_interval: i64,
    pub seed: u64,
    /// Train the head alone: ResNet-34's weights and batch-norm statistics stay as they
    /// start (a warm start's), and its features of every image are taken once, as a frozen
    /// Lite0's are. The shipped file then repeats the backbone bytes of the file it started
    /// from, which costs a repository next to nothing.
    pub head_only: bool,
}

impl Default for InitConfig {
    fn default() -> Self {
        Self {
            backbone: Backbone::Resnet34,
            resolution: 64,
            samples: 12,
            count: 4096,
            held_out: 256,
            batch_size: 32,
            steps: 2000,
            lr: 1e-3,
            lr_drops: Vec::new(),
            pose_weight: 1.0,
            appearance_weight: 0.0,
            image_weight: 0.0,
            image_resolution: 32,
            real_weight: 0.0,
            real_batch: 16,
            real_held_out: 256,
            eval_interval: 250,
            seed: 0,
            head_only: false,
        }
    }
}

impl InitConfig {
    /// The learning rate of step `step` (counted from 0).
    pub fn lr_at(&self, step: i64) -> f64 {
        self.lr_drops.iter().rev().find(|(from, _)| *from <= step).map_or(self.lr, |&(_, lr)| lr)
    }

    pub fn validate(&self) -> Result<()> {
        let bad = |k: &str, v: String, want: &str| Err(Error::Config(format!("init.{k} is {v}, expected {want}")));
        if !(16..=512).contains(&self.resolution) {
            return bad("resolution", self.resolution.to_string(), "16 to 512");
        }
        if self.samples < 3 {
            return bad("samples", self.samples.to_string(), "at least 3");
        }
        if self.held_out < 1 || self.count < self.held_out + 1 {
            return bad(
                "count",
                format!("{} with held_out {}", self.count, self.held_out),
                "more tuples than held out (≥ 1)",
            );
        }
        if self.batch_size < 1 || self.steps < 0 || self.eval_interval < 1 || self.real_batch < 1 {
            return bad(
                "batch_size/steps/eval_interval/real_batch",
                format!("{}/{}/{}/{}", self.batch_size, self.steps, self.eval_interval, self.real_batch),
                "positive",
            );
        }
        if self.real_held_out < 0 {
            return bad("real_held_out", self.real_held_out.to_string(), "≥ 0");
        }
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            return bad("lr", self.lr.to_string(), "a positive number");
        }
        for (i, &(step, lr)) in self.lr_drops.iter().enumerate() {
            if !(lr > 0.0 && lr.is_finite()) || step < 1 || (i > 0 && step <= self.lr_drops[i - 1].0) {
                return bad(
                    "lr_drops",
                    format!("{:?}", self.lr_drops),
                    "STEP:LR pairs with positive learning rates at increasing steps",
                );
            }
        }
        for (k, v) in [
            ("pose_weight", self.pose_weight),
            ("appearance_weight", self.appearance_weight),
            ("image_weight", self.image_weight),
            ("real_weight", self.real_weight),
        ] {
            if !(v >= 0.0 && v.is_finite()) {
                return bad(k, v.to_string(), "a weight ≥ 0");
            }
        }
        if !(4..=512).contains(&self.image_resolution) {
            return bad("image_resolution", self.image_resolution.to_string(), "4 to 512");
        }
        if self.head_only && self.image_weight > 0.0 {
            // The re-rendering term backpropagates through F's input images, which a
            // head-only training never reads again.
            return bad("head_only", "true with image_weight > 0".into(), "one of them");
        }
        Ok(())
    }
}

#[derive(Debug, Clone, Serialize, Deserialize)]
struct InitHeader {
    format_version: u32,
    generator: String,
    backbone: Backbone,
    resolution: i64,
    mapping_hidden: i64,
    /// Width of the predicted raw appearance (0: F predicts none).
    appearance_dim: i64,
    step: i64,
    /// Weights rounded to half precision, without the optimiser's state (a shipped file).
    half: bool,
    config: InitConfig,
}

const FORMAT_VERSION: u32 = 2;

/// The frozen EfficientNet-Lite0 and the tensors it was built from (saved with F).
struct Lite0 {
    net: EfficientNetLite0,
    tensors: Vec<(String, Tensor)>,
}

impl Lite0 {
    fn from_tensors(tensors: Vec<(String, Tensor)>, device: Device) -> Result<Self> {
        let list = tensors.iter().map(|(n, t)| (n.clone(), t.shallow_clone())).collect();
        let w = Weights::from_tensors(Path::new("initialiser (EfficientNet-Lite0)"), list, device);
        Ok(Self { net: EfficientNetLite0::from_weights(w, device)?, tensors })
    }

    /// `(B, 3, R, R)` in [−1, 1] → `(B, 1280 + 320·4·4)`: the pooled feature and the last
    /// feature map, read at [`EFFNET_INPUT`]².
    fn features(&self, img: &Tensor) -> Result<Tensor> {
        let x = self.net.prepare(img, EFFNET_INPUT)?;
        let f = tch::no_grad(|| self.net.forward(&x));
        let tap = f.taps.last().expect("five taps").flatten(1, -1);
        Ok(Tensor::cat(&[f.pooled, tap], 1))
    }
}

/// EfficientNet-Lite0's float tensors from its weights file (scripts/setup.sh converts it:
/// [`EfficientNetLite0::default_path`]), for a new [`Backbone::EffnetLite0`] initialiser.
pub fn lite0_weights(path: &Path) -> Result<Vec<(String, Tensor)>> {
    if !path.is_file() {
        return Err(Error::Data {
            path: path.to_path_buf(),
            reason: "no EfficientNet-Lite0 weights here; scripts/setup.sh converts them".into(),
        });
    }
    let list = Tensor::read_safetensors(path)
        .map_err(|e| Error::NotACheckpoint { path: path.to_path_buf(), reason: e.to_string() })?;
    Ok(list.into_iter().filter(|(_, t)| t.is_floating_point()).map(|(n, t)| (n, t.to_kind(Kind::Float))).collect())
}

/// The feature standardisation's tensors, which a half-precision file keeps in float32.
fn is_statistic(name: &str) -> bool {
    name == "feat_mean" || name == "feat_std"
}

/// F: a backbone, then a head to (w_s, pitch, cos yaw, sin yaw[, raw appearance]).
pub struct Initialiser {
    /// The trained variables: the head (and ResNet-34's), and the feature standardisation.
    pub vs: nn::VarStore,
    backbone: Backbone,
    resnet: Option<nn::FuncT<'static>>,
    lite0: Option<Lite0>,
    head: nn::Sequential,
    /// Lite0's feature mean and standard deviation over the training images.
    feat_mean: Option<Tensor>,
    feat_std: Option<Tensor>,
    pub mapping_hidden: i64,
    pub appearance_dim: i64,
    pub resolution: i64,
}

impl Initialiser {
    /// A fresh F. `lite0` holds EfficientNet-Lite0's weights for that backbone.
    pub fn new(
        backbone: Backbone,
        device: Device,
        mapping_hidden: i64,
        appearance_dim: i64,
        resolution: i64,
        lite0: Option<Vec<(String, Tensor)>>,
    ) -> Result<Self> {
        let vs = nn::VarStore::new(device);
        let out = mapping_hidden + 3 + appearance_dim;
        let root = vs.root();
        // tch's layers draw their start from libtorch's global generator ([`Self::reinitialise`]
        // draws it again from the seed).
        let (resnet, lite0, head, stats) = crate::rng::with_global_generator(|| -> Result<_> {
            Ok(match backbone {
                Backbone::Resnet34 => {
                    let net = tch::vision::resnet::resnet34_no_final_layer(&(&root / "resnet"));
                    let head = nn::seq().add(nn::linear(&root / "head", 512, out, Default::default()));
                    (Some(net), None, head, None)
                }
                Backbone::EffnetLite0 => {
                    let tensors = lite0.ok_or_else(|| {
                        Error::Invalid("the EfficientNet-Lite0 initialiser needs the network's weights".into())
                    })?;
                    let dim = FEATURE_DIM + EFFNET_TAP;
                    let h = &root / "head";
                    let head = nn::seq()
                        .add(nn::linear(&h / "0", dim, EFFNET_HIDDEN, Default::default()))
                        .add_fn(|x| x.relu())
                        .add(nn::linear(&h / "1", EFFNET_HIDDEN, out, Default::default()));
                    let mean = root.zeros_no_train("feat_mean", &[dim]);
                    let std = root.ones_no_train("feat_std", &[dim]);
                    (None, Some(Lite0::from_tensors(tensors, device)?), head, Some((mean, std)))
                }
            })
        })?;
        let (feat_mean, feat_std) = match stats {
            Some((m, s)) => (Some(m), Some(s)),
            None => (None, None),
        };
        Ok(Self { vs, backbone, resnet, lite0, head, feat_mean, feat_std, mapping_hidden, appearance_dim, resolution })
    }

    /// Draws every trained weight matrix and kernel again, He-uniform (U(±√(6 / fan_in))),
    /// from the counter-based generator of `seed`, and zeroes the head's last bias: the same
    /// start on every run whatever else draws from libtorch's global generator meanwhile.
    /// Batch-norm scales and shifts keep their 1 and 0, the feature standardisation its 0
    /// and 1.
    pub fn reinitialise(&self, seed: u64) {
        let mut vars: Vec<(String, Tensor)> =
            self.vs.variables().into_iter().filter(|(_, v)| v.requires_grad()).collect();
        vars.sort_by(|a, b| a.0.cmp(&b.0));
        let last_bias = self.last_bias_name();
        tch::no_grad(|| {
            for (i, (name, mut v)) in vars.into_iter().enumerate() {
                let dims = v.size();
                if dims.len() >= 2 {
                    let fan_in: i64 = dims[1..].iter().product();
                    let bound = (6.0 / fan_in as f64).sqrt();
                    let u = StepRng::new(seed, i as u64, Purpose::InitWeights, Kind::Float, v.device()).uniform(&dims);
                    v.copy_(&((u * 2.0 - 1.0) * bound).to_kind(v.kind()));
                } else if name == last_bias {
                    let _ = v.zero_();
                }
            }
        });
    }

    fn last_bias_name(&self) -> &'static str {
        match self.backbone {
            Backbone::Resnet34 => "head.bias",
            Backbone::EffnetLite0 => "head.1.bias",
        }
    }

    /// What the head reads: ResNet-34's pooled feature (with gradients when training), or
    /// Lite0's standardised features (never with gradients).
    fn body(&self, img: &Tensor, train: bool) -> Result<Tensor> {
        Ok(match (&self.resnet, &self.lite0) {
            (Some(net), _) => net.forward_t(img, train),
            (_, Some(l)) => self.standardise(&l.features(img)?),
            _ => unreachable!("one backbone"),
        })
    }

    /// The frozen backbone's features, before any standardisation: Lite0's, or ResNet-34's
    /// pooled feature in inference mode (batch-norm statistics as they are).
    fn frozen_features(&self, img: &Tensor) -> Result<Tensor> {
        Ok(match (&self.resnet, &self.lite0) {
            (_, Some(l)) => l.features(img)?,
            (Some(net), None) => net.forward_t(img, false),
            _ => unreachable!("one backbone"),
        })
    }

    fn standardise(&self, f: &Tensor) -> Tensor {
        match (&self.feat_mean, &self.feat_std) {
            (Some(m), Some(s)) => (f - m) / s,
            _ => f.shallow_clone(),
        }
    }

    /// The head on what [`Self::body`] gave: w_s `(B, H)`, the raw pose `(B, 3)` (pitch,
    /// cos yaw, sin yaw) and the raw appearance `(B, A)` (`A` = 0 when not predicted).
    fn head(&self, body: &Tensor) -> (Tensor, Tensor, Tensor) {
        let out = self.head.forward(body);
        let h = self.mapping_hidden;
        (out.narrow(1, 0, h), out.narrow(1, h, 3), out.narrow(1, h + 3, self.appearance_dim))
    }

    /// `img: (B, 3, R, R)` in [−1, 1] at F's resolution → w_s, raw pose, raw appearance
    /// ([`Self::head`]).
    pub fn forward_t(&self, img: &Tensor, train: bool) -> Result<(Tensor, Tensor, Tensor)> {
        Ok(self.head(&self.body(img, train)?))
    }

    /// The prediction for one photo `(1, 3, S, S)` in [−1, 1] (resized to F's input).
    pub fn predict(&self, photo: &Tensor) -> Result<Prediction> {
        let s = photo.size();
        if s.len() != 4 || s[0] != 1 || s[1] != 3 {
            return Err(Error::Shape(format!("the initialiser takes a (1, 3, S, S) photo, got {s:?}")));
        }
        let x = resize(&photo.to_kind(Kind::Float).to_device(self.vs.device()), self.resolution);
        let (w, p, a) = tch::no_grad(|| self.forward_t(&x, false))?;
        let v: Vec<f64> = Vec::try_from(p.get(0).to_kind(Kind::Double))?;
        Ok(Prediction {
            w_s: w,
            pose: (v[0], v[2].atan2(v[1])),
            appearance_raw: (self.appearance_dim > 0).then_some(a),
        })
    }

    /// F's outputs for a batch `(B, 3, R, R)` at its resolution, without gradients: w_s, the
    /// raw pose and the raw appearance.
    pub fn predict_batch(&self, images: &Tensor) -> Result<(Tensor, Tensor, Tensor)> {
        tch::no_grad(|| self.forward_t(&images.to_kind(Kind::Float).to_device(self.vs.device()), false))
    }

    /// Every stored tensor: the VarStore's and Lite0's (under `lite0.`).
    fn tensors(&self) -> Vec<(String, Tensor)> {
        let mut t: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        if let Some(l) = &self.lite0 {
            t.extend(l.tensors.iter().map(|(n, v)| (format!("lite0.{n}"), v.shallow_clone())));
        }
        t.sort_by(|a, b| a.0.cmp(&b.0));
        t
    }

    /// Rounds every weight to half precision in place (the frozen Lite0 rebuilt from the
    /// rounded tensors), so that [`Self::save_half`] stores exactly this network. The
    /// feature statistics stay float32: standardising divides by them.
    pub fn round_to_half(&mut self) -> Result<()> {
        tch::no_grad(|| {
            for (name, mut v) in self.vs.variables() {
                if !is_statistic(&name) {
                    let r = v.to_kind(Kind::Half).to_kind(v.kind());
                    v.copy_(&r);
                }
            }
        });
        if let Some(l) = &self.lite0 {
            let rounded = l.tensors.iter().map(|(n, v)| (n.clone(), v.to_kind(Kind::Half).to_kind(v.kind()))).collect();
            self.lite0 = Some(Lite0::from_tensors(rounded, self.vs.device())?);
        }
        Ok(())
    }

    fn header(&self, generator_id: &str, step: i64, half: bool, config: &InitConfig) -> InitHeader {
        InitHeader {
            format_version: FORMAT_VERSION,
            generator: generator_id.into(),
            backbone: self.backbone,
            resolution: self.resolution,
            mapping_hidden: self.mapping_hidden,
            appearance_dim: self.appearance_dim,
            step,
            half,
            config: config.clone(),
        }
    }

    fn save(&self, path: &Path, header: &InitHeader, adam: Option<&Adam>) -> Result<()> {
        let mut tensors = self.tensors();
        if header.half {
            tensors = tensors
                .into_iter()
                .map(|(n, t)| {
                    let t = if is_statistic(&n) { t } else { t.to_kind(Kind::Half) };
                    (n, t)
                })
                .collect();
        }
        if let Some(a) = adam {
            tensors.extend(a.named_tensors("adam."));
        }
        let json = serde_json::to_string(header)?;
        write_atomic(path, &tensors_to_bytes(&tensors, INIT_KEY, &json)?)
    }

    /// Writes the file to ship: every weight in half precision, without the optimiser's
    /// state, for the generator `generator_id`. Call [`Self::round_to_half`] first, so the
    /// network in memory is the one written.
    pub fn save_half(&self, path: &Path, generator_id: &str, step: i64, config: &InitConfig) -> Result<()> {
        self.save(path, &self.header(generator_id, step, true, config), None)
    }

    /// Sets every weight (and batch-norm statistic) to those of the initialiser file `from`,
    /// made for any generator: the start of a warm-started training. Its backbone, input
    /// side and output sizes must be this network's.
    pub fn copy_weights_from(&self, from: &Path) -> Result<()> {
        let device = self.vs.device();
        let (src, _, _) = Self::load_with_state(from, None, device)?;
        let same = (src.backbone, src.resolution, src.mapping_hidden, src.appearance_dim)
            == (self.backbone, self.resolution, self.mapping_hidden, self.appearance_dim);
        if !same {
            return Err(Error::Data {
                path: from.to_path_buf(),
                reason: format!(
                    "initialiser: a warm start needs the same network: it has backbone {}, input {}², w_s {} and appearance {}, this training {}, {}², {} and {}",
                    src.backbone.name(), src.resolution, src.mapping_hidden, src.appearance_dim,
                    self.backbone.name(), self.resolution, self.mapping_hidden, self.appearance_dim
                ),
            });
        }
        let theirs = src.vs.variables();
        tch::no_grad(|| {
            for (name, mut v) in self.vs.variables() {
                // The same constructor made both, so every name is there with its shape.
                v.copy_(&theirs[&name]);
            }
        });
        Ok(())
    }

    /// Loads an initialiser file made for the generator of identity `generator_id`.
    pub fn load(path: &Path, generator_id: &str, device: Device) -> Result<Self> {
        Ok(Self::load_with_state(path, Some(generator_id), device)?.0)
    }

    fn load_with_state(
        path: &Path,
        generator_id: Option<&str>,
        device: Device,
    ) -> Result<(Self, InitHeader, std::collections::BTreeMap<String, Tensor>)> {
        let (json, mut t) = load_tensors_with(path, INIT_KEY)?;
        let bad = |why: String| Error::Data { path: path.to_path_buf(), reason: format!("initialiser: {why}") };
        let h: InitHeader = serde_json::from_str(&json).map_err(|e| bad(format!("bad header ({e})")))?;
        if h.format_version != FORMAT_VERSION {
            return Err(bad(format!(
                "format version {}, this build reads {FORMAT_VERSION}; train it again (gdrf-invert train-init)",
                h.format_version
            )));
        }
        if let Some(id) = generator_id {
            if h.generator != id {
                return Err(bad(format!(
                    "it was trained for generator {}, not for this one ({id}); train one for it with gdrf-invert train-init",
                    h.generator
                )));
            }
        }
        // Checked before the network is built from them: a damaged header must not allocate.
        if !(16..=512).contains(&h.resolution) {
            return Err(bad(format!("resolution {} is out of range, expected 16 to 512", h.resolution)));
        }
        let (last, inputs) = match h.backbone {
            Backbone::Resnet34 => ("head.weight", 512),
            Backbone::EffnetLite0 => ("head.1.weight", EFFNET_HIDDEN),
        };
        let out = h.mapping_hidden.saturating_add(3).saturating_add(h.appearance_dim);
        let head = t.get(last).ok_or_else(|| bad(format!("no tensor '{last}'")))?;
        if h.mapping_hidden < 1 || h.appearance_dim < 0 || head.size() != [out, inputs] {
            return Err(bad(format!(
                "'{last}' has shape {:?}, but the header's mapping_hidden {} and appearance_dim {} need [{out}, {inputs}]",
                head.size(),
                h.mapping_hidden,
                h.appearance_dim
            )));
        }
        let lite0 = (h.backbone == Backbone::EffnetLite0).then(|| {
            let names: Vec<String> = t.keys().filter(|k| k.starts_with("lite0.")).cloned().collect();
            names
                .into_iter()
                .map(|n| {
                    let v = t.remove(&n).expect("listed");
                    (n["lite0.".len()..].to_string(), v.to_kind(Kind::Float).to_device(device))
                })
                .collect()
        });
        let init = Self::new(h.backbone, device, h.mapping_hidden, h.appearance_dim, h.resolution, lite0)
            .map_err(|e| bad(format!("its EfficientNet-Lite0: {e}")))?;
        tch::no_grad(|| -> Result<()> {
            for (name, mut v) in init.vs.variables() {
                let src = t.remove(&name).ok_or_else(|| bad(format!("no tensor '{name}'")))?;
                if src.size() != v.size() {
                    return Err(bad(format!("'{name}' has shape {:?}, expected {:?}", src.size(), v.size())));
                }
                v.copy_(&src.to_kind(v.kind()).to_device(device));
            }
            Ok(())
        })?;
        let rest = t.into_iter().filter(|(k, _)| k.starts_with("adam.")).collect();
        Ok((init, h, rest))
    }
}

/// The check file written beside a shipped initialiser (`initialiser.safetensors` →
/// `initialiser-check.safetensors`).
pub fn check_path(shipped: &Path) -> std::path::PathBuf {
    let stem = shipped.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    shipped.with_file_name(format!("{stem}-check.safetensors"))
}

const CHECK_KEY: &str = "gdrf_initialiser_check";

/// Rounds `f` to half precision and ships it to `path` for `generator_id`, with its check
/// file ([`check_path`]): `images` (stored in half precision, the inputs as the check reads
/// them) and the predictions on them of the float32 network and of the rounded one shipped,
/// so a test can hold the shipped file to both.
pub fn ship(
    f: &mut Initialiser,
    path: &Path,
    generator_id: &str,
    step: i64,
    cfg: &InitConfig,
    images: &Tensor,
) -> Result<()> {
    let images = images.to_kind(Kind::Half).to_kind(Kind::Float);
    let (w32, p32, _) = f.predict_batch(&images)?;
    f.round_to_half()?;
    let (w16, p16, _) = f.predict_batch(&images)?;
    f.save_half(path, generator_id, step, cfg)?;
    let tensors: Vec<(String, Tensor)> = [
        ("images", images.to_kind(Kind::Half)),
        ("w_s_float32", w32),
        ("pose_float32", p32),
        ("w_s_shipped", w16),
        ("pose_shipped", p16),
    ]
    .into_iter()
    .map(|(n, t)| (n.to_string(), t.to_device(Device::Cpu)))
    .collect();
    let json = serde_json::json!({ "generator": generator_id }).to_string();
    write_atomic(&check_path(path), &tensors_to_bytes(&tensors, CHECK_KEY, &json)?)
}

/// The check file of a shipped initialiser: its images and the predictions (w_s, raw pose)
/// of the float32 network and of the shipped one, by name.
pub fn load_check(shipped: &Path) -> Result<std::collections::BTreeMap<String, Tensor>> {
    Ok(load_tensors_with(&check_path(shipped), CHECK_KEY)?.1)
}

/// What F reads from one photo.
pub struct Prediction {
    /// `(1, mapping_hidden)`.
    pub w_s: Tensor,
    /// (pitch, yaw) in radians.
    pub pose: (f64, f64),
    /// `(1, 2·L_c·H)`, when F predicts the appearance.
    pub appearance_raw: Option<Tensor>,
}

#[cfg(test)]
mod tests {
    use super::training::f64_of;
    use super::*;
    use crate::field::generator::Generator;
    use crate::{CameraConfig, GeneratorConfig};

    fn small() -> (nn::VarStore, Generator) {
        tch::manual_seed(2);
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        let g = Generator::new(&vs.root(), &cfg).unwrap();
        (vs, g)
    }

    fn cfg() -> InitConfig {
        InitConfig {
            resolution: 16,
            samples: 4,
            count: 12,
            held_out: 4,
            batch_size: 4,
            steps: 4,
            eval_interval: 2,
            ..Default::default()
        }
    }

    #[test]
    fn the_learning_rate_drops_at_its_steps() {
        let c = InitConfig { lr: 1e-3, lr_drops: vec![(4000, 3e-4), (6000, 1e-4)], ..cfg() };
        let at: Vec<f64> = [0, 3999, 4000, 5999, 6000, 9000].iter().map(|&s| c.lr_at(s)).collect();
        assert_eq!(at, [1e-3, 1e-3, 3e-4, 3e-4, 1e-4, 1e-4]);
        assert_eq!(cfg().lr_at(10), 1e-3);
        for bad in [vec![(10, 1e-4), (5, 1e-5)], vec![(0, 1e-4)], vec![(10, 0.0)], vec![(10, f64::NAN)]] {
            let e = InitConfig { lr_drops: bad, ..cfg() }.validate().err().map(|e| e.to_string());
            assert!(e.as_deref().unwrap_or("").contains("init.lr_drops"), "{e:?}");
        }
    }

    #[test]
    fn tuples_are_reproducible_and_training_resumes_exactly() {
        let (_vs, g) = small();
        let cam = CameraConfig::default();
        let t = generate(&g, &cam, &cfg(), &mut |_| {}).unwrap();
        assert_eq!(t.images.size(), [12, 3, 16, 16]);
        assert_eq!(t.w_s.size(), [12, 16]);
        assert_eq!(t.poses.size(), [12, 2]);
        assert!(t.images.equal(&generate(&g, &cam, &cfg(), &mut |_| {}).unwrap().images));

        let dir = std::env::temp_dir().join(format!("gdrf-init-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (a, b) = (dir.join("a.safetensors"), dir.join("b.safetensors"));
        let mut steps = Vec::new();
        let mut record = |p: TrainProgress| {
            if let TrainProgress::Step(s, _) = p {
                steps.push(s)
            }
        };
        let (full, evals) = train(&g, &cam, "gen", &t, None, None, &cfg(), &a, Start::Fresh, &mut record).unwrap();
        assert_eq!(steps, [1, 2, 3, 4]);
        assert_eq!(evals.iter().map(|e| e.step).collect::<Vec<_>>(), [2, 4]);
        assert_eq!(evals.iter().map(|e| e.images_seen).collect::<Vec<_>>(), [8, 16]);
        assert!(evals.iter().all(|e| e.w_mse.is_finite() && e.mean_code_w_mse > 0.0 && e.appearance_mse.is_none()));
        // Two steps, then a resume from the file saved at step 2: the file holds exactly the
        // state at step 2 (weights, batch-norm statistics), and the resumed run continues from
        // it to step 4. (Bit-exact equality with the uninterrupted run is not promised: the
        // multithreaded CPU convolution backward is not deterministic, so two fresh runs already
        // differ in the last bits, which Adam amplifies for near-zero gradients.)
        let two = InitConfig { steps: 2, ..cfg() };
        let (part, _) = train(&g, &cam, "gen", &t, None, None, &two, &b, Start::Fresh, &mut |_| {}).unwrap();
        let (saved, h, state) = Initialiser::load_with_state(&b, None, Device::Cpu).unwrap();
        assert_eq!(h.step, 2);
        assert!(state.keys().any(|k| k.starts_with("adam.m.")), "the Adam state is saved");
        for (name, v) in part.vs.variables() {
            assert!(v.equal(&saved.vs.variables()[&name]), "{name}");
        }
        let mut resumed_steps = Vec::new();
        let (_, evals) = train(&g, &cam, "gen", &t, None, None, &cfg(), &b, Start::Resume, &mut |p| {
            if let TrainProgress::Step(s, _) = p {
                resumed_steps.push(s)
            }
        })
        .unwrap();
        assert_eq!(resumed_steps, [3, 4]);
        assert_eq!(evals.iter().map(|e| e.step).collect::<Vec<_>>(), [4]);
        let other = InitConfig { pose_weight: 0.5, ..cfg() };
        let e =
            train(&g, &cam, "gen", &t, None, None, &other, &b, Start::Resume, &mut |_| {}).err().map(|e| e.to_string());
        assert!(e.as_deref().unwrap_or("").contains("other initialiser settings"), "{e:?}");
        // Another generator's initialiser is refused, naming both; predictions are finite.
        let err = Initialiser::load(&a, "other", Device::Cpu).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(err.contains("other") && err.contains("gen"), "{err}");
        let p = full.predict(&t.images.narrow(0, 0, 1)).unwrap();
        assert_eq!(p.w_s.size(), [1, 16]);
        assert!(p.pose.0.is_finite() && p.pose.1.is_finite() && p.appearance_raw.is_none());
        assert!(full.predict(&t.images).is_err());
        std::fs::remove_dir_all(dir).ok();
    }

    /// Real images join the loss through their poses alone, their held-out rows are scored
    /// and never trained on, and the appearance head predicts the raw appearance's width.
    #[test]
    fn real_images_and_the_appearance_head() {
        let (_vs, g) = small();
        let cam = CameraConfig::default();
        let c = InitConfig { real_weight: 1.0, real_batch: 3, real_held_out: 2, appearance_weight: 1.0, ..cfg() };
        let t = generate(&g, &cam, &c, &mut |_| {}).unwrap();
        let reals = RealImages { images: t.images.narrow(0, 0, 5).flip([3]), poses: t.poses.narrow(0, 0, 5) };
        let dir = std::env::temp_dir().join(format!("gdrf-init-real-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let out = dir.join("f.safetensors");
        let (f, evals) = train(&g, &cam, "gen", &t, Some(&reals), None, &c, &out, Start::Fresh, &mut |_| {}).unwrap();
        let e = evals.last().unwrap();
        assert_eq!(e.images_seen, 4 * (4 + 3));
        assert!(e.real_yaw_error_deg.is_some_and(f64::is_finite) && e.appearance_mse.is_some_and(f64::is_finite));
        let p = f.predict(&t.images.narrow(0, 0, 1)).unwrap();
        assert_eq!(p.appearance_raw.unwrap().size(), t.appearance_raw.narrow(0, 0, 1).size());
        // Every real image held out: nothing to train on, an error naming the key.
        let none = InitConfig { real_held_out: 5, ..c };
        let err = train(&g, &cam, "gen", &t, Some(&reals), None, &none, &out, Start::Fresh, &mut |_| {}).err();
        assert!(err.map(|e| e.to_string()).unwrap_or_default().contains("init.real_held_out"));
        std::fs::remove_dir_all(dir).ok();
    }

    /// The shipped file holds the network rounded to half precision: loaded, it predicts
    /// exactly what the rounded network in memory predicts, and within 5 % (of the largest
    /// w_s component) and 2° of the float32 one it was rounded from, for both backbones.
    #[test]
    fn the_half_precision_file_predicts_what_the_rounded_network_does() {
        let (_vs, g) = small();
        let cam = CameraConfig::default();
        let dir = std::env::temp_dir().join(format!("gdrf-init-half-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = InitConfig { resolution: 32, count: 10, held_out: 2, steps: 3, ..cfg() };
        let t = generate(&g, &cam, &c, &mut |_| {}).unwrap();
        for backbone in [Backbone::Resnet34, Backbone::EffnetLite0] {
            let c = InitConfig { backbone, appearance_weight: 1.0, ..c.clone() };
            let w =
                (backbone == Backbone::EffnetLite0).then(|| lite0_weights(&EfficientNetLite0::default_path()).unwrap());
            let out = dir.join("train.safetensors");
            let _ = std::fs::remove_file(&out);
            let (mut f, _) = train(&g, &cam, "gen", &t, None, w, &c, &out, Start::Fresh, &mut |_| {}).unwrap();
            let photo = t.images.narrow(0, 0, 1);
            let full = f.predict(&photo).unwrap();
            f.round_to_half().unwrap();
            let rounded = f.predict(&photo).unwrap();
            let shipped = dir.join("half.safetensors");
            f.save_half(&shipped, "gen", 3, &c).unwrap();
            let loaded = Initialiser::load(&shipped, "gen", Device::Cpu).unwrap();
            let again = loaded.predict(&photo).unwrap();
            assert!(again.w_s.equal(&rounded.w_s), "{backbone:?}");
            assert_eq!(again.pose, rounded.pose, "{backbone:?}");
            assert!(again.appearance_raw.as_ref().unwrap().equal(rounded.appearance_raw.as_ref().unwrap()));
            // Every weight of the file is half precision (the feature statistics float32),
            // and no optimiser state is in it.
            let (_, tensors) = load_tensors_with(&shipped, INIT_KEY).unwrap();
            assert!(tensors.iter().all(|(n, v)| v.kind() == if is_statistic(n) { Kind::Float } else { Kind::Half }));
            assert!(!tensors.keys().any(|k| k.starts_with("adam.")));
            let err = Initialiser::load(&shipped, "another", Device::Cpu).err().map(|e| e.to_string());
            assert!(err.as_deref().unwrap_or("").contains("another") && err.as_deref().unwrap().contains("gen"));
            // Within 5 % of the largest w_s component, and 2° of pose, of the float32 network.
            // Not for Lite0: the feature statistics of this test's 8 images are degenerate, so
            // rounding moves its outputs arbitrarily here. (The shipped ResNet-34's rounding is
            // held to the float32 network in gdrf-core/tests/invert.rs; no Lite0 file ships.)
            if backbone == Backbone::EffnetLite0 {
                continue;
            }
            let (w32, w16) = (&full.w_s, &rounded.w_s);
            let (off, scale) = (f64_of(&(w16 - w32).abs().max()), f64_of(&w32.abs().max()));
            assert!(off <= 0.05 * scale, "{backbone:?}: w_s off by {off} at a largest component of {scale}");
            let (dp, dy) = ((again.pose.0 - full.pose.0).to_degrees(), (again.pose.1 - full.pose.1).to_degrees());
            assert!(dp.abs() < 2.0 && dy.abs() < 2.0, "{backbone:?}: pose off by {dp}°, {dy}°");
        }
        std::fs::remove_dir_all(dir).ok();
    }

    /// A warm start takes every weight of another generator's initialiser; with `head_only`
    /// the backbone's weights and batch-norm statistics stay exactly as they started, so the
    /// shipped file repeats them; a file of another shape is refused, naming it.
    #[test]
    fn a_warm_start_takes_another_initialisers_weights_and_head_only_keeps_the_backbone() {
        let (_vs, g) = small();
        let cam = CameraConfig::default();
        let dir = std::env::temp_dir().join(format!("gdrf-init-warm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let t = generate(&g, &cam, &cfg(), &mut |_| {}).unwrap();
        let (first, shipped) = (dir.join("first.safetensors"), dir.join("first-half.safetensors"));
        let (mut a, _) = train(&g, &cam, "old", &t, None, None, &cfg(), &first, Start::Fresh, &mut |_| {}).unwrap();
        a.round_to_half().unwrap();
        a.save_half(&shipped, "old", 4, &cfg()).unwrap();
        let a_vars = a.vs.variables();

        // The copy alone (a fresh network of the same shape, then the file's weights).
        let b = Initialiser::new(Backbone::Resnet34, Device::Cpu, 16, 0, 16, None).unwrap();
        b.reinitialise(7);
        b.copy_weights_from(&shipped).unwrap();
        for (name, v) in b.vs.variables() {
            assert!(v.equal(&a_vars[&name]), "{name}");
        }
        // Head only, for another generator: only head.* moves.
        let c = InitConfig { head_only: true, ..cfg() };
        let out = dir.join("head.safetensors");
        let (h, evals) =
            train(&g, &cam, "new", &t, None, None, &c, &out, Start::WarmFrom(&shipped), &mut |_| {}).unwrap();
        assert!(evals.iter().all(|e| e.w_mse.is_finite()));
        let mut moved = Vec::new();
        for (name, v) in h.vs.variables() {
            if !v.equal(&a_vars[&name]) {
                moved.push(name);
            }
        }
        moved.sort();
        assert_eq!(moved, ["head.bias", "head.weight"]);
        // Its file names the new generator and loads for it alone.
        assert!(Initialiser::load(&out, "new", Device::Cpu).is_ok());
        assert!(Initialiser::load(&out, "old", Device::Cpu).is_err());
        // The whole network warm-started: the backbone moves too.
        let whole = dir.join("whole.safetensors");
        let (w, _) =
            train(&g, &cam, "new", &t, None, None, &cfg(), &whole, Start::WarmFrom(&shipped), &mut |_| {}).unwrap();
        assert!(w.vs.variables().iter().any(|(n, v)| n.starts_with("resnet.") && !v.equal(&a_vars[n])));
        // Another input side is another network: refused, naming the file.
        let c32 = InitConfig { resolution: 32, ..cfg() };
        let t32 = generate(&g, &cam, &c32, &mut |_| {}).unwrap();
        let err = train(
            &g,
            &cam,
            "new",
            &t32,
            None,
            None,
            &c32,
            &dir.join("x.safetensors"),
            Start::WarmFrom(&shipped),
            &mut |_| {},
        )
        .err()
        .map(|e| e.to_string())
        .unwrap_or_default();
        assert!(err.contains("first-half.safetensors") && err.contains("same network"), "{err}");
        // A head-only training that re-renders through its input is refused, naming the key.
        let e = InitConfig { image_weight: 1.0, ..c }.validate().err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains("init.head_only"), "{e}");
        std::fs::remove_dir_all(dir).ok();
    }
}
