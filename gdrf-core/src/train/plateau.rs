//! When a learning curve counts as flat: the campaign ends when it has stayed flat for
//! [`FLAT_STEPS`] after the last change the evidence pointed to, and goes on while any score
//! still improves (docs/training.md, "The campaign"). Fixed at step 110 300, before the
//! step-115 000 evaluation.
//!
//! An evaluation improves a score when that score's seed mean beats its best seed mean over
//! the evaluations of the [`FLAT_STEPS`] before it by more than the score's noise: the
//! median, over the whole curve, of how far the seeds of one evaluation lie apart. A gain
//! smaller than two seeds of the same generator disagree by is not evidence of learning.
//! Evaluations at different resolutions are different measurements (the calibrated ends and
//! the scores move with it): an evaluation is compared, and its noise taken, only among those
//! at its own resolution.
use crate::stats::{mean, median};
use serde_json::Value;

/// How long the curve must go without an improvement to count as flat, in steps.
pub const FLAT_STEPS: i64 = 20_000;

/// The values followed, per seed, each higher-is-better: the calibrated scores' positions,
/// capped at 1 (past the real end is no better), and the swap tests' rates (structure has
/// no random end on most seeds, so no position; colour's position is not calibrated at 32²).
const FOLLOWED: &[(&str, &str)] = &[
    ("frechet distance", "position"),
    ("kernel distance", "position"),
    ("coverage tv", "position"),
    ("pose yaw error deg", "position"),
    ("pose pitch error deg", "position"),
    ("shape follows i", "model"),
    ("appearance follows j", "model"),
];

/// `name`'s per-seed values in a curve line (positions capped at 1); `None` unless every
/// seed has a finite one.
fn per_seed(line: &Value, name: &str, key: &str) -> Option<Vec<f64>> {
    let score = line["scores"]["scores"].as_array()?.iter().find(|s| s["score"] == name)?;
    let v: Vec<f64> =
        score[key].as_array()?.iter().map(|x| x.as_f64().filter(|x| x.is_finite())).collect::<Option<_>>()?;
    let cap = if key == "position" { 1.0 } else { f64::INFINITY };
    (!v.is_empty()).then(|| v.into_iter().map(|x| x.min(cap)).collect())
}

/// One evaluation's verdict.
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    pub step: i64,
    /// The scores it improves (empty: none, or no earlier evaluation within [`FLAT_STEPS`]),
    /// by their evaluation names.
    pub improves: Vec<String>,
}

/// A curve line's evaluation resolution (`None` in lines written before it was recorded).
fn resolution(line: &Value) -> Option<i64> {
    line["scores"]["resolution"].as_i64()
}

/// Each curve line's verdict, in the curve's order.
pub fn verdicts(lines: &[Value]) -> Vec<Verdict> {
    // Each resolution's noise, once.
    let mut noise: Vec<(Option<i64>, Vec<f64>)> = Vec::new();
    for res in lines.iter().map(resolution) {
        if !noise.iter().any(|(r, _)| *r == res) {
            noise.push((res, noise_at(lines.iter().filter(|l| resolution(l) == res))));
        }
    }
    lines
        .iter()
        .filter_map(|l| Some((l["step"].as_i64()?, l)))
        .map(|(step, line)| {
            let res = resolution(line);
            let before: Vec<&Value> = lines
                .iter()
                .filter(|e| resolution(e) == res)
                .filter(|e| e["step"].as_i64().is_some_and(|s| s < step && s >= step - FLAT_STEPS))
                .collect();
            let improves = FOLLOWED
                .iter()
                .zip(&noise.iter().find(|(r, _)| *r == res).expect("every line's resolution").1)
                .filter(|((name, key), noise)| {
                    let Some(now) = per_seed(line, name, key) else { return false };
                    let best = before
                        .iter()
                        .filter_map(|e| per_seed(e, name, key))
                        .map(|v| mean(&v))
                        .fold(f64::NEG_INFINITY, f64::max);
                    best.is_finite() && mean(&now) > best + **noise
                })
                .map(|((name, _), _)| name.to_string())
                .collect();
            Verdict { step, improves }
        })
        .collect()
}

/// Each followed value's noise over `lines`: the median spread of its seeds.
fn noise_at<'a>(lines: impl Iterator<Item = &'a Value> + Clone) -> Vec<f64> {
    FOLLOWED
        .iter()
        .map(|(name, key)| {
            let spreads: Vec<f64> = lines
                .clone()
                .filter_map(|l| per_seed(l, name, key))
                .filter(|v| v.len() > 1)
                .map(|v| {
                    v.iter().copied().fold(f64::NEG_INFINITY, f64::max)
                        - v.iter().copied().fold(f64::INFINITY, f64::min)
                })
                .collect();
            if spreads.is_empty() {
                0.0
            } else {
                median(&spreads)
            }
        })
        .collect()
}

/// Where a curve stands: its last evaluation, the last one that improved a score (or,
/// where none did, its first evaluation), and the last change of the schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct Standing {
    pub last: i64,
    pub last_improvement: i64,
    pub improved: Vec<String>,
    /// The step of the schedule's last change (a stage's start), if the run had one.
    pub last_change: Option<i64>,
}

impl Standing {
    /// The step the flat stretch counts from: the last improvement or the schedule's last
    /// change, whichever came later (a change restarts the count: the issue's "flat for
    /// 20 000 steps after the last change").
    pub fn since(&self) -> i64 {
        self.last_change.map_or(self.last_improvement, |c| c.max(self.last_improvement))
    }

    /// Whether the curve has gone [`FLAT_STEPS`] without an improvement or a change.
    pub fn flat(&self) -> bool {
        self.last - self.since() >= FLAT_STEPS
    }
}

/// The curve's standing (`None` for an empty curve), given the step of the schedule's last
/// change so far.
pub fn standing(lines: &[Value], last_change: Option<i64>) -> Option<Standing> {
    let v = verdicts(lines);
    let last = v.last()?.step;
    let at = v.iter().rev().find(|v| !v.improves.is_empty()).unwrap_or(&v[0]);
    Some(Standing { last, last_improvement: at.step, improved: at.improves.clone(), last_change })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A line scored on two seeds: Fréchet positions, and the colour test's rates.
    fn line(step: i64, frechet: [f64; 2], colour: [f64; 2]) -> Value {
        json!({"step": step, "scores": {"scores": [
            {"score": "frechet distance", "position": frechet},
            {"score": "appearance follows j", "model": colour, "position": [null, null]},
        ]}})
    }

    #[test]
    fn a_gain_counts_only_beyond_the_seeds_spread_and_within_the_window() {
        // Fréchet seeds lie 0.02 apart at every evaluation (the noise), colour 0.1.
        let lines = [
            line(5000, [0.50, 0.52], [0.60, 0.70]),
            line(10000, [0.60, 0.62], [0.60, 0.70]), // +0.10 Fréchet: an improvement
            line(15000, [0.61, 0.63], [0.65, 0.75]), // +0.01 and +0.05: within the noise
            line(20000, [0.60, 0.62], [0.70, 0.80]), // colour 0.75 against the best 0.70: within 0.1
            line(25000, [0.60, 0.62], [0.85, 0.95]), // colour 0.90 > 0.75 + 0.1: an improvement
        ];
        let v = verdicts(&lines);
        let improves: Vec<Vec<String>> = v.iter().map(|v| v.improves.clone()).collect();
        assert_eq!(
            improves,
            [vec![], vec!["frechet distance".to_string()], vec![], vec![], vec!["appearance follows j".to_string()]]
        );
        let s = standing(&lines, None).unwrap();
        assert_eq!((s.last, s.last_improvement, s.flat()), (25000, 25000, false));

        // Positions past the real end count as 1; the best is taken over the window only.
        let capped = [line(0, [1.0, 1.0], [0.5, 0.5]), line(5000, [1.3, 1.3], [0.5, 0.5])];
        assert!(verdicts(&capped)[1].improves.is_empty());
        // A far better evaluation more than FLAT_STEPS after the last one has nothing to beat.
        let far = [line(0, [0.5, 0.5], [0.5, 0.5]), line(25000, [0.9, 0.9], [0.5, 0.5])];
        assert!(verdicts(&far)[1].improves.is_empty());
        let near = [line(0, [0.5, 0.5], [0.5, 0.5]), line(20000, [0.9, 0.9], [0.5, 0.5])];
        assert_eq!(verdicts(&near)[1].improves, ["frechet distance"]);

        // 20 000 steps without an improvement after the last one: flat.
        let mut flat = lines.to_vec();
        for step in [30000, 35000, 40000, 45000] {
            flat.push(line(step, [0.60, 0.62], [0.70, 0.80]));
        }
        let s = standing(&flat, None).unwrap();
        assert_eq!((s.last, s.last_improvement, s.flat()), (45000, 25000, true));
        assert_eq!(s.improved, ["appearance follows j"]);
        assert_eq!(standing(&[], None), None);

        // A change of the schedule restarts the count: after one at step 40 231 the same
        // curve is not flat, and 20 000 steps on it is; a change before the last
        // improvement changes nothing.
        let s = standing(&flat, Some(40231)).unwrap();
        assert_eq!((s.since(), s.flat()), (40231, false));
        let mut later = flat.clone();
        for step in [50000, 55000, 60000] {
            later.push(line(step, [0.60, 0.62], [0.70, 0.80]));
        }
        assert!(!standing(&later, Some(40231)).unwrap().flat(), "19 769 steps after the change");
        later.push(line(65000, [0.60, 0.62], [0.70, 0.80]));
        assert!(standing(&later, Some(40231)).unwrap().flat(), "24 769 steps after the change");
        let s = standing(&flat, Some(20000)).unwrap();
        assert_eq!((s.since(), s.flat()), (25000, true));
    }

    #[test]
    fn evaluations_are_compared_only_at_their_own_resolution() {
        let at = |res: i64, mut l: Value| {
            l["scores"]["resolution"] = json!(res);
            l
        };
        // At 32² the Fréchet positions reach 0.9; the curve then evaluates at 64², where the
        // same model stands lower and its seeds lie 0.1 apart.
        let lines = [
            at(32, line(5000, [0.88, 0.90], [0.7, 0.7])),
            at(32, line(10000, [0.89, 0.91], [0.7, 0.7])),
            at(64, line(15000, [0.60, 0.70], [0.7, 0.7])),
            at(64, line(20000, [0.72, 0.82], [0.7, 0.7])), // +0.12 over 15 000 > its noise 0.1
            at(64, line(25000, [0.75, 0.85], [0.7, 0.7])), // +0.03: within it
        ];
        let improves: Vec<bool> = verdicts(&lines).iter().map(|v| !v.improves.is_empty()).collect();
        // Against the 32² positions (0.90), step 20 000's 0.77 would be no gain; against
        // 32²'s noise (0.02), step 25 000's +0.03 would be one.
        assert_eq!(improves, [false, false, false, true, false]);
    }
}
