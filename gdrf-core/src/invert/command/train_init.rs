//! `gdrf-invert train-init`: the initialiser, trained for a generator, its flags, curve and
//! shipped file.
use crate::checkpoint::load_generator;
use crate::edit::generator_id;
use crate::error::Context;
use crate::invert::init::{self as init_stage, InitConfig};
use crate::invert::InvertConfig;
use crate::io::save_png;
use crate::plot::draw_panels;
use crate::progress;
use crate::{device, Error, Result};
use std::path::PathBuf;
use tch::{Kind, Tensor};

use super::json;

/// The flags of `gdrf-invert train-init`.
#[derive(clap::Args)]
pub struct TrainInitOptions {
    /// Generator checkpoint (.safetensors); default: the shipped models/chairs-campaign.
    #[arg(long, visible_alias = "checkpoint", value_name = "FILE")]
    pub generator: Option<PathBuf>,
    /// The training state to write (weights and optimiser, float32), with OUT.json (the
    /// settings and every evaluation) and OUT.png (the curve).
    #[arg(long, short, default_value = "initialiser-training.safetensors")]
    pub out: PathBuf,
    /// Also write the file to ship: the weights in half precision, without the optimiser
    /// (for the shipped generator: models/chairs-campaign/initialiser.safetensors, which
    /// gdrf-invert and gdrf-edit then use by default).
    #[arg(long, value_name = "FILE")]
    pub ship: Option<PathBuf>,
    /// Continue the training saved in --out.
    #[arg(long, conflicts_with = "warm_from")]
    pub resume: bool,
    /// Start from the weights of this initialiser file instead of random ones, with a new
    /// optimiser: one made for another generator, such as the default generator's before a
    /// new one replaced it (models/chairs-campaign-32/initialiser.safetensors). It needs the
    /// same --backbone and --resolution; the pose reading carries over, so far fewer --steps
    /// are needed.
    #[arg(long, value_name = "FILE")]
    pub warm_from: Option<PathBuf>,
    /// With --warm-from and ResNet-34: train the head alone, the backbone kept as it starts
    /// (its features of every image are taken once, so the steps cost next to nothing). The
    /// shipped file then repeats the backbone bytes of the --warm-from file, so a repository
    /// that holds both grows by the head alone.
    #[arg(long)]
    pub head_only: bool,
    /// Keep the rendered tuples in FILE: read them from it when it holds the same generator's
    /// renders at the same settings, else render them and write it (several trainings on
    /// the same renders then render them once).
    #[arg(long, value_name = "FILE")]
    pub tuples: Option<PathBuf>,
    /// The network that reads the photo: resnet34 (the paper's, trained from scratch) or
    /// effnet-lite0 (ImageNet-pretrained and frozen, with a trained head).
    #[arg(long, value_enum, default_value = "resnet34")]
    pub backbone: init_stage::Backbone,
    /// Generated training tuples (the last --held-out are for validation).
    #[arg(long, default_value_t = InitConfig::default().count)]
    pub count: i64,
    #[arg(long, default_value_t = InitConfig::default().held_out)]
    pub held_out: i64,
    /// Side of the generated images and of F's input. Default: where the generator learned
    /// (the resolution of its last training step, 32 for the shipped model), as gdrf-invert's.
    #[arg(long)]
    pub resolution: Option<i64>,
    /// Samples per ray of the generated images (coarse; as many importance samples).
    /// Default: those of the generator's last training step (12 for the shipped model).
    #[arg(long)]
    pub samples: Option<usize>,
    #[arg(long, default_value_t = InitConfig::default().steps)]
    pub steps: i64,
    #[arg(long, default_value_t = InitConfig::default().batch_size)]
    pub batch_size: i64,
    /// Adam's learning rate, until the first of --lr-drops.
    #[arg(long, default_value_t = InitConfig::default().lr)]
    pub lr: f64,
    /// STEP:LR,…: the learning rate from each STEP on (e.g. 4000:3e-4,6000:1e-4).
    #[arg(long, value_delimiter = ',', value_parser = parse_lr_drop)]
    pub lr_drops: Vec<(i64, f64)>,
    #[arg(long, default_value_t = InitConfig::default().pose_weight)]
    pub pose_weight: f64,
    /// Weight of the raw appearance's error; above 0, F also predicts the appearance, which
    /// then starts the optimisation instead of the mean appearance.
    #[arg(long, default_value_t = InitConfig::default().appearance_weight)]
    pub appearance_weight: f64,
    /// Weight of the paper's re-rendering term (renders every batch again with gradients).
    #[arg(long, default_value_t = InitConfig::default().image_weight)]
    pub image_weight: f64,
    /// A procedural dataset whose training-split images, at their stored poses, teach F to
    /// read real photos' poses (its held-out objects are never read).
    #[arg(long, value_name = "DIR")]
    pub real: Option<PathBuf>,
    /// Weight of the pose error on the --real images.
    #[arg(long, default_value_t = 1.0)]
    pub real_weight: f64,
    /// --real images in each batch.
    #[arg(long, default_value_t = InitConfig::default().real_batch)]
    pub real_batch: i64,
    /// The last this many --real images are validation only.
    #[arg(long, default_value_t = InitConfig::default().real_held_out)]
    pub real_held_out: i64,
    #[arg(long, default_value_t = InitConfig::default().eval_interval)]
    pub eval_interval: i64,
    /// Seed of the initialiser's training: its rendered codes and poses, its initial weights
    /// and its batches.
    #[arg(long, default_value_t = InitConfig::default().seed)]
    pub seed: u64,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    pub device: String,
}

/// One `STEP:LR` of `--lr-drops`.
fn parse_lr_drop(s: &str) -> std::result::Result<(i64, f64), String> {
    let (step, lr) = s.split_once(':').ok_or_else(|| format!("'{s}': expected STEP:LR, e.g. 4000:3e-4"))?;
    let step = step.trim().parse::<i64>().map_err(|e| format!("'{s}': the step: {e}"))?;
    let lr = lr.trim().parse::<f64>().map_err(|e| format!("'{s}': the learning rate: {e}"))?;
    Ok((step, lr))
}

/// Trains the initialiser and writes `--out`, `--out`.json, `--out`.png and `--ship`.
pub fn train_init(a: &TrainInitOptions) -> Result<()> {
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    let gen_path = a.generator.clone().unwrap_or_else(crate::paths::shipped_generator);
    let m = load_generator(&gen_path, dev, Kind::Float)
        .with_context(|| format!("loading --generator {}", gen_path.display()))?;
    let cfg = config_of(a, &InvertConfig::where_learned(&m.header));
    cfg.validate()?;
    if a.head_only && a.warm_from.is_none() && !a.resume {
        return Err(Error::Invalid(
            "--head-only keeps the backbone as it starts, so it needs --warm-from FILE (or --resume of a head-only training)".into(),
        ));
    }
    if a.resume && !a.out.is_file() {
        return Err(Error::Invalid(format!("--resume: {} does not exist", a.out.display())));
    }
    if !a.resume && a.out.exists() {
        return Err(Error::Invalid(format!(
            "--out {} exists; pass --resume to continue it or choose another file",
            a.out.display()
        )));
    }
    let (g, cam) = (&m.generator, m.header.camera.clone().unwrap_or_default());
    let id = generator_id(&m.vs, g);
    let lite0 = match cfg.backbone {
        init_stage::Backbone::EffnetLite0 if !a.resume => {
            Some(init_stage::lite0_weights(&crate::pretrained::effnet::EfficientNetLite0::default_path())?)
        }
        _ => None,
    };
    let bar = |len: i64, task: &'static str, unit: &str| {
        let b = progress::bar(len as u64, unit, false);
        b.set_prefix(task);
        b
    };
    let reals = match &a.real {
        Some(dir) => {
            let b = bar(0, "real images", "images");
            let r = init_stage::load_real_images(dir, cfg.resolution, dev, &mut |e| progress::follow(&b, e))
                .with_context(|| format!("loading --real {}", dir.display()))?;
            b.finish_and_clear();
            Some(r)
        }
        None => None,
    };
    // What is trained, said plainly: a warm start is not "from scratch".
    let network = match (&a.warm_from, cfg.backbone, cfg.head_only) {
        (Some(_), init_stage::Backbone::Resnet34, true) => "ResNet-34's head, its backbone kept".to_string(),
        (Some(_), init_stage::Backbone::Resnet34, false) => "ResNet-34, warm-started".to_string(),
        _ => cfg.backbone.name().to_string(),
    };
    eprintln!(
        "training an initialiser ({network}) for {} on {} generated {}² images ({} held out){}, {} steps of {}; device {dev:?}, {threads} threads",
        gen_path.display(),
        cfg.count,
        cfg.resolution,
        cfg.held_out,
        match (&a.real, &reals) {
            (Some(dir), Some(r)) => format!(
                " and {} training-split images of {} at their poses ({} held out)",
                r.images.size()[0],
                dir.display(),
                cfg.real_held_out
            ),
            _ => String::new(),
        },
        cfg.steps,
        cfg.batch_size
    );
    if let Some(from) = &a.warm_from {
        eprintln!("starting from the weights of {}, with a new optimiser", from.display());
    }
    let b = bar(cfg.count, "rendering", "tuples");
    let t0 = std::time::Instant::now();
    let tuples = tuples_for(a, g, &cam, &id, &cfg, dev, &b)?;
    b.finish_and_clear();
    let generate_s = t0.elapsed().as_secs_f64();
    // Only a frozen backbone takes its features before the first step.
    let features = match cfg.backbone {
        init_stage::Backbone::Resnet34 if !cfg.head_only => progress::bar(0, "images", true),
        _ => bar(cfg.count, "features", "images"),
    };
    let training = bar(cfg.steps, "training", "steps");
    let start = match (&a.warm_from, a.resume) {
        (_, true) => init_stage::Start::Resume,
        (Some(from), false) => init_stage::Start::WarmFrom(from),
        (None, false) => init_stage::Start::Fresh,
    };
    let t1 = std::time::Instant::now();
    let (mut f, evals) =
        init_stage::train(g, &cam, &id, &tuples, reals.as_ref(), lite0, &cfg, &a.out, start, &mut |p| match p {
            init_stage::TrainProgress::Features(e) => progress::follow(&features, e),
            init_stage::TrainProgress::Step(step, ev) => {
                if !features.is_finished() {
                    features.finish_and_clear();
                }
                training.set_position(step as u64);
                if let Some(e) = ev {
                    // Above the bar, and in logs too (a hidden bar's println writes nothing).
                    training.suspend(|| eprintln!("{}", describe_eval(e)));
                }
            }
        })?;
    training.finish_and_clear();
    let train_s = t1.elapsed().as_secs_f64();
    let last = evals.last().expect("at least one evaluation").clone();
    // The curve: the training so far, a resumed run's earlier evaluations included.
    let json_path = PathBuf::from(format!("{}.json", a.out.display()));
    let history = history_of(a.resume, &json_path, &evals);
    // A resumed training keeps saying where its first leg started.
    let warm_from = match &a.warm_from {
        Some(p) => serde_json::json!(crate::paths::shown(p)),
        None if a.resume => std::fs::read_to_string(&json_path)
            .ok()
            .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
            .map_or(serde_json::Value::Null, |v| v["warm_from"].clone()),
        None => serde_json::Value::Null,
    };
    let report = serde_json::json!({
        "generator": crate::paths::shown(&gen_path),
        "generator_id": id,
        "backbone": network,
        "real_images": a.real.as_ref().map(|d| d.display().to_string()),
        "warm_from": warm_from,
        "config": cfg,
        "generate_seconds": generate_s,
        "train_seconds": train_s,
        "device": format!("{dev:?}"),
        "threads": threads,
        "evaluations": history,
    });
    crate::paths::write_atomic(&json_path, json(&report)?.as_bytes())?;
    let png_path = PathBuf::from(format!("{}.png", a.out.display()));
    save_png(&png_path, &draw_panels(&init_curve_panels(&history), 2, 420, 280)?)?;
    if let Some(ship) = &a.ship {
        ship_with_check(&mut f, ship, &id, last.step, &cfg, &tuples, reals.as_ref())?;
    }
    println!(
        "{}; rendering {generate_s:.0} s, training {train_s:.0} s; wrote {}, {} and {}",
        describe_eval(&last),
        a.out.display(),
        json_path.display(),
        png_path.display()
    );
    Ok(())
}

/// One evaluation of the initialiser on a line.
fn describe_eval(e: &init_stage::InitEval) -> String {
    let mut s = format!(
        "step {} ({} images): held-out w_s MSE {:.4} (mean code {:.4}), pose error pitch {:.1}°, yaw {:.1}° (median {:.1}°)",
        e.step,
        e.images_seen,
        e.w_mse,
        e.mean_code_w_mse,
        e.pitch_error_deg,
        e.yaw_error_deg,
        e.median_yaw_error_deg
    );
    if let Some(a) = e.appearance_mse {
        s += &format!(", appearance MSE {a:.4} (mean {:.4})", e.mean_appearance_mse);
    }
    if let (Some(p), Some(y), Some(m)) = (e.real_pitch_error_deg, e.real_yaw_error_deg, e.real_median_yaw_error_deg) {
        s += &format!("; real images: pitch {p:.1}°, yaw {y:.1}° (median {m:.1}°)");
    }
    s
}

/// The initialiser's curve against images seen: the held-out w_s error beside the mean
/// code's, and the pose errors on generated and real images.
fn init_curve_panels(evals: &[serde_json::Value]) -> Vec<crate::plot::Panel> {
    use crate::plot::{Panel, Series};
    let series = |name: &str, key: &str| Series {
        name: name.into(),
        points: evals.iter().filter_map(|e| Some((e["images_seen"].as_f64()?, e[key].as_f64()?))).collect(),
    };
    vec![
        Panel {
            title: "held-out w_s MSE vs images seen".into(),
            series: vec![series("initialiser", "w_mse"), series("mean code", "mean_code_w_mse")],
            log_y: false,
            marks: vec![],
        },
        Panel {
            title: "pose error (deg) vs images seen".into(),
            series: vec![
                series("generated yaw", "yaw_error_deg"),
                series("generated pitch", "pitch_error_deg"),
                series("real yaw", "real_yaw_error_deg"),
                series("real median yaw", "real_median_yaw_error_deg"),
                series("real pitch", "real_pitch_error_deg"),
            ]
            .into_iter()
            .filter(|s| !s.points.is_empty())
            .collect(),
            log_y: false,
            marks: vec![],
        },
    ]
}

/// The initialiser's settings from the flags, at the resolution and samples where the
/// generator learned unless given.
fn config_of(a: &TrainInitOptions, learned: &InvertConfig) -> InitConfig {
    InitConfig {
        backbone: a.backbone,
        resolution: a.resolution.unwrap_or(learned.resolution),
        samples: a.samples.unwrap_or(learned.samples),
        count: a.count,
        held_out: a.held_out,
        batch_size: a.batch_size,
        steps: a.steps,
        lr: a.lr,
        lr_drops: a.lr_drops.clone(),
        pose_weight: a.pose_weight,
        appearance_weight: a.appearance_weight,
        image_weight: a.image_weight,
        real_weight: if a.real.is_some() { a.real_weight } else { 0.0 },
        real_batch: a.real_batch,
        real_held_out: a.real_held_out,
        eval_interval: a.eval_interval,
        seed: a.seed,
        head_only: a.head_only,
        ..Default::default()
    }
}

/// The rendered tuples: from `--tuples` where it holds this generator's at these settings,
/// else rendered (and saved there).
fn tuples_for(
    a: &TrainInitOptions,
    g: &crate::Generator,
    cam: &crate::CameraConfig,
    id: &str,
    cfg: &InitConfig,
    dev: tch::Device,
    b: &indicatif::ProgressBar,
) -> Result<init_stage::Tuples> {
    let cached = match &a.tuples {
        Some(p) if p.is_file() => init_stage::Tuples::load(p, id, cfg, dev)?,
        _ => None,
    };
    Ok(match cached {
        Some(t) => {
            eprintln!("the rendered tuples from {}", a.tuples.as_ref().expect("cached").display());
            t
        }
        None => {
            let t = init_stage::generate(g, cam, cfg, &mut |e| progress::follow(b, e))?;
            if let Some(p) = &a.tuples {
                t.save(p, id, cfg)?;
            }
            t
        }
    })
}

/// The curve's evaluations: a resumed run's earlier ones (from its .json, before this
/// session's first) and this session's.
fn history_of(resume: bool, json_path: &std::path::Path, evals: &[init_stage::InitEval]) -> Vec<serde_json::Value> {
    let mut history: Vec<serde_json::Value> = if resume {
        std::fs::read_to_string(json_path)
            .ok()
            .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
            .and_then(|v| v["evaluations"].as_array().cloned())
            .unwrap_or_default()
            .into_iter()
            .filter(|e| e["step"].as_i64().is_some_and(|s| s < evals[0].step))
            .collect()
    } else {
        Vec::new()
    };
    history.extend(evals.iter().map(|e| serde_json::to_value(e).expect("plain fields")));
    history
}

/// Ships `f` to `ship` in half precision with its check file, checked on held-out inputs:
/// 16 rendered tuples, and 16 real images where it trained on some.
fn ship_with_check(
    f: &mut init_stage::Initialiser,
    ship: &std::path::Path,
    id: &str,
    step: i64,
    cfg: &InitConfig,
    tuples: &init_stage::Tuples,
    reals: Option<&init_stage::RealImages>,
) -> Result<()> {
    let held = tuples.images.narrow(0, cfg.count - cfg.held_out, cfg.held_out.min(16));
    let images = match reals {
        Some(r) if cfg.real_held_out > 0 => {
            let n = r.images.size()[0];
            Tensor::cat(&[held, r.images.narrow(0, n - cfg.real_held_out, cfg.real_held_out.min(16))], 0)
        }
        _ => held,
    };
    init_stage::ship(f, ship, id, step, cfg, &images)?;
    eprintln!(
        "shipped {} (half precision, no optimiser state) and its check {}",
        ship.display(),
        init_stage::check_path(ship).display()
    );
    Ok(())
}
