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
    let stage = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let old = parent.join(format!(".{name}.old-{}", std::process::id()));
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
    Ok(Snapshot { step, files: files.len(), frames })
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
}
