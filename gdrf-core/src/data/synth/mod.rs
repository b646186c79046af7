//! The procedural dataset: topology-varying objects (chairs, tables) with appearance
//! drawn independently of shape, rendered exactly (sphere-traced SDFs) with ground truth
//! for every image (pose, shape parameters, appearance parameters, seed).
//!
//! On disk: `images/NNNNNN.png` (RGBA, straight alpha, white where empty),
//! `metadata.json` ([`Metadata`]) and `camera_param.json` (the authors' pose format, so
//! any loader of their layouts reads it). `metadata.json` is written last and atomically:
//! a directory without it is an unfinished generation.
pub mod analytic;
pub mod chairs;
pub mod material;
pub mod render;
pub mod restyle;
pub mod rng;
pub mod sdf;
pub mod tables;

use super::{par_try_map, Metadata, Split, FORMAT_VERSION, METADATA_FILE};
use crate::config::{CameraConfig, PoseDistribution};
use crate::paths::write_atomic;
use crate::progress::{Counter, Event};
use crate::{Error, Result};
use material::Appearance;
use render::{fit_radius, render, RenderOptions, Rendered, Scene};
use rng::{object_seed, Rng, Stream};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::Path;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Category {
    Chairs,
    Tables,
}

impl Category {
    pub const ALL: [Category; 2] = [Category::Chairs, Category::Tables];

    pub fn name(self) -> &'static str {
        match self {
            Category::Chairs => "chairs",
            Category::Tables => "tables",
        }
    }

    /// What each of the four material slots is called.
    pub fn part_names(self) -> [&'static str; material::PARTS] {
        match self {
            Category::Chairs => chairs::PART_NAMES,
            Category::Tables => tables::PART_NAMES,
        }
    }
}

impl std::str::FromStr for Category {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        Category::ALL
            .into_iter()
            .find(|c| c.name() == s)
            .ok_or_else(|| Error::Invalid(format!("unknown category '{s}', expected one of: chairs, tables")))
    }
}

/// Shape parameters of one object (tagged with its category in JSON).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "category", rename_all = "snake_case")]
pub enum ShapeParams {
    Chair(chairs::ChairParams),
    Table(tables::TableParams),
}

impl ShapeParams {
    pub fn sample(category: Category, rng: &mut Rng) -> Self {
        match category {
            Category::Chairs => ShapeParams::Chair(chairs::ChairParams::sample(rng)),
            Category::Tables => ShapeParams::Table(tables::TableParams::sample(rng)),
        }
    }

    pub fn geometry(&self) -> render::Geometry {
        match self {
            ShapeParams::Chair(c) => c.geometry(),
            ShapeParams::Table(t) => t.geometry(),
        }
    }
}

/// Shape and appearance of object `seed` (an [`object_seed`]), from separate streams.
pub fn sample_object(category: Category, seed: u64) -> (ShapeParams, Appearance) {
    let shape = ShapeParams::sample(category, &mut Rng::new(seed, Stream::Shape));
    let appearance = Appearance::sample(&mut Rng::new(seed, Stream::Appearance));
    (shape, appearance)
}

/// Everything that determines a generated dataset (same options → identical bytes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SynthOptions {
    pub category: Category,
    /// Number of images.
    pub count: usize,
    pub resolution: usize,
    pub seed: u64,
    /// K × K samples per pixel.
    pub supersample: usize,
    /// Views rendered of each object (the authors' chairs: 1, cars: 3).
    pub views_per_object: usize,
    /// Probability that an object (all its views) is held out of training.
    pub held_out_fraction: f64,
    /// Soft shadows from the key light.
    pub shadows: bool,
    /// Field of view, ray range (objects are scaled to fit it) and pose distribution.
    pub camera: CameraConfig,
}

impl Default for SynthOptions {
    fn default() -> Self {
        Self {
            category: Category::Chairs,
            count: 10_000,
            resolution: 128,
            seed: 0,
            supersample: 3,
            views_per_object: 1,
            held_out_fraction: 0.1,
            shadows: true,
            camera: CameraConfig::chair(),
        }
    }
}

impl SynthOptions {
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::Config(m));
        if self.count == 0 {
            return bad("synth.count must be at least 1".into());
        }
        if !(2..=4096).contains(&self.resolution) {
            return bad(format!("synth.resolution is {}, expected 2..=4096", self.resolution));
        }
        if !(1..=16).contains(&self.supersample) {
            return bad(format!("synth.supersample is {}, expected 1..=16", self.supersample));
        }
        if self.views_per_object == 0 {
            return bad("synth.views_per_object must be at least 1".into());
        }
        if !(0.0..=1.0).contains(&self.held_out_fraction) {
            return bad(format!("synth.held_out_fraction is {}, expected a value in [0, 1]", self.held_out_fraction));
        }
        self.camera.validate()?;
        if self.camera.ray_start >= 1.0 || self.camera.ray_end <= 1.0 {
            return bad(format!(
                "camera ray range [{}, {}] must contain the origin's distance 1",
                self.camera.ray_start, self.camera.ray_end
            ));
        }
        Ok(())
    }

    fn render_options(&self) -> RenderOptions {
        RenderOptions {
            resolution: self.resolution,
            supersample: self.supersample,
            fov_deg: self.camera.fov_deg,
            shadows: self.shadows,
        }
    }
}

/// Ground truth of one image.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageRecord {
    /// Path relative to the dataset folder, `images/NNNNNN.png`.
    pub file: String,
    pub object: usize,
    pub view: usize,
    /// The object's seed (derived from the dataset seed and `object`); it alone
    /// determines `shape`, `appearance` and `split`.
    pub seed: u64,
    pub split: Split,
    /// Polar angle φ from +y, radians (`crate::camera` convention).
    pub pitch: f64,
    /// Yaw θ, radians.
    pub yaw: f64,
    pub shape: ShapeParams,
    pub appearance: Appearance,
}

/// The ground truth of image `index` (no rendering).
pub fn image_record(opts: &SynthOptions, index: usize) -> ImageRecord {
    let (object, view) = (index / opts.views_per_object, index % opts.views_per_object);
    let seed = object_seed(opts.seed, object as u64);
    let (shape, appearance) = sample_object(opts.category, seed);
    let split =
        if Rng::new(seed, Stream::Split).unit() < opts.held_out_fraction { Split::HeldOut } else { Split::Train };
    let (pitch, yaw) = sample_pose(&opts.camera, &mut Rng::new(object_seed(seed, view as u64), Stream::Pose));
    ImageRecord { file: format!("images/{index:06}.png"), object, view, seed, split, pitch, yaw, shape, appearance }
}

/// A pose from the camera's distribution, as `crate::camera::Poses::sample` draws it
/// (including its pitch clamp), from our own generator instead of libtorch's.
pub fn sample_pose(cam: &CameraConfig, rng: &mut Rng) -> (f64, f64) {
    use std::f64::consts::PI;
    let mut sym = || rng.range(-1.0, 1.0);
    let (pitch, yaw) = match cam.distribution {
        PoseDistribution::Uniform => {
            let yaw = cam.h_mean + cam.h_std * sym();
            (cam.v_mean + cam.v_std * sym(), yaw)
        }
        PoseDistribution::Normal => {
            let yaw = cam.h_mean + cam.h_std * rng.normal();
            (cam.v_mean + cam.v_std * rng.normal(), yaw)
        }
        PoseDistribution::SphericalUniform => {
            let yaw = cam.h_mean + cam.h_std * sym();
            let v = (cam.v_mean / PI + cam.v_std / PI * sym()).clamp(1e-5, 1.0 - 1e-5);
            ((1.0 - 2.0 * v).acos(), yaw)
        }
        PoseDistribution::Fixed => (cam.v_mean, cam.h_mean),
    };
    (pitch.clamp(1e-5, PI - 1e-5), yaw)
}

/// Renders a shape with an appearance at a pose, scaled to fit `opts.camera`.
pub fn render_object(
    shape: &ShapeParams,
    appearance: &Appearance,
    pitch: f64,
    yaw: f64,
    opts: &SynthOptions,
) -> Result<Rendered> {
    let scene = Scene::new(&shape.geometry(), appearance, fit_radius(&opts.camera))?;
    render(&scene, pitch, yaw, &opts.render_options())
}

/// Encodes 8-bit RGBA as PNG bytes.
pub fn encode_png(rgba: Vec<u8>, res: usize) -> Result<Vec<u8>> {
    let img = image::RgbaImage::from_raw(res as u32, res as u32, rgba)
        .ok_or_else(|| Error::Invalid("RGBA buffer does not match the resolution".into()))?;
    let mut bytes = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut bytes), image::ImageFormat::Png)
        .map_err(|e| Error::Invalid(format!("PNG encoding failed: {e}")))?;
    Ok(bytes)
}

/// Renders the dataset into `dir` (created if needed) on `threads` threads, reporting each
/// image to `progress`. Output bytes do not depend on `threads`.
pub fn generate(
    dir: &Path,
    opts: &SynthOptions,
    threads: usize,
    progress: &(dyn Fn(Event) + Sync),
) -> Result<Metadata> {
    opts.validate()?;
    let images_dir = dir.join("images");
    std::fs::create_dir_all(&images_dir).map_err(|source| Error::Io { path: images_dir.clone(), err: source })?;
    // Any older description goes first: until the new one is written the folder reads
    // as unfinished, never as a mix of two datasets.
    let meta_path = dir.join(METADATA_FILE);
    match std::fs::remove_file(&meta_path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(Error::Io { path: meta_path, err: e }),
        _ => {}
    }
    let counter = Counter::new("generating images", opts.count as u64, progress);
    let records = par_try_map(opts.count, threads, |i| {
        let rec = image_record(opts, i);
        let img = render_object(&rec.shape, &rec.appearance, rec.pitch, rec.yaw, opts)?;
        let path = dir.join(&rec.file);
        // Plain writes: the atomic metadata file, written last, is the commit point.
        std::fs::write(&path, encode_png(img.to_rgba8(), opts.resolution)?)
            .map_err(|source| Error::Io { path: path.clone(), err: source })?;
        counter.tick();
        Ok(rec)
    })?;
    remove_stale_images(&images_dir, &records)?;
    let poses: BTreeMap<&str, serde_json::Value> =
        records.iter().map(|r| (r.file.as_str(), serde_json::json!({ "phi": r.pitch, "theta": r.yaw }))).collect();
    write_json(&dir.join(super::layouts::CAMERA_PARAM_FILE), &poses)?;
    let meta = Metadata {
        format_version: FORMAT_VERSION,
        options: opts.clone(),
        part_names: opts.category.part_names().iter().map(|s| s.to_string()).collect(),
        images: records,
    };
    write_json(&meta_path, &meta)?;
    Ok(meta)
}

/// Deletes PNGs in `images/` that this generation did not write (left by an earlier,
/// larger or interrupted one), so the folder holds exactly the dataset described.
fn remove_stale_images(images_dir: &Path, records: &[ImageRecord]) -> Result<()> {
    let io = |path: &Path| {
        let path = path.to_path_buf();
        move |source| Error::Io { path, err: source }
    };
    let keep: std::collections::HashSet<&str> = records.iter().filter_map(|r| r.file.strip_prefix("images/")).collect();
    for entry in std::fs::read_dir(images_dir).map_err(io(images_dir))? {
        let path = entry.map_err(io(images_dir))?.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or_default();
        if name.ends_with(".png") && !keep.contains(name) {
            std::fs::remove_file(&path).map_err(io(&path))?;
        }
    }
    Ok(())
}

fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<()> {
    let text = serde_json::to_string_pretty(value).map_err(|e| Error::Invalid(format!("{}: {e}", path.display())))?;
    write_atomic(path, text.as_bytes())
}

/// "Shape of object `shape_from` with the appearance of object `appearance_from`", at
/// `pose` (default: the pose of the shape object's first view) and the dataset's
/// rendering options unless `resolution`/`supersample` override them.
pub fn render_swap(
    meta: &Metadata,
    shape_from: usize,
    appearance_from: usize,
    pose: Option<(f64, f64)>,
    resolution: Option<usize>,
    supersample: Option<usize>,
) -> Result<Rendered> {
    let s = meta.object(shape_from)?;
    let a = meta.object(appearance_from)?;
    let (pitch, yaw) = pose.unwrap_or((s.pitch, s.yaw));
    let mut opts = meta.options.clone();
    opts.resolution = resolution.unwrap_or(opts.resolution);
    opts.supersample = supersample.unwrap_or(opts.supersample);
    opts.validate()?;
    render_object(&s.shape, &a.appearance, pitch, yaw, &opts)
}
