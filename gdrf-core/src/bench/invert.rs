//! `gdrf-invert bench`: inversion accuracy against wall time on held-out objects of a
//! procedural dataset, whose ground truth renders any object at any pose.
use super::write_json;
use crate::checkpoint::load_generator;
use crate::data::synth::render_object;
use crate::data::{Metadata, Split};
use crate::edit::{generator_id, Features};
use crate::error::Context;
use crate::eval::fidelity::{psnr, ssim};
use crate::eval::probe::{structure_classes, Probe};
use crate::invert::init::Initialiser;
use crate::invert::photo::{load_photo, Fit};
use crate::invert::{load_effnet, render_views, start_for_photo, InvertConfig, Inverter, Perceptual};
use crate::plot::{draw_panels, Panel, Series};
use crate::pretrained::effnet::EfficientNetLite0;
use crate::render::GridChoice;
use crate::{device, CameraConfig, Error, Generator, Result};
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// The flags of `gdrf-invert bench`.
#[derive(clap::Args)]
pub struct Options {
    /// Generator checkpoint; default: the shipped models/chairs-campaign.
    #[arg(long, visible_alias = "checkpoint", value_name = "FILE")]
    pub generator: Option<PathBuf>,
    /// The initialiser (from train-init); without it only the mean-code start is measured.
    #[arg(long, value_name = "FILE")]
    pub init: Option<PathBuf>,
    /// A procedural dataset folder (its held-out objects are inverted).
    #[arg(long, default_value = "data/chairs-64")]
    pub dataset: PathBuf,
    /// Held-out objects to invert.
    #[arg(long, default_value_t = 4)]
    pub images: usize,
    /// Held-out objects passed over before the --images inverted: choose settings on one
    /// set of objects, report on another.
    #[arg(long, default_value_t = 0)]
    pub skip: usize,
    /// Run only the methods whose name contains one of these (e.g. `grid,samples`); the
    /// reference and the defaults always run.
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// Novel views per object (yaw offsets spread over the turn, same pitch).
    #[arg(long, default_value_t = 4)]
    pub views: usize,
    /// Renderer-noise seeds (`gdrf-invert --noise-seed`: the jitter and the ray subsets):
    /// every object is inverted once per seed and every score averaged over all of them.
    /// Inversion is chaotic in such differences (docs/inversion.md), so one seed does not
    /// rank settings.
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub noise_seeds: Vec<u64>,
    /// Steps of the reference optimisation (the first method; the paper's 2 000).
    #[arg(long, default_value_t = 2000)]
    pub reference_steps: usize,
    /// Steps of every other method.
    #[arg(long, default_value_t = 200)]
    pub steps: usize,
    /// Render side during the optimisation and for every comparison.
    #[arg(long, default_value_t = 32)]
    pub resolution: i64,
    #[arg(long, default_value_t = 12)]
    pub samples: usize,
    /// Adam's learning rate of the reference (the plain optimisation).
    #[arg(long, default_value_t = 0.01)]
    pub reference_lr: f64,
    /// Adam's learning rate of every other method.
    #[arg(long, default_value_t = InvertConfig::default().lr)]
    pub lr: f64,
    /// The ground-truth probe (`gdrf-train eval train-probe`) whose structure classes on the novel
    /// views are compared with the objects' own; default: the shipped
    /// models/chairs-probe.
    #[arg(long, value_name = "FILE")]
    pub probe: Option<PathBuf>,
    /// Output stem: STEM.json, STEM.png (novel-view PSNR against seconds), STEM.md.
    #[arg(long, default_value = "docs/bench/invert")]
    pub out: PathBuf,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    pub device: String,
}

/// STEM.json: the run's settings, the initialiser's pose error and every method's points.
#[derive(Serialize)]
pub struct Report {
    /// The generator and the probe as shown in committed figures (relative to the
    /// repository).
    pub generator: String,
    pub init: Option<String>,
    pub dataset: String,
    pub images: usize,
    pub skip: usize,
    pub noise_seeds: Vec<u64>,
    pub views: usize,
    pub steps: usize,
    pub reference_steps: usize,
    pub resolution: i64,
    pub samples: usize,
    pub lr: f64,
    pub reference_lr: f64,
    pub device: String,
    pub threads: usize,
    pub initialiser_pose_error_deg: PoseError,
    pub probe: String,
    /// The probe on the ground-truth novel views themselves: the best agreement it can give.
    pub structure_agreement_of_the_ground_truth_views: f64,
    pub points: Vec<Point>,
}

/// The initialiser's mean pose error in degrees over the objects (none without --init).
#[derive(Serialize)]
pub struct PoseError {
    pub pitch: Option<f64>,
    pub yaw: Option<f64>,
}

/// One measured point of one method.
#[derive(Serialize, Clone)]
pub struct Point {
    pub method: String,
    /// The step budget at this point, and the steps actually run (fewer after an early stop),
    /// averaged over the objects and noise seeds (as is every score below).
    pub steps: usize,
    pub steps_run: f64,
    /// Seconds inside the optimisation's steps (the initialiser's prediction included).
    pub seconds: f64,
    pub input_psnr: f64,
    pub input_ssim: f64,
    pub novel_psnr: f64,
    pub novel_ssim: f64,
    /// Fraction of the probe's structure classes (legs, back, arms, seat) on the novel
    /// views that match the object's true ones.
    pub structure_agreement: f64,
    /// The novel-view PSNR of each object (its mean over the noise seeds), in the order
    /// inverted.
    pub novel_psnr_per_object: Vec<f64>,
    /// The novel-view PSNR of each noise seed (its mean over the objects), in the order of
    /// `--noise-seeds`: how far one draw of the noise moves the score.
    pub novel_psnr_per_noise_seed: Vec<f64>,
}

struct Case {
    photo: Tensor,
    pose: (f64, f64),
    /// `(V, 3, R, R)` ground truth and their poses.
    novel: Tensor,
    novel_poses: Vec<(f64, f64)>,
    /// `(1, 4)` the object's true structure classes.
    structure: Tensor,
}

/// The ground-truth probe and the features it reads.
struct Judge<'a> {
    probe: &'a Probe,
    effnet: &'a EfficientNetLite0,
}

fn to_tensor(rgb: &[f32], res: i64) -> Tensor {
    Tensor::from_slice(rgb).view([res, res, 3]).permute([2, 0, 1]).unsqueeze(0) * 2.0 - 1.0
}

fn mean(v: &Tensor) -> f64 {
    f64::try_from(v.mean(Kind::Double)).unwrap_or(f64::NAN)
}

/// Fidelity of `f` on `case` (input view and novel views) and the probe's structure
/// agreement on the novel views.
fn score(
    g: &Generator,
    cam: &CameraConfig,
    f: &Features,
    case: &Case,
    res: i64,
    n: usize,
    judge: &Judge,
) -> Result<[f64; 5]> {
    let at_input = render_views(g, cam, f, &[case.pose], res, n)?;
    let novel = render_views(g, cam, f, &case.novel_poses, res, n)?;
    let classes = judge.probe.predict(Some(judge.effnet), &novel)?.classes;
    let agree = classes.eq_tensor(&case.structure.to_device(classes.device())).to_kind(Kind::Float);
    Ok([
        mean(&psnr(&at_input, &case.photo)?),
        mean(&ssim(&at_input, &case.photo)?),
        mean(&psnr(&novel, &case.novel)?),
        mean(&ssim(&novel, &case.novel)?),
        mean(&agree),
    ])
}

/// Runs the benchmark and writes STEM.json, STEM.png and STEM.md (STEM: `--out`).
pub fn run(a: &Options) -> Result<Report> {
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    if a.images == 0 || a.views == 0 || a.steps == 0 || a.reference_steps == 0 {
        return Err(Error::Invalid("--images, --views, --steps and --reference-steps must be at least 1".into()));
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
    let init = a.init.as_deref().map(|p| Initialiser::load(p, &id, dev)).transpose()?;
    let meta = Metadata::load(&a.dataset)?;
    let mut opts = meta.options.clone();
    opts.resolution = a.resolution as usize;
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
    let res = a.resolution;
    let mut cases = Vec::new();
    for r in &held {
        let photo = load_photo(&a.dataset.join(&r.file), None, Fit::Crop, res, dev)?;
        let novel_poses: Vec<(f64, f64)> =
            (1..=a.views).map(|k| (r.pitch, r.yaw + std::f64::consts::TAU * k as f64 / (a.views + 1) as f64)).collect();
        let novel = novel_poses
            .iter()
            .map(|p| Ok(to_tensor(&render_object(&r.shape, &r.appearance, p.0, p.1, &opts)?.rgb, res)))
            .collect::<Result<Vec<_>>>()?;
        let structure = Tensor::from_slice(&structure_classes(&r.shape)?).view([1, 4]);
        cases.push(Case {
            photo,
            pose: (r.pitch, r.yaw),
            novel: Tensor::cat(&novel, 0).to_device(dev),
            novel_poses,
            structure,
        });
    }
    let probe_path =
        a.probe.clone().unwrap_or_else(|| crate::paths::repo_root().join("models/chairs-probe/probe.safetensors"));
    let probe = Probe::load(&probe_path, dev).with_context(|| format!("loading --probe {}", probe_path.display()))?;
    let effnet = load_effnet(dev)?;
    let perc = Perceptual::effnet(&effnet);
    let judge = Judge { probe: &probe, effnet: &effnet };
    // The probe on the ground-truth novel views themselves: the best agreement it can give.
    let mut truth_agreement = 0.0;
    for case in &cases {
        let classes = probe.predict(Some(&effnet), &case.novel)?.classes;
        truth_agreement += mean(&classes.eq_tensor(&case.structure.to_device(dev)).to_kind(Kind::Float));
    }
    let truth_agreement = truth_agreement / cases.len() as f64;
    let base = InvertConfig {
        steps: a.steps,
        resolution: res,
        samples: a.samples,
        lr: a.reference_lr,
        coarse_fraction: 0.0,
        patience: 0,
        ray_fraction: 1.0,
        ..Default::default()
    };
    let checkpoints = |steps: usize| -> Vec<usize> {
        let mut v: Vec<usize> =
            [0.0, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0].iter().map(|f| (f * steps as f64).round() as usize).collect();
        v.dedup();
        v
    };
    // (name, uses the initialiser, config); the first is the reference.
    let with_init = init.is_some();
    let tag = if with_init { "initialiser" } else { "mean code" };
    let reference = InvertConfig { steps: a.reference_steps, ..base };
    let mut methods: Vec<(String, bool, InvertConfig)> =
        vec![(format!("{tag}, {} steps, lr {}, all rays", a.reference_steps, a.reference_lr), with_init, reference)];
    // The defaults, and each speed option turned off or on against them.
    let defaults = InvertConfig { resolution: res, samples: a.samples, lr: a.lr, steps: a.steps, ..Default::default() };
    let d = defaults.clone();
    let defaults_name = format!("{tag}, defaults");
    methods.push((defaults_name.clone(), with_init, d.clone()));
    if with_init {
        methods.push(("mean code, defaults".to_string(), false, d.clone()));
    }
    methods.push((format!("{tag}, defaults, all rays"), with_init, InvertConfig { ray_fraction: 1.0, ..d.clone() }));
    methods.push((
        format!("{tag}, defaults, coarse half"),
        with_init,
        InvertConfig { coarse_fraction: 0.5, ..d.clone() },
    ));
    methods.push((format!("{tag}, defaults, patience 20"), with_init, InvertConfig { patience: 20, ..d.clone() }));
    methods.push((format!("{tag}, defaults, bf16"), with_init, InvertConfig { bf16: true, ..d.clone() }));
    // The occupancy grid of the current shape: sampling only its occupied cells, at the
    // size `--grid auto` picks and at both sizes it can pick; and the first-to-last
    // interval (threshold 5, the best of the CLI measurements in docs/inversion.md), alone
    // and with half the samples per ray.
    let auto = d.clone().with_grid(GridChoice::Auto, true);
    let picked = if auto.grid == 0 { "none at this size".to_string() } else { format!("{}³ cells", auto.grid) };
    methods.push((format!("{tag}, defaults, grid auto ({picked})"), with_init, auto));
    for cells in [32, 64] {
        let c = d.clone().with_grid(GridChoice::Cells(cells), true);
        methods.push((format!("{tag}, defaults, grid {cells} cells"), with_init, c));
    }
    let grid = InvertConfig { grid: 32, grid_threshold: 5.0, ..d.clone() };
    let half = (a.samples / 2).max(3);
    methods.push((format!("{tag}, defaults, grid 32 (threshold 5)"), with_init, grid.clone()));
    methods.push((
        format!("{tag}, defaults, grid 32 (threshold 5), {half} samples"),
        with_init,
        InvertConfig { samples: half, ..grid },
    ));
    methods.push((format!("{tag}, defaults, {half} samples"), with_init, InvertConfig { samples: half, ..d }));
    // The reference and the defaults (the baseline of every speed option) always run.
    let always = [methods[0].0.clone(), defaults_name];
    methods.retain(|(name, ..)| {
        always.contains(name) || a.only.is_empty() || a.only.iter().any(|o| name.contains(o.as_str()))
    });
    eprintln!(
        "benchmarking inversion on {} held-out objects of {} at {res}², {} noise seed(s), {} novel views each, {} steps; {} methods; device {dev:?}, {threads} threads",
        cases.len(),
        a.dataset.display(),
        seeds.len(),
        a.views,
        a.steps,
        methods.len()
    );
    let mut points: Vec<Point> = Vec::new();
    let mut pose_errors = Vec::new();
    // Optimisation steps over every method and object (the reference's dominate).
    let total: usize = methods.iter().map(|(_, _, c)| c.steps).sum();
    let bar = ProgressBar::new((total * cases.len() * seeds.len()) as u64).with_style(
        ProgressStyle::with_template("{bar:30} {pos}/{len} steps [{elapsed_precise}<{eta_precise}] {msg}")
            .expect("valid template"),
    );
    for (name, use_init, cfg) in &methods {
        bar.set_message(name.clone());
        // Sums over the cases and noise seeds, per checkpoint; novel-view PSNR per
        // (checkpoint, object, seed).
        let checkpoints = checkpoints(cfg.steps);
        let mut sums = vec![[0.0f64; 7]; checkpoints.len()];
        let mut novel = vec![vec![vec![0.0f64; seeds.len()]; cases.len()]; checkpoints.len()];
        for (oi, case) in cases.iter().enumerate() {
            // At the known pose; the initialiser's own estimate of it is only scored. The
            // start does not depend on the noise seed: found once, its time counted in each
            // seed's run.
            let t0 = std::time::Instant::now();
            let init = if *use_init { init.as_ref() } else { None };
            let started = start_for_photo(g, &cam, &case.photo, Some(case.pose), init)?;
            let start = started.start;
            if let Some(p) = started.predicted_pose {
                let d = p.1 - case.pose.1;
                let err = ((p.0 - case.pose.0).abs().to_degrees(), d.sin().atan2(d.cos()).abs().to_degrees());
                if pose_errors.len() < cases.len() {
                    pose_errors.push(err);
                }
            }
            let start_seconds = t0.elapsed().as_secs_f64();
            for (si, &seed) in seeds.iter().enumerate() {
                let cfg = InvertConfig { seed, ..cfg.clone() };
                let mut inv = Inverter::new(g, &cam, &case.photo, &start, &cfg, Some(&perc))?;
                let mut last = (0usize, 0.0f64);
                let counted = bar.position();
                for (ci, &cp) in checkpoints.iter().enumerate() {
                    while inv.history.len() < cp && !inv.done() {
                        if let Some(l) = inv.step()? {
                            last = (l.step + 1, l.seconds);
                        }
                        bar.set_position(counted + inv.history.len() as u64);
                    }
                    // Steps an early stop skips count as done.
                    bar.set_position(counted + cp as u64);
                    let s = score(g, &cam, &inv.features(), case, res, a.samples, &judge)?;
                    let row = &mut sums[ci];
                    row[0] += last.1 + start_seconds;
                    for k in 0..5 {
                        row[k + 1] += s[k];
                    }
                    row[6] += last.0 as f64;
                    novel[ci][oi][si] = s[2];
                }
            }
        }
        let n = (cases.len() * seeds.len()) as f64;
        for (ci, &cp) in checkpoints.iter().enumerate() {
            let r = &sums[ci];
            points.push(Point {
                method: name.clone(),
                steps: cp,
                steps_run: r[6] / n,
                seconds: r[0] / n,
                input_psnr: r[1] / n,
                input_ssim: r[2] / n,
                novel_psnr: r[3] / n,
                novel_ssim: r[4] / n,
                structure_agreement: r[5] / n,
                novel_psnr_per_object: novel[ci].iter().map(|o| o.iter().sum::<f64>() / seeds.len() as f64).collect(),
                novel_psnr_per_noise_seed: (0..seeds.len())
                    .map(|si| novel[ci].iter().map(|o| o[si]).sum::<f64>() / cases.len() as f64)
                    .collect(),
            });
        }
        // Above the bar, and in logs too (a hidden bar's println writes nothing).
        bar.suspend(|| eprintln!("done: {name}"));
    }
    bar.finish_and_clear();
    let mean_pose = |k: usize| {
        if pose_errors.is_empty() {
            None
        } else {
            Some(pose_errors.iter().map(|e| if k == 0 { e.0 } else { e.1 }).sum::<f64>() / pose_errors.len() as f64)
        }
    };
    let report = Report {
        generator: crate::paths::shown(&gen_path),
        init: a.init.as_deref().map(crate::paths::shown),
        dataset: a.dataset.display().to_string(),
        images: a.images,
        skip: a.skip,
        noise_seeds: seeds.clone(),
        views: a.views,
        steps: a.steps,
        reference_steps: a.reference_steps,
        resolution: a.resolution,
        samples: a.samples,
        lr: a.lr,
        reference_lr: a.reference_lr,
        device: format!("{dev:?}"),
        threads,
        initialiser_pose_error_deg: PoseError { pitch: mean_pose(0), yaw: mean_pose(1) },
        probe: crate::paths::shown(&probe_path),
        structure_agreement_of_the_ground_truth_views: truth_agreement,
        points,
    };
    report.write(&a.out)?;
    Ok(report)
}

impl Report {
    /// The methods in the order they ran (the reference first).
    fn methods(&self) -> Vec<String> {
        self.points.iter().fold(Vec::new(), |mut v, p| {
            if !v.contains(&p.method) {
                v.push(p.method.clone());
            }
            v
        })
    }

    /// Writes STEM.png (PSNR against seconds), STEM.json and STEM.md, and prints the table.
    fn write(&self, out: &Path) -> Result<()> {
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
        let panels = [
            Panel {
                title: "novel-view PSNR vs seconds".into(),
                series: series(&|p| (p.seconds, p.novel_psnr)),
                log_y: false,
                marks: vec![],
            },
            Panel {
                title: "input-view PSNR vs seconds".into(),
                series: series(&|p| (p.seconds, p.input_psnr)),
                log_y: false,
                marks: vec![],
            },
        ];
        if let Some(dir) = out.parent() {
            std::fs::create_dir_all(dir).ok();
        }
        let stem = out.display().to_string();
        crate::io::save_png(&PathBuf::from(format!("{stem}.png")), &draw_panels(&panels, 2, 420, 280))?;
        write_json(&PathBuf::from(format!("{stem}.json")), self)?;
        let md = self.markdown();
        crate::paths::write_atomic(&PathBuf::from(format!("{stem}.md")), md.as_bytes())?;
        print!("{md}");
        println!("wrote {stem}.json, {stem}.png, {stem}.md");
        Ok(())
    }

    /// Every point; then, against the reference (the first method), the first point of each
    /// method reaching 95 % of the reference's novel-view PSNR gain.
    pub fn markdown(&self) -> String {
        let (points, methods) = (&self.points, self.methods());
        let list = |v: &[f64]| v.iter().map(|x| format!("{x:.2}")).collect::<Vec<_>>().join(", ");
        let mut md = format!(
            "Scores are means over {} held-out object(s) × noise seed(s) {:?}.\n\n| method | steps (run) | seconds | input PSNR | input SSIM | novel PSNR | novel SSIM | structure agreement | novel PSNR per object | novel PSNR per noise seed |\n|---|---|---|---|---|---|---|---|---|---|\n",
            self.images, self.noise_seeds
        );
        for p in points {
            md += &format!(
                "| {} | {} ({:.0}) | {:.2} | {:.2} | {:.3} | {:.2} | {:.3} | {:.3} | {} | {} |\n",
                p.method,
                p.steps,
                p.steps_run,
                p.seconds,
                p.input_psnr,
                p.input_ssim,
                p.novel_psnr,
                p.novel_ssim,
                p.structure_agreement,
                list(&p.novel_psnr_per_object),
                list(&p.novel_psnr_per_noise_seed)
            );
        }
        // Against the reference (the first method): the novel-view PSNR gain of its last
        // point over its start, and the first point of each method reaching 95 % of that gain.
        let reference: Vec<&Point> = points.iter().filter(|p| p.method == methods[0]).collect();
        let (r0, r1) = (reference[0], reference[reference.len() - 1]);
        let gain = r1.novel_psnr - r0.novel_psnr;
        md += &format!(
            "\nReference: {}, novel-view PSNR {:.2} → {:.2} dB (gain {gain:.2} dB) in {:.1} s.\n\n| method | first point with ≥ 95 % of the gain | seconds | fraction of the reference's time |\n|---|---|---|---|\n",
            methods[0], r0.novel_psnr, r1.novel_psnr, r1.seconds
        );
        for m in &methods {
            let hit = points.iter().filter(|p| &p.method == m).find(|p| p.novel_psnr - r0.novel_psnr >= 0.95 * gain);
            md += &match hit {
                Some(p) => format!("| {m} | {} steps | {:.2} | {:.3} |\n", p.steps, p.seconds, p.seconds / r1.seconds),
                None => format!("| {m} | not reached | — | — |\n"),
            };
        }
        md += &format!(
            "\nStructure agreement: the fraction of the probe's structure classes (legs, back, arms, seat) on the novel views that match the object's own; on the ground-truth views themselves the probe agrees {:.3}.\n",
            self.structure_agreement_of_the_ground_truth_views
        );
        md
    }
}
