//! The commands of gdrf-invert: `gdrf-invert PHOTO` (a photo into shape and appearance
//! features, [`run`]), `gdrf-invert train-init` (the initialiser, [`train_init`]) and
//! `gdrf-invert framing` (where the training images' objects sit, [`framing`]),
//! their flags and progress bars (the `cli` feature).
mod framing;
mod run;
mod train_init;

pub use framing::{framing, FramingOptions};
pub use run::{run, Options};
pub use train_init::{train_init, TrainInitOptions};

use crate::{Error, Result};

/// `report` as the pretty JSON of invert.json and the initialiser's .json.
fn json(report: &serde_json::Value) -> Result<String> {
    serde_json::to_string_pretty(report).map_err(|e| Error::Invalid(e.to_string()))
}
