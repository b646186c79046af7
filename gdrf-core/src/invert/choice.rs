//! Which initialiser and which pose an inversion of a photo uses, and how the user is told:
//! by default the initialiser shipped beside the generator ([`init::INIT_FILE`]), its
//! estimate of the photo's pose, refined with the features.
use super::init::{self, Initialiser};
use super::PoseFrom;
use crate::error::Context;
use crate::{Error, Result};
use std::path::{Path, PathBuf};
use tch::Device;

/// What `--init` asked for.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum InitChoice {
    /// The initialiser beside the generator file, when there is one.
    #[default]
    Beside,
    /// None: w_s starts at the mean code's (`--init none`).
    None,
    /// This file.
    File(PathBuf),
}

impl std::str::FromStr for InitChoice {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "" => Err(Error::Invalid("--init: give a file, or none for the mean code".into())),
            "none" => Ok(InitChoice::None),
            p => Ok(InitChoice::File(PathBuf::from(p))),
        }
    }
}

/// The initialiser an inversion starts from, and a line that says where it came from.
pub struct Chosen {
    pub init: Option<Initialiser>,
    /// The file it was read from.
    pub path: Option<PathBuf>,
    /// Where w_s starts, said for the user.
    pub said: String,
}

/// The initialiser file of the generator at `generator_path`: [`init::INIT_FILE`] in its
/// folder.
pub fn beside(generator_path: &Path) -> PathBuf {
    generator_path.with_file_name(init::INIT_FILE)
}

/// Opens the initialiser `choice` names for the generator at `generator_path` (identity
/// `generator_id`), given with `flag` (`--init`, `--photo-init`). A file made for another
/// generator is an error naming both, whether it was given or found beside the generator;
/// a generator without one beside it starts from the mean code, and the line says so.
pub fn open(
    choice: &InitChoice,
    flag: &str,
    generator_path: &Path,
    generator_id: &str,
    device: Device,
) -> Result<Chosen> {
    let load = |p: &Path, what: &str| {
        Initialiser::load(p, generator_id, device)
            .with_context(|| format!("loading {what} {} ({flag} none starts from the mean code)", p.display()))
    };
    Ok(match choice {
        InitChoice::None => {
            Chosen { init: None, path: None, said: format!("{flag} none: w_s starts at the mean code's") }
        }
        InitChoice::File(p) => Chosen {
            init: Some(load(p, flag)?),
            path: Some(p.clone()),
            said: format!("w_s starts at the prediction of the initialiser {}", crate::paths::shown(p)),
        },
        InitChoice::Beside => {
            let p = beside(generator_path);
            if p.is_file() {
                Chosen {
                    init: Some(load(&p, "the initialiser beside the generator,")?),
                    said: format!("w_s starts at the prediction of the initialiser {}", crate::paths::shown(&p)),
                    path: Some(p),
                }
            } else {
                Chosen {
                    init: None,
                    path: None,
                    said: format!(
                        "no initialiser beside {} (gdrf-invert train-init --ship {} trains one): w_s starts at the mean code's",
                        crate::paths::shown(generator_path),
                        crate::paths::shown(&p)
                    ),
                }
            }
        }
    })
}

/// Whether the pose is optimised with the features (`--refine-pose`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum RefinePose {
    /// When the initialiser estimated it; not a pose given with --pose, nor the camera's
    /// mean pose (from which shape and pitch trade off).
    #[default]
    Auto,
    On,
    Off,
}

impl RefinePose {
    pub fn resolve(self, from: PoseFrom) -> bool {
        match self {
            RefinePose::Auto => from == PoseFrom::Initialiser,
            RefinePose::On => true,
            RefinePose::Off => false,
        }
    }
}

/// The pose in degrees and how it was obtained, for the user.
pub fn describe_pose(pose: (f64, f64), from: PoseFrom, refined: bool) -> String {
    let how = match from {
        PoseFrom::Given => "given by --pose",
        PoseFrom::Initialiser => "estimated by the initialiser",
        PoseFrom::CameraMean => "the camera's mean pose: no --pose and no initialiser",
    };
    format!(
        "pose: pitch {:.1}°, yaw {:.1}° ({how}){}",
        pose.0.to_degrees(),
        pose.1.to_degrees(),
        if refined { ", refined with the features" } else { "" }
    )
}

impl PoseFrom {
    /// The name invert.json records.
    pub fn name(self) -> &'static str {
        match self {
            PoseFrom::Given => "given",
            PoseFrom::Initialiser => "initialiser",
            PoseFrom::CameraMean => "camera mean",
        }
    }
}
