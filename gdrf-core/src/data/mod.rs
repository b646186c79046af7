//! Training images: the procedural dataset ([`synth`]) and loaders for real collections
//! ([`layouts`], [`folder`]).
//!
//! Loading decodes every image once, in parallel, to `3 × R × R` bytes at the training
//! resolution and keeps them in one `(N, 3, R, R)` uint8 tensor (and the alpha, where any
//! image has transparent pixels, in one `(N, 1, R, R)`); a cache file at that
//! resolution (safetensors, written atomically) makes later loads a single read. Poses
//! are re-read from their source on every load (cheap), so the cache never holds
//! stale poses; the cache is rebuilt when any image or pose file changes (names, sizes,
//! modification times).
pub mod folder;
pub mod layouts;
pub mod npy;
pub mod synth;

use crate::paths::write_atomic;
use crate::progress::{Counter, Event};
use crate::{Error, Result};
use layouts::{Flip, Layout, ListOptions};
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use synth::{ImageRecord, SynthOptions};
use tch::{Device, Kind, Tensor};

/// The description of a generated dataset ([`Metadata`]), written last and atomically by
/// [`synth::generate`]: a folder without it is unfinished.
pub const METADATA_FILE: &str = "metadata.json";
/// The version of [`METADATA_FILE`]'s format.
pub const FORMAT_VERSION: u32 = 1;

/// Which images a loader takes from a generated dataset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    Train,
    HeldOut,
}

/// A generated dataset's description: the options that made it and every image's ground truth.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Metadata {
    pub format_version: u32,
    pub options: SynthOptions,
    pub part_names: Vec<String>,
    pub images: Vec<ImageRecord>,
}

impl Metadata {
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(METADATA_FILE);
        let text = std::fs::read_to_string(&path).map_err(|source| Error::Io { path: path.clone(), err: source })?;
        let meta: Metadata = serde_json::from_str(&text).map_err(|e| Error::Data {
            path: path.clone(),
            reason: format!("not a gdrf synthetic dataset description: {e}"),
        })?;
        if meta.format_version != FORMAT_VERSION {
            return Err(Error::Data {
                path,
                reason: format!("format_version {} is not supported (expected {FORMAT_VERSION})", meta.format_version),
            });
        }
        Ok(meta)
    }

    /// The first view of object `i`.
    pub fn object(&self, i: usize) -> Result<&ImageRecord> {
        let objects = self.images.last().map_or(0, |r| r.object + 1);
        self.images
            .iter()
            .find(|r| r.object == i && r.view == 0)
            .ok_or_else(|| Error::Invalid(format!("object {i} does not exist; this dataset has objects 0..{objects}")))
    }
}

/// A file left out of a dataset (only with `skip_bad`), and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Skipped {
    pub path: PathBuf,
    pub reason: String,
}

/// How to load a dataset folder.
#[derive(Debug, Clone, PartialEq)]
pub struct LoadOptions {
    /// Side of the square training images.
    pub resolution: usize,
    pub layout: Layout,
    /// Folder layout: a pose file in the `camera_param` format; `camera_param` layout:
    /// replaces `camera_param.json`; CARLA: the folder of `*_extrinsics.npy`.
    pub poses: Option<PathBuf>,
    /// Fail when the dataset has no poses at all.
    pub require_poses: bool,
    /// Skip bad files (with a recorded reason) instead of failing on the first one.
    pub skip_bad: bool,
    /// Synthetic datasets: which split to load (None = all images).
    pub split: Option<Split>,
    /// Read and write a cache at the training resolution.
    pub cache: bool,
    /// Where the cache lives (default: `<dataset>/.gdrf-cache`).
    pub cache_dir: Option<PathBuf>,
    /// Decoding threads (0 = all cores).
    pub threads: usize,
}

impl LoadOptions {
    pub fn new(resolution: usize) -> Self {
        Self {
            resolution,
            layout: Layout::Auto,
            poses: None,
            require_poses: false,
            skip_bad: false,
            split: None,
            cache: true,
            cache_dir: None,
            threads: 0,
        }
    }
}

/// Where a loaded dataset's pixels came from.
#[derive(Debug, Clone, PartialEq)]
pub enum CacheStatus {
    /// Read from this cache file.
    Hit(PathBuf),
    /// Decoded; written to this cache file (None: caching off).
    Decoded(Option<PathBuf>),
    /// Decoded, but the cache could not be written (the reason).
    WriteFailed(PathBuf, String),
}

/// Images at the training resolution, with their poses and names.
#[derive(Debug)]
pub struct Dataset {
    /// `(N, 3, R, R)` uint8, RGB on white. Bytes rather than floats: a quarter of the
    /// memory; [`Dataset::images`] and [`Dataset::batch`] convert.
    pub pixels: Tensor,
    /// `(N, 1, R, R)` uint8 alpha, where some image has a pixel that is not opaque
    /// ([`Dataset::alpha_batch`] converts); `None` when every pixel is.
    pub alpha: Option<Tensor>,
    /// `(N, 2)` float32 `[pitch, yaw]` in radians, when the source has poses.
    pub poses: Option<Tensor>,
    /// File names relative to the dataset folder, aligned with `pixels`.
    pub names: Vec<String>,
    pub resolution: usize,
    pub layout: Layout,
    /// Horizontal flip augmentation the layout prescribes (CARLA).
    pub flip: Option<Flip>,
    pub skipped: Vec<Skipped>,
    pub cache: CacheStatus,
}

impl Dataset {
    pub fn len(&self) -> usize {
        self.names.len()
    }

    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }

    /// All images `(N, 3, R, R)` float32 in [−1, 1] ((x − 0.5) / 0.5, as the release).
    pub fn images(&self) -> Tensor {
        to_unit_range(&self.pixels)
    }

    /// Images `(B, 3, R, R)` in [−1, 1] and poses `(B, 2)` for `indices`; where `flips[b]`
    /// is set the image is mirrored left↔right and its yaw mapped by [`Flip::yaw`].
    pub fn batch(&self, indices: &[i64], flips: Option<&[bool]>) -> Result<(Tensor, Option<Tensor>)> {
        let n = self.len() as i64;
        if let Some(&bad) = indices.iter().find(|&&i| i < 0 || i >= n) {
            return Err(Error::Invalid(format!("batch index {bad} out of range for a dataset of {n} images")));
        }
        if flips.is_some_and(|f| f.len() != indices.len()) {
            return Err(Error::Shape("batch: one flip flag per index expected".into()));
        }
        let idx = Tensor::from_slice(indices);
        let images = flipped(to_unit_range(&self.pixels.index_select(0, &idx)), flips);
        let mut poses = self.poses.as_ref().map(|p| p.index_select(0, &idx));
        if let Some(flips) = flips.filter(|f| f.iter().any(|&x| x)) {
            let mask = Tensor::from_slice(flips).to_kind(Kind::Bool);
            if let Some(p) = &poses {
                let yaw = p.select(1, 1);
                let flipped = yaw.neg() + std::f64::consts::PI;
                poses = Some(Tensor::stack(&[p.select(1, 0), flipped.where_self(&mask, &yaw)], 1));
            }
        }
        Ok((images, poses))
    }

    /// The alpha `(B, 1, R, R)` in [0, 1] of the images [`Dataset::batch`] gives for the same
    /// arguments (mirrored alike); `None` when every pixel is opaque.
    pub fn alpha_batch(&self, indices: &[i64], flips: Option<&[bool]>) -> Option<Tensor> {
        let idx = Tensor::from_slice(indices);
        self.alpha.as_ref().map(|a| flipped(a.index_select(0, &idx).to_kind(Kind::Float) / 255.0, flips))
    }
}

/// `images: (B, C, H, W)` with row b mirrored left↔right where `flips[b]` is set.
fn flipped(images: Tensor, flips: Option<&[bool]>) -> Tensor {
    match flips.filter(|f| f.iter().any(|&x| x)) {
        Some(flips) => {
            let mask = Tensor::from_slice(flips).to_kind(Kind::Bool);
            images.flip([3]).where_self(&mask.view([-1, 1, 1, 1]), &images)
        }
        None => images,
    }
}

fn to_unit_range(pixels: &Tensor) -> Tensor {
    (pixels.to_kind(Kind::Float) / 255.0 - 0.5) / 0.5
}

/// Threads to use for `requested` (0 = all cores).
pub fn thread_count(requested: usize) -> usize {
    if requested > 0 {
        requested
    } else {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    }
}

/// `f(0..n)` on `threads` worker threads (0 = all cores), results in index order. Stops
/// handing out work after the first error and returns the error of the lowest failing
/// index among those attempted.
pub fn par_try_map<T: Send>(n: usize, threads: usize, f: impl Fn(usize) -> Result<T> + Sync) -> Result<Vec<T>> {
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let workers = thread_count(threads).clamp(1, n.max(1));
    let parts: Vec<Vec<(usize, Result<T>)>> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..workers)
            .map(|_| {
                s.spawn(|| {
                    let mut done = Vec::new();
                    while !failed.load(Ordering::Relaxed) {
                        let i = next.fetch_add(1, Ordering::Relaxed);
                        if i >= n {
                            break;
                        }
                        let r = f(i);
                        if r.is_err() {
                            failed.store(true, Ordering::Relaxed);
                        }
                        done.push((i, r));
                    }
                    done
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p))).collect()
    });
    let mut slots: Vec<Option<Result<T>>> = (0..n).map(|_| None).collect();
    for (i, r) in parts.into_iter().flatten() {
        slots[i] = Some(r);
    }
    let mut out = Vec::with_capacity(n);
    for slot in slots {
        match slot {
            Some(Ok(v)) => out.push(v),
            Some(Err(e)) => return Err(e),
            // Not attempted: only possible after an error at a higher index.
            None => continue,
        }
    }
    if out.len() == n {
        Ok(out)
    } else {
        Err(Error::Invalid("parallel work stopped without an error (internal)".into()))
    }
}

/// Loads the dataset in `dir`, reporting each decoded image to `progress`.
pub fn load(dir: &Path, opts: &LoadOptions, progress: &(dyn Fn(Event) + Sync)) -> Result<Dataset> {
    if !(2..=4096).contains(&opts.resolution) {
        return Err(Error::Config(format!("data resolution {} is out of range, expected 2..=4096", opts.resolution)));
    }
    let listing = layouts::list(
        dir,
        &ListOptions {
            layout: opts.layout,
            poses: opts.poses.as_deref(),
            require_poses: opts.require_poses,
            skip_bad: opts.skip_bad,
            split: opts.split,
        },
    )?;
    let fingerprint = fingerprint(opts, &listing);
    let cache_path = opts.cache.then(|| {
        let split = opts.split.map_or("", |s| if s == Split::Train { "-train" } else { "-held_out" });
        let dir = opts.cache_dir.clone().unwrap_or_else(|| dir.join(".gdrf-cache"));
        dir.join(format!("{}{split}-r{}.safetensors", listing.layout.name(), opts.resolution))
    });
    let res = opts.resolution;

    let cached = cache_path.as_deref().and_then(|p| read_cache(p, &fingerprint, res));
    let (Decoded { pixels, alpha, names, mut skipped }, cache) = match cached {
        Some(d) => (d, CacheStatus::Hit(cache_path.clone().unwrap_or_default())),
        None => {
            let counter = Counter::new("decoding images", listing.files.len() as u64, progress);
            let decoded = par_try_map(listing.files.len(), opts.threads, |i| {
                let r = folder::load_image(&listing.files[i], res);
                counter.tick();
                match r {
                    Err(Error::Data { path, reason }) if opts.skip_bad => Ok(Err(Skipped { path, reason })),
                    r => r.map(Ok),
                }
            })?;
            let plane = res * res;
            let mut d = Decoded {
                pixels: Vec::with_capacity(decoded.len() * 3 * plane),
                alpha: Some(Vec::with_capacity(decoded.len() * plane)),
                names: Vec::new(),
                skipped: Vec::new(),
            };
            for (i, px) in decoded.into_iter().enumerate() {
                match px {
                    Ok(px) => {
                        d.pixels.extend_from_slice(&px[..3 * plane]);
                        if let Some(a) = d.alpha.as_mut() {
                            a.extend_from_slice(&px[3 * plane..]);
                        }
                        d.names.push(listing.names[i].clone());
                    }
                    Err(s) => d.skipped.push(s),
                }
            }
            if d.alpha.as_ref().is_some_and(|a| a.iter().all(|&v| v == 255)) {
                d.alpha = None;
            }
            let status = match &cache_path {
                None => CacheStatus::Decoded(None),
                Some(p) => match write_cache(p, &fingerprint, res, &d) {
                    Ok(()) => CacheStatus::Decoded(Some(p.clone())),
                    Err(e) => CacheStatus::WriteFailed(p.clone(), e.to_string()),
                },
            };
            (d, status)
        }
    };
    if names.is_empty() {
        return Err(Error::Data { path: dir.to_path_buf(), reason: "every image was skipped as bad".into() });
    }
    let n = names.len();
    let pixels = Tensor::from_slice(&pixels).view([n as i64, 3, res as i64, res as i64]);
    let alpha = alpha.map(|a| Tensor::from_slice(&a).view([n as i64, 1, res as i64, res as i64]));
    let poses = match &listing.poses {
        None => None,
        Some(all) => {
            let by_name: HashMap<&str, [f64; 2]> =
                listing.names.iter().map(String::as_str).zip(all.iter().copied()).collect();
            let mut flat = Vec::with_capacity(2 * n);
            for name in &names {
                let p = by_name.get(name.as_str()).ok_or_else(|| Error::Data {
                    path: dir.join(name),
                    reason: "cached image is no longer listed (stale cache)".into(),
                })?;
                flat.extend(p.iter().map(|&x| x as f32));
            }
            Some(Tensor::from_slice(&flat).view([n as i64, 2]))
        }
    };
    let mut all_skipped = listing.skipped;
    all_skipped.append(&mut skipped);
    Ok(Dataset {
        pixels: pixels.to_device(Device::Cpu),
        alpha,
        poses,
        names,
        resolution: res,
        layout: listing.layout,
        flip: listing.flip,
        skipped: all_skipped,
        cache,
    })
}

/// FNV-1a over everything the cached pixels depend on.
fn fingerprint(opts: &LoadOptions, listing: &layouts::Listing) -> String {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h = (h ^ *b as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
        h = (h ^ 0xff).wrapping_mul(0x0000_0100_0000_01b3); // field separator
    };
    // v2: the cache holds the alpha too.
    eat(format!("v2 {} {} {}", listing.layout.name(), opts.resolution, opts.skip_bad).as_bytes());
    for f in listing.files.iter().chain(&listing.pose_files) {
        eat(f.to_string_lossy().as_bytes());
        // A file that cannot be stat'ed (a dangling link) fails or is skipped when decoded.
        let Ok(meta) = std::fs::metadata(f) else {
            eat(b"unreadable");
            continue;
        };
        let mtime =
            meta.modified().ok().and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok()).map_or(0, |d| d.as_nanos());
        eat(&meta.len().to_le_bytes());
        eat(&mtime.to_le_bytes());
    }
    format!("{h:016x}")
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CacheHeader {
    fingerprint: String,
    resolution: usize,
    names: Vec<String>,
    skipped: Vec<Skipped>,
}

const CACHE_KEY: &str = "gdrf_image_cache";

/// Decoded images: RGB bytes `(N, 3, R, R)`, alpha bytes `(N, 1, R, R)` where some pixel
/// is not opaque, names, and the files skipped as bad.
struct Decoded {
    pixels: Vec<u8>,
    alpha: Option<Vec<u8>>,
    names: Vec<String>,
    skipped: Vec<Skipped>,
}

/// The cached images, or None when the cache is missing, unreadable or out of date (it is
/// then rebuilt).
fn read_cache(path: &Path, fingerprint: &str, res: usize) -> Option<Decoded> {
    let bytes = std::fs::read(path).ok()?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).ok()?;
    let header: CacheHeader = serde_json::from_str(meta.metadata().as_ref()?.get(CACHE_KEY)?).ok()?;
    if header.fingerprint != fingerprint || header.resolution != res {
        return None;
    }
    let st = SafeTensors::deserialize(&bytes).ok()?;
    let n = header.names.len();
    let read = |name: &str, channels: usize| -> Option<Vec<u8>> {
        let t = st.tensor(name).ok()?;
        (t.dtype() == Dtype::U8 && t.shape() == [n, channels, res, res]).then(|| t.data().to_vec())
    };
    let alpha = match st.names().contains(&"alpha") {
        true => Some(read("alpha", 1)?),
        false => None,
    };
    Some(Decoded { pixels: read("pixels", 3)?, alpha, names: header.names, skipped: header.skipped })
}

fn write_cache(path: &Path, fingerprint: &str, res: usize, d: &Decoded) -> Result<()> {
    let header = CacheHeader {
        fingerprint: fingerprint.into(),
        resolution: res,
        names: d.names.clone(),
        skipped: d.skipped.clone(),
    };
    let json = serde_json::to_string(&header)?;
    let n = d.names.len();
    let view = |channels: usize, data| {
        TensorView::new(Dtype::U8, vec![n, channels, res, res], data)
            .map_err(|e| Error::Invalid(format!("cache tensor: {e}")))
    };
    let mut views = vec![("pixels", view(3, d.pixels.as_slice())?)];
    if let Some(a) = &d.alpha {
        views.push(("alpha", view(1, a.as_slice())?));
    }
    let meta: HashMap<String, String> = [(CACHE_KEY.to_string(), json)].into();
    let bytes = safetensors::tensor::serialize(views, Some(meta))
        .map_err(|e| Error::Invalid(format!("cache serialisation: {e}")))?;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), err: source })?;
    }
    write_atomic(path, &bytes)
}

/// A training config's `[data]` table: where the images are and how to load them; with
/// `synth` set, a missing dataset is generated there on first use.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DataConfig {
    pub path: PathBuf,
    #[serde(default = "default_layout")]
    pub layout: Layout,
    #[serde(default)]
    pub poses: Option<PathBuf>,
    #[serde(default = "yes")]
    pub require_poses: bool,
    #[serde(default)]
    pub skip_bad: bool,
    /// Synthetic datasets: `train` (default), `held_out`, or `all`.
    #[serde(default = "default_split")]
    pub split: SplitChoice,
    #[serde(default = "yes")]
    pub cache: bool,
    #[serde(default)]
    pub cache_dir: Option<PathBuf>,
    #[serde(default)]
    pub synth: Option<synth::SynthOptions>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SplitChoice {
    Train,
    HeldOut,
    All,
}

fn default_layout() -> Layout {
    Layout::Auto
}
fn default_split() -> SplitChoice {
    SplitChoice::Train
}
fn yes() -> bool {
    true
}

/// What [`DataConfig::prepare`] did before loading.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Prepared {
    /// The synthetic dataset was generated now.
    Generated,
    /// It was there already (same options).
    Existing,
    /// Not a synthetic dataset.
    External,
}

impl DataConfig {
    pub fn load_options(&self, resolution: usize, threads: usize) -> LoadOptions {
        LoadOptions {
            resolution,
            layout: self.layout,
            poses: self.poses.clone(),
            require_poses: self.require_poses,
            skip_bad: self.skip_bad,
            split: match self.split {
                SplitChoice::Train => Some(Split::Train),
                SplitChoice::HeldOut => Some(Split::HeldOut),
                SplitChoice::All => None,
            },
            cache: self.cache,
            cache_dir: self.cache_dir.clone(),
            threads,
        }
    }

    /// Generates the synthetic dataset at `path` when `synth` is set and no finished
    /// dataset is there; an existing one generated with other options is an error
    /// (never overwritten silently).
    pub fn prepare(&self, threads: usize, progress: &(dyn Fn(Event) + Sync)) -> Result<Prepared> {
        let Some(want) = &self.synth else {
            return Ok(Prepared::External);
        };
        if self.path.join(METADATA_FILE).is_file() {
            let have = Metadata::load(&self.path)?;
            if &have.options != want {
                return Err(Error::Config(format!(
                    "{} holds a synthetic dataset generated with other options ({}); remove it or change data.path",
                    self.path.display(),
                    option_diff(&have.options, want)
                )));
            }
            return Ok(Prepared::Existing);
        }
        synth::generate(&self.path, want, threads, progress)?;
        Ok(Prepared::Generated)
    }
}

/// The option keys whose values differ, e.g. "count: 100 vs 200".
fn option_diff(have: &synth::SynthOptions, want: &synth::SynthOptions) -> String {
    let (a, b) = (serde_json::to_value(have).unwrap_or_default(), serde_json::to_value(want).unwrap_or_default());
    let (Some(a), Some(b)) = (a.as_object(), b.as_object()) else {
        return String::new();
    };
    let keys: BTreeMap<&String, ()> = a.keys().chain(b.keys()).map(|k| (k, ())).collect();
    keys.into_keys()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| {
            format!(
                "{k}: {} on disk vs {} wanted",
                a.get(k).unwrap_or(&serde_json::Value::Null),
                b.get(k).unwrap_or(&serde_json::Value::Null)
            )
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// A contact sheet: the images `indices` of `images` (`(N, 3, R, R)` in [−1, 1]) in a
/// grid of `cols` columns, as 8-bit RGB.
pub fn contact_sheet(images: &Tensor, indices: &[i64], cols: i64) -> Result<image::RgbImage> {
    let picked = images.index_select(0, &Tensor::from_slice(indices));
    crate::io::to_rgb8(&crate::io::grid(&picked, cols), false)
}

/// `k` distinct indices from `0..n`, drawn deterministically from `seed` and sorted.
pub fn sample_indices(n: usize, k: usize, seed: u64) -> Vec<i64> {
    let mut rng = synth::rng::Rng::new(seed, synth::rng::Stream::Split);
    let mut all: Vec<i64> = (0..n as i64).collect();
    let k = k.min(n);
    for i in 0..k {
        let j = i + (rng.unit() * (n - i) as f64) as usize;
        all.swap(i, j.min(n - 1));
    }
    all.truncate(k);
    all.sort_unstable();
    all
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn par_try_map_keeps_order_and_reports_the_first_error() {
        let v = par_try_map(100, 3, |i| Ok(i * 2)).unwrap();
        assert_eq!(v, (0..100).map(|i| i * 2).collect::<Vec<_>>());
        let e =
            par_try_map(100, 2, |i| if i == 7 { Err(Error::Invalid(format!("bad {i}"))) } else { Ok(i) }).unwrap_err();
        assert!(e.to_string().contains("bad 7"));
        assert!(par_try_map(0, 2, Ok).unwrap().is_empty());
    }

    #[test]
    fn sampled_indices_are_distinct_and_in_range() {
        let v = sample_indices(50, 20, 3);
        let mut u = v.clone();
        u.sort();
        u.dedup();
        assert_eq!(u.len(), 20);
        assert!(v.iter().all(|&i| (0..50).contains(&i)));
        assert_eq!(sample_indices(5, 10, 0).len(), 5);
    }
}
