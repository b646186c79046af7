//! `gdrf-invert PHOTO`: a photo into shape and appearance features, its flags and outputs.
use crate::checkpoint::load_generator;
use crate::config::CameraPreset;
use crate::edit::generator_id;
use crate::edit::view::GridFlags;
use crate::error::Context;
use crate::eval::fidelity::psnr_all;
use crate::invert::choice::{self, describe_pose, InitChoice, RefinePose};
use crate::invert::framing::{Framing, FRAMING_FILE};
use crate::invert::photo::{prepare_photo, Fit};
use crate::invert::{
    invert_photo, load_effnet, loss_panels, parse_pose_degrees, render_orbit, render_views, start_for_photo,
    InvertConfig, Perceptual, PhotoStart, PoseFrom, StepLog,
};
use crate::io::{save_gif, save_png, to_rgb8};
use crate::plot::draw_panels;
use crate::pretrained::lpips::{Lpips, LpipsNet};
use crate::progress;
use crate::render::GridChoice;
use crate::{device, Error, Result};
use std::path::PathBuf;
use tch::{Kind, Tensor};

use super::json;

/// The flags of `gdrf-invert PHOTO`.
#[derive(clap::Args)]
pub struct Options {
    /// The photo: PNG or JPEG, any size. Its object is found (from --mask, its alpha
    /// channel, or a uniform background on its border, which becomes white), and framed as
    /// the training images frame theirs (see --fit); the first lines say what was done.
    #[arg(required = true)]
    pub photo: Option<PathBuf>,
    /// Generator checkpoint (.safetensors); default: the shipped models/chairs-campaign.
    #[arg(long, visible_alias = "checkpoint", value_name = "FILE")]
    pub generator: Option<PathBuf>,
    /// The initialiser (from `gdrf-invert train-init`): w_s (and the appearance, where it
    /// predicts one) starts at its prediction, and its estimate of the pose is used when
    /// --pose is not given. Default: initialiser.safetensors beside the generator (shipped
    /// with models/chairs-campaign); `none`: w_s starts at the mean code's (the paper's
    /// ablation), as it does for a generator without one.
    #[arg(long, value_name = "FILE|none")]
    pub init: Option<InitChoice>,
    /// Camera pose of the photo as PITCH,YAW in degrees (pitch from the +y axis, as
    /// gdrf-edit's --pitch/--yaw); it overrides the initialiser's estimate. Default: the
    /// initialiser's estimate, else the camera's mean pose.
    #[arg(long, value_name = "PITCH,YAW", allow_hyphen_values = true)]
    pub pose: Option<String>,
    /// Camera preset (chair, car, carla: field of view, ray range, mean pitch) instead of the
    /// camera stored with the generator, as gdrf-edit's --camera.
    #[arg(long, value_enum)]
    pub camera: Option<CameraPreset>,
    /// A mask image of the photo's size: white pixels are the object, black ones become
    /// background (white). It overrides the alpha channel and the background found on the
    /// border, for the framing and the silhouette.
    #[arg(long, value_name = "FILE")]
    pub mask: Option<PathBuf>,
    /// How the photo becomes the square image compared with renders: auto (the object
    /// moved and scaled, by cropping or padding, to the nearest placement that the
    /// training images' objects have, per framing.json beside the generator; a photo
    /// already so framed, or without a silhouette, is centre-cropped), crop (the centred
    /// square) or pad (white borders to a square).
    #[arg(long, default_value = "auto")]
    pub fit: Fit,
    /// Optimisation steps at most. `--steps 2000` is the paper's setting: 2 000 Adam steps
    /// of w_s, γ_a and β_a (and of the pose, when it was estimated) through all rays at lr
    /// 0.01, the reference of `gdrf-invert bench`. The default is the same optimisation cut
    /// short: it keeps ≥ 95 % of those 2 000 steps' novel-view gain (the novel views peak
    /// near 50 steps, then the features overfit the photo's view), chosen on objects the
    /// benchmark does not report (docs/inversion.md).
    #[arg(long, default_value_t = InvertConfig::default().steps)]
    pub steps: usize,
    /// Adam's learning rate (the paper's 0.01).
    #[arg(long, default_value_t = InvertConfig::default().lr)]
    pub lr: f64,
    /// Side of the renders compared with the photo. Default: the resolution the generator
    /// was last trained at, as its header records (32 for the shipped models), else 64.
    #[arg(long)]
    pub resolution: Option<i64>,
    /// Coarse samples per ray during the optimisation (the importance pass adds as many).
    /// Default: those of the generator's last training step, as its header records (12 for
    /// the shipped models), else 24.
    #[arg(long)]
    pub samples: Option<usize>,
    /// Perceptual term: effnet (EfficientNet-Lite0 distance, offline default), lpips-vgg or
    /// lpips-alex (real LPIPS; needs --lpips-backbone), or none.
    #[arg(long, default_value = "effnet", value_parser = ["effnet", "lpips-vgg", "lpips-alex", "none"])]
    pub perceptual: String,
    /// The LPIPS backbone file (scripts/export_lpips_backbone.py writes it).
    #[arg(long, value_name = "FILE")]
    pub lpips_backbone: Option<PathBuf>,
    /// Weights of the loss terms.
    #[arg(long, default_value_t = InvertConfig::default().mse_weight)]
    pub mse_weight: f64,
    #[arg(long, default_value_t = InvertConfig::default().perceptual_weight)]
    pub perceptual_weight: f64,
    /// Weight of the silhouette term, mean (opacity − silhouette)², where the photo has a
    /// silhouette (0 = off, the paper's optimisation).
    #[arg(long, default_value_t = InvertConfig::default().silhouette_weight)]
    pub silhouette_weight: f64,
    #[arg(long, default_value_t = InvertConfig::default().prior_shape)]
    pub prior_shape: f64,
    #[arg(long, default_value_t = InvertConfig::default().prior_appearance)]
    pub prior_appearance: f64,
    /// Fraction of the rays whose gradients are taken each step (1 = all, the paper's; 0.25
    /// makes a step about 1.5× cheaper and gained less per second from the initialiser's start).
    #[arg(long, default_value_t = InvertConfig::default().ray_fraction)]
    pub ray_fraction: f64,
    /// Fraction of the steps, from the start, compared at half resolution.
    #[arg(long, default_value_t = InvertConfig::default().coarse_fraction)]
    pub coarse_fraction: f64,
    /// Stop after this many steps without a relative improvement of 1e-3 (0 = never).
    #[arg(long, default_value_t = InvertConfig::default().patience)]
    pub patience: usize,
    /// Run the generator's hidden layers in bfloat16 (integration and the features stay
    /// float32): faster on GPUs and on CPUs with bfloat16 instructions (AVX512-BF16, AMX),
    /// slower elsewhere. See `gdrf-invert bench`.
    #[arg(long)]
    pub bf16: bool,
    /// Optimise the camera pose along with the features: auto (when the initialiser
    /// estimated it), on (`--refine-pose` alone: from --pose or the camera's mean pose too)
    /// or off.
    #[arg(long, value_enum, num_args = 0..=1, default_value = "auto", default_missing_value = "on")]
    pub refine_pose: RefinePose,
    /// Adam's learning rate of the refined pose, in degrees per step.
    #[arg(long, default_value_t = InvertConfig::default().pose_lr.to_degrees())]
    pub pose_lr: f64,
    /// Occupancy grid of the current shape, rebuilt from w_s every --grid-refresh steps:
    /// `auto` builds one where it pays, as gdrf-edit's --grid does, counting the samples
    /// one grid serves (--grid-refresh steps × pixels × samples per ray): a 32³ grid from
    /// 100 000, a 64³ one from 1 000 000, sampling only its occupied cells. `off` (or 0)
    /// builds none; a number is the cells per side, each ray sampled between its first and
    /// last occupied cell (only in the occupied cells with --grid-cells).
    #[arg(long, default_value = "off")]
    pub grid: GridChoice,
    /// With a grid size: sample only the occupied cells along each ray (empty stretches
    /// between them count as empty space). `auto` always does.
    #[arg(long)]
    pub grid_cells: bool,
    /// Steps between rebuilds of the occupancy grid (--grid).
    #[arg(long, default_value_t = InvertConfig::default().grid_refresh)]
    pub grid_refresh: usize,
    /// Density softplus(σ) under which a grid cell counts as empty (--grid).
    #[arg(long, default_value_t = InvertConfig::default().grid_threshold)]
    pub grid_threshold: f64,
    /// Views of the novel-view orbit (turntable at the photo's pitch); 0 = none.
    #[arg(long, default_value_t = 24)]
    pub orbit: usize,
    /// Side of the orbit's and the reconstruction's renders (default: --resolution).
    #[arg(long)]
    pub render_resolution: Option<i64>,
    /// Seed of the renderer noise and ray subsets (gdrf-edit's --noise-seed; --seed is the
    /// same flag, its older name).
    #[arg(long, alias = "seed", default_value_t = 0)]
    pub noise_seed: u64,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    pub device: String,
    /// Output folder.
    #[arg(long, short, default_value = "inversion")]
    pub out: PathBuf,
    /// Write into a folder that already holds files.
    #[arg(long)]
    pub force: bool,
    /// No progress bars, in this command and every subcommand (`train-init --quiet`,
    /// `bench --quiet`), e.g. for logs.
    #[arg(long, global = true)]
    pub quiet: bool,
}

/// Inverts the photo and writes into `--out` what the command's help lists (features,
/// images, orbit, loss plot, invert.json).
pub fn run(a: &Options) -> Result<()> {
    let photo_path = a.photo.clone().expect("clap requires the photo");
    if !(a.pose_lr > 0.0 && a.pose_lr.is_finite()) {
        return Err(Error::Invalid(format!("--pose-lr {}: expected a positive number of degrees per step", a.pose_lr)));
    }
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    let gen_path = a.generator.clone().unwrap_or_else(crate::paths::shipped_generator);
    let m = load_generator(&gen_path, dev, Kind::Float)
        .with_context(|| format!("loading --generator {}", gen_path.display()))?;
    let (cfg, said) = settings(a, &m.header)?;
    let (resolution, samples) = (cfg.resolution, cfg.samples);
    let view_res = a.render_resolution.unwrap_or(resolution);
    if !(4..=1024).contains(&view_res) {
        return Err(Error::Invalid(format!("--render-resolution {view_res}: expected 4 to 1024")));
    }
    let pose = a.pose.as_deref().map(|p| parse_pose_degrees(p, "--pose")).transpose()?;
    let cam = match &a.camera {
        Some(preset) => preset.camera(),
        None => m.header.camera.clone().unwrap_or_default(),
    };
    let g = &m.generator;
    let id = generator_id(&m.vs, g);
    // Read the photo before anything is written, so a bad one leaves no folder behind.
    let framing = Framing::beside(&gen_path)?;
    let prepared = prepare_photo(&photo_path, a.mask.as_deref(), a.fit, framing.as_ref(), resolution, dev)?;
    let photo = prepared.rgb.shallow_clone();
    let chosen = choice::open(&a.init.clone().unwrap_or_default(), "--init", &gen_path, &id, dev)?;
    crate::io::output_dir(&a.out, a.force, "--out")?;

    let PhotoStart { start, pose_from, predicted_pose } = start_for_photo(g, &cam, &photo, pose, chosen.init.as_ref())?;
    let pose = start.pose;
    let cfg = InvertConfig { refine_pose: a.refine_pose.resolve(pose_from), ..cfg };
    eprintln!("{}", prepared.describe());
    if framing.is_none() && a.fit == Fit::Auto && prepared.object.is_some() {
        eprintln!(
            "warning: no {FRAMING_FILE} beside {}, so the photo is centre-cropped, not framed (gdrf-invert framing --dataset DIR writes one)",
            gen_path.display()
        );
    }
    for w in &prepared.warnings {
        eprintln!("warning: {w}");
    }
    let silhouette_said = match (&prepared.silhouette, cfg.silhouette_weight > 0.0) {
        (Some(_), true) => format!("silhouette term weight {}", cfg.silhouette_weight),
        (Some(_), false) => "silhouette term off".to_string(),
        (None, _) => "no silhouette term".to_string(),
    };
    eprintln!("{}", chosen.said);
    eprintln!("{}", describe_pose(pose, pose_from, false));
    if let (Some(p), PoseFrom::Given) = (predicted_pose, pose_from) {
        eprintln!("(the initialiser's estimate: pitch {:.1}°, yaw {:.1}°)", p.0.to_degrees(), p.1.to_degrees());
    }
    let nets = PerceptualNet::load(a, dev)?;
    let perc = nets.as_ref().map(PerceptualNet::term);
    let perc_name = perc.as_ref().map(|p| p.name.clone()).unwrap_or_else(|| "none".into());
    let grid = match (cfg.grid, cfg.grid_cells) {
        (0, _) => String::new(),
        (g, cells) => format!(
            ", in a {g}³ occupancy grid ({}, rebuilt every {} steps)",
            if cells { "its occupied cells" } else { "first to last occupied cell" },
            cfg.grid_refresh
        ),
    };
    eprintln!(
        "inverting {} at {}²{said} with {} + {} samples per ray{grid}, {} steps at most, perceptual term: {perc_name}, {silhouette_said}; device {dev:?}, {threads} threads",
        photo_path.display(),
        resolution,
        samples,
        samples,
        a.steps
    );
    let bar = progress::bar(cfg.steps as u64, "steps", a.quiet);
    bar.set_prefix("inverting");
    let inv = invert_photo(g, &cam, &prepared, &start, &cfg, perc.as_ref(), &mut |l: &StepLog| {
        bar.set_position(l.step as u64 + 1);
        bar.set_message(format!("loss {:.4} (mse {:.4}, perceptual {:.4})", l.loss, l.mse, l.perceptual));
    })?;
    bar.finish_and_clear();
    let seconds = inv.history.last().map(|l| l.seconds).unwrap_or(0.0);
    // The pose the features were fitted at (refined, with --refine-pose).
    let start_pose = pose;
    let pose = inv.features.pose.unwrap_or(pose);
    if cfg.refine_pose {
        eprintln!("{}", describe_pose(pose, pose_from, true));
    }

    // Outputs.
    inv.features.save(&a.out.join("features.safetensors"), &id)?;
    let psnr = write_images(a, g, &cam, &inv, &start, (start_pose, pose), &photo, view_res, samples)?;
    let report = serde_json::json!({
        "photo": photo_path.display().to_string(),
        "framing": {
            "silhouette_from": prepared.from,
            "photo_size": [prepared.size.0, prepared.size.1],
            "object_box": prepared.object,
            "window": prepared.window,
            "reframed": prepared.reframed,
            "framing_file": framing.as_ref().map(|_| crate::paths::shown(&Framing::file_beside(&gen_path))),
            "warnings": prepared.warnings,
        },
        "init": chosen.path.as_deref().map(crate::paths::shown),
        "pose_from": pose_from.name(),
        "predicted_pose_deg": predicted_pose.map(|p| [p.0.to_degrees(), p.1.to_degrees()]),
        "generator": gen_path.display().to_string(),
        "generator_id": id,
        "camera": cam,
        "pose_deg": [pose.0.to_degrees(), pose.1.to_degrees()],
        "start_pose_deg": [start_pose.0.to_degrees(), start_pose.1.to_degrees()],
        "refine_pose": cfg.refine_pose,
        "perceptual": perc_name,
        "config": cfg,
        "steps_run": inv.history.len(),
        "stopped_early": inv.stopped_early,
        "seconds": seconds,
        "reconstruction_psnr_db": psnr,
        "device": format!("{dev:?}"),
        "threads": threads,
        "history": inv.history,
    });
    crate::paths::write_atomic(&a.out.join("invert.json"), json(&report)?.as_bytes())?;
    println!(
        "{} steps in {seconds:.1} s{}; reconstruction PSNR {psnr:.2} dB at {view_res}²; wrote {}/features.safetensors, reconstruction.png, compare.png{}, loss.png, invert.json",
        inv.history.len(),
        if inv.stopped_early { " (stopped early)" } else { "" },
        a.out.display(),
        if a.orbit > 0 { ", orbit.gif" } else { "" }
    );
    Ok(())
}

/// The inversion's settings from the flags, at the resolution and samples where the
/// generator learned unless given; and the words that say so.
fn settings(a: &Options, header: &crate::checkpoint::Header) -> Result<(InvertConfig, &'static str)> {
    let learned = InvertConfig::where_learned(header);
    let (resolution, samples) = (a.resolution.unwrap_or(learned.resolution), a.samples.unwrap_or(learned.samples));
    let said = if a.resolution.is_none() && header.trained_resolution().is_some() {
        " (where the generator learned)"
    } else {
        ""
    };
    let cfg = InvertConfig {
        steps: a.steps,
        lr: a.lr,
        resolution,
        samples,
        mse_weight: a.mse_weight,
        perceptual_weight: if a.perceptual == "none" { 0.0 } else { a.perceptual_weight },
        silhouette_weight: a.silhouette_weight,
        prior_shape: a.prior_shape,
        prior_appearance: a.prior_appearance,
        ray_fraction: a.ray_fraction,
        coarse_fraction: a.coarse_fraction,
        patience: a.patience,
        seed: a.noise_seed,
        bf16: a.bf16,
        pose_lr: a.pose_lr.to_radians(),
        grid_refresh: a.grid_refresh,
        grid_threshold: a.grid_threshold,
        ..Default::default()
    };
    // gdrf-edit's grid flags, checked by the same rules.
    GridFlags { grid: a.grid, grid_threshold: a.grid_threshold, grid_cells: a.grid_cells }.check()?;
    let cfg = cfg.with_grid(a.grid, a.grid_cells);
    cfg.validate()?;
    Ok((cfg, said))
}

/// The perceptual term's network: EfficientNet-Lite0, or LPIPS on the user's backbone.
enum PerceptualNet {
    Effnet(Box<crate::pretrained::effnet::EfficientNetLite0>),
    Lpips(Lpips),
}

impl PerceptualNet {
    /// The network `--perceptual` names, none for `none`.
    fn load(a: &Options, dev: tch::Device) -> Result<Option<Self>> {
        Ok(Some(match a.perceptual.as_str() {
            "none" => return Ok(None),
            "effnet" => PerceptualNet::Effnet(Box::new(load_effnet(dev)?)),
            name => {
                let net = if name == "lpips-vgg" { LpipsNet::Vgg16 } else { LpipsNet::Alex };
                let Some(backbone) = &a.lpips_backbone else {
                    return Err(Error::Invalid(format!(
                        "--perceptual {name} needs --lpips-backbone FILE (scripts/export_lpips_backbone.py writes it)"
                    )));
                };
                let heads = crate::paths::repo_root().join(format!("weights/lpips-{}-heads.safetensors", net.name()));
                PerceptualNet::Lpips(Lpips::load(net, backbone, &heads, dev)?)
            }
        }))
    }

    fn term(&self) -> Perceptual<'_> {
        match self {
            PerceptualNet::Effnet(n) => Perceptual::effnet(n),
            PerceptualNet::Lpips(n) => Perceptual::lpips(n),
        }
    }
}

/// input.png, reconstruction.png, compare.png (photo, start, result), the orbit and
/// loss.png; returns the reconstruction's PSNR against the photo at `view_res`.
#[allow(clippy::too_many_arguments)]
fn write_images(
    a: &Options,
    g: &crate::Generator,
    cam: &crate::CameraConfig,
    inv: &crate::invert::Inversion,
    start: &crate::invert::Start,
    (start_pose, pose): ((f64, f64), (f64, f64)),
    photo: &Tensor,
    view_res: i64,
    samples: usize,
) -> Result<f64> {
    let view_samples = samples.max(12);
    let view = |f: &crate::edit::Features, poses: &[(f64, f64)]| render_views(g, cam, f, poses, view_res, view_samples);
    let recon = view(&inv.features, &[pose])?;
    let start_features = crate::edit::Features {
        w_s: start.w_s.shallow_clone(),
        appearance: crate::nn::film::Film::from_raw(&start.appearance_raw),
        pose: Some(start_pose),
        z: None,
    };
    let start_img = view(&start_features, &[start_pose])?;
    let input = crate::io::resize(photo, view_res);
    save_png(&a.out.join("input.png"), &to_rgb8(&input.get(0), false)?)?;
    save_png(&a.out.join("reconstruction.png"), &to_rgb8(&recon.get(0), false)?)?;
    let compare = Tensor::cat(&[input.get(0), start_img.get(0), recon.get(0)], 2);
    save_png(&a.out.join("compare.png"), &to_rgb8(&compare, false)?)?;
    let psnr = psnr_all(&recon, &input)?;
    if a.orbit > 0 {
        let views = render_orbit(g, cam, &inv.features, pose, a.orbit, view_res, view_samples)?;
        let dir = a.out.join("orbit");
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let frames = (0..a.orbit as i64).map(|i| to_rgb8(&views.get(i), false)).collect::<Result<Vec<_>>>()?;
        for (i, f) in frames.iter().enumerate() {
            save_png(&dir.join(format!("frame-{i:03}.png")), f)?;
        }
        save_gif(&a.out.join("orbit.gif"), &frames, 80)?;
    }
    save_png(&a.out.join("loss.png"), &draw_panels(&loss_panels(&inv.history), 2, 360, 240)?)?;
    Ok(psnr)
}
