//! Where things are and how files are written: the repository's folder and what lies in it
//! (the shipped generator, the project's Python), paths as shown in committed files, and
//! atomic writes.
use crate::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The project's folder (its scripts, weights, shipped models and virtual environment):
/// `$GDRF_ROOT` when set (binaries copied to another machine or folder), else the
/// repository the binaries were built in.
pub fn repo_root() -> PathBuf {
    match std::env::var_os("GDRF_ROOT") {
        Some(p) => p.into(),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).parent().map(Path::to_path_buf).unwrap_or_default(),
    }
}

/// The shipped generator (models/chairs-campaign: the campaign's checkpoint its learning
/// curve ranks best), the default of the commands that need one.
pub fn shipped_generator() -> PathBuf {
    repo_root().join("models/chairs-campaign/generator.safetensors")
}

/// `path` as written into committed figures: relative to the repository when it lies in it
/// (a shipped model), so that no machine's folder appears in them.
pub fn shown(path: &Path) -> String {
    path.strip_prefix(repo_root()).unwrap_or(path).display().to_string()
}

/// `$GDRF_PYTHON`, else the project's `.venv` (made by `scripts/setup.sh`).
pub fn python() -> PathBuf {
    std::env::var_os("GDRF_PYTHON").map(PathBuf::from).unwrap_or_else(|| repo_root().join(".venv/bin/python"))
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io { path: path.to_path_buf(), err: source }
}

/// What [`write_atomic`]'s temporary files carry in their name: `.NAME.tmp-PID`.
const TEMPORARY: &str = ".tmp-";

/// Whether `name` is one of [`write_atomic`]'s temporary files (left behind only by a
/// process killed while writing).
pub fn is_temporary(name: &str) -> bool {
    name.rsplit_once(TEMPORARY).is_some_and(|(dot_name, pid)| {
        dot_name.len() > 1 && dot_name.starts_with('.') && !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit())
    })
}

/// Writes `bytes` to `path` atomically: a temporary file in the same folder, flushed to
/// disk, then renamed over the target. A crash leaves either the old or the new file.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path.file_name().ok_or_else(|| Error::Invalid(format!("{}: not a file path", path.display())))?;
    let tmp = dir.join(format!(".{}{TEMPORARY}{}", name.to_string_lossy(), std::process::id()));
    let result = (|| {
        // Errors name the file being written, not its temporary.
        let mut f = std::fs::File::create(&tmp).map_err(io_err(path))?;
        f.write_all(bytes).map_err(io_err(path))?;
        f.sync_all().map_err(io_err(path))?;
        std::fs::rename(&tmp, path).map_err(io_err(path))?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// A fresh folder under the system's temporary folder, removed (best effort) when dropped:
/// the scratch space of the benchmarks and the tests. Its name holds `tag`, the process id
/// and a counter, so folders of one process never collide.
#[derive(Debug)]
pub struct TempDir(pub PathBuf);

impl TempDir {
    pub fn new(tag: &str) -> Result<Self> {
        static COUNT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let n = COUNT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("gdrf-{tag}-{}-{n}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        Ok(Self(dir))
    }

    /// `name` inside the folder.
    pub fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}
