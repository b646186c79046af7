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
use crate::checkpoint::load_generator;
use crate::edit::generator_id;
use crate::error::Context;
use crate::eval::probe::Probe;
use crate::invert::choice::{self, InitChoice};
use crate::invert::framing::Framing;
use crate::invert::{load_effnet, start_for_photo, InvertConfig, Inverter, Perceptual};
use crate::pretrained::effnet::EfficientNetLite0;
use crate::pretrained::lpips::{Lpips, LpipsNet};
use crate::{device, Error, Result};
use serde::Serialize;
use std::path::PathBuf;
use tch::Kind;

mod judge;
mod report;

use judge::{angle_deg, figure_row, load_cases, mean, Case, Cell, Judge};
use report::summarise;
pub use report::{Point, Report};

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
    /// Weight of the silhouette term of every method but the paper's (default:
    /// gdrf-invert's; 0 = off). The photos' silhouettes are their alpha.
    #[arg(long)]
    pub silhouette_weight: Option<f64>,
    /// Photos restyled out of the house style with this seed instead of the dataset's own
    /// (data::synth::restyle: another frame, scale and place, a background that is not
    /// white, no alpha, JPEG), written to STEM-photos/; adds the row "gdrf-invert, the
    /// photo as it is" (centre-cropped, no silhouette, no framing). Choose on one seed,
    /// report on another.
    #[arg(long, value_name = "SEED")]
    pub restyle: Option<u64>,
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
    /// Inverts the photo as it is ([`Case::as_is`]) instead of the prepared one.
    as_is: bool,
    /// How many of the objects it runs on (the first ones).
    objects: usize,
}

/// The methods: the mean code and the initialiser at the true pose, gdrf-invert's defaults
/// (the initialiser's pose, refined), the paper's 2 000 steps, and with `variants` what
/// the defaults were chosen among.
fn methods(a: &Options, defaults: &InvertConfig, with_init: bool) -> Vec<Method> {
    let m = |name: &str, from, pose, cfg: InvertConfig, objects| Method {
        name: name.into(),
        from,
        pose,
        cfg,
        as_is: false,
        objects,
    };
    let all = a.images;
    let refine = InvertConfig { refine_pose: true, ..defaults.clone() };
    let fixed = InvertConfig { refine_pose: false, ..defaults.clone() };
    let paper = InvertConfig {
        steps: a.reference_steps,
        lr: a.reference_lr,
        ray_fraction: 1.0,
        refine_pose: true,
        silhouette_weight: 0.0,
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
        if a.restyle.is_some() {
            let plain = InvertConfig { silhouette_weight: 0.0, ..refine.clone() };
            let name = "gdrf-invert, the photo as it is: centre-cropped, no silhouette";
            v.push(Method { as_is: true, ..m(name, From::Initialiser, PoseUsed::Estimated, plain, all) });
        }
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

impl Options {
    fn check(&self) -> Result<()> {
        if self.images == 0 || self.views == 0 || self.reference_steps == 0 || self.reference_images == 0 {
            return Err(Error::Invalid(
                "--images, --views, --reference-steps and --reference-images must be at least 1".into(),
            ));
        }
        let seeds = &self.noise_seeds;
        if seeds.is_empty() {
            return Err(Error::Invalid("--noise-seeds: give at least one seed".into()));
        }
        if let Some(twice) = seeds.iter().enumerate().find_map(|(i, s)| seeds[..i].contains(s).then_some(s)) {
            return Err(Error::Invalid(format!("--noise-seeds: seed {twice} is given twice")));
        }
        Ok(())
    }

    /// gdrf-invert's defaults where the generator learned, with the resolution, samples and
    /// steps the flags give.
    fn defaults(&self, header: &crate::checkpoint::Header) -> Result<InvertConfig> {
        let learned = InvertConfig::where_learned(header);
        let defaults = InvertConfig {
            resolution: self.resolution.unwrap_or(learned.resolution),
            samples: self.samples.unwrap_or(learned.samples),
            steps: self.steps.unwrap_or(learned.steps),
            silhouette_weight: self.silhouette_weight.unwrap_or(learned.silhouette_weight),
            ..learned
        };
        defaults.validate()?;
        Ok(defaults)
    }
}

/// How often the probe reads the true structure off the objects' own novel views: the
/// ceiling of the structure score.
fn ground_truth_agreement(probe: &Probe, effnet: &EfficientNetLite0, cases: &[Case], dev: tch::Device) -> Result<f64> {
    let mut agreement = 0.0;
    for case in cases {
        let classes = probe.predict(Some(effnet), &case.novel)?.classes;
        agreement += mean(&classes.eq_tensor(&case.structure.to_device(dev)).to_kind(Kind::Float));
    }
    Ok(agreement / cases.len() as f64)
}

/// Runs the benchmark and writes its outputs (see `--out`).
pub fn run(a: &Options) -> Result<Report> {
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    a.check()?;
    let seeds = &a.noise_seeds;
    let gen_path = a.generator.clone().unwrap_or_else(crate::paths::shipped_generator);
    let m = load_generator(&gen_path, dev, Kind::Float).with_context(|| format!("loading {}", gen_path.display()))?;
    let (g, cam) = (&m.generator, m.header.camera.clone().unwrap_or_default());
    let id = generator_id(&m.vs, g);
    let chosen = choice::open(&a.init.clone().unwrap_or_default(), "--init", &gen_path, &id, dev)?;
    let defaults = a.defaults(&m.header)?;
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
    let framing = Framing::beside(&gen_path)?;
    let cases = load_cases(a, res, dev, &scorer, framing.as_ref())?;
    let probe_path =
        a.probe.clone().unwrap_or_else(|| crate::paths::repo_root().join("models/chairs-probe/probe.safetensors"));
    let probe = Probe::load(&probe_path, dev).with_context(|| format!("loading --probe {}", probe_path.display()))?;
    let truth_agreement = ground_truth_agreement(&probe, &effnet, &cases, dev)?;
    let judge =
        Judge { g, cam: &cam, probe: &probe, effnet: &effnet, perceptual: &scorer, res, samples: defaults.samples };
    let methods = methods(a, &defaults, chosen.init.is_some());
    eprintln!(
        "benchmarking inversion on {} held-out objects of {} (after --skip {}) at {res}², noise seeds {seeds:?}, {} novel views each; {} methods; silhouette weight {}; {}; device {dev:?}, {threads} threads",
        cases.len(),
        a.dataset.display(),
        a.skip,
        a.views,
        methods.len(),
        defaults.silhouette_weight,
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
            let (photo, silhouette) = match (&case.as_is, method.as_is) {
                (Some(as_is), true) => (as_is, None),
                _ => (&case.photo, case.silhouette.as_ref()),
            };
            let started = start_for_photo(g, &cam, photo, known, init)?;
            let start_seconds = t0.elapsed().as_secs_f64();
            for (si, &seed) in seeds.iter().enumerate() {
                let cfg = InvertConfig { seed, ..method.cfg.clone() };
                let mut inv = Inverter::new(g, &cam, photo, &started.start, &cfg, Some(&loss_term))?
                    .with_silhouette(silhouette)?;
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
                    if last && si == 0 && oi < a.figure_objects && method.name.starts_with("gdrf-invert:") {
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
        silhouette_weight: defaults.silhouette_weight,
        restyle: a.restyle,
        framing: framing.as_ref().map(|_| crate::paths::shown(&Framing::file_beside(&gen_path))),
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
