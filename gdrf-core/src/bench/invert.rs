//! `gdrf-invert bench`: inversion of held-out objects of a procedural dataset, whose ground
//! truth renders any object at any pose, scored at novel views against the time it took.
//!
//! Each object's view 0 (the dataset image) is inverted; the result is rendered at `--views`
//! other known poses and compared with the ground truth there: PSNR, a perceptual distance
//! (LPIPS with a backbone the user supplies, else the EfficientNet-Lite0 distance, named as
//! such), silhouette IoU against the ground-truth alpha, and the probe's structure
//! agreement; and the pose the inversion ended at against the true one. Every score is a
//! mean over the objects and the renderer-noise seeds (inversion is chaotic in the noise,
//! docs/inversion.md, so one object or one seed ranks nothing).
use super::write_json;
use crate::camera::{Poses, Rays};
use crate::checkpoint::load_generator;
use crate::config::RenderConfig;
use crate::data::synth::render_object;
use crate::data::{Metadata, Split};
use crate::edit::{generator_id, Features};
use crate::error::Context;
use crate::eval::fidelity::psnr;
use crate::eval::probe::{structure_classes, Probe};
use crate::invert::choice::{self, InitChoice};
use crate::invert::photo::{load_photo, Fit};
use crate::invert::{load_effnet, render_views, start_for_photo, InvertConfig, Inverter, Perceptual};
use crate::plot::{draw_panels, Panel, Series};
use crate::pretrained::effnet::EfficientNetLite0;
use crate::pretrained::lpips::{Lpips, LpipsNet};
use crate::render::{Noise, Renderer};
use crate::{device, CameraConfig, Error, Generator, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// The flags of `gdrf-invert bench`.
#[derive(clap::Args)]
pub struct Options {
    /// Generator checkpoint; default: the shipped models/chairs-campaign.
    #[arg(long, visible_alias = "checkpoint", value_name = "FILE")]
    pub generator: Option<PathBuf>,
    /// The initialiser, as gdrf-invert's --init: default the one beside the generator;
    /// `none` measures the mean-code start alone.
    #[arg(long, value_name = "FILE|none")]
    pub init: Option<InitChoice>,
    /// A procedural dataset folder (its held-out objects are inverted).
    #[arg(long, default_value = "data/chairs-64")]
    pub dataset: PathBuf,
    /// Held-out objects to invert.
    #[arg(long, default_value_t = 16)]
    pub images: usize,
    /// Held-out objects passed over before the --images inverted: choose settings on one
    /// set of objects, report on another. The first 16 chose the shipped defaults.
    #[arg(long, default_value_t = 16)]
    pub skip: usize,
    /// Novel views per object (yaw offsets spread over the turn, same pitch).
    #[arg(long, default_value_t = 4)]
    pub views: usize,
    /// Renderer-noise seeds (`gdrf-invert --noise-seed`: the jitter and the ray subsets):
    /// every object is inverted once per seed and every score averaged over all of them.
    #[arg(long, value_delimiter = ',', default_value = "0,1")]
    pub noise_seeds: Vec<u64>,
    /// Steps of every method but the paper's (default: gdrf-invert's).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Steps of the paper's setting (all rays, --reference-lr), and on how many of the
    /// objects it runs (it is the slow one).
    #[arg(long, default_value_t = 2000)]
    pub reference_steps: usize,
    #[arg(long, default_value_t = 8)]
    pub reference_images: usize,
    /// Adam's learning rate of the paper's setting.
    #[arg(long, default_value_t = InvertConfig::PAPER_LR)]
    pub reference_lr: f64,
    /// Render side during the optimisation and for every comparison (default: where the
    /// generator learned, as gdrf-invert).
    #[arg(long)]
    pub resolution: Option<i64>,
    #[arg(long)]
    pub samples: Option<usize>,
    /// Also run the variants the defaults were chosen among: the initialiser's pose kept
    /// fixed, and gradients through a quarter of the rays at lr 0.03 (the defaults before
    /// an initialiser shipped).
    #[arg(long)]
    pub variants: bool,
    /// Run only the methods whose name contains one of these (comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// The ground-truth probe (`gdrf-train eval train-probe`); default: the shipped
    /// models/chairs-probe.
    #[arg(long, value_name = "FILE")]
    pub probe: Option<PathBuf>,
    /// LPIPS (VGG) as the perceptual score, with this backbone file
    /// (scripts/export_lpips_backbone.py); default: the EfficientNet-Lite0 distance.
    #[arg(long, value_name = "FILE")]
    pub lpips_backbone: Option<PathBuf>,
    /// Objects in the figure (photo | reconstruction | novel views | ground truth), from the
    /// gdrf-invert row.
    #[arg(long, default_value_t = 4)]
    pub figure_objects: usize,
    /// Output stem: STEM.json, STEM.md, STEM.png (novel-view PSNR against seconds),
    /// STEM-figure.png.
    #[arg(long, default_value = "docs/bench/invert")]
    pub out: PathBuf,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    pub device: String,
}

/// Where a method's features start.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
enum From {
    MeanCode,
    Initialiser,
}

/// Which pose a method inverts at.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(rename_all = "snake_case")]
enum PoseUsed {
    True,
    Estimated,
}

struct Method {
    name: String,
    from: From,
    pose: PoseUsed,
    cfg: InvertConfig,
    /// How many of the objects it runs on (the first ones).
    objects: usize,
}

/// STEM.json: the run's settings and every method's points.
#[derive(Serialize)]
pub struct Report {
    /// The generator, initialiser and probe as shown in committed figures.
    pub generator: String,
    pub init: Option<String>,
    pub dataset: String,
    /// The objects inverted (dataset files) and the first `skip` held-out ones passed over.
    pub objects: Vec<String>,
    pub skip: usize,
    pub noise_seeds: Vec<u64>,
    pub views: usize,
    pub resolution: i64,
    pub samples: usize,
    pub perceptual: String,
    pub device: String,
    pub threads: usize,
    pub probe: String,
    /// The probe on the ground-truth novel views themselves: the best agreement it can give.
    pub structure_agreement_of_the_ground_truth_views: f64,
    pub points: Vec<Point>,
}

/// One measured point of one method: means over its objects and the noise seeds.
#[derive(Serialize, Clone)]
pub struct Point {
    pub method: String,
    pub start: String,
    pub pose: String,
    pub objects: usize,
    /// The step budget at this point and the steps actually run.
    pub steps: usize,
    /// Seconds from the photo to this point: the initialiser's prediction and the steps.
    pub seconds: f64,
    pub input_psnr: f64,
    pub novel_psnr: f64,
    /// The novel-view PSNR above the mean code's at the true pose (0 steps), on the same
    /// objects.
    pub novel_gain_db: f64,
    pub novel_perceptual: f64,
    pub silhouette_iou: f64,
    pub structure_agreement: f64,
    /// The pose at this point against the true one (the given one has none).
    pub pitch_error_deg: f64,
    pub yaw_error_deg: f64,
    pub median_yaw_error_deg: f64,
    /// The novel-view PSNR of each object (its mean over the noise seeds).
    pub novel_psnr_per_object: Vec<f64>,
    /// The novel-view PSNR of each noise seed (its mean over the objects).
    pub novel_psnr_per_noise_seed: Vec<f64>,
}

struct Case {
    file: String,
    photo: Tensor,
    pose: (f64, f64),
    /// `(V, 3, R, R)` ground truth, its alpha `(V, 1, R, R)` and the poses.
    novel: Tensor,
    alpha: Tensor,
    novel_poses: Vec<(f64, f64)>,
    /// The perceptual distance's prepared target of each ground-truth view.
    targets: Vec<Vec<Tensor>>,
    /// `(1, 4)` the object's true structure classes.
    structure: Tensor,
}

/// What scores a set of features on a case.
struct Judge<'a> {
    g: &'a Generator,
    cam: &'a CameraConfig,
    probe: &'a Probe,
    effnet: &'a EfficientNetLite0,
    perceptual: &'a Perceptual<'a>,
    res: i64,
    samples: usize,
}

fn to_tensor(v: &[f32], res: i64, channels: i64) -> Tensor {
    Tensor::from_slice(v).view([res, res, channels]).permute([2, 0, 1]).unsqueeze(0)
}

fn mean(v: &Tensor) -> f64 {
    f64::try_from(v.mean(Kind::Double)).unwrap_or(f64::NAN)
}

/// The wrapped absolute angle between two angles, in degrees.
fn angle_deg(a: f64, b: f64) -> f64 {
    let d = a - b;
    d.sin().atan2(d.cos()).abs().to_degrees()
}

/// Scores of one inversion state: [input PSNR, novel PSNR, perceptual, IoU, structure].
type Scores = [f64; 5];

impl Judge<'_> {
    /// The opacity in front of the far plane of `f` at `poses`, `(V, 1, R, R)`: the weights
    /// of every sample but the last, which paints the background.
    fn foreground(&self, f: &Features, poses: &[(f64, f64)]) -> Result<Tensor> {
        let rc = RenderConfig { num_steps: self.samples, jitter: false, ..Default::default() };
        let r = Renderer::new(self.g, self.cam, &rc)?;
        let (kind, device) = self.g.kind_device();
        let k = poses.len() as i64;
        let one = crate::edit::latents(self.g, f, f, None);
        let rep = |t: &Tensor| t.repeat([k, 1]);
        let lat = crate::Latents {
            shape: crate::nn::film::Film { gamma: rep(&one.shape.gamma), beta: rep(&one.shape.beta) },
            appearance: crate::nn::film::Film { gamma: rep(&one.appearance.gamma), beta: rep(&one.appearance.beta) },
        };
        let rays = Rays::from_poses(&Poses::from_angles(poses, kind, device), self.res, self.cam.fov_deg);
        let noise = Noise::midpoints(k, self.res * self.res, self.samples as i64, device);
        let out = tch::no_grad(|| r.render_rays(&lat, &rays, &noise))?;
        let s = out.weights.size()[2];
        let front = out.weights.narrow(2, 0, s - 1).sum_dim_intlist(2, false, Kind::Float);
        Ok(front.view([k, self.res, self.res, 1]).permute([0, 3, 1, 2]))
    }

    fn score(&self, f: &Features, case: &Case, at: (f64, f64)) -> Result<Scores> {
        let (g, cam) = (self.g, self.cam);
        let input = render_views(g, cam, f, &[at], self.res, self.samples)?;
        let novel = render_views(g, cam, f, &case.novel_poses, self.res, self.samples)?;
        let mut perceptual = 0.0;
        for (i, target) in case.targets.iter().enumerate() {
            perceptual += mean(&(self.perceptual.to_target)(&novel.narrow(0, i as i64, 1), target)?);
        }
        let fg = self.foreground(f, &case.novel_poses)?.gt(0.5);
        let truth = case.alpha.gt(0.5);
        let inter = fg.logical_and(&truth).sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float);
        let union = fg.logical_or(&truth).sum_dim_intlist([1i64, 2, 3].as_slice(), false, Kind::Float);
        let iou = inter / union.clamp_min(1.0);
        let classes = self.probe.predict(Some(self.effnet), &novel)?.classes;
        let agree = classes.eq_tensor(&case.structure.to_device(classes.device())).to_kind(Kind::Float);
        Ok([
            mean(&psnr(&input, &case.photo)?),
            mean(&psnr(&novel, &case.novel)?),
            perceptual / case.targets.len() as f64,
            mean(&iou),
            mean(&agree),
        ])
    }
}

/// One (checkpoint, object, seed) measurement.
#[derive(Clone, Copy, Default)]
struct Cell {
    seconds: f64,
    scores: Scores,
    pitch_err: f64,
    yaw_err: f64,
}

fn load_cases(a: &Options, res: i64, dev: tch::Device, perceptual: &Perceptual) -> Result<Vec<Case>> {
    let meta = Metadata::load(&a.dataset)?;
    let mut opts = meta.options.clone();
    opts.resolution = res as usize;
    let held: Vec<_> = meta.images.iter().filter(|r| r.split == Split::HeldOut).skip(a.skip).take(a.images).collect();
    if held.len() < a.images {
        return Err(Error::Invalid(format!(
            "{} has {} held-out images after --skip {}, --images asks for {}",
            a.dataset.display(),
            held.len(),
            a.skip,
            a.images
        )));
    }
    let mut cases = Vec::new();
    for r in &held {
        let photo = load_photo(&a.dataset.join(&r.file), None, Fit::Crop, res, dev)?;
        let novel_poses: Vec<(f64, f64)> =
            (1..=a.views).map(|k| (r.pitch, r.yaw + std::f64::consts::TAU * k as f64 / (a.views + 1) as f64)).collect();
        let (mut novel, mut alpha) = (Vec::new(), Vec::new());
        for p in &novel_poses {
            let out = render_object(&r.shape, &r.appearance, p.0, p.1, &opts)?;
            novel.push(to_tensor(&out.rgb, res, 3) * 2.0 - 1.0);
            alpha.push(to_tensor(&out.alpha, res, 1));
        }
        let novel = Tensor::cat(&novel, 0).to_device(dev);
        let targets = (0..a.views as i64)
            .map(|i| tch::no_grad(|| (perceptual.target)(&novel.narrow(0, i, 1))))
            .collect::<Result<Vec<_>>>()?;
        cases.push(Case {
            file: r.file.clone(),
            photo,
            pose: (r.pitch, r.yaw),
            novel,
            alpha: Tensor::cat(&alpha, 0).to_device(dev),
            novel_poses,
            targets,
            structure: Tensor::from_slice(&structure_classes(&r.shape)?).view([1, 4]),
        });
    }
    Ok(cases)
}

/// The methods: the mean code and the initialiser at the true pose, gdrf-invert's defaults
/// (the initialiser's pose, refined), the paper's 2 000 steps, and with `variants` what
/// the defaults were chosen among.
fn methods(a: &Options, defaults: &InvertConfig, with_init: bool) -> Vec<Method> {
    let m = |name: &str, from, pose, cfg: InvertConfig, objects| Method { name: name.into(), from, pose, cfg, objects };
    let all = a.images;
    let refine = InvertConfig { refine_pose: true, ..defaults.clone() };
    let fixed = InvertConfig { refine_pose: false, ..defaults.clone() };
    let paper = InvertConfig {
        steps: a.reference_steps,
        lr: a.reference_lr,
        ray_fraction: 1.0,
        refine_pose: true,
        ..defaults.clone()
    };
    let mut v = vec![m("mean code, true pose", From::MeanCode, PoseUsed::True, fixed.clone(), all)];
    if with_init {
        v.push(m("initialiser, true pose", From::Initialiser, PoseUsed::True, fixed.clone(), all));
        v.push(m(
            "gdrf-invert: initialiser, its pose refined",
            From::Initialiser,
            PoseUsed::Estimated,
            refine.clone(),
            all,
        ));
        let name = format!("paper: initialiser, its pose refined, {} steps", a.reference_steps);
        v.push(m(&name, From::Initialiser, PoseUsed::Estimated, paper.clone(), a.reference_images.min(all)));
        if a.variants {
            v.push(m("variant: initialiser, its pose fixed", From::Initialiser, PoseUsed::Estimated, fixed, all));
            let quarter = InvertConfig { lr: 0.03, ray_fraction: 0.25, ..refine.clone() };
            v.push(m("variant: a quarter of the rays, lr 0.03", From::Initialiser, PoseUsed::Estimated, quarter, all));
        }
    }
    v.retain(|m| {
        a.only.is_empty() || m.name.starts_with("mean code, true") || a.only.iter().any(|o| m.name.contains(o.as_str()))
    });
    v
}

/// Runs the benchmark and writes its outputs (see `--out`).
pub fn run(a: &Options) -> Result<Report> {
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    if a.images == 0 || a.views == 0 || a.reference_steps == 0 || a.reference_images == 0 {
        return Err(Error::Invalid(
            "--images, --views, --reference-steps and --reference-images must be at least 1".into(),
        ));
    }
    let seeds = &a.noise_seeds;
    if seeds.is_empty() {
        return Err(Error::Invalid("--noise-seeds: give at least one seed".into()));
    }
    if let Some(twice) = seeds.iter().enumerate().find_map(|(i, s)| seeds[..i].contains(s).then_some(s)) {
        return Err(Error::Invalid(format!("--noise-seeds: seed {twice} is given twice")));
    }
    let gen_path = a.generator.clone().unwrap_or_else(crate::paths::shipped_generator);
    let m = load_generator(&gen_path, dev, Kind::Float).with_context(|| format!("loading {}", gen_path.display()))?;
    let (g, cam) = (&m.generator, m.header.camera.clone().unwrap_or_default());
    let id = generator_id(&m.vs, g);
    let chosen = choice::open(&a.init.clone().unwrap_or_default(), "--init", &gen_path, &id, dev)?;
    let learned = InvertConfig::where_learned(&m.header);
    let defaults = InvertConfig {
        resolution: a.resolution.unwrap_or(learned.resolution),
        samples: a.samples.unwrap_or(learned.samples),
        steps: a.steps.unwrap_or(learned.steps),
        ..learned
    };
    defaults.validate()?;
    let res = defaults.resolution;
    let effnet = load_effnet(dev)?;
    let lpips;
    let (scorer, perceptual_name) = match &a.lpips_backbone {
        Some(b) => {
            let heads = crate::paths::repo_root().join("weights/lpips-vgg-heads.safetensors");
            lpips = Lpips::load(LpipsNet::Vgg16, b, &heads, dev)?;
            (Perceptual::lpips(&lpips), "LPIPS (VGG)".to_string())
        }
        None => (Perceptual::effnet(&effnet), "EfficientNet-Lite0 distance, LPIPS-style, not LPIPS".to_string()),
    };
    // The inversion's own perceptual term is gdrf-invert's default, whatever scores it.
    let loss_term = Perceptual::effnet(&effnet);
    let cases = load_cases(a, res, dev, &scorer)?;
    let probe_path =
        a.probe.clone().unwrap_or_else(|| crate::paths::repo_root().join("models/chairs-probe/probe.safetensors"));
    let probe = Probe::load(&probe_path, dev).with_context(|| format!("loading --probe {}", probe_path.display()))?;
    let mut truth_agreement = 0.0;
    for case in &cases {
        let classes = probe.predict(Some(&effnet), &case.novel)?.classes;
        truth_agreement += mean(&classes.eq_tensor(&case.structure.to_device(dev)).to_kind(Kind::Float));
    }
    let truth_agreement = truth_agreement / cases.len() as f64;
    let judge =
        Judge { g, cam: &cam, probe: &probe, effnet: &effnet, perceptual: &scorer, res, samples: defaults.samples };
    let methods = methods(a, &defaults, chosen.init.is_some());
    eprintln!(
        "benchmarking inversion on {} held-out objects of {} (after --skip {}) at {res}², noise seeds {seeds:?}, {} novel views each; {} methods; {}; device {dev:?}, {threads} threads",
        cases.len(),
        a.dataset.display(),
        a.skip,
        a.views,
        methods.len(),
        chosen.said
    );
    let total: usize = methods.iter().map(|m| m.cfg.steps * m.objects).sum::<usize>() * seeds.len();
    let bar = crate::progress::bar(total as u64, "steps", false);
    let mut points = Vec::new();
    let mut figure_rows = Vec::new();
    // The mean code at the true pose, 0 steps, per object: every gain is measured from it.
    let mut baseline: Vec<f64> = Vec::new();
    for method in &methods {
        bar.set_prefix(method.name.clone());
        let checkpoints = checkpoints(method.cfg.steps);
        let n = method.objects;
        let mut cells = vec![vec![vec![Cell::default(); seeds.len()]; n]; checkpoints.len()];
        for (oi, case) in cases.iter().take(n).enumerate() {
            let t0 = std::time::Instant::now();
            let init = (method.from == From::Initialiser).then_some(chosen.init.as_ref()).flatten();
            let known = (method.pose == PoseUsed::True).then_some(case.pose);
            let started = start_for_photo(g, &cam, &case.photo, known, init)?;
            let start_seconds = t0.elapsed().as_secs_f64();
            for (si, &seed) in seeds.iter().enumerate() {
                let cfg = InvertConfig { seed, ..method.cfg.clone() };
                let mut inv = Inverter::new(g, &cam, &case.photo, &started.start, &cfg, Some(&loss_term))?;
                let counted = bar.position();
                let mut seconds = 0.0;
                for (ci, &cp) in checkpoints.iter().enumerate() {
                    while inv.history.len() < cp && !inv.done() {
                        if let Some(l) = inv.step()? {
                            seconds = l.seconds;
                        }
                        bar.set_position(counted + inv.history.len() as u64);
                    }
                    let f = inv.features();
                    let at = f.pose.unwrap_or(started.start.pose);
                    cells[ci][oi][si] = Cell {
                        seconds: seconds + start_seconds,
                        scores: judge.score(&f, case, at)?,
                        pitch_err: (at.0 - case.pose.0).abs().to_degrees(),
                        yaw_err: angle_deg(at.1, case.pose.1),
                    };
                    let last = ci + 1 == checkpoints.len();
                    if last && si == 0 && oi < a.figure_objects && method.name.starts_with("gdrf-invert") {
                        figure_rows.push(figure_row(&judge, &f, case, at)?);
                    }
                }
                bar.set_position(counted + cfg.steps as u64);
            }
        }
        if baseline.is_empty() {
            baseline =
                (0..n).map(|oi| cells[0][oi].iter().map(|c| c.scores[1]).sum::<f64>() / seeds.len() as f64).collect();
        }
        for (ci, &cp) in checkpoints.iter().enumerate() {
            points.push(summarise(method, cp, &cells[ci], &baseline));
        }
        bar.suspend(|| eprintln!("done: {}", method.name));
    }
    bar.finish_and_clear();
    let report = Report {
        generator: crate::paths::shown(&gen_path),
        init: chosen.path.as_deref().map(crate::paths::shown),
        dataset: a.dataset.display().to_string(),
        objects: cases.iter().map(|c| c.file.clone()).collect(),
        skip: a.skip,
        noise_seeds: seeds.clone(),
        views: a.views,
        resolution: res,
        samples: defaults.samples,
        perceptual: perceptual_name,
        device: format!("{dev:?}"),
        threads,
        probe: crate::paths::shown(&probe_path),
        structure_agreement_of_the_ground_truth_views: truth_agreement,
        points,
    };
    report.write(&a.out, &figure_rows)?;
    Ok(report)
}

/// The step budgets scored along a method of `steps` steps.
fn checkpoints(steps: usize) -> Vec<usize> {
    let mut v: Vec<usize> =
        [0.0, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0].iter().map(|f| (f * steps as f64).round() as usize).collect();
    v.dedup();
    v
}

/// The means of one checkpoint over objects and seeds.
fn summarise(m: &Method, steps: usize, cells: &[Vec<Cell>], baseline: &[f64]) -> Point {
    let all: Vec<&Cell> = cells.iter().flatten().collect();
    let avg = |f: &dyn Fn(&Cell) -> f64| all.iter().map(|c| f(c)).sum::<f64>() / all.len() as f64;
    let per_object: Vec<f64> =
        cells.iter().map(|o| o.iter().map(|c| c.scores[1]).sum::<f64>() / o.len() as f64).collect();
    let seeds = cells[0].len();
    let per_seed = (0..seeds).map(|s| cells.iter().map(|o| o[s].scores[1]).sum::<f64>() / cells.len() as f64).collect();
    let gain = per_object.iter().zip(baseline).map(|(p, b)| p - b).sum::<f64>() / per_object.len() as f64;
    let mut yaws: Vec<f64> = all.iter().map(|c| c.yaw_err).collect();
    yaws.sort_by(f64::total_cmp);
    let known = m.pose == PoseUsed::True;
    Point {
        method: m.name.clone(),
        start: format!("{:?}", m.from),
        pose: format!("{:?}", m.pose),
        objects: cells.len(),
        steps,
        seconds: avg(&|c| c.seconds),
        input_psnr: avg(&|c| c.scores[0]),
        novel_psnr: avg(&|c| c.scores[1]),
        novel_gain_db: gain,
        novel_perceptual: avg(&|c| c.scores[2]),
        silhouette_iou: avg(&|c| c.scores[3]),
        structure_agreement: avg(&|c| c.scores[4]),
        pitch_error_deg: if known { f64::NAN } else { avg(&|c| c.pitch_err) },
        yaw_error_deg: if known { f64::NAN } else { avg(&|c| c.yaw_err) },
        median_yaw_error_deg: if known { f64::NAN } else { super::median(&yaws) },
        novel_psnr_per_object: per_object,
        novel_psnr_per_noise_seed: per_seed,
    }
}

/// One row of the figure, `(3, R, 10·R)`: photo | reconstruction | novel views | their
/// ground truth.
fn figure_row(j: &Judge, f: &Features, case: &Case, at: (f64, f64)) -> Result<Tensor> {
    let recon = render_views(j.g, j.cam, f, &[at], j.res, j.samples)?;
    let novel = render_views(j.g, j.cam, f, &case.novel_poses, j.res, j.samples)?;
    let tiles = Tensor::cat(&[case.photo.to_device(recon.device()), recon, novel, case.novel.shallow_clone()], 0);
    Ok(crate::io::grid(&tiles, tiles.size()[0]))
}

impl Report {
    /// The methods in the order they ran.
    fn methods(&self) -> Vec<String> {
        self.points.iter().fold(Vec::new(), |mut v, p| {
            if !v.contains(&p.method) {
                v.push(p.method.clone());
            }
            v
        })
    }

    /// Writes STEM.png, STEM.json, STEM.md and STEM-figure.png, and prints the table.
    fn write(&self, out: &Path, figure_rows: &[Tensor]) -> Result<()> {
        let methods = self.methods();
        let series = |f: &dyn Fn(&Point) -> (f64, f64)| -> Vec<Series> {
            methods
                .iter()
                .map(|m| Series {
                    name: m.clone(),
                    points: self.points.iter().filter(|p| &p.method == m).map(f).collect(),
                })
                .collect()
        };
        let panel = |title: &str, f: &dyn Fn(&Point) -> (f64, f64)| Panel {
            title: title.into(),
            series: series(f),
            log_y: false,
            marks: vec![],
        };
        let panels = [
            panel("novel-view PSNR (dB) vs seconds", &|p| (p.seconds, p.novel_psnr)),
            panel("structure agreement vs seconds", &|p| (p.seconds, p.structure_agreement)),
        ];
        if let Some(dir) = out.parent() {
            std::fs::create_dir_all(dir).map_err(|err| Error::Io { path: dir.to_path_buf(), err })?;
        }
        let stem = out.display().to_string();
        crate::io::save_png(&PathBuf::from(format!("{stem}.png")), &draw_panels(&panels, 2, 480, 300)?)?;
        write_json(&PathBuf::from(format!("{stem}.json")), self)?;
        if !figure_rows.is_empty() {
            let fig = Tensor::cat(figure_rows, 1);
            let big =
                fig.unsqueeze(0).upsample_nearest2d([fig.size()[1] * 3, fig.size()[2] * 3], None, None).squeeze_dim(0);
            crate::io::save_png(&PathBuf::from(format!("{stem}-figure.png")), &crate::io::to_rgb8(&big, false)?)?;
        }
        let md = self.markdown();
        crate::paths::write_atomic(&PathBuf::from(format!("{stem}.md")), md.as_bytes())?;
        print!("{md}");
        let fig = if figure_rows.is_empty() { String::new() } else { format!(", {stem}-figure.png") };
        println!("wrote {stem}.json, {stem}.md, {stem}.png{fig}");
        Ok(())
    }

    /// Each method's last point (and its start), then every point.
    pub fn markdown(&self) -> String {
        let deg = |x: f64| if x.is_nan() { "—".to_string() } else { format!("{x:.1}°") };
        let row = |p: &Point| {
            format!(
                "| {} | {} | {} | {:.1} | {:.2} | {:+.2} | {:.3} | {:.3} | {:.3} | {} / {} ({}) |\n",
                p.method,
                p.objects,
                p.steps,
                p.seconds,
                p.novel_psnr,
                p.novel_gain_db,
                p.novel_perceptual,
                p.silhouette_iou,
                p.structure_agreement,
                deg(p.pitch_error_deg),
                deg(p.yaw_error_deg),
                deg(p.median_yaw_error_deg),
            )
        };
        let head = format!(
            "| method | objects | steps | seconds | novel PSNR | gain over the mean code | perceptual ({}) | silhouette IoU | structure | pose error pitch / yaw (median yaw) |\n|---|---|---|---|---|---|---|---|---|---|\n",
            self.perceptual
        );
        let mut md = format!(
            "{} held-out objects of {} (after the first {}), view 0 inverted, {} novel views each at {}², means over the objects and noise seeds {:?}. The gain is over the mean code at the true pose (0 steps) on the same objects. The probe agrees {:.3} with the ground-truth views themselves.\n\n",
            self.objects.len(),
            self.dataset,
            self.skip,
            self.views,
            self.resolution,
            self.noise_seeds,
            self.structure_agreement_of_the_ground_truth_views
        );
        md += &head;
        for m in self.methods() {
            let mine: Vec<&Point> = self.points.iter().filter(|p| p.method == m).collect();
            if mine[0].method.starts_with("mean code") || mine[0].method.starts_with("gdrf-invert") {
                md += &row(mine[0]).replacen(&mine[0].method, &format!("{} (start)", mine[0].method), 1);
            }
            md += &row(mine[mine.len() - 1]);
        }
        md += "\nEvery point:\n\n";
        md += &head;
        for p in &self.points {
            md += &row(p);
        }
        md
    }
}
