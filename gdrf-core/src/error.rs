//! Library errors: each names the file, tensor or key at fault and what was expected.
use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// `err` is not named `source` on purpose: its text is already in this error's, and a
    /// source would be printed a second time by every error chain (`{:#}`).
    #[error("{path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    #[error("{path}: not a gdrf checkpoint ({reason})")]
    NotACheckpoint { path: PathBuf, reason: String },
    #[error("{path}: tensor '{name}' has shape {found:?}, the model expects {expected:?}")]
    ShapeMismatch { path: PathBuf, name: String, found: Vec<usize>, expected: Vec<usize> },
    #[error("{path}: tensor '{name}' is missing (the model expects shape {expected:?})")]
    MissingTensor { path: PathBuf, name: String, expected: Vec<usize> },
    #[error("{path}: unexpected tensor '{name}' with shape {found:?} (not part of this model)")]
    UnexpectedTensor { path: PathBuf, name: String, found: Vec<usize> },
    #[error("{path}: tensor '{name}' has dtype {found}, expected F32 or F64")]
    DType { path: PathBuf, name: String, found: String },
    /// An input file (a dataset's image, pose file or metadata, a photo, a feature file, an
    /// initialiser) that cannot be used, and why.
    #[error("{path}: {reason}")]
    Data { path: PathBuf, reason: String },
    #[error("invalid configuration: {0}")]
    Config(String),
    /// A tensor handed to the library whose shape or batch size does not fit (checked at
    /// the API boundary, so that it is an error here and not a panic inside libtorch).
    #[error("wrong tensor shape: {0}")]
    Shape(String),
    /// A helper program (the PyTorch reference, a plotting script) that could not start or
    /// failed.
    #[error("{program}: {reason}")]
    Subprocess { program: String, reason: String },
    /// A value that could not be written as JSON (a header, a metrics or curve line).
    #[error("JSON encoding: {0}")]
    Json(#[from] serde_json::Error),
    /// A new run started in a folder that already holds one (`--force` starts over).
    #[error(
        "{path} already holds a run; continue it with `gdrf-train --resume {path}`, or pass --force to start over"
    )]
    RunExists { path: PathBuf },
    /// An argument value outside what the function accepts.
    #[error("invalid argument: {0}")]
    Invalid(String),
    #[error(transparent)]
    Torch(#[from] tch::TchError),
    /// A launcher variable that is missing or wrong (named), or a collective of the
    /// data-parallel process group that failed (a peer that died or never came, a timeout).
    #[error("distributed: {0}")]
    Distributed(String),
    /// What was being done when `err` stopped it, naming the flag or file
    /// (`loading --checkpoint FILE: …`). Not `source`, as for [`Error::Io`].
    #[error("{what}: {err}")]
    While { what: String, err: Box<dyn std::error::Error + Send + Sync> },
}

pub type Result<T> = std::result::Result<T, Error>;

/// Puts what was being done in front of an error, as [`Error::While`].
pub trait Context<T> {
    /// `what` names the flag or file at fault (`loading --probe FILE`).
    fn with_context(self, what: impl FnOnce() -> String) -> Result<T>;
}

impl<T, E: std::error::Error + Send + Sync + 'static> Context<T> for std::result::Result<T, E> {
    fn with_context(self, what: impl FnOnce() -> String) -> Result<T> {
        self.map_err(|e| Error::While { what: what(), err: Box::new(e) })
    }
}

/// A configuration key's check: `Ok` when `ok`, else the error every config section gives,
/// "`key` is `value`, expected `expected`".
pub(crate) fn require(ok: bool, key: &str, value: impl std::fmt::Display, expected: &str) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(Error::Config(format!("{key} is {value}, expected {expected}")))
    }
}
