//! `gdrf-bench step-summary`: several step benchmarks (`gdrf-bench step` JSON files, e.g.
//! the full-image step at 32², 64² and 128² beside the scaled-patch step) side by side in
//! one table, one JSON and one bar chart, each file's first run (gdrf's).
use super::{write_json, Run};
use crate::error::Context;
use crate::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

#[derive(clap::Args, Debug, Clone)]
pub struct Options {
    /// `gdrf-bench step` outputs (step-….json), in the order they are drawn.
    #[arg(required = true)]
    pub files: Vec<PathBuf>,
    /// Output stem: writes STEM.json and STEM.png.
    #[arg(long)]
    pub out: PathBuf,
    /// The chart's title (default: the machine); the rows keep each benchmark's own.
    #[arg(long)]
    pub title: Option<String>,
}

/// What a step benchmark's settings say of the images it rendered.
#[derive(Deserialize)]
struct Sizes {
    resolution: i64,
    #[serde(default)]
    patch: Option<i64>,
}

#[derive(Deserialize)]
struct StepDoc {
    title: String,
    machine: String,
    settings: Sizes,
    runs: Vec<Run>,
}

/// One benchmark's row: what was rendered, and gdrf's median step, images a second and
/// peak memory.
#[derive(Debug, Serialize)]
pub struct Row {
    pub file: String,
    pub label: String,
    pub title: String,
    pub machine: String,
    pub median_step_s: f64,
    pub images_per_second: f64,
    pub peak_rss_mb: f64,
}

/// Reads the files, prints the table and writes `--out`.json and .png.
pub fn run(a: &Options) -> Result<Vec<Row>> {
    let rows = a.files.iter().map(|f| row(f)).collect::<Result<Vec<_>>>()?;
    println!("{:<24} {:>14} {:>10} {:>10}", "", "median s/step", "images/s", "peak MB");
    for r in &rows {
        println!("{:<24} {:>14.3} {:>10.2} {:>10.0}", r.label, r.median_step_s, r.images_per_second, r.peak_rss_mb);
    }
    let stem = a.out.display().to_string();
    let (json, png) = (PathBuf::from(format!("{stem}.json")), PathBuf::from(format!("{stem}.png")));
    if let Some(dir) = json.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    write_json(&json, &rows)?;
    let bars = crate::plot::Bars {
        title: a.title.clone().unwrap_or_else(|| format!("Training step (median s, gdrf): {}", rows[0].machine)),
        y_label: "median seconds a step".into(),
        groups: rows.iter().map(|r| r.label.clone()).collect(),
        series: vec![("gdrf (tch)".into(), rows.iter().map(|r| r.median_step_s).collect())],
    };
    crate::io::save_png(&png, &crate::plot::draw_bars(&bars, 820, 420)?)?;
    println!("wrote {} and {}", json.display(), png.display());
    Ok(rows)
}

fn row(path: &Path) -> Result<Row> {
    let bad = |reason: String| Error::Data { path: path.to_path_buf(), reason };
    let text = std::fs::read_to_string(path).map_err(|err| Error::Io { path: path.to_path_buf(), err })?;
    let doc: StepDoc = serde_json::from_str(&text).map_err(|e| bad(format!("not a `gdrf-bench step` output: {e}")))?;
    let run = doc.runs.first().ok_or_else(|| bad("holds no run".into()))?;
    let r = doc.settings.resolution;
    let label = match doc.settings.patch {
        Some(p) => format!("{p}² patches of {r}²"),
        None => format!("{r}²"),
    };
    Ok(Row {
        file: path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
        label,
        title: doc.title,
        machine: doc.machine,
        median_step_s: run.median("step"),
        images_per_second: run.images_per_second.unwrap_or(f64::NAN),
        peak_rss_mb: run.peak_rss_mb,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::TempDir;

    #[test]
    fn rows_name_what_was_rendered_and_bad_files_are_named() {
        let dir = TempDir::new("step-summary").unwrap();
        let doc = |patch: &str| {
            format!(
                r#"{{"title": "t", "machine": "2 CPU threads", "settings": {{"resolution": 64{patch}}},
                "runs": [{{"implementation": "gdrf (tch)", "threads": 2, "median_s": {{"step": 2.5}},
                "samples_s": {{"step": [2.5]}}, "peak_rss_mb": 1800.0, "images_per_second": 3.2}}]}}"#
            )
        };
        let (whole, patch, bad) = (dir.path("whole.json"), dir.path("patch.json"), dir.path("bad.json"));
        std::fs::write(&whole, doc("")).unwrap();
        std::fs::write(&patch, doc(r#", "patch": 32"#)).unwrap();
        std::fs::write(&bad, r#"{"title": "t"}"#).unwrap();
        let out = dir.path("summary");
        let rows = run(&Options { files: vec![whole.clone(), patch], out: out.clone(), title: None }).unwrap();
        let labels: Vec<&str> = rows.iter().map(|r| r.label.as_str()).collect();
        assert_eq!(labels, ["64²", "32² patches of 64²"]);
        assert_eq!((rows[1].median_step_s, rows[1].images_per_second, rows[1].peak_rss_mb), (2.5, 3.2, 1800.0));
        assert!(dir.path("summary.json").exists() && dir.path("summary.png").exists());
        let e = run(&Options { files: vec![whole, bad.clone()], out, title: None }).unwrap_err().to_string();
        assert!(e.contains(&bad.display().to_string()) && e.contains("not a `gdrf-bench step` output"), "{e}");
    }
}
