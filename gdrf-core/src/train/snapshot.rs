//! A run's full state copied into one folder that `gdrf-train --resume` continues from, and
//! that a repository can commit in place of the previous copy (the campaign's
//! models/chairs-campaign/run, docs/training.md "The campaign").
//!
//! ```text
//! OUT/checkpoints/step-NNNNNNNN.safetensors   the run's newest checkpoint (only that one)
//! OUT/config.toml, metrics.jsonl               the resolved config and the logged steps
//! OUT/curve.jsonl, curve.png, filmstrip.png    the learning curve, where the run has one
//! OUT/evals/step-NNNNNNNN/frame.png            each evaluation's filmstrip row
//! ```
//!
//! The frames travel because a run re-draws its filmstrip from them at every evaluation: a
//! run resumed from a copy without them would draw only the evaluations made after the copy.
//! The rest of each evaluation folder (its generator, per-seed reports) stays behind; the
//! scores are on the curve.
use super::{curve, run};
use crate::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// What [`snapshot`] copied.
#[derive(Debug, Clone, PartialEq)]
pub struct Snapshot {
    /// The step of the checkpoint copied.
    pub step: i64,
    /// Files written under the output folder.
    pub files: usize,
    /// Evaluation frames among them.
    pub frames: usize,
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |err| Error::Io { path: path.to_path_buf(), err }
}

/// Whether `dir` can be replaced by a snapshot: missing, empty, or an earlier snapshot or
/// run (it holds config.toml or checkpoints/). Anything else is refused, so that a wrong
/// `--out` (a parent folder, a dataset) is never deleted.
fn replaceable(dir: &Path) -> Result<bool> {
    if !dir.exists() {
        return Ok(true);
    }
    if !dir.is_dir() {
        return Ok(false);
    }
    let empty = std::fs::read_dir(dir).map_err(io(dir))?.next().is_none();
    Ok(empty || dir.join(run::CONFIG).is_file() || dir.join(run::CHECKPOINTS).is_dir())
}

/// `path` (absolute) with links resolved as far as it exists, the rest appended: where a
/// folder that is still to be made would stand.
fn resolved(path: &Path) -> PathBuf {
    let mut rest = Vec::new();
    let mut at = path;
    loop {
        if let Ok(real) = at.canonicalize() {
            return rest.iter().rev().fold(real, |p, name| p.join(name));
        }
        match (at.parent(), at.file_name()) {
            (Some(parent), Some(name)) => {
                rest.push(name.to_owned());
                at = parent;
            }
            _ => return path.to_path_buf(),
        }
    }
}

/// Copies `run_dir`'s newest checkpoint, config, metrics, learning curve and evaluation
/// frames into `out`, replacing `out` whole. The copy is made in a temporary folder beside
/// `out` and renamed into place, so `out` holds either the previous snapshot or the new one,
/// never a mixture (between the two renames, the previous one is kept as `.NAME.old-PID`).
/// What a killed snapshot left beside `out` goes once the new one is in place.
/// Holds the run's lock while copying: a run being trained is refused, not copied midway.
pub fn snapshot(run_dir: &Path, out: &Path) -> Result<Snapshot> {
    if !run_dir.join(run::CONFIG).is_file() {
        return Err(Error::Data {
            path: run_dir.to_path_buf(),
            reason: format!("no {} here; is this a gdrf-train run directory?", run::CONFIG),
        });
    }
    let to = std::path::absolute(out).map_err(io(out))?;
    let (from_real, to_real) = (run_dir.canonicalize().map_err(io(run_dir))?, resolved(&to));
    if from_real.starts_with(&to_real) || to_real.starts_with(&from_real) {
        return Err(Error::Invalid(format!(
            "--out {} and the run {} must not hold one another",
            out.display(),
            run_dir.display()
        )));
    }
    if !replaceable(out)? {
        return Err(Error::Invalid(format!(
            "--out {} exists and is neither empty nor a run directory (no {} or {}/); refusing to replace it",
            out.display(),
            run::CONFIG,
            run::CHECKPOINTS
        )));
    }
    let _lock = run::RunLock::acquire(run_dir)?;
    let (step, checkpoint) = run::latest_checkpoint(run_dir)?;
    // (source, path under OUT)
    let mut files = vec![(checkpoint, Path::new(run::CHECKPOINTS).join(run::checkpoint_name(step)))];
    for name in [run::CONFIG, run::METRICS, curve::CURVE, curve::CURVE_PLOT, curve::FILMSTRIP] {
        if run_dir.join(name).is_file() {
            files.push((run_dir.join(name), PathBuf::from(name)));
        }
    }
    let mut frames = 0;
    for line in curve::read(run_dir)? {
        let Some(at) = line["step"].as_i64() else { continue };
        let frame = curve::eval_dir(run_dir, at).join(curve::FRAME);
        if frame.is_file() {
            let under = frame.strip_prefix(run_dir).expect("eval_dir is under the run").to_path_buf();
            files.push((frame, under));
            frames += 1;
        }
    }

    let parent = match to.parent() {
        Some(p) => p.to_path_buf(),
        None => return Err(Error::Invalid(format!("--out {}: not a folder path", out.display()))),
    };
    let name = to.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    std::fs::create_dir_all(&parent).map_err(io(&parent))?;
    let pid = std::process::id();
    let stage = parent.join(format!("{}{pid}", side_prefix(&name, STAGE)));
    let old = parent.join(format!("{}{pid}", side_prefix(&name, OLD)));
    let _ = std::fs::remove_dir_all(&stage);
    let copied = (|| -> Result<()> {
        for (source, under) in &files {
            let bytes = std::fs::read(source).map_err(io(source))?;
            let target = stage.join(under);
            // Errors name the file as it will be called, not its temporary folder.
            let named = out.join(under);
            std::fs::create_dir_all(target.parent().expect("a file under the stage")).map_err(io(&named))?;
            let mut f = std::fs::File::create(&target).map_err(io(&named))?;
            f.write_all(&bytes).map_err(io(&named))?;
            f.sync_all().map_err(io(&named))?;
        }
        Ok(())
    })();
    if let Err(e) = copied {
        let _ = std::fs::remove_dir_all(&stage);
        return Err(e);
    }
    if to.exists() {
        std::fs::rename(&to, &old).map_err(io(out))?;
    }
    std::fs::rename(&stage, &to).map_err(io(out))?;
    if old.exists() {
        std::fs::remove_dir_all(&old).map_err(io(&old))?;
    }
    remove_leftovers(&parent, &name)?;
    Ok(Snapshot { step, files: files.len(), frames })
}

/// The kinds of folder a snapshot into `parent/NAME` keeps beside it while it runs: the copy
/// being written, and the previous snapshot between the two renames.
const STAGE: &str = "tmp";
const OLD: &str = "old";

/// `.NAME.KIND-`, which the process id completes: hidden, and one per process, so that two
/// snapshots never share one.
fn side_prefix(name: &str, kind: &str) -> String {
    format!(".{name}.{kind}-")
}

/// Removes the `.NAME.tmp-PID` and `.NAME.old-PID` folders that an earlier snapshot into
/// `parent/NAME` left when it was killed, now that a complete snapshot stands in their place.
/// Only those of processes that no longer run (no `/proc/PID`): another snapshot into the
/// same folder may be copying right now. Where there is no `/proc`, nothing is removed.
fn remove_leftovers(parent: &Path, name: &str) -> Result<()> {
    let proc = Path::new("/proc");
    if !proc.is_dir() {
        return Ok(());
    }
    for entry in std::fs::read_dir(parent).map_err(io(parent))? {
        let path = entry.map_err(io(parent))?.path();
        let file = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let pid = [STAGE, OLD].iter().find_map(|kind| file.strip_prefix(&side_prefix(name, kind)));
        let Some(pid) = pid.filter(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit())) else { continue };
        if path.is_dir() && !proc.join(pid).exists() {
            std::fs::remove_dir_all(&path).map_err(io(&path))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_out_reached_through_a_link_into_the_run_is_refused() {
        let tmp = crate::paths::TempDir::new("snapshot-link").unwrap();
        let run_dir = tmp.path("run");
        std::fs::create_dir_all(&run_dir).unwrap();
        std::fs::write(run_dir.join(run::CONFIG), "").unwrap();
        std::os::unix::fs::symlink(&run_dir, tmp.path("link")).unwrap();
        let inside = tmp.path("link").join("copies").join("snap");
        assert_eq!(resolved(&inside), run_dir.canonicalize().unwrap().join("copies").join("snap"));
        let e = snapshot(&run_dir, &inside).unwrap_err().to_string();
        assert!(e.contains("must not hold one another"), "{e}");
        assert!(!run_dir.join("copies").exists() && !run_dir.join(run::LOCK).exists());
    }

    #[test]
    fn leftovers_of_dead_snapshots_are_removed_and_nothing_else() {
        let tmp = crate::paths::TempDir::new("snapshot-leftovers").unwrap();
        // 4 194 305 is above Linux's largest process id (2^22), so never a running process.
        let dead = [".snap.tmp-4194305", ".snap.old-4194305"];
        let live = format!(".snap.tmp-{}", std::process::id());
        let others = [".other.tmp-4194305", ".snap.tmp-", ".snap.tmp-12x", "snap"];
        for d in dead.iter().copied().chain([live.as_str()]).chain(others) {
            std::fs::create_dir_all(tmp.path(d).join("checkpoints")).unwrap();
        }
        remove_leftovers(&tmp.0, "snap").unwrap();
        for d in dead {
            assert!(!tmp.path(d).exists(), "{d}");
        }
        for d in [live.as_str()].into_iter().chain(others) {
            assert!(tmp.path(d).join("checkpoints").is_dir(), "{d}");
        }
    }
}
