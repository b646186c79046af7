//! The evaluator of `gdrf-train eval`: every score of a generator beside its two calibrated ends — real
//! held-out images (what a perfect generator would get) and a random-weight generator of
//! the same architecture (what learning nothing gets) — written as `eval.json` and a
//! one-page `report.png`.
//!
//! - **Fréchet / kernel distance** of pretrained features (EfficientNet-Lite0's pooled
//!   1280-d feature by default, FID's Inception-v3 with a user-supplied file) against the
//!   held-out split. The real end uses as many training-split images.
//! - **Topology coverage**: total variation between the probe's predicted structure classes
//!   over generated images and the held-out split's true classes, averaged over factors.
//! - **Disentanglement** on a k × k swap matrix (shape of i, appearance of j): over pairs
//!   whose originals differ, how often each structure factor follows i, and how often the
//!   part colours are nearer j's than i's. The real end renders the procedural dataset's
//!   own swaps.
//! - **Pose consistency**: the probe's yaw and pitch against the pose an image was rendered at.
use super::distance;
use super::metrics::{colour_histograms, coverage, pose_errors, swap_scores, through_resolution, PoseErrors, Verdict};
use super::probe::{self, class_histograms, Predictions, Probe, FACTORS};
use super::provenance::{resolution_warning, trained_against_projected, SHARED_FEATURES_WARNING};
use super::result::{Calibrated, ClassTable, EvalResult, FrameOffsets, LowResolutionEnd};
use crate::camera::Poses;
use crate::checkpoint::load_generator;
use crate::data::synth;
use crate::data::{Metadata, Split};
use crate::edit::matrix::swap_pairs;
use crate::field::generator::Truncation;
use crate::pretrained::effnet::EfficientNetLite0;
use crate::pretrained::inception::InceptionV3;
use crate::progress::Event;
use crate::render::{Noise, Renderer};
use crate::rng::{Purpose, RandomSource, StepRng};
use crate::{CameraConfig, Error, Generator, RenderConfig, Result};
use std::path::{Path, PathBuf};
use tch::{nn, Device, Kind, Tensor};

/// Which pretrained features the distances use.
#[derive(Debug, Clone)]
pub enum FeatureKind {
    Efficientnet,
    /// FID's Inception-v3 from this weights file.
    Inception(PathBuf),
}

#[derive(Debug, Clone)]
pub struct EvalOptions {
    /// Generated images per distribution.
    pub num: i64,
    /// Side of the swap matrix.
    pub swap: i64,
    /// Render resolution (default: the dataset's).
    pub resolution: Option<i64>,
    /// Coarse samples per ray (as many fine).
    pub samples: i64,
    pub seed: u64,
    pub features: FeatureKind,
    pub effnet_weights: PathBuf,
    pub threads: usize,
    /// Also score the real images seen at this lower resolution (antialiased down, then
    /// bilinearly back up to the evaluation's): what the resolution alone costs real data,
    /// a reference for a generator trained at it. `None`: not scored.
    pub real_resolution: Option<i64>,
    /// Truncation ψ of the model's codes toward its mean mapping output (1 = none, the
    /// usual way to score a GAN). The random end is never truncated, so positions stay on
    /// one scale whatever ψ is.
    pub psi: f64,
}

impl Default for EvalOptions {
    /// `gdrf-train eval`'s defaults: 1 000 images, an 8 × 8 swap matrix, 24 + 24 samples,
    /// EfficientNet-Lite0 features, seed 0, no truncation.
    fn default() -> Self {
        Self {
            num: 1000,
            swap: 8,
            resolution: None,
            samples: 24,
            seed: 0,
            features: FeatureKind::Efficientnet,
            effnet_weights: crate::pretrained::effnet::EfficientNetLite0::default_path(),
            threads: 0,
            real_resolution: None,
            psi: 1.0,
        }
    }
}

/// Renders `z` at `poses` (batches of 16, no jitter, importance samples at the midpoints:
/// no random numbers) with `g`, its codes truncated by `trunc` when given. `codes`: shape
/// and appearance codes `(N, latent)` each.
pub fn render_codes(
    (g, trunc): (&Generator, Option<&Truncation>),
    cam: &CameraConfig,
    rc: &RenderConfig,
    codes: (&Tensor, &Tensor),
    poses: &Poses,
    res: i64,
    tick: &mut dyn FnMut(i64),
) -> Result<Tensor> {
    let (zs, za) = codes;
    let renderer = Renderer::new(g, cam, rc)?;
    let n = zs.size()[0];
    let mut out = Vec::new();
    let mut i = 0;
    while i < n {
        let b = 16.min(n - i);
        let lat = tch::no_grad(|| g.latents(&zs.narrow(0, i, b), &za.narrow(0, i, b), trunc))?;
        let p = Poses { pitch: poses.pitch.narrow(0, i, b), yaw: poses.yaw.narrow(0, i, b) };
        let nz = Noise::midpoints(b, res * res, rc.num_steps as i64, zs.device());
        out.push(tch::no_grad(|| renderer.render_image(&lat, &p, res, &nz))?.rgb.to_device(Device::Cpu));
        i += b;
        tick(b);
    }
    Ok(Tensor::cat(&out, 0))
}

enum Extractor {
    Effnet,
    Inception(Box<InceptionV3>),
}

/// The real images' scores at a lower resolution, from their [`Scores`] there.
fn low_resolution_end(resolution: i64, s: &Scores) -> LowResolutionEnd {
    LowResolutionEnd {
        resolution,
        frechet: s.frechet,
        kernel: s.kernel,
        coverage_tv: s.coverage_tv,
        shape_follows: s.shape_follows,
        appearance_follows: s.appearance_follows,
        pose_yaw_error_deg: s.pose.yaw,
        pose_yaw_error_in_frame_deg: s.pose.yaw_in_frame,
        pose_pitch_error_deg: s.pose.pitch,
        pitch_bias_deg: s.pose.pitch_bias,
    }
}

/// What one distribution of images (a generator's, or the real data's) scores.
pub struct Scores {
    pub frechet: f64,
    pub kernel: f64,
    pub warnings: Vec<String>,
    pub coverage_tv: f64,
    /// Predicted class histograms per factor.
    pub histograms: Vec<Vec<f64>>,
    pub shape_follows: f64,
    pub appearance_follows: f64,
    pub pose: PoseErrors,
    /// Up to 24 of the images `(n, 3, S, S)`.
    pub samples: Tensor,
    /// The swap matrix `(k², 3, S, S)` and its verdicts.
    pub swap_images: Tensor,
    pub swap_verdicts: Vec<Verdict>,
}

/// The real data's side of the evaluation, computed once: the reference features, the
/// held-out truth, and the real-data end of every score. [`Evaluator::score`] then scores
/// any generator (the CLI: the model and a random one; training: the EMA generator every
/// `eval.interval` steps).
pub struct Evaluator {
    effnet: EfficientNetLite0,
    extractor: Extractor,
    pub probe: Probe,
    pub opts: EvalOptions,
    pub resolution: i64,
    held_feats: Tensor,
    reference: Vec<Vec<f64>>,
    /// The real-data end.
    pub real: Scores,
    /// The real end's distance features, kept so that [`Evaluator::reseed`] can redraw its
    /// kernel distance's subsets.
    real_feats: Tensor,
    /// The real images at [`EvalOptions::real_resolution`], when set, and their features.
    pub real_low: Option<LowResolutionEnd>,
    low_feats: Option<Tensor>,
    pub device: Device,
}

impl Evaluator {
    pub fn new(
        dataset: &Path,
        probe_path: &Path,
        opts: &EvalOptions,
        device: Device,
        progress: &mut dyn FnMut(Event),
    ) -> Result<Self> {
        if opts.num < 2 || opts.swap < 2 || opts.samples < 2 {
            return Err(Error::Invalid(format!(
                "eval needs num ≥ 2, swap ≥ 2 and samples ≥ 2, got {}, {}, {}",
                opts.num, opts.swap, opts.samples
            )));
        }
        if !(opts.psi.is_finite() && opts.psi >= 0.0) {
            return Err(Error::Invalid(format!(
                "eval's truncation ψ is {}, expected a finite number ≥ 0 (1 = none)",
                opts.psi
            )));
        }
        let meta = Metadata::load(dataset)?;
        let res = opts.resolution.unwrap_or(meta.options.resolution as i64);
        if !(8..=512).contains(&res) {
            return Err(Error::Invalid(format!("eval resolution {res} is out of range, expected 8 to 512")));
        }
        if let Some(low) = opts.real_resolution {
            if !(2..res).contains(&low) {
                return Err(Error::Invalid(format!(
                    "--real-resolution {low} must lie between 2 and the evaluation's resolution {res} (exclusive)"
                )));
            }
        }
        let probe = Probe::load(probe_path, device)?;
        let effnet = EfficientNetLite0::load(&opts.effnet_weights, device)?;
        let extractor = match &opts.features {
            FeatureKind::Efficientnet => Extractor::Effnet,
            FeatureKind::Inception(p) => Extractor::Inception(Box::new(InceptionV3::load(p, device)?)),
        };
        progress(Event::new("loading the dataset", 0, 1));
        let data = probe::load_labelled(dataset, res as usize, opts.threads, &|_| {})?;
        let (held_x, held_t, held_records) = data.split(Split::HeldOut, None);
        // The real end of the distances: as many training images as generated ones.
        let (train_x, train_t, _) = data.split(Split::Train, Some(opts.num as usize));
        if held_x.size()[0] < 2 || train_x.size()[0] < 2 {
            return Err(Error::Data {
                path: dataset.to_path_buf(),
                reason: "fewer than 2 held-out or training images to compare with".into(),
            });
        }
        let k = opts.swap.min(held_x.size()[0]);
        // The dataset's own swaps of k held-out objects (shape of i, appearance of j).
        let mut real_swap = Vec::new();
        for i in 0..k as usize {
            for j in 0..k as usize {
                let r = synth::render_swap(
                    &meta,
                    held_records[i].object,
                    held_records[j].object,
                    None,
                    Some(res as usize),
                    Some(2),
                )?;
                real_swap
                    .push(Tensor::from_slice(&r.rgb).view([res, res, 3]).permute([2, 0, 1]).unsqueeze(0) * 2.0 - 1.0);
            }
            progress(Event::new("rendering the dataset's swaps", (i as u64 + 1) * k as u64, (k * k) as u64));
        }
        let real_swap = Tensor::cat(&real_swap, 0).to_kind(Kind::Float);
        let mut ev = Self {
            effnet,
            extractor,
            probe,
            opts: opts.clone(),
            resolution: res,
            held_feats: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
            reference: class_histograms(&held_t.classes),
            real: Scores::empty(),
            real_feats: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
            real_low: None,
            low_feats: None,
            device,
        };
        let (held_feats, held_pred) = ev.features(&held_x, "features: held-out images", progress)?;
        ev.held_feats = held_feats;
        (ev.real, ev.real_feats) = ev.score_images(&train_x, &train_t.poses, &real_swap, k, "real images", progress)?;
        // The probe's coverage and pose ends are taken on held-out images: on the training
        // images it learned from they would be optimistic.
        let p_real = match held_pred {
            Some(p) => p,
            None => ev.predict(&held_x)?,
        };
        ev.real.coverage_tv = coverage(&p_real.classes, &ev.reference).0;
        ev.real.histograms = class_histograms(&p_real.classes);
        ev.real.pose = pose_errors(&p_real, &held_t.poses);
        if let Some(low) = opts.real_resolution {
            let blur = |x: &Tensor| through_resolution(x, low);
            let what = format!("real images at {low}²");
            let (mut s, feats) =
                ev.score_images(&blur(&train_x), &train_t.poses, &blur(&real_swap), k, &what, progress)?;
            // Coverage and pose on the held-out images, as for the real end.
            let p = ev.predict(&blur(&held_x))?;
            s.coverage_tv = coverage(&p.classes, &ev.reference).0;
            s.pose = pose_errors(&p, &held_t.poses);
            ev.real_low = Some(low_resolution_end(low, &s));
            ev.low_feats = Some(feats);
        }
        Ok(ev)
    }

    /// Makes `seed` the evaluation seed: [`Evaluator::score`] then draws its codes and poses
    /// from it, and every kernel distance (the real end's included, recomputed from its kept
    /// features) its subsets. The real images and the probe's scores of them do not depend on
    /// the seed, so one evaluator scores several seeds for the price of one real end, each
    /// exactly as a fresh evaluator with that seed would.
    pub fn reseed(&mut self, seed: u64) -> Result<()> {
        self.opts.seed = seed;
        self.real.kernel = distance::kernel(&self.real_feats, &self.held_feats, 50, 1000, seed)?.mean;
        if let (Some(low), Some(feats)) = (self.real_low.as_mut(), self.low_feats.as_ref()) {
            low.kernel = distance::kernel(feats, &self.held_feats, 50, 1000, seed)?.mean;
        }
        Ok(())
    }

    fn predict(&self, imgs: &Tensor) -> Result<Predictions> {
        let net = (self.probe.header.config.backbone == probe::Backbone::Efficientnet).then_some(&self.effnet);
        self.probe.predict(net, imgs)
    }

    /// Distance features of `imgs`, and the probe's predictions when they come from the
    /// same EfficientNet pass (the efficientnet probe with efficientnet features).
    fn features(
        &self,
        imgs: &Tensor,
        what: &str,
        progress: &mut dyn FnMut(Event),
    ) -> Result<(Tensor, Option<Predictions>)> {
        let n = imgs.size()[0];
        let shared = self.probe.header.config.backbone == probe::Backbone::Efficientnet;
        match &self.extractor {
            Extractor::Effnet => {
                let (pooled, tap) =
                    self.effnet.pooled_and_last_tap(imgs, 32, &mut |e| progress(Event { task: what, ..e }))?;
                Ok((pooled, shared.then(|| self.probe.predict_inputs(&probe::with_colour(&tap, imgs)))))
            }
            Extractor::Inception(net) => {
                let mut out = Vec::new();
                let mut i = 0;
                while i < n {
                    let b = 16.min(n - i);
                    out.push(net.features_from_signed(&imgs.narrow(0, i, b))?.to_device(Device::Cpu));
                    i += b;
                    progress(Event::new(what, i as u64, n as u64));
                }
                Ok((Tensor::cat(&out, 0), None))
            }
        }
    }

    /// Scores a set of images (`images` with the poses they show, a k × k swap matrix);
    /// also returns their distance features.
    #[allow(clippy::too_many_arguments)]
    fn score_images(
        &self,
        images: &Tensor,
        poses: &Tensor,
        swap: &Tensor,
        k: i64,
        what: &str,
        progress: &mut dyn FnMut(Event),
    ) -> Result<(Scores, Tensor)> {
        let (feats, pred) = self.features(images, &format!("features: {what}"), progress)?;
        let fd = distance::frechet(&feats, &self.held_feats)?;
        let kid = distance::kernel(&feats, &self.held_feats, 50, 1000, self.opts.seed)?;
        progress(Event::new(&format!("probe: {what}"), 0, 1));
        let p = match pred {
            Some(p) => p,
            None => self.predict(images)?,
        };
        let (tv, hist) = coverage(&p.classes, &self.reference);
        let pose = pose_errors(&p, poses);
        let ps = self.predict(swap)?;
        let (shape_follows, appearance_follows, verdicts) = swap_scores(&ps, &colour_histograms(swap), k);
        let scores = Scores {
            frechet: fd.value,
            kernel: kid.mean,
            warnings: fd.warning.into_iter().collect(),
            coverage_tv: tv,
            histograms: hist,
            shape_follows,
            appearance_follows,
            pose,
            samples: images.narrow(0, 0, images.size()[0].min(24)),
            swap_images: swap.shallow_clone(),
            swap_verdicts: verdicts,
        };
        Ok((scores, feats))
    }

    /// Renders `num` images (codes and poses from the evaluation seed: the same for every
    /// generator) and a swap matrix with `g`, its codes truncated by `trunc` when given,
    /// and scores them.
    pub fn score(
        &self,
        g: &Generator,
        cam: &CameraConfig,
        trunc: Option<&Truncation>,
        what: &str,
        progress: &mut dyn FnMut(Event),
    ) -> Result<Scores> {
        let (num, k, res) = (self.opts.num, self.opts.swap, self.resolution);
        let device = g.kind_device().1;
        let rc = RenderConfig { num_steps: self.opts.samples as usize, jitter: false, ..RenderConfig::default() };
        let latent = g.cfg.latent_dim as i64;
        let z = StepRng::new(self.opts.seed, 0, Purpose::EvalCodes, Kind::Float, device).normal(&[num, latent]);
        let poses =
            Poses::sample_from(cam, num, &mut StepRng::new(self.opts.seed, 0, Purpose::EvalPoses, Kind::Float, device));
        let k = k.min(num);
        let zk = z.narrow(0, 0, k);
        let (swap_s, swap_a) = swap_pairs(&zk);
        // Every swap cell at its shape code's pose, so that a row differs only in appearance.
        let rep = |t: &Tensor| swap_pairs(&t.narrow(0, 0, k)).0;
        let swap_poses = Poses { pitch: rep(&poses.pitch), yaw: rep(&poses.yaw) };
        let total = num + k * k;
        let mut done = 0;
        let label = format!("rendering: {what}");
        let mut tick = |b: i64| {
            done += b;
            progress(Event::new(&label, done as u64, total as u64));
        };
        let imgs = render_codes((g, trunc), cam, &rc, (&z, &z), &poses, res, &mut tick)?;
        let swap = render_codes((g, trunc), cam, &rc, (&swap_s, &swap_a), &swap_poses, res, &mut tick)?;
        Ok(self.score_images(&imgs, &poses.stacked().to_device(Device::Cpu), &swap, k, what, progress)?.0)
    }
}

impl Scores {
    fn empty() -> Self {
        let none = Tensor::zeros([0], (Kind::Float, Device::Cpu));
        Self {
            frechet: f64::NAN,
            kernel: f64::NAN,
            warnings: Vec::new(),
            coverage_tv: f64::NAN,
            histograms: Vec::new(),
            shape_follows: f64::NAN,
            appearance_follows: f64::NAN,
            pose: PoseErrors {
                yaw: f64::NAN,
                yaw_in_frame: f64::NAN,
                yaw_offset: f64::NAN,
                pitch: f64::NAN,
                pitch_bias: f64::NAN,
            },
            samples: none.shallow_clone(),
            swap_images: none,
            swap_verdicts: Vec::new(),
        }
    }
}

/// Scores `generator` against `dataset` (a procedural chairs dataset) with `probe`, beside
/// the real-data end and a random-weight generator of the same architecture.
pub fn evaluate(
    generator: &Path,
    dataset: &Path,
    probe_path: &Path,
    opts: &EvalOptions,
    device: Device,
    progress: &mut dyn FnMut(Event),
) -> Result<EvalResult> {
    let mut all = evaluate_seeds(generator, dataset, probe_path, opts, &[opts.seed], device, progress)?;
    Ok(all.remove(0))
}

/// [`evaluate`] once per seed in `seeds` (each seed draws the codes, the poses, the random
/// generator and the kernel distance's subsets), sharing one real end. Each result equals
/// what `evaluate` gives with that seed; its `seconds` counts its own scoring, and the first
/// one also the real end's.
pub fn evaluate_seeds(
    generator: &Path,
    dataset: &Path,
    probe_path: &Path,
    opts: &EvalOptions,
    seeds: &[u64],
    device: Device,
    progress: &mut dyn FnMut(Event),
) -> Result<Vec<EvalResult>> {
    let Some(&first) = seeds.first() else {
        return Err(Error::Invalid("eval needs at least one seed".into()));
    };
    let mut start = std::time::Instant::now();
    let loaded = load_generator(generator, device, Kind::Float)?;
    let mut ev = Evaluator::new(dataset, probe_path, &EvalOptions { seed: first, ..opts.clone() }, device, progress)?;
    let mut out = Vec::with_capacity(seeds.len());
    for &seed in seeds {
        ev.reseed(seed)?;
        let what = if seeds.len() > 1 { format!(" (seed {seed})") } else { String::new() };
        let names = (generator.display().to_string(), dataset);
        out.push(score_generator(&ev, &loaded.generator, &loaded.header, names, &what, start, progress)?);
        start = std::time::Instant::now();
    }
    Ok(out)
}

/// One seed's [`EvalResult`] (the seed is the evaluator's) of `generator`, whose header
/// `header` gives its camera and provenance: the model beside a random-weight generator of
/// its architecture and the evaluator's real end. `names` (the generator as shown, the
/// dataset) go into the result; `what` follows the progress labels.
pub fn score_generator(
    ev: &Evaluator,
    generator: &Generator,
    header: &crate::checkpoint::Header,
    (name, dataset): (String, &Path),
    what: &str,
    start: std::time::Instant,
    progress: &mut dyn FnMut(Event),
) -> Result<EvalResult> {
    let (opts, device) = (&ev.opts, ev.device);
    let cam = header.camera.clone().unwrap_or_default();
    let rvs = nn::VarStore::new(device);
    let random = crate::rng::with_global_seed(opts.seed as i64 + 1, || Generator::new(&rvs.root(), &generator.cfg))?;
    let trunc = generator.truncation_at(opts.psi);
    let model = ev.score(generator, &cam, trunc.as_ref(), &format!("model{what}"), progress)?;
    let rand = ev.score(&random, &cam, None, &format!("random generator{what}"), progress)?;
    let real = &ev.real;
    let mut warnings: Vec<String> = Vec::new();
    if matches!(opts.features, FeatureKind::Efficientnet) && trained_against_projected(header) {
        warnings.push(SHARED_FEATURES_WARNING.into());
    }
    warnings.extend(resolution_warning(header, ev.resolution));
    for w in model.warnings.iter().chain(&rand.warnings).chain(&real.warnings) {
        if !warnings.contains(w) {
            warnings.push(w.clone());
        }
    }
    let classes = FACTORS
        .iter()
        .enumerate()
        .map(|(f, (name, cls))| ClassTable {
            factor: name.to_string(),
            classes: cls.iter().map(|s| s.to_string()).collect(),
            reference: ev.reference[f].clone(),
            real_predicted: real.histograms[f].clone(),
            model: model.histograms[f].clone(),
            random: rand.histograms[f].clone(),
        })
        .collect();
    let c = |f: fn(&Scores) -> f64| Calibrated::new(f(&model), f(real), f(&rand));
    Ok(EvalResult {
        generator: name,
        dataset: dataset.display().to_string(),
        features: match &opts.features {
            FeatureKind::Efficientnet => "efficientnet-lite0 pooled (1280-d, 224², ImageNet)".into(),
            FeatureKind::Inception(p) => {
                format!("inception-v3 pool3 (2048-d, 299², {})", p.display())
            }
        },
        seed: opts.seed,
        images: opts.num,
        resolution: ev.resolution,
        samples_per_ray: 2 * opts.samples,
        psi: opts.psi,
        frechet: c(|s| s.frechet),
        kernel: c(|s| s.kernel),
        warnings,
        coverage_tv: c(|s| s.coverage_tv),
        classes,
        shape_follows: c(|s| s.shape_follows),
        appearance_follows: c(|s| s.appearance_follows),
        pose_yaw_error_deg: c(|s| s.pose.yaw),
        pose_yaw_error_in_frame_deg: c(|s| s.pose.yaw_in_frame),
        yaw_frame_offset_deg: FrameOffsets {
            model: model.pose.yaw_offset,
            real: real.pose.yaw_offset,
            random: rand.pose.yaw_offset,
        },
        pose_pitch_error_deg: c(|s| s.pose.pitch),
        pitch_bias_deg: FrameOffsets {
            model: model.pose.pitch_bias,
            real: real.pose.pitch_bias,
            random: rand.pose.pitch_bias,
        },
        real_at_resolution: ev.real_low.clone(),
        probe_held_out_accuracy: ev.probe.header.held_out.accuracy.clone(),
        seconds: start.elapsed().as_secs_f64(),
        samples: model.samples,
        swap_images: model.swap_images,
        swap_verdicts: model.swap_verdicts,
        swap_side: opts.swap.min(opts.num),
    })
}
