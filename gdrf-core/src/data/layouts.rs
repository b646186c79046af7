//! Which files make up a dataset and their poses, for each supported layout:
//!
//! - `folder`: the PNG/JPEG files directly in a folder (sorted by name), with an
//!   optional pose file in the `camera_param` format.
//! - `camera_param`: the authors' PhotoShape/ShapeNet layout, `camera_param.json`
//!   mapping file name → {"phi": pitch, "theta": yaw, ...}; the JSON lists the images.
//! - `carla`: `*.png` with poses in `../carla_poses/<stem>_extrinsics.npy`
//!   (camera-to-world), converted with the release's rule; random horizontal flips
//!   with θ → π − θ.
//! - `synth`: a dataset written by [`super::synth::generate`] (`metadata.json`).
//!
//! Every inconsistency (a pose naming a missing image, an image without a pose, an
//! unreadable pose) is an error naming the file, or with `skip_bad` a skipped entry.
use super::npy;
use super::{folder, Skipped};
use super::{Metadata, Split, METADATA_FILE};
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

pub const CAMERA_PARAM_FILE: &str = "camera_param.json";
pub const CARLA_POSES_DIR: &str = "carla_poses";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layout {
    /// `synth` if `metadata.json` exists, else `camera_param` if `camera_param.json`
    /// exists, else `carla` if `../carla_poses` exists, else `folder`.
    Auto,
    Folder,
    CameraParam,
    Carla,
    Synth,
}

impl Layout {
    pub fn name(self) -> &'static str {
        match self {
            Layout::Auto => "auto",
            Layout::Folder => "folder",
            Layout::CameraParam => "camera_param",
            Layout::Carla => "carla",
            Layout::Synth => "synth",
        }
    }

    pub fn resolve(self, dir: &Path) -> Layout {
        match self {
            Layout::Auto if dir.join(METADATA_FILE).is_file() => Layout::Synth,
            Layout::Auto if dir.join(CAMERA_PARAM_FILE).is_file() => Layout::CameraParam,
            Layout::Auto if carla_poses_dir(dir).is_dir() => Layout::Carla,
            Layout::Auto => Layout::Folder,
            l => l,
        }
    }
}

impl std::str::FromStr for Layout {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        [Layout::Auto, Layout::Folder, Layout::CameraParam, Layout::Carla, Layout::Synth]
            .into_iter()
            .find(|l| l.name() == s || l.name().replace('_', "-") == s)
            .ok_or_else(|| {
                Error::Invalid(format!("unknown layout '{s}', expected auto, folder, camera_param, carla or synth"))
            })
    }
}

/// A horizontal flip the layout prescribes as augmentation, mapping yaw θ → π − θ
/// (the release's CARLA rule).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Flip {
    pub probability: f64,
}

impl Flip {
    pub fn yaw(theta: f64) -> f64 {
        std::f64::consts::PI - theta
    }
}

/// The images of a dataset and their poses, before decoding.
#[derive(Debug, Clone)]
pub struct Listing {
    pub layout: Layout,
    pub files: Vec<PathBuf>,
    /// Names relative to the dataset folder, aligned with `files`.
    pub names: Vec<String>,
    /// `[pitch, yaw]` per file, when the dataset has poses.
    pub poses: Option<Vec<[f64; 2]>>,
    pub flip: Option<Flip>,
    /// Pose files read (they take part in the cache fingerprint).
    pub pose_files: Vec<PathBuf>,
    pub skipped: Vec<Skipped>,
}

/// What to list: see [`super::LoadOptions`].
pub struct ListOptions<'a> {
    pub layout: Layout,
    pub poses: Option<&'a Path>,
    pub require_poses: bool,
    pub skip_bad: bool,
    pub split: Option<Split>,
}

fn carla_poses_dir(dir: &Path) -> PathBuf {
    let abs = dir.canonicalize().unwrap_or_else(|_| dir.to_path_buf());
    abs.parent().unwrap_or(&abs).join(CARLA_POSES_DIR)
}

/// Collects problems: an error, or with `skip_bad` a skipped entry.
struct Problems {
    skip_bad: bool,
    skipped: Vec<Skipped>,
}

impl Problems {
    fn report(&mut self, path: &Path, reason: String) -> Result<()> {
        if self.skip_bad {
            self.skipped.push(Skipped { path: path.to_path_buf(), reason });
            Ok(())
        } else {
            Err(Error::Data { path: path.to_path_buf(), reason })
        }
    }
}

fn name_of(dir: &Path, file: &Path) -> String {
    file.strip_prefix(dir).unwrap_or(file).to_string_lossy().replace('\\', "/")
}

pub fn list(dir: &Path, opts: &ListOptions) -> Result<Listing> {
    if !dir.is_dir() {
        return Err(Error::Data {
            path: dir.to_path_buf(),
            reason: "not a folder (expected a folder of images)".into(),
        });
    }
    let layout = opts.layout.resolve(dir);
    let mut problems = Problems { skip_bad: opts.skip_bad, skipped: Vec::new() };
    let mut listing = Listing {
        layout,
        files: Vec::new(),
        names: Vec::new(),
        poses: None,
        flip: None,
        pose_files: Vec::new(),
        skipped: Vec::new(),
    };
    match layout {
        Layout::Folder => match opts.poses {
            Some(pose_file) => list_with_pose_file(dir, pose_file, &mut listing, &mut problems)?,
            None => {
                if opts.require_poses {
                    return Err(Error::Data {
                        path: dir.to_path_buf(),
                        reason: format!(
                            "poses are required but there is no pose file (give one, or add {CAMERA_PARAM_FILE})"
                        ),
                    });
                }
                listing.files = folder::list_images(dir)?;
                listing.names = listing.files.iter().map(|f| name_of(dir, f)).collect();
            }
        },
        Layout::CameraParam => {
            let pose_file = opts.poses.map(Path::to_path_buf).unwrap_or_else(|| dir.join(CAMERA_PARAM_FILE));
            list_with_pose_file(dir, &pose_file, &mut listing, &mut problems)?;
        }
        Layout::Carla => list_carla(dir, opts, &mut listing, &mut problems)?,
        Layout::Synth => {
            let meta = Metadata::load(dir)?;
            listing.pose_files.push(dir.join(METADATA_FILE));
            let mut poses = Vec::new();
            for r in meta.images.iter().filter(|r| opts.split.is_none_or(|s| r.split == s)) {
                let f = dir.join(&r.file);
                if f.is_file() {
                    listing.files.push(f);
                    listing.names.push(r.file.clone());
                    poses.push([r.pitch, r.yaw]);
                } else {
                    problems.report(&f, format!("listed in {METADATA_FILE} but missing"))?;
                }
            }
            listing.poses = Some(poses);
        }
        Layout::Auto => unreachable!("resolved above"),
    }
    if listing.files.is_empty() {
        return Err(Error::Data {
            path: dir.to_path_buf(),
            reason: format!("no images found ({} layout)", layout.name()),
        });
    }
    listing.skipped = problems.skipped;
    Ok(listing)
}

/// Images named by a `camera_param`-format pose file; images in the folder that the
/// file does not name are images without poses.
fn list_with_pose_file(dir: &Path, pose_file: &Path, listing: &mut Listing, problems: &mut Problems) -> Result<()> {
    let poses = read_camera_param(pose_file)?;
    listing.pose_files.push(pose_file.to_path_buf());
    let mut named = BTreeSet::new();
    let mut out = Vec::new();
    for (name, pose) in poses {
        let f = dir.join(&name);
        named.insert(f.clone());
        if f.is_file() {
            listing.files.push(f);
            listing.names.push(name);
            out.push(pose);
        } else {
            problems.report(&f, format!("named in the pose file {} but missing", pose_file.display()))?;
        }
    }
    for f in folder::list_images(dir)? {
        if !named.contains(&f) {
            problems.report(&f, format!("image has no pose in {}", pose_file.display()))?;
        }
    }
    listing.poses = Some(out);
    Ok(())
}

/// Reads a `camera_param.json`: file name → {"phi": pitch, "theta": yaw, ...}, in name order.
pub fn read_camera_param(path: &Path) -> Result<BTreeMap<String, [f64; 2]>> {
    let data_err = |reason: String| Error::Data { path: path.to_path_buf(), reason };
    let text = std::fs::read_to_string(path).map_err(|e| data_err(format!("cannot read the pose file: {e}")))?;
    let map: BTreeMap<String, serde_json::Value> = serde_json::from_str(&text).map_err(|e| {
        data_err(format!("not a pose file (expected {{\"image.png\": {{\"phi\": …, \"theta\": …}}}}): {e}"))
    })?;
    let mut out = BTreeMap::new();
    for (name, v) in map {
        let angle = |k: &str| {
            v.get(k)
                .and_then(serde_json::Value::as_f64)
                .filter(|x| x.is_finite())
                .ok_or_else(|| data_err(format!("entry '{name}' has no finite number '{k}'")))
        };
        out.insert(name.clone(), [angle("phi")?, angle("theta")?]);
    }
    Ok(out)
}

fn list_carla(dir: &Path, opts: &ListOptions, listing: &mut Listing, problems: &mut Problems) -> Result<()> {
    let files: Vec<PathBuf> = folder::list_images(dir)?
        .into_iter()
        .filter(|f| f.extension().is_some_and(|e| e.eq_ignore_ascii_case("png")))
        .collect();
    let pose_dir = opts.poses.map(Path::to_path_buf).unwrap_or_else(|| carla_poses_dir(dir));
    listing.flip = Some(Flip { probability: 0.5 });
    if !pose_dir.is_dir() {
        if opts.require_poses {
            return Err(Error::Data {
                path: pose_dir,
                reason: "poses are required but this CARLA pose folder does not exist".into(),
            });
        }
        listing.names = files.iter().map(|f| name_of(dir, f)).collect();
        listing.files = files;
        return Ok(());
    }
    let mut poses = Vec::new();
    for f in files {
        let stem = f.file_stem().unwrap_or_default().to_string_lossy();
        let npy_path = pose_dir.join(format!("{stem}_extrinsics.npy"));
        let pose = match npy::read_matrix(&npy_path) {
            Ok(m) => carla_pose(&m).map_err(|reason| Error::Data { path: npy_path.clone(), reason }),
            Err(Error::Io { err, .. }) if err.kind() == std::io::ErrorKind::NotFound => Err(Error::Data {
                path: f.clone(),
                reason: format!("image has no pose ({} is missing)", npy_path.display()),
            }),
            Err(e) => Err(e),
        };
        match pose {
            Ok(p) => {
                listing.pose_files.push(npy_path);
                listing.names.push(name_of(dir, &f));
                listing.files.push(f);
                poses.push(p);
            }
            Err(Error::Data { path, reason }) => problems.report(&path, reason)?,
            Err(e) => problems.report(&npy_path, e.to_string())?,
        }
    }
    listing.poses = Some(poses);
    Ok(())
}

/// The release's CARLA conversion (`transform_matrix_to_camera_pos`, unflipped): rows
/// permuted to (y, z, x), p = translation; θ = atan2(−p₀, p₂) + π/2,
/// φ = atan(−p₁ / ‖(p₀, p₂)‖) + π/2. Returns `[pitch φ, yaw θ]`.
pub fn carla_pose(c2w: &npy::Matrix3x4) -> std::result::Result<[f64; 2], String> {
    let p = [c2w[1][3], c2w[2][3], c2w[0][3]];
    let horizontal = p[0].hypot(p[2]);
    if horizontal == 0.0 && p[1] == 0.0 {
        return Err("camera position is the origin; no pose can be derived".into());
    }
    let theta = (-p[0]).atan2(p[2]) + std::f64::consts::FRAC_PI_2;
    let phi = (-p[1] / horizontal).atan() + std::f64::consts::FRAC_PI_2;
    Ok([phi, theta])
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::{FRAC_PI_2, PI};

    /// CARLA's convention is z-up; a camera above the object (+z) has φ = 0 and a camera
    /// in the ground plane has φ = π/2, as in our y-up convention.
    #[test]
    fn carla_conversion_follows_the_release() {
        let at = |x: f64, y: f64, z: f64| [[1.0, 0.0, 0.0, x], [0.0, 1.0, 0.0, y], [0.0, 0.0, 1.0, z]];
        let [phi, _] = carla_pose(&at(0.0, 1e-9, 1.0)).unwrap();
        assert!(phi.abs() < 1e-6, "{phi}");
        let [phi, theta] = carla_pose(&at(1.0, 0.0, 0.0)).unwrap();
        assert!((phi - FRAC_PI_2).abs() < 1e-12);
        // p = (y, z, x) = (0, 0, 1): θ = atan2(0, 1) + π/2 = π/2.
        assert!((theta - FRAC_PI_2).abs() < 1e-12);
        let [_, theta] = carla_pose(&at(0.0, 1.0, 0.0)).unwrap();
        // p = (1, 0, 0): θ = atan2(−1, 0) + π/2 = 0.
        assert!(theta.abs() < 1e-12);
        assert!((Flip::yaw(0.25) - (PI - 0.25)).abs() < 1e-15);
        assert!(carla_pose(&at(0.0, 0.0, 0.0)).is_err());
    }
}
