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
use super::config::TrainConfig;
use super::run;
use crate::eval::result::EvalResult;
use crate::eval::seeds::SeedSummary;
use crate::plot::{draw_dashes, draw_panels, draw_text, Lettering, Panel, Series, TEXT};
use crate::{io, Error, Result};
use serde::Serialize;
use serde_json::Value;
use std::path::{Path, PathBuf};

pub const CURVE: &str = "curve.jsonl";
pub const CURVE_PLOT: &str = "curve.png";
pub const FILMSTRIP: &str = "filmstrip.png";
pub const EVALS: &str = "evals";
/// Each evaluation's scores over its seeds, in its `evals/step-NNNNNNNN/` folder (as
/// `gdrf-train eval --seeds` names them).
const SEEDS: &str = "seeds.json";
/// Each evaluation's filmstrip row, in its `evals/step-NNNNNNNN/` folder.
pub const FRAME: &str = "frame.png";

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
    // Both pictures mark the stage starts; the run's metrics are read once for them.
    let metrics = if run_dir.join(run::METRICS).exists() { run::read_metrics(run_dir)? } else { Vec::new() };
    let starts = run_stage_starts(run_dir, &metrics)?;
    plot(run_dir, &starts)?;
    filmstrip(run_dir, &starts)?;
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
    /// Whether it meets the goal on every seed it was scored on ([`meets_goal`]).
    pub meets_goal: bool,
    /// The lowest seed-mean position over [`RULE_SCORES`] (scores without a position skipped).
    pub lowest: f64,
    /// The score that holds it.
    pub score: String,
}

/// The shipping rule (docs/training.md, "The campaign"): the evaluations that meet the goal
/// on every seed they were scored on come first; among them (or among all, while none
/// does) the one whose lowest seed-mean position over [`RULE_SCORES`] is highest, ties to
/// the later step. The second part was fixed before the campaign's first evaluation; the
/// first was added at step 102 067, after an evaluation first met the goal and the
/// positions alone ranked below it one whose swaps fell short of it. Only the evaluations
/// at the curve's highest resolution rank (fixed at step 205 046, before the 64² stage's
/// first evaluation): a model is shipped for the images it draws at its newest size, and
/// scores at another size are not comparable. `None` for a curve without a counted score.
pub fn best(lines: &[serde_json::Value]) -> Option<RulePoint> {
    let highest = lines.iter().filter_map(resolution).max();
    lines
        .iter()
        .filter(|l| resolution(l) == highest)
        .filter_map(|l| rule_point(l, l["step"].as_i64()?))
        .max_by(|a, b| rule_order(a, b).then(a.step.cmp(&b.step)))
}

/// The resolution a curve line (or a model folder's scores, wrapped as one) was scored at.
fn resolution(line: &serde_json::Value) -> Option<i64> {
    line["scores"]["resolution"].as_i64()
}

/// `line` as the rule sees it, as step `step`; `None` without a counted position.
fn rule_point(line: &serde_json::Value, step: i64) -> Option<RulePoint> {
    let (score, lowest) = line["scores"]["scores"]
        .as_array()?
        .iter()
        .filter(|s| s["score"].as_str().is_some_and(|n| RULE_SCORES.contains(&n)))
        .filter_map(|s| Some((s["score"].as_str()?.to_string(), s["mean"]["position"].as_f64()?)))
        .filter(|(_, p)| p.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))?;
    Some(RulePoint { step, meets_goal: meets_goal(line), lowest, score })
}

/// The rule's order without the steps: the goal met first, then the higher lowest position.
fn rule_order(a: &RulePoint, b: &RulePoint) -> std::cmp::Ordering {
    a.meets_goal.cmp(&b.meets_goal).then(a.lowest.total_cmp(&b.lowest))
}

/// What [`ship`] copied.
#[derive(Debug)]
pub struct Shipped {
    pub point: RulePoint,
    /// Evaluations on the curve.
    pub evaluations: usize,
    /// Where the generator came from: its evaluation folder's copy, the run's checkpoint of
    /// that step, or `out` itself when it already held that step's export or kept its own.
    pub from: PathBuf,
    /// Whether nothing was written: `out` already held that step's export, or kept its own.
    pub unchanged: bool,
    /// Where `out` holds another generator that ranks at or above the curve's best by the
    /// same rule, scored the same way ([`held_scores`]): that generator's standing (its
    /// step −1), and nothing was written.
    pub kept: Option<RulePoint>,
}

/// A model folder's scores at resolution R besides its own `seeds.json`, named
/// `seeds-R.json` (`seeds-64.json`): those of its generator scored at another resolution than
/// the one it was shipped at, which an evaluation at R must beat to replace it.
fn held_scores_name(resolution: i64) -> String {
    format!("seeds-{resolution}.json")
}

/// The scores at `line`'s resolution of the generator `out` holds, for the rule to compare
/// with `line`: `out/seeds.json` where it was scored at that resolution, else
/// `out/seeds-R.json`; `None` where `out` holds no generator. An error where it holds one
/// without scores at R, or where they were not scored as `line` was (seeds, images,
/// samples), naming the file.
pub fn held_scores(out: &Path, line: &Value) -> Result<Option<Value>> {
    if !out.join(run::GENERATOR).is_file() {
        return Ok(None);
    }
    let r = resolution(line).unwrap_or(0);
    let read = |path: &Path| -> Result<Value> {
        let text = std::fs::read_to_string(path).map_err(|err| Error::Io { path: path.to_path_buf(), err })?;
        serde_json::from_str(&text).map_err(|e| Error::Invalid(format!("{}: not a scores file: {e}", path.display())))
    };
    let own = out.join(SEEDS);
    let at_r = out.join(held_scores_name(r));
    let (path, held) = match own.is_file().then(|| read(&own)).transpose()? {
        Some(s) if s["resolution"].as_i64() == Some(r) => (own, s),
        _ if at_r.is_file() => {
            let s = read(&at_r)?;
            (at_r, s)
        }
        _ => {
            return Err(Error::Invalid(format!(
                "{} holds a generator without scores at {r}², the resolution the curve ranks: score it as the \
                 curve does (gdrf-train eval --generator {} --resolution {r} with the run's [eval] num, samples, \
                 swap and seeds) and copy that seeds.json to {}, or ship into another folder",
                out.display(),
                out.join(run::GENERATOR).display(),
                at_r.display()
            )))
        }
    };
    for key in ["resolution", "seeds", "images", "samples_per_ray", "psi"] {
        if held[key] != line["scores"][key] {
            return Err(Error::Invalid(format!(
                "{}: scored with {key} {}, the curve's evaluation with {}: the rule compares scores taken the same way",
                path.display(),
                held[key],
                line["scores"][key]
            )));
        }
    }
    Ok(Some(held))
}

/// `scores` as a curve line without a step, so the rule can read it.
fn json_line(scores: Value) -> Value {
    serde_json::json!({ "scores": scores })
}

/// Writes the generator [`best`] ranks first into `out` (created when missing) as
/// generator.safetensors, and its scores as seeds.json, each atomically. Both come from its
/// evaluation folder; where that folder lost them (a run continued from a committed
/// snapshot holds its checkpoints and curve, not its evaluation folders), the generator is
/// the EMA generator of the run's checkpoint of that step, the file its run exported then,
/// and the scores are the curve's. Where the run keeps neither (its checkpoint of that step
/// was overwritten too) but `out` already holds a generator beside seeds.json equal to that
/// step's curve scores, that step is shipped already and nothing is written. Where `out`
/// holds another generator, its scores at the curve's resolution ([`held_scores`]) must rank
/// below that step's by the same rule, or it is kept and nothing is written; once replaced,
/// its scores at other resolutions (`seeds-R.json`) are removed.
pub fn ship(run_dir: &Path, out: &Path) -> Result<Shipped> {
    let lines = read(run_dir)?;
    let point = best(&lines).ok_or_else(|| {
        Error::Invalid(format!(
            "{}: no evaluation with a calibrated score on its curve ({CURVE}; see [eval] interval)",
            run_dir.display()
        ))
    })?;
    let line = lines.iter().find(|l| l["step"].as_i64() == Some(point.step)).expect("best is one of the lines");
    let evaluations = lines.len();
    let held_generator = out.join(run::GENERATOR);
    if !holds_scores(&out.join(SEEDS), &line["scores"]) {
        // The model folder's own generator stays unless the curve's best beats it (its
        // standing as the rule reads it; one without a counted position is beaten).
        if let Some(held) = held_scores(out, line)? {
            if let Some(kept) = rule_point(&json_line(held), -1) {
                if rule_order(&kept, &point).is_ge() {
                    return Ok(Shipped { point, evaluations, from: held_generator, unchanged: true, kept: Some(kept) });
                }
            }
        }
    }
    let dir = eval_dir(run_dir, point.step);
    let copy = |name: &str| -> Result<Option<()>> {
        let from = dir.join(name);
        if !from.is_file() {
            return Ok(None);
        }
        let bytes = std::fs::read(&from).map_err(|err| Error::Io { path: from.clone(), err })?;
        crate::paths::write_atomic(&out.join(name), &bytes)?;
        Ok(Some(()))
    };
    let generator = dir.join(run::GENERATOR);
    let checkpoint = run_dir.join(run::CHECKPOINTS).join(run::checkpoint_name(point.step));
    if !generator.is_file() && !checkpoint.is_file() {
        if held_generator.is_file() && holds_scores(&out.join(SEEDS), &line["scores"]) {
            return Ok(Shipped { point, evaluations, from: held_generator, unchanged: true, kept: None });
        }
        return Err(Error::Invalid(format!(
            "the curve ranks step {} first, but neither {} nor {} is there to ship it from, \
             and {} does not hold it already (a generator beside a {SEEDS} with that step's scores)",
            point.step,
            generator.display(),
            checkpoint.display(),
            out.display()
        )));
    }
    std::fs::create_dir_all(out).map_err(|err| Error::Io { path: out.to_path_buf(), err })?;
    let from = if copy(run::GENERATOR)?.is_some() {
        generator
    } else {
        crate::checkpoint::export_generator(&checkpoint, &out.join(run::GENERATOR))?;
        checkpoint
    };
    if copy(SEEDS)?.is_none() {
        crate::paths::write_atomic(&out.join(SEEDS), serde_json::to_string_pretty(&line["scores"])?.as_bytes())?;
    }
    // Scores of the replaced generator at other resolutions no longer describe the folder.
    let entries = std::fs::read_dir(out).map_err(|err| Error::Io { path: out.to_path_buf(), err })?;
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let other = name.strip_prefix("seeds-").and_then(|n| n.strip_suffix(".json"));
        if other.is_some_and(|r| r.parse::<i64>().is_ok()) {
            std::fs::remove_file(e.path()).map_err(|err| Error::Io { path: e.path(), err })?;
        }
    }
    Ok(Shipped { point, evaluations, from, unchanged: false, kept: None })
}

/// Whether the JSON file at `path` equals `scores`; false where it is missing or unreadable,
/// since then it cannot say what was shipped.
fn holds_scores(path: &Path, scores: &serde_json::Value) -> bool {
    std::fs::read_to_string(path)
        .ok()
        .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok())
        .is_some_and(|held| &held == scores)
}

/// Whether a curve line meets the goal (docs/training.md, "The campaign") on every seed
/// it was scored on: each of [`RULE_SCORES`]' positions at least [`GOAL_POSITION`] where it
/// has one, the yaw error at most [`GOAL_YAW_DEG`], the structure test at least
/// [`GOAL_STRUCTURE`], and the colour test at least its real end. A line without the yaw
/// error or either swap test does not meet it.
pub fn meets_goal(line: &serde_json::Value) -> bool {
    let Some(scores) = line["scores"]["scores"].as_array() else { return false };
    let per_seed = |name: &str, key: &str| -> Option<Vec<Option<f64>>> {
        let s = scores.iter().find(|s| s["score"] == name)?;
        let v: Vec<_> = s[key].as_array()?.iter().map(|x| x.as_f64()).collect();
        (!v.is_empty()).then_some(v)
    };
    let positions_meet = RULE_SCORES
        .iter()
        .all(|name| per_seed(name, "position").is_none_or(|p| p.iter().flatten().all(|&p| p >= GOAL_POSITION)));
    let all = |v: Option<Vec<Option<f64>>>, ok: &dyn Fn(f64, usize) -> bool| {
        v.is_some_and(|v| v.iter().enumerate().all(|(i, x)| x.is_some_and(|x| ok(x, i))))
    };
    let colour_real = per_seed("appearance follows j", "real").unwrap_or_default();
    positions_meet
        && all(per_seed("pose yaw error deg", "model"), &|x, _| x <= GOAL_YAW_DEG)
        && all(per_seed("shape follows i", "model"), &|x, _| x >= GOAL_STRUCTURE)
        && all(per_seed("appearance follows j", "model"), &|x, i| {
            colour_real.get(i).copied().flatten().is_some_and(|r| x >= r)
        })
}

/// What the goal asks of the yaw error, in degrees.
pub const GOAL_YAW_DEG: f64 = 40.0;
/// What the goal asks of the structure test: how often a shape swap keeps the shape code's
/// structure.
pub const GOAL_STRUCTURE: f64 = 0.75;

/// What the goal asks of every position (docs/training.md, "The campaign").
pub const GOAL_POSITION: f64 = 0.75;

/// Where a run's schedule changed: the step and the images seen at the start of each stage
/// of `cfg` after the first that the run's logged steps (`metrics`, its metrics.jsonl)
/// reached. A change made outside the stages is not in the config's history and is not seen.
pub fn stage_starts(cfg: &TrainConfig, metrics: &[serde_json::Value]) -> Vec<(i64, i64)> {
    let logged = |r: &&serde_json::Value| r.get("event").is_none();
    cfg.stages
        .iter()
        .skip(1)
        .filter_map(|s| {
            // The first logged step at or after the start. Its record counts the images
            // up to and including that step, and each step since the start took the stage's
            // own batch.
            let r = metrics.iter().filter(logged).find(|r| r["step"].as_i64().is_some_and(|k| k >= s.from_step))?;
            let (k, images, batch) = (r["step"].as_i64()?, r["images_seen"].as_i64()?, r["batch_size"].as_i64()?);
            Some((s.from_step, images - (k + 1 - s.from_step) * batch))
        })
        .collect()
}

/// [`stage_starts`] of the run in `run_dir`: the stages of its config.toml against its
/// `metrics`; none for a folder without a config (a copy of the curve alone).
pub fn run_stage_starts(run_dir: &Path, metrics: &[serde_json::Value]) -> Result<Vec<(i64, i64)>> {
    let config = run_dir.join(run::CONFIG);
    if !config.exists() {
        return Ok(Vec::new());
    }
    Ok(stage_starts(&TrainConfig::load(&config)?, metrics))
}

/// Draws RUN_DIR/curve.png from curve.jsonl: the position of each calibrated score's seed
/// mean, the worst position over seeds, the yaw error in degrees, how often swaps follow
/// their code (structure, colour, beside the real ends) and the seconds per step, all
/// against thousands of images seen, with a dashed line at each of the run's `starts`
/// ([`run_stage_starts`]) that the curve spans. Nothing is drawn for a run without a curve.
pub fn plot(run_dir: &Path, starts: &[(i64, i64)]) -> Result<Option<PathBuf>> {
    let lines = read(run_dir)?;
    if lines.is_empty() {
        return Ok(None);
    }
    // Only the starts the curve spans: a line beyond its last evaluation is not drawn.
    let span = |l: Option<&Value>| l.and_then(|l| l["images_seen"].as_i64()).unwrap_or(0);
    let (first, last) = (span(lines.first()), span(lines.last()));
    let starts: Vec<(i64, i64)> =
        starts.iter().copied().filter(|&(_, images)| (first..=last).contains(&images)).collect();
    let marks: Vec<f64> = starts.iter().map(|&(_, images)| images as f64 / 1000.0).collect();
    let panels = vec![
        Panel {
            title: "position, mean of seeds".into(),
            series: per_score(&lines, &|s| number(&s["mean"]["position"])),
            log_y: false,
            marks: marks.clone(),
        },
        Panel {
            title: "position, worst seed".into(),
            series: per_score(&lines, &|s| number(&s["worst_position"])),
            log_y: false,
            marks: marks.clone(),
        },
        Panel { title: "yaw error deg".into(), series: yaw_series(&lines), log_y: false, marks: marks.clone() },
        // No goal line: structure's is in the title, and colour's is its real line, which a
        // line at 0.75 would hide whenever the real rate is 0.75 too.
        Panel {
            title: format!("swaps following code, goal structure {GOAL_STRUCTURE}"),
            series: swap_series(&lines),
            log_y: false,
            marks: marks.clone(),
        },
        Panel {
            title: "seconds per step".into(),
            series: vec![
                Series {
                    name: "median".into(),
                    points: lines
                        .iter()
                        .map(|l| (thousand_images(l), l["step_seconds"].as_f64().unwrap_or(f64::NAN)))
                        .collect(),
                },
                Series {
                    name: "mean".into(),
                    points: lines.iter().map(thousand_images).zip(mean_step_seconds(&lines)).collect(),
                },
            ],
            log_y: false,
            marks,
        },
    ];
    let changes = resolution_changes(&lines);
    let panels: Vec<Panel> = panels
        .into_iter()
        .map(|mut p| {
            p.series.iter_mut().for_each(|s| break_at(s, &changes));
            p
        })
        .collect();
    let img = draw_panels(&panels, 2, 520, 320)?;
    let mut caption = format!(
        "x: thousand images seen. {} evaluations, last at step {}",
        lines.len(),
        lines.last().map_or(0, |l| l["step"].as_i64().unwrap_or(0))
    );
    if !starts.is_empty() {
        let steps: Vec<String> = starts.iter().map(|(step, _)| step.to_string()).collect();
        caption += &format!(". Dashed: a stage of config.toml starts (step {})", steps.join(", "));
    }
    if let Some(&k) = changes.last() {
        caption += &format!(
            ". Lines break where the evaluations' size changes (to {}² at step {})",
            resolution(&lines[k]).unwrap_or(0),
            lines[k]["step"].as_i64().unwrap_or(0)
        );
    }
    let mut with_caption = image::RgbImage::from_pixel(img.width(), img.height() + 22, image::Rgb([255, 255, 255]));
    image::imageops::overlay(&mut with_caption, &img, 0, 0);
    draw_text(&mut with_caption, 10, img.height() as i64 + 4, &caption, image::Rgb([20, 20, 20]), TEXT)?;
    let path = run_dir.join(CURVE_PLOT);
    io::save_png(&path, &with_caption)?;
    Ok(Some(path))
}

/// The indices of the evaluations scored at another resolution than the one before them.
fn resolution_changes(lines: &[Value]) -> Vec<usize> {
    (1..lines.len()).filter(|&k| resolution(&lines[k]) != resolution(&lines[k - 1])).collect()
}

/// Breaks a series of one point per evaluation before each of `changes`, with a NaN point
/// (a gap): a score at 64² is not the quantity it was at 32², so the two are not joined.
fn break_at(s: &mut Series, changes: &[usize]) {
    for &k in changes.iter().rev() {
        if let Some(&(x, _)) = s.points.get(k) {
            s.points.insert(k, (x, f64::NAN));
        }
    }
}

/// A curve line's x: thousands of images seen.
fn thousand_images(l: &Value) -> f64 {
    l["images_seen"].as_f64().unwrap_or(f64::NAN) / 1000.0
}

/// The evaluation's entry for the score `name` in a curve line.
fn score_of(l: &Value, name: &str) -> Option<Value> {
    l["scores"]["scores"].as_array()?.iter().find(|s| s["score"] == name).cloned()
}

fn number(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

/// One series per calibrated score that has a finite value, of what `f` takes from its
/// entry, and the goal line.
fn per_score(lines: &[Value], f: &dyn Fn(&Value) -> f64) -> Vec<Series> {
    let mut series: Vec<Series> = SCORES
        .iter()
        .map(|(name, short)| Series {
            name: short.to_string(),
            points: lines.iter().map(|l| (thousand_images(l), score_of(l, name).map_or(f64::NAN, |s| f(&s)))).collect(),
        })
        .filter(|s| s.points.iter().any(|p| p.1.is_finite()))
        .collect();
    series.push(Series {
        name: format!("goal {GOAL_POSITION}"),
        points: lines.iter().map(|l| (thousand_images(l), GOAL_POSITION)).collect(),
    });
    series
}

/// The yaw error of each seed of the last evaluation, the real end's, and the goal.
fn yaw_series(lines: &[Value]) -> Vec<Series> {
    let seeds: Vec<u64> = lines
        .last()
        .and_then(|l| l["scores"]["seeds"].as_array())
        .map(|a| a.iter().filter_map(|s| s.as_u64()).collect())
        .unwrap_or_default();
    let yaw = |l: &Value, f: &dyn Fn(&Value) -> f64| score_of(l, "pose yaw error deg").map_or(f64::NAN, |s| f(&s));
    let mut series: Vec<Series> = seeds
        .iter()
        .enumerate()
        .map(|(k, seed)| Series {
            name: format!("seed {seed}"),
            points: lines.iter().map(|l| (thousand_images(l), yaw(l, &|s| number(&s["model"][k])))).collect(),
        })
        .collect();
    series.push(Series {
        name: "real end".into(),
        points: lines.iter().map(|l| (thousand_images(l), yaw(l, &|s| number(&s["mean"]["real"])))).collect(),
    });
    series.push(Series { name: "goal 40".into(), points: lines.iter().map(|l| (thousand_images(l), 40.0)).collect() });
    series
}

/// The swap tests' rates, seed means: the model's and the real end's of each.
fn swap_series(lines: &[Value]) -> Vec<Series> {
    let seed_mean = |v: &Value| {
        let xs: Vec<f64> = v.as_array().map(|a| a.iter().filter_map(|x| x.as_f64()).collect()).unwrap_or_default();
        xs.iter().sum::<f64>() / xs.len() as f64
    };
    SWAP_SCORES
        .iter()
        .flat_map(|(name, short)| {
            ["model", "real"].map(|end| Series {
                name: match (end, *short) {
                    ("model", _) => short.to_string(),
                    (_, "colour") => "colour, real = goal".into(),
                    _ => format!("{short}, real"),
                },
                points: lines
                    .iter()
                    .map(|l| (thousand_images(l), score_of(l, name).map_or(f64::NAN, |s| seed_mean(&s[end]))))
                    .collect(),
            })
        })
        .collect()
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

/// The filmstrip's labels: four lines 12 px apart fit beside the smallest frame (two rows
/// of 16 px samples beside a 3 × 3 swap matrix, 48 px).
const LABEL: Lettering = Lettering { px: 10.0, mono: false };

/// Stacks the frames of every evaluation on the curve into RUN_DIR/filmstrip.png, each
/// row labelled with its step and images seen. Where one of the run's `starts`
/// ([`run_stage_starts`]) falls between two rows, a dashed line runs through the gap above
/// the first row its stage trained, and that row's label names the stage's first step.
pub fn filmstrip(run_dir: &Path, starts: &[(i64, i64)]) -> Result<Option<PathBuf>> {
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
        rows.push((step, l["images_seen"].as_i64().unwrap_or(0) / 1000, img));
    }
    if rows.is_empty() {
        return Ok(None);
    }
    let label_w = 96u32;
    let pad = 6u32;
    let w = label_w + rows.iter().map(|r| r.2.width()).max().unwrap_or(0) + pad;
    let h: u32 = rows.iter().map(|r| r.2.height() + pad).sum::<u32>() + pad;
    let mut out = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let (ink, grey) = (image::Rgb([20, 20, 20]), image::Rgb([90, 90, 90]));
    let mut y = pad;
    let mut before: Option<i64> = None;
    for (step, kimages, img) in &rows {
        // Only a start the strip spans. The evaluation at step k scored the generator after
        // steps 0..k, so a stage whose first step is s shows from the first row past s.
        if let Some(from) = before.and_then(|b| starts.iter().map(|s| s.0).rev().find(|&s| b <= s && s < *step)) {
            draw_dashes(&mut out, 0, (y - pad / 2) as i64, w as i64, false);
            draw_text(&mut out, 6, y as i64 + 26, "stage from", grey, LABEL)?;
            draw_text(&mut out, 6, y as i64 + 38, &format!("step {from}"), grey, LABEL)?;
        }
        draw_text(&mut out, 6, y as i64 + 2, &format!("step {step}"), ink, LABEL)?;
        draw_text(&mut out, 6, y as i64 + 14, &format!("{kimages}k images"), grey, LABEL)?;
        image::imageops::overlay(&mut out, img, label_w as i64, y as i64);
        y += img.height() + pad;
        before = Some(*step);
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
        assert_eq!(b, RulePoint { step: 15000, meets_goal: false, lowest: 0.62, score: "kernel distance".into() });
        assert_eq!(best(&lines[..2]).unwrap().step, 10000);
        assert_eq!(
            best(&lines[..1]).unwrap(),
            RulePoint { step: 5000, meets_goal: false, lowest: 0.23, score: "pose yaw error deg".into() }
        );
        assert_eq!(best(&[line(5, &[("appearance follows j", Some(1.0))])]), None);
        assert_eq!(best(&[]), None);
    }

    /// A curve line scored on two seeds: `frechet` positions, yaw errors in degrees, and the
    /// structure and colour tests' rates (colour's real end 0.75 on both seeds).
    fn scored(
        step: i64,
        frechet: [Option<f64>; 2],
        yaw: [f64; 2],
        structure: [f64; 2],
        colour: [f64; 2],
    ) -> serde_json::Value {
        let mean = |v: [Option<f64>; 2]| v[0].zip(v[1]).map(|(a, b)| (a + b) / 2.0);
        json!({"step": step, "scores": {"scores": [
            {"score": "frechet distance", "position": frechet, "mean": {"position": mean(frechet)}},
            {"score": "pose yaw error deg", "model": yaw, "position": [1.0, 1.0], "mean": {"position": 1.0}},
            {"score": "shape follows i", "model": structure, "position": [null, null], "mean": {"position": null}},
            {"score": "appearance follows j", "model": colour, "real": [0.75, 0.75], "position": [null, null],
             "mean": {"position": null}},
        ]}})
    }

    #[test]
    fn the_goal_is_met_on_every_seed_or_not_at_all() {
        let good = [Some(0.8), Some(0.9)];
        assert!(meets_goal(&scored(1, good, [25.0, 40.0], [0.75, 0.9], [0.75, 0.8])));
        // A position without a span is skipped; one seed short of the goal on any test fails.
        assert!(meets_goal(&scored(1, [Some(0.8), None], [25.0, 25.0], [0.8, 0.8], [0.8, 0.8])));
        assert!(!meets_goal(&scored(1, [Some(0.8), Some(0.74)], [25.0, 25.0], [0.8, 0.8], [0.8, 0.8])));
        assert!(!meets_goal(&scored(1, good, [25.0, 40.5], [0.8, 0.8], [0.8, 0.8])));
        assert!(!meets_goal(&scored(1, good, [25.0, 25.0], [0.8, 0.74], [0.8, 0.8])));
        assert!(!meets_goal(&scored(1, good, [25.0, 25.0], [0.8, 0.8], [0.74, 0.8])));
        // Without the swap tests or the yaw error there is nothing to meet the goal with.
        assert!(!meets_goal(&line(1, &[("frechet distance", Some(0.9))])));
        assert!(!meets_goal(&json!({"step": 1})));
    }

    #[test]
    fn an_evaluation_that_meets_the_goal_ships_before_higher_positions() {
        let lines = [
            scored(60000, [Some(0.91), Some(0.92)], [26.0, 26.0], [0.72, 0.68], [0.62, 0.68]),
            scored(95000, [Some(0.89), Some(0.9)], [24.0, 26.0], [0.92, 0.88], [0.77, 0.77]),
            scored(100000, [Some(0.95), Some(0.95)], [25.0, 25.0], [0.87, 0.78], [0.73, 0.84]),
        ];
        assert_eq!(
            best(&lines).unwrap(),
            RulePoint { step: 95000, meets_goal: true, lowest: (0.89 + 0.9) / 2.0, score: "frechet distance".into() }
        );
        // Among those that meet it, the positions decide; while none does, they decide alone.
        let later = scored(105000, [Some(0.93), Some(0.92)], [25.0, 25.0], [0.8, 0.8], [0.8, 0.8]);
        assert_eq!(best(&[lines[1].clone(), later]).unwrap().step, 105000);
        assert_eq!(best(&[lines[0].clone(), lines[2].clone()]).unwrap().step, 100000);
    }

    #[test]
    fn only_the_evaluations_at_the_highest_resolution_rank() {
        let at = |resolution: i64, mut l: serde_json::Value| {
            l["scores"]["resolution"] = json!(resolution);
            l
        };
        let lines = [
            at(32, scored(95000, [Some(0.89), Some(0.9)], [24.0, 26.0], [0.92, 0.88], [0.77, 0.77])),
            at(64, scored(210000, [Some(0.6), Some(0.7)], [30.0, 30.0], [0.7, 0.7], [0.7, 0.7])),
            at(64, scored(215000, [Some(0.5), Some(0.5)], [30.0, 30.0], [0.7, 0.7], [0.7, 0.7])),
        ];
        // Step 95 000 meets the goal at 32², but only the 64² evaluations rank.
        assert_eq!(
            best(&lines).unwrap(),
            RulePoint { step: 210000, meets_goal: false, lowest: (0.6 + 0.7) / 2.0, score: "frechet distance".into() }
        );
        assert_eq!(best(&lines[..1]).unwrap().step, 95000);
    }

    /// `scored`'s line with the settings an evaluation records, at `resolution`.
    fn taken(resolution: i64, mut l: serde_json::Value) -> serde_json::Value {
        let s = &mut l["scores"];
        (s["resolution"], s["seeds"], s["images"], s["samples_per_ray"], s["psi"]) =
            (json!(resolution), json!([0, 1]), json!(500), json!(24), json!(1.0));
        l
    }

    #[test]
    fn a_shipped_generator_is_replaced_only_by_a_better_evaluation_at_the_curves_resolution() {
        let tmp = crate::paths::TempDir::new("ship-guard").unwrap();
        let (run_dir, out) = (tmp.path("run"), tmp.path("model"));
        let write = |path: &Path, text: &str| {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(path, text).unwrap();
        };
        // The curve: step 210 000 at 64², lowest position 0.6 (its Fréchet).
        let at_64 = taken(64, scored(210000, [Some(0.6), Some(0.6)], [30.0, 30.0], [0.8, 0.8], [0.8, 0.8]));
        write(&run_dir.join(CURVE), &format!("{at_64}\n"));
        let evaluated = eval_dir(&run_dir, 210000);
        write(&evaluated.join(run::GENERATOR), "the 64² generator");
        write(&evaluated.join(SEEDS), &at_64["scores"].to_string());
        // The folder ships a generator scored at 32² only: refused, naming the missing file.
        let at_32 = taken(32, scored(95000, [Some(0.9), Some(0.9)], [25.0, 25.0], [0.9, 0.9], [0.9, 0.9]));
        write(&out.join(run::GENERATOR), "the 32² generator");
        write(&out.join(SEEDS), &at_32["scores"].to_string());
        let err = ship(&run_dir, &out).unwrap_err().to_string();
        assert!(err.contains(&out.join("seeds-64.json").display().to_string()), "{err}");
        // Its 64² scores taken another way are refused, naming the file and the setting.
        let mut other_seeds = taken(64, scored(95000, [Some(0.5), Some(0.5)], [30.0, 30.0], [0.8, 0.8], [0.8, 0.8]));
        other_seeds["scores"]["seeds"] = json!([2, 3]);
        write(&out.join("seeds-64.json"), &other_seeds["scores"].to_string());
        let err = ship(&run_dir, &out).unwrap_err().to_string();
        assert!(err.contains("seeds-64.json") && err.contains("seeds [2,3]"), "{err}");
        // Scored the same way and ranking at or above the curve's best: kept, nothing written.
        for lowest in [0.6, 0.65] {
            let held = taken(64, scored(95000, [Some(lowest), Some(lowest)], [30.0, 30.0], [0.8, 0.8], [0.8, 0.8]));
            write(&out.join("seeds-64.json"), &held["scores"].to_string());
            let s = ship(&run_dir, &out).unwrap();
            assert!(s.unchanged && s.kept.as_ref().is_some_and(|k| k.lowest == lowest), "{s:?}");
            assert_eq!(std::fs::read_to_string(out.join(run::GENERATOR)).unwrap(), "the 32² generator");
        }
        // Ranking below it: replaced, and the replaced generator's 64² scores removed.
        let held = taken(64, scored(95000, [Some(0.55), Some(0.55)], [30.0, 30.0], [0.8, 0.8], [0.8, 0.8]));
        write(&out.join("seeds-64.json"), &held["scores"].to_string());
        let s = ship(&run_dir, &out).unwrap();
        assert!(!s.unchanged && s.kept.is_none() && s.point.step == 210000, "{s:?}");
        assert_eq!(std::fs::read_to_string(out.join(run::GENERATOR)).unwrap(), "the 64² generator");
        assert_eq!(std::fs::read_to_string(out.join(SEEDS)).unwrap(), at_64["scores"].to_string());
        assert!(!out.join("seeds-64.json").exists());
        // Shipped: the same step again leaves it as it is.
        assert!(ship(&run_dir, &out).unwrap().kept.is_none());
    }

    #[test]
    fn series_break_where_the_evaluations_resolution_changes() {
        let at = |step: i64, r: i64| json!({"step": step, "scores": {"resolution": r}});
        let lines = [at(1, 32), at(2, 32), at(3, 64), at(4, 64), at(5, 128)];
        assert_eq!(resolution_changes(&lines), [2, 4]);
        let mut s = Series { name: "x".into(), points: (1..=5).map(|k| (k as f64, k as f64)).collect() };
        break_at(&mut s, &[2, 4]);
        let ys: Vec<f64> = s.points.iter().map(|p| p.1).collect();
        assert_eq!(ys.len(), 7);
        assert_eq!([ys[0], ys[1], ys[3], ys[4], ys[6]], [1.0, 2.0, 3.0, 4.0, 5.0]);
        assert!(ys[2].is_nan() && ys[5].is_nan());
        assert_eq!([s.points[2].0, s.points[5].0], [3.0, 5.0]);
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
