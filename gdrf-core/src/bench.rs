//! What the benchmark commands share: medians, the process's peak memory, and running a
//! PyTorch reference script (`scripts/reference/`) with the project's Python.
use crate::paths::{python, repo_root};
use crate::{Error, Result};
use std::path::Path;
use std::process::{Command, Stdio};

/// Median of `v` (NaN for an empty slice).
pub fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    match s.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => s[n / 2],
        n => 0.5 * (s[n / 2 - 1] + s[n / 2]),
    }
}

/// The process's peak resident memory so far in MB (Linux `VmHWM`; NaN elsewhere).
pub fn peak_rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).map(|l| l.to_string()))
        .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<f64>().ok()))
        .map(|kb| kb / 1024.0)
        .unwrap_or(f64::NAN)
}

/// Runs `scripts/reference/<script>` with the project's Python and reads the JSON it
/// prints (its progress messages go to our stderr).
pub fn run_reference(script: &str, args: &[String]) -> Result<serde_json::Value> {
    eprintln!("running the PyTorch reference ({script}) …");
    let out = Command::new(python())
        .arg(repo_root().join("scripts/reference").join(script))
        .args(args)
        .stderr(Stdio::inherit())
        .output()
        .map_err(|e| {
            Error::Invalid(format!("starting the PyTorch reference {} (run scripts/setup.sh): {e}", python().display()))
        })?;
    if !out.status.success() {
        return Err(Error::Invalid(format!("the PyTorch reference {script} failed (its messages are above)")));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| Error::Invalid(format!("reading the JSON of {script}: {e}")))
}

/// Runs `scripts/<script> ARGS…` (a plotting script) with the project's Python.
pub fn run_script(script: &str, args: &[&Path]) -> Result<()> {
    let status = Command::new(python())
        .arg(repo_root().join("scripts").join(script))
        .args(args)
        .status()
        .map_err(|e| Error::Invalid(format!("starting scripts/{script}: {e}")))?;
    if !status.success() {
        return Err(Error::Invalid(format!("scripts/{script} failed (is matplotlib installed? run scripts/setup.sh)")));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(median(&[]).is_nan());
    }
}
