//! The generator every subcommand renders: the flags that choose it (the shipped model by
//! default), how photo sources are inverted, what it learned at, and sources resolved to
//! features.
use anyhow::{Context, Result};
use clap::Args;
use gdrf_core::checkpoint::{load_generator, Header};
use gdrf_core::config::CameraPreset;
use gdrf_core::edit::view::Learned;
use gdrf_core::edit::{Features, Source};
use gdrf_core::field::generator::Generator;
use gdrf_core::invert::choice::{self, InitChoice, RefinePose};
use gdrf_core::{device, CameraConfig, GeneratorConfig};
use std::path::{Path, PathBuf};
use tch::{nn, Kind};

#[derive(Args)]
pub struct ModelArgs {
    /// Generator checkpoint (.safetensors; --generator is the same). Default: the shipped
    /// model (models/chairs-campaign).
    #[arg(long, visible_alias = "generator", value_name = "FILE", conflicts_with = "random_init")]
    checkpoint: Option<PathBuf>,
    /// A randomly initialised generator (the release's initialisation, seeded by
    /// --init-seed) instead of a checkpoint.
    #[arg(long)]
    random_init: bool,
    /// Seed of --random-init's generator.
    #[arg(long, default_value_t = 0)]
    init_seed: i64,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    device: String,
    /// Camera preset (chair, car, carla: field of view, ray range, mean pitch) instead of the
    /// camera stored with the checkpoint.
    #[arg(long, value_enum)]
    camera: Option<CameraPreset>,
    /// Photo sources (.png/.jpg) are inverted on the fly (as gdrf-invert with its defaults,
    /// where the generator learned; gdrf-invert writes a reusable feature file): the
    /// photo's pose as PITCH,YAW in degrees (default: the initialiser's estimate, refined
    /// with the features, else the camera's mean pose).
    #[arg(long, value_name = "PITCH,YAW", allow_hyphen_values = true)]
    photo_pose: Option<String>,
    /// The initialiser for photo sources (gdrf-invert train-init), or none (the mean code).
    /// Default: initialiser.safetensors beside the generator, as gdrf-invert's --init.
    #[arg(long, value_name = "FILE|none")]
    photo_init: Option<InitChoice>,
    /// Optimisation steps for photo sources.
    #[arg(long, default_value_t = gdrf_core::invert::InvertConfig::default().steps)]
    photo_steps: usize,
}

/// A loaded generator with what rendering and editing need beside it.
pub struct Model {
    pub _vs: nn::VarStore,
    pub generator: Generator,
    pub camera: CameraConfig,
    pub device: tch::Device,
    /// The generator's identity, which feature files carry.
    pub id: String,
    /// How photo sources are inverted.
    pub photo: PhotoSettings,
    /// Where the generator learned: the default resolution and samples per ray.
    pub learned: Learned,
}

/// The generator of `checkpoint`, or a randomly initialised one (the release's
/// initialisation, seeded by `init_seed`) for `None` (`--random-init`).
pub fn load_model(checkpoint: Option<&std::path::Path>, init_seed: i64, dev: tch::Device) -> Result<Model> {
    let (vs, generator, header) = match checkpoint {
        Some(p) => {
            let l =
                load_generator(p, dev, Kind::Float).with_context(|| format!("loading --checkpoint {}", p.display()))?;
            (l.vs, l.generator, l.header)
        }
        None => {
            eprintln!("--random-init: a randomly initialised generator (seed {init_seed})");
            let vs = nn::VarStore::new(dev);
            let cfg = GeneratorConfig::default();
            let g = gdrf_core::rng::with_global_seed(init_seed, || Generator::new(&vs.root(), &cfg))?;
            (vs, g, Header::generator(cfg, Some(CameraConfig::chair())))
        }
    };
    let id = gdrf_core::edit::generator_id(&vs, &generator);
    let learned = Learned::of(&header);
    Ok(Model {
        _vs: vs,
        generator,
        camera: header.camera.clone().unwrap_or_default(),
        device: dev,
        id,
        photo: PhotoSettings { cfg: gdrf_core::invert::InvertConfig::where_learned(&header), ..Default::default() },
        learned,
    })
}

pub fn open(m: &ModelArgs) -> Result<(Model, usize)> {
    let threads = device::init_threads();
    let dev = device::select(&m.device)?;
    let checkpoint = (!m.random_init).then(|| m.checkpoint.clone().unwrap_or_else(gdrf_core::paths::shipped_generator));
    let mut model = load_model(checkpoint.as_deref(), m.init_seed, dev)?;
    if let Some(preset) = m.camera {
        model.camera = preset.camera();
    }
    model.photo = PhotoSettings {
        pose: m.photo_pose.as_deref().map(|p| gdrf_core::invert::parse_pose_degrees(p, "--photo-pose")).transpose()?,
        init: m.photo_init.clone().unwrap_or_default(),
        framing: checkpoint.as_deref().map(gdrf_core::invert::framing::Framing::beside).transpose()?.flatten(),
        generator_path: checkpoint.clone(),
        cfg: gdrf_core::invert::InvertConfig { steps: m.photo_steps, ..model.photo.cfg.clone() },
    };
    model.photo.cfg.validate()?;
    Ok((model, threads))
}

/// How photo sources are inverted (see [`ModelArgs`]).
#[derive(Default)]
pub struct PhotoSettings {
    pub pose: Option<(f64, f64)>,
    pub init: InitChoice,
    /// The generator's file, beside which its initialiser lies (None: a random generator).
    pub generator_path: Option<PathBuf>,
    /// Where the training images' objects sit (framing.json beside the generator): photos
    /// are framed as `gdrf-invert PHOTO` frames them.
    pub framing: Option<gdrf_core::invert::framing::Framing>,
    pub cfg: gdrf_core::invert::InvertConfig,
}

pub fn resolve(model: &Model, source: &Source, flag: &str) -> Result<Features> {
    match source {
        Source::Image(p) => invert_photo(model, p, flag, &mut |_| {}),
        _ => Features::resolve(source, &model.generator, &model.id).with_context(|| flag.to_string()),
    }
}

/// The features of photo `p`, inverted as the model's photo settings say, telling
/// `progress` each optimisation step; `flag` names the photo's origin in messages.
pub fn invert_photo(
    model: &Model,
    p: &Path,
    flag: &str,
    progress: &mut dyn FnMut(&gdrf_core::invert::StepLog),
) -> Result<Features> {
    let ph = &model.photo;
    let chosen = match (&ph.generator_path, &ph.init) {
        (Some(g), init) => choice::open(init, "--photo-init", g, &model.id, model.device)?,
        // A random generator has no initialiser beside it; a file given with
        // --photo-init is still opened (and refused by the generator's identity).
        (None, InitChoice::Beside) => {
            choice::open(&InitChoice::None, "--photo-init", Path::new("random"), &model.id, model.device)?
        }
        (None, init) => choice::open(init, "--photo-init", Path::new("random"), &model.id, model.device)?,
    };
    let photo = gdrf_core::invert::photo::prepare_photo(
        p,
        None,
        gdrf_core::invert::photo::Fit::Auto,
        ph.framing.as_ref(),
        ph.cfg.resolution,
        model.device,
    )
    .with_context(|| format!("{flag} {}", p.display()))?;
    eprintln!("{flag}: {}", photo.describe());
    for w in &photo.warnings {
        eprintln!("{flag}: warning: {w}");
    }
    eprintln!(
        "{flag}: inverting {} ({} steps at {}² with {} + {} samples per ray); {}",
        p.display(),
        ph.cfg.steps,
        ph.cfg.resolution,
        ph.cfg.samples,
        ph.cfg.samples,
        chosen.said
    );
    let (f, from) = gdrf_core::invert::features_of_photo(
        &model.generator,
        &model.camera,
        &photo,
        ph.pose,
        chosen.init.as_ref(),
        RefinePose::Auto,
        &ph.cfg,
        progress,
    )
    .with_context(|| format!("{flag} {}", p.display()))?;
    if let Some(pose) = f.pose {
        eprintln!("{flag}: {}", choice::describe_pose(pose, from, RefinePose::Auto.resolve(from)));
    }
    Ok(f)
}
