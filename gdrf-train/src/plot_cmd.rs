//! `gdrf-train plot RUN_DIR`: loss curves and training health from metrics.jsonl, and the
//! learning curve from curve.jsonl.
use anyhow::{bail, Result};
use clap::Args;
use gdrf_core::plot::{draw_panels, smooth, Panel, Series};
use gdrf_core::train::config::TrainConfig;
use gdrf_core::train::{curve, plateau, run};
use std::path::{Path, PathBuf};

#[derive(Args)]
pub struct PlotArgs {
    /// A run directory written by `gdrf-train --config`.
    run_dir: PathBuf,
    /// Output PNG (default: RUN_DIR/losses.png).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Moving-average window in logged steps (GAN losses are noisy; 1 = raw).
    #[arg(long, default_value_t = 25)]
    smooth: usize,
}

/// (panel title, log y axis, [(series name, JSON path)]).
type PanelSpec = (&'static str, bool, &'static [(&'static str, &'static str)]);

const PANELS: &[PanelSpec] = &[
    ("discriminator", false, &[("d_real", "d.d_real"), ("d_fake", "d.d_fake"), ("d_total", "d_total")]),
    ("generator adversarial", false, &[("g_adv", "g.g_adv"), ("g_total", "g_total")]),
    ("pose 1-cos", true, &[("g_pose", "g.g_pose"), ("d_pose_fake", "d.d_pose_fake"), ("d_pose_real", "d.d_pose_real")]),
    ("r1", true, &[("d_r1", "d.d_r1")]),
    (
        "regularisers",
        true,
        &[
            ("correction", "g.reg_correction"),
            ("smoothness", "g.reg_smoothness"),
            ("rigidity", "g.reg_rigidity"),
            ("normal", "g.reg_normal"),
        ],
    ),
    ("grad norm before clip", true, &[("g", "grad_norm_g"), ("d", "grad_norm_d")]),
    ("learning rate", true, &[("g", "lr_g"), ("d", "lr_d")]),
    ("images/s", false, &[("images/s", "images_per_second")]),
];

fn lookup(v: &serde_json::Value, path: &str) -> f64 {
    path.split('.').fold(v, |v, k| &v[k]).as_f64().unwrap_or(f64::NAN)
}

pub fn plot(a: PlotArgs) -> Result<()> {
    let all = run::read_metrics(&a.run_dir)?;
    let records: Vec<_> = all.iter().filter(|r| r.get("event").is_none()).collect();
    if records.is_empty() {
        bail!("{}: metrics.jsonl holds no logged step yet", a.run_dir.display());
    }
    // Where a stage of the run's config starts, so a jump in a loss can be read against it
    // (none for a folder of metrics without its config).
    let starts = curve::run_stage_starts(&a.run_dir, &all)?;
    let marks: Vec<f64> = starts.iter().map(|&(step, _)| step as f64).collect();
    let panels: Vec<Panel> = PANELS
        .iter()
        .map(|(title, log_y, series)| Panel {
            title: title.to_string(),
            log_y: *log_y,
            marks: marks.clone(),
            series: series
                .iter()
                .map(|(name, path)| {
                    let pts: Vec<(f64, f64)> =
                        records.iter().map(|r| (r["step"].as_f64().unwrap_or(f64::NAN), lookup(r, path))).collect();
                    let k = if title.starts_with("learning") { 1 } else { a.smooth };
                    Series { name: name.to_string(), points: smooth(&pts, k) }
                })
                .filter(|s| s.points.iter().any(|p| p.1.is_finite()))
                .collect(),
        })
        .collect();
    let img = draw_panels(&panels, 4, 360, 240)?;
    let out = a.out.unwrap_or_else(|| a.run_dir.join("losses.png"));
    gdrf_core::io::save_png(&out, &img)?;
    println!("wrote {} ({} logged steps, moving average over {})", out.display(), records.len(), a.smooth);
    // The learning curve, where the run scores itself (`[eval] interval`).
    // A curve whose evaluation frames are gone (a copy made without them) still has a
    // standing; only the filmstrip is left out.
    if let Some(c) = curve::plot(&a.run_dir, &starts)? {
        let lines = curve::read(&a.run_dir)?;
        match curve::filmstrip(&a.run_dir, &starts)? {
            Some(f) => println!("wrote {} and {} ({} evaluations)", c.display(), f.display(), lines.len()),
            None => println!(
                "wrote {} ({} evaluations; no filmstrip: no evaluation kept its frame)",
                c.display(),
                lines.len()
            ),
        }
        if let Some(s) = standing(&a.run_dir, &lines, &all)? {
            println!("{s}");
        }
    }
    Ok(())
}

/// Where the learning curve stands under the campaign's flatness rule
/// ([`gdrf_core::train::plateau`]), in one line, given its curve and its metrics.jsonl. The
/// schedule's last change is the start of the stage (its config.toml) in force at the newest
/// logged step; a change made otherwise (a loss weight, say) is not in the config's history
/// and is not seen.
pub fn standing(run_dir: &Path, lines: &[serde_json::Value], metrics: &[serde_json::Value]) -> Result<Option<String>> {
    let cfg = TrainConfig::load(&run_dir.join(run::CONFIG))?;
    let now = metrics.iter().chain(lines).filter_map(|l| l["step"].as_i64()).max();
    let last_change = now.map(|n| cfg.stage(n).from_step).filter(|&f| f > 0);
    let Some(s) = plateau::standing(lines, last_change) else { return Ok(None) };
    let what = if s.improved.is_empty() {
        "first evaluated".to_string()
    } else {
        format!("last improved ({})", s.improved.join(", "))
    };
    let counted = match s.last_change {
        Some(c) if c > s.last_improvement => {
            format!("; a stage changed the schedule at step {c}, and the rule counts from there")
        }
        _ => String::new(),
    };
    let gap = s.last - s.since();
    let gap = if gap >= 0 { format!("{gap} steps before") } else { format!("{} steps after", -gap) };
    Ok(Some(format!(
        "the curve {what} at step {}{counted}, {gap} its last evaluation (step {}): {}",
        s.last_improvement,
        s.last,
        if s.flat() { format!("flat (at least {} steps)", plateau::FLAT_STEPS) } else { "not flat".to_string() }
    )))
}
