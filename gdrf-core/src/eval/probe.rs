//! A probe trained on the procedural chairs' ground truth: from an image it predicts the
//! structure (leg kind, back kind, arms, seat shape), each part's colour (its material's mean albedo) and the
//! camera pose. It answers what FID cannot — which topologies a generator covers, whether
//! a swap keeps the shape of one code and the colours of the other, whether an image was
//! rendered at the pose asked for.
//!
//! Two backbones, measured against each other in the evaluation notes: `efficientnet`
//! (a small head on frozen EfficientNet-Lite0 features: the last block's 320 × 7 × 7 map
//! of the 224² input) and `scratch` (a four-layer CNN on the 64² image).
use crate::checkpoint::{copy_into, load_tensors_with, tensors_to_bytes};
use crate::data::synth::chairs::{Arms, Back, Legs, SeatShape};
use crate::data::synth::{ImageRecord, ShapeParams};
use crate::data::{self, LoadOptions, Metadata, Split};
use crate::paths::write_atomic;
use crate::pretrained::effnet::EfficientNetLite0;
use crate::progress::Event;
use crate::rng::{Purpose, StepRng};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;
use tch::nn::{self, Module, OptimizerConfig};
use tch::{Device, Kind, Tensor};

pub const LEGS: [&str; 5] = ["four", "three", "swivel", "sled", "pedestal"];
pub const BACKS: [&str; 5] = ["none", "solid", "slats", "ladder", "frame"];
pub const ARMS: [&str; 3] = ["none", "open", "panel"];
pub const SEATS: [&str; 2] = ["square", "round"];
/// The structure factors and their classes, in output order.
pub const FACTORS: [(&str, &[&str]); 4] = [("legs", &LEGS), ("back", &BACKS), ("arms", &ARMS), ("seat", &SEATS)];
/// Parts with a colour (the dataset's material slots).
pub const PARTS: [&str; 4] = ["seat", "back", "legs", "arms"];
const CLASS_OUTPUTS: i64 = 15;
/// 15 class logits, 12 colours, pitch, sin yaw, cos yaw.
const OUTPUTS: i64 = CLASS_OUTPUTS + 12 + 3;
/// Resolution the scratch backbone sees.
pub const SCRATCH_SIZE: i64 = 64;
/// The efficientnet probe also sees the image at 28² folded into 48 channels of 7 × 7
/// (pixel-unshuffle by 4): ImageNet features at 7 × 7 keep shape and pose but little of
/// the colour (a head on them alone read part colours no better than guessing the mean).
const COLOUR_CHANNELS: i64 = 48;
/// Metadata key of a probe file.
pub const PROBE_KEY: &str = "gdrf_probe";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Backbone {
    Efficientnet,
    Scratch,
}

impl std::str::FromStr for Backbone {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "efficientnet" => Ok(Self::Efficientnet),
            "scratch" => Ok(Self::Scratch),
            _ => Err(Error::Invalid(format!("unknown probe backbone '{s}', expected efficientnet or scratch"))),
        }
    }
}

/// Ground truth of N images.
#[derive(Debug)]
pub struct Truth {
    /// `(N, 4)` class indices in [`FACTORS`] order.
    pub classes: Tensor,
    /// `(N, 4, 3)` part colours in [0, 1] (sRGB), [`PARTS`] order: each material's
    /// albedo averaged over its pattern (`Material::mean_albedo`), which is what an image
    /// shows — the base colour alone is hidden under stripes and checkers.
    pub colours: Tensor,
    /// `(N, 4)`: 1 where the part exists (no back colour for a stool, no arm colour without arms).
    pub colour_mask: Tensor,
    /// `(N, 2)` pitch, yaw in radians.
    pub poses: Tensor,
}

/// Class indices of a chair's structure, [`FACTORS`] order.
pub fn structure_classes(shape: &ShapeParams) -> Result<[i64; 4]> {
    let ShapeParams::Chair(c) = shape else {
        return Err(Error::Invalid("the probe knows chairs only; this dataset holds another category".into()));
    };
    let legs = match c.legs {
        Legs::Four { .. } => 0,
        Legs::Three { .. } => 1,
        Legs::Swivel { .. } => 2,
        Legs::Sled { .. } => 3,
        Legs::Pedestal { .. } => 4,
    };
    let back = match c.back {
        Back::None => 0,
        Back::Solid => 1,
        Back::Slats { .. } => 2,
        Back::Ladder { .. } => 3,
        Back::Frame { .. } => 4,
    };
    let arms = match c.arms {
        Arms::None => 0,
        Arms::Open => 1,
        Arms::Panel => 2,
    };
    let seat = match c.seat {
        SeatShape::Square => 0,
        SeatShape::Round => 1,
    };
    Ok([legs, back, arms, seat])
}

impl Truth {
    pub fn from_records(records: &[&ImageRecord]) -> Result<Self> {
        let n = records.len() as i64;
        let mut classes = Vec::new();
        let mut colours = Vec::new();
        let mut mask = Vec::new();
        let mut poses = Vec::new();
        for r in records {
            let c = structure_classes(&r.shape)?;
            classes.extend_from_slice(&c);
            for m in &r.appearance.materials {
                colours.extend_from_slice(&m.mean_albedo());
            }
            mask.extend_from_slice(&[1.0f32, (c[1] != 0) as i32 as f32, 1.0, (c[2] != 0) as i32 as f32]);
            poses.extend_from_slice(&[r.pitch as f32, r.yaw as f32]);
        }
        Ok(Self {
            classes: Tensor::from_slice(&classes).view([n, 4]),
            colours: Tensor::from_slice(&colours).view([n, 4, 3]),
            colour_mask: Tensor::from_slice(&mask).view([n, 4]),
            poses: Tensor::from_slice(&poses).view([n, 2]),
        })
    }

    pub fn select(&self, idx: &Tensor) -> Self {
        Self {
            classes: self.classes.index_select(0, idx),
            colours: self.colours.index_select(0, idx),
            colour_mask: self.colour_mask.index_select(0, idx),
            poses: self.poses.index_select(0, idx),
        }
    }
}

/// What the probe says about N images.
#[derive(Debug)]
pub struct Predictions {
    /// `(N, 4)` predicted class per factor.
    pub classes: Tensor,
    /// `(N, 4, 3)` predicted part colours.
    pub colours: Tensor,
    /// `(N, 2)` predicted pitch and yaw (radians, yaw in (−π, π]).
    pub poses: Tensor,
}

fn split_outputs(out: &Tensor) -> (Vec<Tensor>, Tensor, Tensor) {
    let mut logits = Vec::new();
    let mut at = 0;
    for (_, classes) in FACTORS {
        logits.push(out.narrow(1, at, classes.len() as i64));
        at += classes.len() as i64;
    }
    let colours = out.narrow(1, CLASS_OUTPUTS, 12).view([-1, 4, 3]);
    let pose = out.narrow(1, CLASS_OUTPUTS + 12, 3);
    (logits, colours, pose)
}

/// The probe's network after the (frozen or absent) feature extractor.
fn head(vs: &nn::Path, backbone: Backbone) -> nn::Sequential {
    let conv = |i: i64, o: i64, name: &str| {
        nn::conv2d(vs / name, i, o, 3, nn::ConvConfig { stride: 2, padding: 1, ..Default::default() })
    };
    match backbone {
        // 64² → 32² → 16² → 8² → 4².
        Backbone::Scratch => nn::seq()
            .add(conv(3, 32, "c0"))
            .add_fn(|x| x.relu())
            .add(conv(32, 64, "c1"))
            .add_fn(|x| x.relu())
            .add(conv(64, 128, "c2"))
            .add_fn(|x| x.relu())
            .add(conv(128, 128, "c3"))
            .add_fn(|x| x.relu().flatten(1, -1))
            .add(nn::linear(vs / "fc", 128 * 16, 256, Default::default()))
            .add_fn(|x| x.relu())
            .add(nn::linear(vs / "out", 256, OUTPUTS, Default::default())),
        // 320 + 48 channels × 7 × 7 → 64 × 7 × 7, flattened: position matters for pose
        // and structure.
        Backbone::Efficientnet => nn::seq()
            .add(nn::conv2d(vs / "reduce", 320 + COLOUR_CHANNELS, 64, 1, Default::default()))
            .add_fn(|x| x.relu().flatten(1, -1))
            .add(nn::linear(vs / "fc", 64 * 49, 256, Default::default()))
            .add_fn(|x| x.relu())
            .add(nn::linear(vs / "out", 256, OUTPUTS, Default::default())),
    }
}

/// Training settings.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeConfig {
    pub backbone: Backbone,
    pub epochs: usize,
    pub batch_size: i64,
    pub lr: f64,
    pub seed: u64,
}

impl Default for ProbeConfig {
    fn default() -> Self {
        Self { backbone: Backbone::Efficientnet, epochs: 8, batch_size: 64, lr: 1e-3, seed: 0 }
    }
}

/// Held-out scores of a probe.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct ProbeScores {
    /// Accuracy per factor, [`FACTORS`] order.
    pub accuracy: Vec<f64>,
    /// What always answering the most frequent class of the training split scores.
    pub chance: Vec<f64>,
    /// Mean absolute error of the part colours of existing parts (0–1 sRGB units).
    pub colour_mae: f64,
    /// Mean absolute pitch error, degrees.
    pub pitch_error_deg: f64,
    /// Mean absolute yaw error (wrapped to ±180°), degrees.
    pub yaw_error_deg: f64,
    pub images: i64,
}

/// What a probe file's header holds.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ProbeHeader {
    pub config: ProbeConfig,
    pub held_out: ProbeScores,
    /// Per-factor class names, so that a report never depends on this program's order.
    pub factors: Vec<(String, Vec<String>)>,
    pub train_images: i64,
}

pub struct Probe {
    pub vs: nn::VarStore,
    net: nn::Sequential,
    pub header: ProbeHeader,
}

/// The probe's input for `images (N, 3, H, W)` in [−1, 1]: frozen EfficientNet features
/// (batches of `batch`, no gradient) or the images resized to 64² (antialiased).
pub fn probe_inputs(
    backbone: Backbone,
    effnet: Option<&EfficientNetLite0>,
    images: &Tensor,
    batch: i64,
    progress: &mut dyn FnMut(Event),
) -> Result<Tensor> {
    let n = images.size()[0];
    match backbone {
        Backbone::Scratch => {
            let s = images.size();
            let x = if s[2] == SCRATCH_SIZE && s[3] == SCRATCH_SIZE {
                images.to_kind(Kind::Float)
            } else {
                images.to_kind(Kind::Float).internal_upsample_bilinear2d_aa(
                    &[SCRATCH_SIZE, SCRATCH_SIZE][..],
                    false,
                    None,
                    None,
                )
            };
            progress(Event::new("probe inputs", n as u64, n as u64));
            Ok(x)
        }
        Backbone::Efficientnet => {
            let net = effnet
                .ok_or_else(|| Error::Invalid("the efficientnet probe needs the EfficientNet-Lite0 weights".into()))?;
            let tap = net.pooled_and_last_tap(images, batch, progress)?.1;
            Ok(with_colour(&tap, images))
        }
    }
}

/// The efficientnet probe's input: the last tap `(N, 320, 7, 7)` with the image at 28²
/// folded into [`COLOUR_CHANNELS`] more channels.
pub fn with_colour(tap: &Tensor, images: &Tensor) -> Tensor {
    let small = images.to_kind(Kind::Float).to_device(tap.device()).internal_upsample_bilinear2d_aa(
        &[28i64, 28][..],
        false,
        None,
        None,
    );
    Tensor::cat(&[tap.shallow_clone(), small.pixel_unshuffle(4)], 1)
}

fn wrap_deg(d: &Tensor) -> Tensor {
    // (d + 180) mod 360 − 180, for angles in degrees.
    (d + 180.0).remainder(360.0) - 180.0
}

impl Probe {
    fn build(backbone: Backbone, device: Device) -> (nn::VarStore, nn::Sequential) {
        let vs = nn::VarStore::new(device);
        let net = head(&vs.root(), backbone);
        (vs, net)
    }

    /// Raw outputs for probe inputs, in batches, without gradients.
    fn outputs(&self, inputs: &Tensor) -> Tensor {
        let n = inputs.size()[0];
        let dev = self.vs.device();
        let mut out = Vec::new();
        let mut i = 0;
        while i < n {
            let b = 256.min(n - i);
            out.push(tch::no_grad(|| self.net.forward(&inputs.narrow(0, i, b).to_device(dev))).to_device(Device::Cpu));
            i += b;
        }
        Tensor::cat(&out, 0)
    }

    /// Predictions for probe inputs (see [`probe_inputs`]).
    pub fn predict_inputs(&self, inputs: &Tensor) -> Predictions {
        let out = self.outputs(inputs);
        let (logits, colours, pose) = split_outputs(&out);
        let classes = Tensor::stack(&logits.iter().map(|l| l.argmax(1, false)).collect::<Vec<_>>(), 1);
        let yaw = pose.select(1, 1).atan2(&pose.select(1, 2));
        Predictions { classes, colours: colours.clamp(0.0, 1.0), poses: Tensor::stack(&[pose.select(1, 0), yaw], 1) }
    }

    /// Predictions for images `(N, 3, H, W)` in [−1, 1].
    pub fn predict(&self, effnet: Option<&EfficientNetLite0>, images: &Tensor) -> Result<Predictions> {
        let inputs = probe_inputs(self.header.config.backbone, effnet, images, 32, &mut |_| {})?;
        Ok(self.predict_inputs(&inputs))
    }

    /// Scores predictions against the truth.
    pub fn score(pred: &Predictions, truth: &Truth, chance: Vec<f64>) -> ProbeScores {
        let accuracy = (0..4)
            .map(|f| {
                f64::try_from(
                    pred.classes
                        .select(1, f)
                        .eq_tensor(&truth.classes.select(1, f))
                        .to_kind(Kind::Double)
                        .mean(Kind::Double),
                )
                .unwrap()
            })
            .collect();
        let m = truth.colour_mask.unsqueeze(2);
        let colour_mae = f64::try_from(
            ((&pred.colours - &truth.colours).abs() * &m).sum(Kind::Double)
                / (m.sum(Kind::Double) * 3.0).clamp_min(1.0),
        )
        .unwrap();
        let deg = 180.0 / std::f64::consts::PI;
        let dp = (pred.poses.select(1, 0) - truth.poses.select(1, 0)).abs() * deg;
        let dy = wrap_deg(&((pred.poses.select(1, 1) - truth.poses.select(1, 1)) * deg)).abs();
        ProbeScores {
            accuracy,
            chance,
            colour_mae,
            pitch_error_deg: f64::try_from(dp.mean(Kind::Double)).unwrap(),
            yaw_error_deg: f64::try_from(dy.mean(Kind::Double)).unwrap(),
            images: truth.classes.size()[0],
        }
    }

    /// Trains a probe on `(inputs, truth)` of the training split and scores it on the
    /// held-out pair. `progress(epoch, loss)` after each epoch.
    pub fn train(
        cfg: &ProbeConfig,
        train: (&Tensor, &Truth),
        held_out: (&Tensor, &Truth),
        device: Device,
        progress: &mut dyn FnMut(usize, f64),
    ) -> Result<Self> {
        if cfg.epochs == 0 || cfg.batch_size < 1 || cfg.lr <= 0.0 || !cfg.lr.is_finite() {
            return Err(Error::Invalid(format!(
                "probe training needs epochs ≥ 1, batch size ≥ 1 and a positive lr, got {cfg:?}"
            )));
        }
        let (x, truth) = train;
        let n = x.size()[0];
        if n < 2 {
            return Err(Error::Invalid(format!("the probe needs at least 2 training images, got {n}")));
        }
        let (vs, net) = crate::rng::with_global_seed(cfg.seed as i64, || Self::build(cfg.backbone, device));
        let mut opt = nn::Adam::default().build(&vs, cfg.lr)?;
        for epoch in 0..cfg.epochs {
            let mut rng = StepRng::new(cfg.seed, epoch as u64, Purpose::ProbeBatches, Kind::Float, Device::Cpu);
            let order = Tensor::from_slice(&rng.u64s(n as usize).iter().map(|&v| v as f64).collect::<Vec<_>>())
                .argsort(0, false);
            let mut total = 0.0;
            let mut batches = 0;
            let mut i = 0;
            while i < n {
                let b = cfg.batch_size.min(n - i);
                let idx = order.narrow(0, i, b);
                let t = truth.select(&idx);
                let out = net.forward(&x.index_select(0, &idx).to_device(device));
                let (logits, colours, pose) = split_outputs(&out);
                let mut loss = Tensor::zeros([], (Kind::Float, device));
                for (f, l) in logits.iter().enumerate() {
                    loss += l.cross_entropy_for_logits(&t.classes.select(1, f as i64).to_device(device));
                }
                let m = t.colour_mask.to_device(device).unsqueeze(2);
                let colour = ((&colours - t.colours.to_device(device)).square() * &m).sum(Kind::Float)
                    / (m.sum(Kind::Float) * 3.0).clamp_min(1.0);
                let p = t.poses.to_device(device);
                let target = Tensor::stack(&[p.select(1, 0), p.select(1, 1).sin(), p.select(1, 1).cos()], 1);
                let pose_loss = (&pose - target).square().mean(Kind::Float);
                loss = loss + colour * 10.0 + pose_loss;
                opt.backward_step(&loss);
                total += f64::try_from(&loss)?;
                batches += 1;
                i += b;
            }
            progress(epoch + 1, total / batches as f64);
        }
        let chance = majority_rates(&truth.classes, &held_out.1.classes);
        let mut probe = Self {
            vs,
            net,
            header: ProbeHeader {
                config: cfg.clone(),
                held_out: ProbeScores::default(),
                factors: FACTORS
                    .iter()
                    .map(|(n, c)| (n.to_string(), c.iter().map(|s| s.to_string()).collect()))
                    .collect(),
                train_images: n,
            },
        };
        let pred = probe.predict_inputs(held_out.0);
        probe.header.held_out = Self::score(&pred, held_out.1, chance);
        Ok(probe)
    }

    /// Writes the probe (weights and header) atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut tensors: Vec<(String, Tensor)> = self.vs.variables().into_iter().collect();
        tensors.sort_by(|a, b| a.0.cmp(&b.0));
        let json = serde_json::to_string(&self.header)?;
        write_atomic(path, &tensors_to_bytes(&tensors, PROBE_KEY, &json)?)
    }

    pub fn load(path: &Path, device: Device) -> Result<Self> {
        let (json, tensors) = load_tensors_with(path, PROBE_KEY)?;
        let not = |reason: String| Error::NotACheckpoint { path: path.to_path_buf(), reason };
        let header: ProbeHeader = serde_json::from_str(&json).map_err(|e| not(format!("bad probe header: {e}")))?;
        let want: Vec<(String, Vec<String>)> =
            FACTORS.iter().map(|(n, c)| (n.to_string(), c.iter().map(|s| s.to_string()).collect())).collect();
        if header.factors != want {
            return Err(not(format!("the probe predicts {:?}, this program expects {:?}", header.factors, want)));
        }
        let (mut vs, net) = Self::build(header.config.backbone, device);
        copy_into(path, &tensors, &mut vs)?;
        Ok(Self { vs, net, header })
    }
}

/// A procedural dataset's images with their ground truth.
pub struct Labelled {
    /// `(N, 3, R, R)` in [−1, 1].
    pub images: Tensor,
    pub truth: Truth,
    pub records: Vec<ImageRecord>,
}

impl Labelled {
    /// The first `limit` rows of one split (all of them with `None`).
    pub fn split(&self, split: Split, limit: Option<usize>) -> (Tensor, Truth, Vec<ImageRecord>) {
        let idx: Vec<i64> = self
            .records
            .iter()
            .enumerate()
            .filter(|(_, r)| r.split == split)
            .map(|(i, _)| i as i64)
            .take(limit.unwrap_or(usize::MAX))
            .collect();
        let t = Tensor::from_slice(&idx);
        let records = idx.iter().map(|&i| self.records[i as usize].clone()).collect();
        (self.images.index_select(0, &t), self.truth.select(&t), records)
    }
}

/// Loads a procedural chairs dataset (`metadata.json` + images) at `resolution` with the
/// ground truth of every image.
pub fn load_labelled(
    dir: &Path,
    resolution: usize,
    threads: usize,
    progress: &(dyn Fn(Event) + Sync),
) -> Result<Labelled> {
    let meta = Metadata::load(dir)?;
    let opts = LoadOptions { threads, ..LoadOptions::new(resolution) };
    let ds = data::load(dir, &opts, progress)?;
    let by_name: std::collections::HashMap<&str, &ImageRecord> =
        meta.images.iter().map(|r| (r.file.as_str(), r)).collect();
    let records: Vec<&ImageRecord> = ds
        .names
        .iter()
        .map(|n| {
            by_name.get(n.as_str()).copied().ok_or_else(|| Error::Data {
                path: dir.join(n),
                reason: "this image is not described in metadata.json".into(),
            })
        })
        .collect::<Result<_>>()?;
    Ok(Labelled {
        images: ds.images(),
        truth: Truth::from_records(&records)?,
        records: records.into_iter().cloned().collect(),
    })
}

/// Per factor: the held-out frequency of the training split's most frequent class.
pub fn majority_rates(train: &Tensor, held_out: &Tensor) -> Vec<f64> {
    FACTORS
        .iter()
        .enumerate()
        .map(|(f, (_, classes))| {
            let counts = train.select(1, f as i64).bincount(None::<Tensor>, classes.len() as i64);
            let top = counts.argmax(0, false);
            f64::try_from(held_out.select(1, f as i64).eq_tensor(&top).to_kind(Kind::Double).mean(Kind::Double))
                .unwrap()
        })
        .collect()
}

/// `(4, classes)` histograms: the fraction of images per class of each factor (rows padded
/// with zeros to 5 classes).
pub fn class_histograms(classes: &Tensor) -> Vec<Vec<f64>> {
    let n = classes.size()[0].max(1) as f64;
    FACTORS
        .iter()
        .enumerate()
        .map(|(f, (_, names))| {
            let counts = classes.select(1, f as i64).bincount(None::<Tensor>, names.len() as i64);
            Vec::<i64>::try_from(counts).unwrap().into_iter().map(|c| c as f64 / n).collect()
        })
        .collect()
}

/// Total variation distance between two histograms.
pub fn total_variation(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).sum::<f64>() / 2.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histograms_and_total_variation() {
        let c = Tensor::from_slice(&[0i64, 1, 2, 0, 4, 0, 0, 1]).view([2, 4]);
        let h = class_histograms(&c);
        assert_eq!(h[0], vec![0.5, 0.0, 0.0, 0.0, 0.5]);
        assert_eq!(h[3], vec![0.5, 0.5]);
        assert_eq!(total_variation(&[1.0, 0.0], &[0.0, 1.0]), 1.0);
        assert_eq!(total_variation(&h[0], &h[0]), 0.0);
        let w = Vec::<f64>::try_from(wrap_deg(&Tensor::from_slice(&[350.0f64, -190.0, 10.0]))).unwrap();
        assert_eq!(w, vec![-10.0, 170.0, 10.0]);
    }
}
