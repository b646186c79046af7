//! The run directory: checkpoints (the last K kept), the exported EMA generator, the
//! resolved config, metrics.jsonl and preview images; and how a session takes it ([`take`]:
//! the lock, starting over with `force`, the ranks of a data-parallel run).
//!
//! ```text
//! RUN_DIR/config.toml                    the resolved config (every default written out)
//! RUN_DIR/checkpoints/step-NNNNNNNN.safetensors   training state after N steps
//! RUN_DIR/generator.safetensors          EMA generator of the latest checkpoint
//! RUN_DIR/metrics.jsonl                  one JSON object per logged step or event
//! RUN_DIR/samples/step-NNNNNNNN-{samples,swap,template}.png and latest-*.png
//! RUN_DIR/.lock                          held by the process training in RUN_DIR
//! RUN_DIR/curve.jsonl, curve.png, filmstrip.png, evals/   the learning curve ([`super::curve`])
//! ```
use crate::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const CHECKPOINTS: &str = "checkpoints";
pub const METRICS: &str = "metrics.jsonl";
pub const CONFIG: &str = "config.toml";
pub const GENERATOR: &str = "generator.safetensors";
pub const SAMPLES: &str = "samples";

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io { path: path.to_path_buf(), err: source }
}

pub const LOCK: &str = ".lock";

/// Exclusive use of a run directory by one process, held until dropped (or the process
/// ends, however it ends: the operating system releases the lock). Two trainers writing
/// into one folder would interleave checkpoints and metrics; a second `gdrf-train` on a
/// folder in use — also `--force` while the old process is still exiting — is refused.
#[derive(Debug)]
pub struct RunLock {
    _file: std::fs::File,
}

impl RunLock {
    /// Takes the lock on `run_dir` (creating the folder), or an error naming the folder and
    /// the process that holds it.
    pub fn acquire(run_dir: &Path) -> Result<Self> {
        std::fs::create_dir_all(run_dir).map_err(io(run_dir))?;
        let path = run_dir.join(LOCK);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .map_err(io(&path))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                let by = if holder.is_empty() { String::new() } else { format!(" (process {holder})") };
                return Err(Error::Invalid(format!(
                    "{} is in use by another gdrf-train{by}; wait for it to finish or stop it first",
                    run_dir.display()
                )));
            }
            Err(std::fs::TryLockError::Error(e)) => return Err(io(&path)(e)),
        }
        file.set_len(0).map_err(io(&path))?;
        write!(file, "{}", std::process::id()).map_err(io(&path))?;
        // Holding the lock, no other process writes here: a temporary file is what a process
        // killed mid-write (kill -9, a crash, power loss) left behind.
        remove_temporaries(run_dir)?;
        Ok(Self { _file: file })
    }
}

/// What a session does with its run folder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Opening {
    /// Continues the run the folder holds.
    Resume,
    /// Starts a new run; `force`: in a folder that already holds one, whose checkpoints,
    /// metrics, config, generator and previews are removed first (refused without it).
    New { force: bool },
}

/// Takes `run_dir` for one session and builds the session's trainer with `open` once the
/// folder is ready; returns the folder's lock (held by the writing process: alone, or rank
/// 0 of `group`) with what `open` built. The other ranks of a group write nothing there,
/// and read it only once rank 0 has taken it (clearing what a killed writer left, or an
/// old run with [`Opening::New`] `force`) and opened it.
pub fn take<T, E: From<Error>>(
    run_dir: &Path,
    opening: Opening,
    group: Option<&crate::dist::ProcessGroup>,
    open: impl FnOnce() -> std::result::Result<T, E>,
) -> std::result::Result<(Option<RunLock>, T), E> {
    let writer = group.is_none_or(|g| g.rank() == 0);
    // One process per run directory, taken before `force` clears anything.
    let lock = writer.then(|| RunLock::acquire(run_dir)).transpose()?;
    if let (Some(g), false) = (group, writer) {
        g.barrier()?;
    }
    if let (Opening::New { force }, true) = (opening, writer) {
        if !list_checkpoints(run_dir)?.is_empty() {
            if !force {
                return Err(Error::RunExists { path: run_dir.to_path_buf() }.into());
            }
            for sub in [CHECKPOINTS, SAMPLES] {
                let _ = std::fs::remove_dir_all(run_dir.join(sub));
            }
            for f in [METRICS, CONFIG, GENERATOR] {
                let _ = std::fs::remove_file(run_dir.join(f));
            }
        }
    }
    let opened = open()?;
    if let (Some(g), true) = (group, writer) {
        g.barrier()?;
    }
    Ok((lock, opened))
}

/// File name of the checkpoint after `step` steps.
pub fn checkpoint_name(step: i64) -> String {
    format!("step-{step:08}.safetensors")
}

/// Checkpoints of a run, oldest first, with their step counts.
pub fn list_checkpoints(run_dir: &Path) -> Result<Vec<(i64, PathBuf)>> {
    let dir = run_dir.join(CHECKPOINTS);
    if !dir.is_dir() {
        return Ok(Vec::new());
    }
    let mut out = Vec::new();
    for entry in std::fs::read_dir(&dir).map_err(io(&dir))? {
        let path = entry.map_err(io(&dir))?.path();
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
        if let Some(step) = name.strip_prefix("step-").and_then(|s| s.strip_suffix(".safetensors")) {
            if let Ok(step) = step.parse::<i64>() {
                out.push((step, path));
            }
        }
    }
    out.sort();
    Ok(out)
}

/// The newest checkpoint, or an error that says what the folder holds.
pub fn latest_checkpoint(run_dir: &Path) -> Result<(i64, PathBuf)> {
    list_checkpoints(run_dir)?.pop().ok_or_else(|| Error::Data {
        path: run_dir.to_path_buf(),
        reason: format!(
            "no checkpoint in {CHECKPOINTS}/ (expected step-NNNNNNNN.safetensors); is this a gdrf-train run directory?"
        ),
    })
}

/// Removes all but the newest `keep` checkpoints.
pub fn prune_checkpoints(run_dir: &Path, keep: usize) -> Result<()> {
    let all = list_checkpoints(run_dir)?;
    for (_, path) in all.iter().take(all.len().saturating_sub(keep)) {
        std::fs::remove_file(path).map_err(io(path))?;
    }
    Ok(())
}

/// Removes [`crate::paths::write_atomic`]'s temporary files from `dir` and the folders in
/// it (checkpoints, samples, evaluations).
fn remove_temporaries(dir: &Path) -> Result<()> {
    for entry in std::fs::read_dir(dir).map_err(io(dir))? {
        let entry = entry.map_err(io(dir))?;
        let path = entry.path();
        let kind = entry.file_type().map_err(io(&path))?;
        if kind.is_dir() {
            remove_temporaries(&path)?;
        } else if kind.is_file() && crate::paths::is_temporary(&entry.file_name().to_string_lossy()) {
            std::fs::remove_file(&path).map_err(io(&path))?;
        }
    }
    Ok(())
}

/// Appends one JSON line to metrics.jsonl (see [`append_jsonl`]).
pub fn append_metrics<T: serde::Serialize>(run_dir: &Path, line: &T) -> Result<()> {
    append_jsonl(&run_dir.join(METRICS), line)
}

/// Appends one JSON line to the file at `path` (a whole line per write, on disk before it
/// returns: a checkpoint written later, which is synced, never outlives the lines before it).
pub fn append_jsonl<T: serde::Serialize>(path: &Path, line: &T) -> Result<()> {
    let mut f = std::fs::OpenOptions::new().create(true).append(true).open(path).map_err(io(path))?;
    let mut text = serde_json::to_string(line)?;
    text.push('\n');
    f.write_all(text.as_bytes()).map_err(io(path))?;
    f.sync_data().map_err(io(path))
}

/// Reads metrics.jsonl; a torn last line (a crash mid-write) is ignored.
pub fn read_metrics(run_dir: &Path) -> Result<Vec<serde_json::Value>> {
    read_jsonl(&run_dir.join(METRICS))
}

/// Reads a file of JSON lines; a torn last line (a crash mid-write) is ignored.
pub fn read_jsonl(path: &Path) -> Result<Vec<serde_json::Value>> {
    let text = std::fs::read_to_string(path).map_err(io(path))?;
    Ok(text.lines().filter_map(|l| serde_json::from_str(l).ok()).collect())
}

/// Keeps only the metrics of steps before `step` (and events before it), so a resumed
/// run does not log the replayed steps twice. Rewritten atomically.
pub fn truncate_metrics(run_dir: &Path, step: i64) -> Result<()> {
    truncate_jsonl(&run_dir.join(METRICS), |s| s < step)
}

/// Keeps the lines of a JSON-lines file whose `step` passes `keep` (none, if the file is
/// missing). Rewritten atomically.
pub fn truncate_jsonl(path: &Path, keep: impl Fn(i64) -> bool) -> Result<()> {
    if !path.exists() {
        return Ok(());
    }
    let kept: Vec<String> = read_jsonl(path)?
        .into_iter()
        .filter(|v| v["step"].as_i64().is_some_and(&keep))
        .map(|v| v.to_string() + "\n")
        .collect();
    crate::paths::write_atomic(path, kept.concat().as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_run_directory_is_locked_while_in_use_and_released_on_drop() {
        let dir = std::env::temp_dir().join(format!("gdrf-lock-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let held = RunLock::acquire(&dir).unwrap();
        let pid = std::process::id().to_string();
        assert_eq!(std::fs::read_to_string(dir.join(LOCK)).unwrap(), pid);
        let e = RunLock::acquire(&dir).unwrap_err().to_string();
        assert!(e.contains("in use by another gdrf-train") && e.contains(&pid), "{e}");
        drop(held);
        RunLock::acquire(&dir).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// What a process killed mid-write leaves (`.NAME.tmp-PID`, in the run folder or one
    /// below it) is removed when the next process takes the folder; nothing else is.
    #[test]
    fn taking_a_run_directory_removes_what_a_killed_writer_left() {
        let dir = std::env::temp_dir().join(format!("gdrf-lock-tmp-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join(CHECKPOINTS)).unwrap();
        let left = [".metrics.jsonl.tmp-123", "checkpoints/.step-00000004.safetensors.tmp-4567"];
        let kept = ["metrics.jsonl", "checkpoints/step-00000002.safetensors", ".tmp-1", "notes.tmp-2", ".a.tmp-x"];
        for f in left.iter().chain(&kept) {
            std::fs::write(dir.join(f), b"x").unwrap();
        }
        let lock = RunLock::acquire(&dir).unwrap();
        for f in left {
            assert!(!dir.join(f).exists(), "{f} left behind");
        }
        for f in kept {
            assert!(dir.join(f).exists(), "{f} removed");
        }
        drop(lock);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
