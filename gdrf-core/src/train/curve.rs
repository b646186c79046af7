//! A run's learning curve: every `eval.interval` steps the EMA generator is scored the way
//! `gdrf-train eval --seeds` scores a generator file (each seed beside its random-weight
//! generator and the real end), and one line per evaluation is appended here.
//!
//! ```text
//! RUN_DIR/curve.jsonl                   one line per evaluation: step, images seen, time, every score per seed
//! RUN_DIR/curve.png                     each score's position (0 random end, 1 real end) against images seen, and the step time
//! RUN_DIR/filmstrip.png                 one row per evaluation: its samples and the top-left corner of its swap matrix
//! RUN_DIR/evals/step-NNNNNNNN/          seeds.json, and seed-S/{eval.json,report.png}, as `gdrf-train eval --seeds` writes them,
//!                                       and the EMA generator scored (generator.safetensors)
//! ```
use super::run;
use crate::eval::result::EvalResult;
use crate::eval::seeds::SeedSummary;
use crate::plot::{draw_panels, draw_text, Panel, Series};
use crate::{io, Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

pub const CURVE: &str = "curve.jsonl";
pub const CURVE_PLOT: &str = "curve.png";
pub const FILMSTRIP: &str = "filmstrip.png";
pub const EVALS: &str = "evals";
/// Each evaluation's filmstrip row, in its `evals/step-NNNNNNNN/` folder.
const FRAME: &str = "frame.png";

/// One line of curve.jsonl.
#[derive(Debug, Serialize)]
pub struct CurvePoint<'a> {
    pub step: i64,
    pub images_seen: i64,
    /// Seconds in training steps over all sessions of the run.
    pub train_seconds: f64,
    /// Median seconds per training step since the previous evaluation (of this session;
    /// `None` right after a resume).
    pub step_seconds: Option<f64>,
    /// Wall time of this evaluation.
    pub eval_seconds: f64,
    /// Every score per seed, the means and their positions.
    pub scores: &'a SeedSummary,
}

/// The folder of the evaluation at `step`.
pub fn eval_dir(run_dir: &Path, step: i64) -> PathBuf {
    run_dir.join(EVALS).join(run::checkpoint_name(step).trim_end_matches(".safetensors"))
}

/// Appends `point` to curve.jsonl, writes the evaluation's records into its folder and
/// re-draws curve.png and filmstrip.png. `results` are the per-seed results `point`
/// summarises.
pub fn record(run_dir: &Path, point: &CurvePoint, results: &[EvalResult]) -> Result<()> {
    let dir = eval_dir(run_dir, point.step);
    crate::eval::seeds::write_all(&dir, results, point.scores)?;
    if let Some(first) = results.first() {
        io::save_png(&dir.join(FRAME), &frame(first)?)?;
    }
    let line = serde_json::to_value(point)?;
    run::append_jsonl(&run_dir.join(CURVE), &line)?;
    plot(run_dir)?;
    filmstrip(run_dir)?;
    Ok(())
}

/// The lines of curve.jsonl (none when the run has no curve yet).
pub fn read(run_dir: &Path) -> Result<Vec<serde_json::Value>> {
    let path = run_dir.join(CURVE);
    if !path.exists() {
        return Ok(Vec::new());
    }
    run::read_jsonl(&path)
}

/// Keeps the evaluations of steps up to `step`: a run resumed from the checkpoint of
/// `step` evaluates the later ones again.
pub fn truncate(run_dir: &Path, step: i64) -> Result<()> {
    run::truncate_jsonl(&run_dir.join(CURVE), |s| s <= step)
}

/// Whether curve.jsonl holds the evaluation of `step`.
pub fn has(run_dir: &Path, step: i64) -> Result<bool> {
    Ok(read(run_dir)?.iter().any(|v| v["step"].as_i64() == Some(step)))
}

/// The calibrated scores whose positions the curve shows (the evaluation's names), and their
/// short names. The colour test's position is left out: its random end often lies above
/// the real one at 32², so its "position" runs off to ±3 and flattens the rest; it is drawn
/// as a rate beside the real end instead, with structure (see [`SWAP_SCORES`]).
const SCORES: &[(&str, &str)] = &[
    ("frechet distance", "frechet"),
    ("kernel distance", "kernel"),
    ("coverage tv", "coverage"),
    ("shape follows i", "structure"),
    ("pose yaw error deg", "yaw"),
    ("pose pitch error deg", "pitch"),
];

/// The swap tests, drawn as rates (how often a swap follows its code) beside the real ends:
/// structure rarely has a random end, so it has no position on most seeds.
const SWAP_SCORES: &[(&str, &str)] = &[("shape follows i", "structure"), ("appearance follows j", "colour")];

/// The scores the shipping rule counts: the calibrated ones. The colour test is compared
/// with the real end instead (its random end often scores above the real one at 32²).
pub const RULE_SCORES: &[&str] = &[
    "frechet distance",
    "kernel distance",
    "coverage tv",
    "shape follows i",
    "pose yaw error deg",
    "pose pitch error deg",
];

/// One evaluation as the shipping rule sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct RulePoint {
    pub step: i64,
    /// The lowest seed-mean position over [`RULE_SCORES`] (scores without a position skipped).
    pub lowest: f64,
    /// The score that holds it.
    pub score: String,
}

/// The shipping rule, fixed before the campaign's first evaluation (docs/training.md): the
/// evaluation whose lowest seed-mean position over [`RULE_SCORES`] is highest, ties to the
/// later step. `None` for a curve without a counted score.
pub fn best(lines: &[serde_json::Value]) -> Option<RulePoint> {
    lines
        .iter()
        .filter_map(|l| {
            let step = l["step"].as_i64()?;
            let (score, lowest) = l["scores"]["scores"]
                .as_array()?
                .iter()
                .filter(|s| s["score"].as_str().is_some_and(|n| RULE_SCORES.contains(&n)))
                .filter_map(|s| Some((s["score"].as_str()?.to_string(), s["mean"]["position"].as_f64()?)))
                .filter(|(_, p)| p.is_finite())
                .min_by(|a, b| a.1.total_cmp(&b.1))?;
            Some(RulePoint { step, lowest, score })
        })
        .max_by(|a, b| a.lowest.total_cmp(&b.lowest).then(a.step.cmp(&b.step)))
}

/// What the goal asks of every position (docs/training.md, "The campaign").
pub const GOAL_POSITION: f64 = 0.75;

/// Draws RUN_DIR/curve.png from curve.jsonl: the position of each calibrated score's seed
/// mean, the worst position over seeds, the yaw error in degrees, how often swaps follow
/// their code (structure, colour, beside the real ends) and the seconds per step, all
/// against thousands of images seen. Nothing is drawn for a run without a curve.
pub fn plot(run_dir: &Path) -> Result<Option<PathBuf>> {
    let lines = read(run_dir)?;
    if lines.is_empty() {
        return Ok(None);
    }
    let x = |l: &serde_json::Value| l["images_seen"].as_f64().unwrap_or(f64::NAN) / 1000.0;
    let score = |l: &serde_json::Value, name: &str| -> Option<serde_json::Value> {
        l["scores"]["scores"].as_array()?.iter().find(|s| s["score"] == name).cloned()
    };
    let num = |v: &serde_json::Value| v.as_f64().unwrap_or(f64::NAN);
    let goal = |points: usize| Series {
        name: format!("goal {GOAL_POSITION}"),
        points: lines.iter().take(points.max(1)).map(|l| (x(l), GOAL_POSITION)).collect(),
    };
    let per_score = |f: &dyn Fn(&serde_json::Value) -> f64| -> Vec<Series> {
        let mut series: Vec<Series> = SCORES
            .iter()
            .map(|(name, short)| Series {
                name: short.to_string(),
                points: lines.iter().map(|l| (x(l), score(l, name).map_or(f64::NAN, |s| f(&s)))).collect(),
            })
            .filter(|s| s.points.iter().any(|p| p.1.is_finite()))
            .collect();
        series.push(goal(lines.len()));
        series
    };
    let seeds: Vec<u64> = lines
        .last()
        .and_then(|l| l["scores"]["seeds"].as_array())
        .map(|a| a.iter().filter_map(|s| s.as_u64()).collect())
        .unwrap_or_default();
    let mut yaw: Vec<Series> = seeds
        .iter()
        .enumerate()
        .map(|(k, seed)| Series {
            name: format!("seed {seed}"),
            points: lines
                .iter()
                .map(|l| (x(l), score(l, "pose yaw error deg").map_or(f64::NAN, |s| num(&s["model"][k]))))
                .collect(),
        })
        .collect();
    yaw.push(Series {
        name: "real end".into(),
        points: lines
            .iter()
            .map(|l| (x(l), score(l, "pose yaw error deg").map_or(f64::NAN, |s| num(&s["mean"]["real"]))))
            .collect(),
    });
    yaw.push(Series { name: "goal 40".into(), points: lines.iter().map(|l| (x(l), 40.0)).collect() });
    let seed_mean = |v: &serde_json::Value| {
        let xs: Vec<f64> = v.as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default();
        xs.iter().sum::<f64>() / xs.len() as f64
    };
    let swaps: Vec<Series> = SWAP_SCORES
        .iter()
        .flat_map(|(name, short)| {
            ["model", "real"].map(|end| Series {
                name: match (end, *short) {
                    ("model", _) => short.to_string(),
                    (_, "colour") => "colour, real = goal".into(),
                    _ => format!("{short}, real"),
                },
                points: lines.iter().map(|l| (x(l), score(l, name).map_or(f64::NAN, |s| seed_mean(&s[end])))).collect(),
            })
        })
        .collect();
    let panels = vec![
        Panel {
            title: "position, mean of seeds".into(),
            series: per_score(&|s| num(&s["mean"]["position"])),
            log_y: false,
        },
        Panel { title: "position, worst seed".into(), series: per_score(&|s| num(&s["worst_position"])), log_y: false },
        Panel { title: "yaw error deg".into(), series: yaw, log_y: false },
        // No goal line: structure's is in the title, and colour's is its real line, which a
        // line at 0.75 would hide whenever the real rate is 0.75 too.
        Panel { title: format!("swaps following code, goal structure {GOAL_POSITION}"), series: swaps, log_y: false },
        Panel {
            title: "seconds per step".into(),
            series: vec![
                Series {
                    name: "median".into(),
                    points: lines.iter().map(|l| (x(l), l["step_seconds"].as_f64().unwrap_or(f64::NAN))).collect(),
                },
                Series { name: "mean".into(), points: lines.iter().map(x).zip(mean_step_seconds(&lines)).collect() },
            ],
            log_y: false,
        },
    ];
    let mut img = draw_panels(&panels, 2, 520, 320);
    let caption = format!(
        "x: thousand images seen. {} evaluations, last at step {}",
        lines.len(),
        lines.last().map_or(0, |l| l["step"].as_i64().unwrap_or(0))
    );
    let mut with_caption = image::RgbImage::from_pixel(img.width(), img.height() + 18, image::Rgb([255, 255, 255]));
    image::imageops::overlay(&mut with_caption, &img, 0, 0);
    draw_text(&mut with_caption, 10, img.height() as i64 + 4, &caption, image::Rgb([20, 20, 20]), 1);
    img = with_caption;
    let path = run_dir.join(CURVE_PLOT);
    io::save_png(&path, &img)?;
    Ok(Some(path))
}

/// Side of the swap matrix's corner a filmstrip row shows.
const FRAME_SWAP: i64 = 4;
/// Samples a filmstrip row shows (two rows of four).
const FRAME_SAMPLES: i64 = 8;

/// Mean seconds per training step between each evaluation and the one before it (NaN for
/// the first): the median hides a term that runs only every k-th step, the mean does not.
/// From `train_seconds`, so it includes whatever else shared the machine.
fn mean_step_seconds(lines: &[serde_json::Value]) -> Vec<f64> {
    let at = |l: &serde_json::Value| (l["step"].as_f64(), l["train_seconds"].as_f64());
    let mut out = vec![f64::NAN; lines.len().min(1)];
    for w in lines.windows(2) {
        out.push(match (at(&w[0]), at(&w[1])) {
            ((Some(s0), Some(t0)), (Some(s1), Some(t1))) if s1 > s0 => (t1 - t0) / (s1 - s0),
            _ => f64::NAN,
        });
    }
    out
}

/// One evaluation's filmstrip row: its first samples (4 × 2) and the top-left 4 × 4 of its
/// swap matrix (rows keep the shape, columns the appearance), at the evaluation's resolution.
fn frame(r: &EvalResult) -> Result<image::RgbImage> {
    let n = r.samples.size()[0].min(FRAME_SAMPLES);
    let samples = io::to_rgb8(&io::grid(&r.samples.narrow(0, 0, n), 4), false)?;
    let k = r.swap_side.min(FRAME_SWAP);
    let idx: Vec<i64> = (0..k).flat_map(|i| (0..k).map(move |j| i * r.swap_side + j)).collect();
    let corner = r.swap_images.index_select(0, &tch::Tensor::from_slice(&idx));
    let swap = io::to_rgb8(&io::grid(&corner, k), false)?;
    let gap = 8;
    let h = samples.height().max(swap.height());
    let mut img = image::RgbImage::from_pixel(samples.width() + gap + swap.width(), h, image::Rgb([255, 255, 255]));
    image::imageops::overlay(&mut img, &samples, 0, 0);
    image::imageops::overlay(&mut img, &swap, (samples.width() + gap) as i64, 0);
    Ok(img)
}

/// Stacks the frames of every evaluation on the curve into RUN_DIR/filmstrip.png, each
/// row labelled with its step and images seen.
pub fn filmstrip(run_dir: &Path) -> Result<Option<PathBuf>> {
    let mut rows = Vec::new();
    for l in read(run_dir)? {
        let step = l["step"].as_i64().unwrap_or(0);
        let path = eval_dir(run_dir, step).join(FRAME);
        if !path.exists() {
            continue;
        }
        let img = image::open(&path)
            .map_err(|e| Error::Data { path: path.clone(), reason: format!("not a readable image: {e}") })?
            .to_rgb8();
        rows.push((format!("step {step}"), format!("{}k images", l["images_seen"].as_i64().unwrap_or(0) / 1000), img));
    }
    if rows.is_empty() {
        return Ok(None);
    }
    let label_w = 96u32;
    let pad = 6u32;
    let w = label_w + rows.iter().map(|r| r.2.width()).max().unwrap_or(0) + pad;
    let h: u32 = rows.iter().map(|r| r.2.height() + pad).sum::<u32>() + pad;
    let mut out = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let mut y = pad;
    for (step, images, img) in &rows {
        draw_text(&mut out, 6, y as i64 + 2, step, image::Rgb([20, 20, 20]), 1);
        draw_text(&mut out, 6, y as i64 + 14, images, image::Rgb([90, 90, 90]), 1);
        image::imageops::overlay(&mut out, img, label_w as i64, y as i64);
        y += img.height() + pad;
    }
    let path = run_dir.join(FILMSTRIP);
    io::save_png(&path, &out)?;
    Ok(Some(path))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn line(step: i64, positions: &[(&str, Option<f64>)]) -> serde_json::Value {
        let scores: Vec<_> =
            positions.iter().map(|(name, p)| json!({"score": name, "mean": {"position": p}})).collect();
        json!({"step": step, "scores": {"scores": scores}})
    }

    #[test]
    fn the_shipping_rule_takes_the_best_lowest_position_and_the_later_tie() {
        let lines = [
            line(
                5000,
                &[("frechet distance", Some(0.58)), ("pose yaw error deg", Some(0.23)), ("shape follows i", None)],
            ),
            // The colour test is not counted, and a missing position is skipped.
            line(
                10000,
                &[("frechet distance", Some(0.69)), ("coverage tv", Some(0.62)), ("appearance follows j", Some(-3.0))],
            ),
            line(15000, &[("frechet distance", Some(0.9)), ("kernel distance", Some(0.62))]),
            line(20000, &[("pose pitch error deg", Some(0.4)), ("pose yaw error deg", Some(1.2))]),
        ];
        let b = best(&lines).unwrap();
        assert_eq!(b, RulePoint { step: 15000, lowest: 0.62, score: "kernel distance".into() });
        assert_eq!(best(&lines[..2]).unwrap().step, 10000);
        assert_eq!(
            best(&lines[..1]).unwrap(),
            RulePoint { step: 5000, lowest: 0.23, score: "pose yaw error deg".into() }
        );
        assert_eq!(best(&[line(5, &[("appearance follows j", Some(1.0))])]), None);
        assert_eq!(best(&[]), None);
    }

    #[test]
    fn the_mean_step_time_is_train_seconds_over_steps_between_evaluations() {
        let l = |step: i64, t: f64| json!({"step": step, "train_seconds": t});
        let m = mean_step_seconds(&[l(5000, 4000.0), l(10000, 8050.0), l(15000, 12050.0), json!({"step": 20000})]);
        assert_eq!(m.len(), 4);
        assert!(m[0].is_nan() && m[3].is_nan());
        assert_eq!(m[1..3], [0.81, 0.8]);
        assert!(mean_step_seconds(&[]).is_empty());
    }
}
