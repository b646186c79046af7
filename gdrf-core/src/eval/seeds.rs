//! One evaluation over several seeds ([`super::evaluator::evaluate_seeds`]): each seed draws
//! other codes, poses and another random-weight generator, so the random end moves between
//! seeds about as much as a model near the middle of the scale stands from it. This puts
//! each score's per-seed values side by side, with their means, the position of the means
//! and the worst position, so that "nearer the real end" can be judged over draws rather
//! than on one.
use super::report::{score_rows, truncation_note, write};
use super::result::{Calibrated, EvalResult};
use crate::paths::write_atomic;
use crate::stats::mean;
use crate::{Error, Result};
use serde::Serialize;
use std::path::Path;

/// One score over the seeds.
#[derive(Debug, Clone, Serialize)]
pub struct SeedSpread {
    pub score: String,
    /// Per seed, in the order of [`SeedSummary::seeds`].
    pub model: Vec<f64>,
    pub real: Vec<f64>,
    pub random: Vec<f64>,
    pub position: Vec<f64>,
    /// How many seeds gave all three values finite (a random generator whose swaps vary in
    /// no structure factor gives the structure test no value); the means and standard
    /// deviations are over those seeds. Where no seed did, the model's and the real end's
    /// means are over the seeds that gave each, and the random end and position are NaN.
    pub counted: usize,
    /// The means, and where the model's mean stands between the ends' means.
    pub mean: Calibrated,
    /// Sample standard deviation of the model's and the random end's values (0 for fewer
    /// than two seeds counted).
    pub model_sd: f64,
    pub random_sd: f64,
    /// The lowest per-seed position (NaN positions, where a score has no span, left out;
    /// NaN when every one is).
    pub worst_position: f64,
}

/// What `gdrf-train eval --seeds` writes as `seeds.json`.
#[derive(Debug, Clone, Serialize)]
pub struct SeedSummary {
    pub generator: String,
    pub dataset: String,
    pub images: i64,
    pub resolution: i64,
    pub samples_per_ray: i64,
    /// The model's truncation ψ (1 = none).
    pub psi: f64,
    pub seeds: Vec<u64>,
    pub scores: Vec<SeedSpread>,
    /// Wall time of the whole evaluation.
    pub seconds: f64,
}

/// Sample standard deviation (n − 1); 0 for fewer than two values.
fn sd(v: &[f64]) -> f64 {
    if v.len() < 2 {
        return 0.0;
    }
    let m = mean(v);
    (v.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
}

/// Gathers each score over `results` (one per seed, all of one generator and settings).
pub fn summarise(results: &[EvalResult]) -> Result<SeedSummary> {
    let Some(first) = results.first() else {
        return Err(Error::Invalid("no evaluation results to summarise".into()));
    };
    let rows: Vec<Vec<(&'static str, &Calibrated)>> = results.iter().map(score_rows).collect();
    let scores = (0..rows[0].len())
        .map(|i| {
            let pick = |f: fn(&Calibrated) -> f64| rows.iter().map(|r| f(r[i].1)).collect::<Vec<f64>>();
            spread(rows[0][i].0.trim(), pick(|c| c.model), pick(|c| c.real), pick(|c| c.random), pick(|c| c.position))
        })
        .collect();
    Ok(SeedSummary {
        generator: first.generator.clone(),
        dataset: first.dataset.clone(),
        images: first.images,
        resolution: first.resolution,
        samples_per_ray: first.samples_per_ray,
        psi: first.psi,
        seeds: results.iter().map(|r| r.seed).collect(),
        scores,
        seconds: results.iter().map(|r| r.seconds).sum(),
    })
}

/// One score's per-seed values gathered into a [`SeedSpread`].
fn spread(score: &str, model: Vec<f64>, real: Vec<f64>, random: Vec<f64>, position: Vec<f64>) -> SeedSpread {
    let worst_position = position.iter().copied().filter(|p| !p.is_nan()).fold(f64::NAN, f64::min);
    let finite =
        |v: &[&[f64]]| -> Vec<usize> { (0..model.len()).filter(|&k| v.iter().all(|s| s[k].is_finite())).collect() };
    let counted = finite(&[&model, &real, &random]);
    let keep = |v: &[f64], at: &[usize]| at.iter().map(|&k| v[k]).collect::<Vec<f64>>();
    let (m, r, x) = if counted.is_empty() {
        // No seed has a random end (the structure test often has none): the model's rate
        // and the real one are still worth their mean, without a position.
        (keep(&model, &finite(&[&model])), keep(&real, &finite(&[&real])), vec![])
    } else {
        (keep(&model, &counted), keep(&real, &counted), keep(&random, &counted))
    };
    SeedSpread {
        score: score.to_string(),
        counted: counted.len(),
        // An empty random end's mean is NaN (0 / 0), and so is the position.
        mean: Calibrated::new(mean(&m), mean(&r), mean(&x)),
        model_sd: sd(&m),
        random_sd: sd(&x),
        worst_position,
        model,
        real,
        random,
        position,
    }
}

/// The spread as text: per score, the model's and the random end's mean ± sd, the real
/// end, each seed's position, the position of the means and the worst one.
pub fn summary(s: &SeedSummary) -> String {
    let seeds: Vec<String> = s.seeds.iter().map(u64::to_string).collect();
    let mut t = format!(
        "{} seeds ({}), {} images at {}² ({} samples/ray{}); position: 0 random end, 1 real end\n",
        s.seeds.len(),
        seeds.join(", "),
        s.images,
        s.resolution,
        s.samples_per_ray,
        truncation_note(s.psi)
    );
    let per_seed: String = s.seeds.iter().map(|k| format!(" {:>7}", format!("seed {k}"))).collect();
    t += &format!(
        "{:<26} {:>17} {:>9} {:>17}{per_seed} {:>8} {:>8}\n",
        "score", "model (mean ± sd)", "real", "random (mean ± sd)", "of means", "worst"
    );
    for c in &s.scores {
        let pos: String = c.position.iter().map(|p| format!(" {p:>7.2}")).collect();
        let name = match c.counted {
            0 => format!("{} (no random end)", c.score),
            n if n < s.seeds.len() => format!("{} ({n} seeds)", c.score),
            _ => c.score.clone(),
        };
        t += &format!(
            "{:<26} {:>17} {:>9.4} {:>17}{pos} {:>8.2} {:>8.2}\n",
            name,
            format!("{:.4} ± {:.4}", c.mean.model, c.model_sd),
            c.mean.real,
            format!("{:.4} ± {:.4}", c.mean.random, c.random_sd),
            c.mean.position,
            c.worst_position
        );
    }
    t
}

/// Writes each seed's `eval.json` and `report.png` into `dir/seed-S/` and the spread into
/// `dir/seeds.json` (all written atomically).
pub fn write_all(dir: &Path, results: &[EvalResult], s: &SeedSummary) -> Result<()> {
    for r in results {
        write(&dir.join(format!("seed-{}", r.seed)), r)?;
    }
    let json = serde_json::to_string_pretty(s)?;
    write_atomic(&dir.join("seeds.json"), json.as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sample_standard_deviation() {
        // Deviations −2, −1, 3: squares sum to 14, over n − 1 = 2 gives 7.
        assert_eq!(sd(&[1.0, 2.0, 6.0]), 7f64.sqrt());
        assert_eq!(sd(&[5.0]), 0.0);
    }

    #[test]
    fn means_over_the_seeds_that_have_every_end() {
        let n = f64::NAN;
        // Seed 1 has no random end: the means are seed 0's and seed 2's.
        let s = spread("x", vec![0.5, 0.9, 0.75], vec![1.0, 1.0, 1.0], vec![0.0, n, 0.5], vec![0.5, n, 0.5]);
        assert_eq!(s.counted, 2);
        assert_eq!((s.mean.model, s.mean.real, s.mean.random, s.mean.position), (0.625, 1.0, 0.25, 0.5));
        assert_eq!((s.model_sd, s.random_sd), (0.03125f64.sqrt(), 0.125f64.sqrt()));
        // No seed has one: the model's and the real end's means stay, without a position.
        let s = spread("x", vec![0.75, 0.875], vec![1.0, 0.5], vec![n, n], vec![n, n]);
        assert_eq!(s.counted, 0);
        assert_eq!((s.mean.model, s.mean.real), (0.8125, 0.75));
        assert_eq!((s.model_sd, s.random_sd), (0.0078125f64.sqrt(), 0.0));
        assert!(s.mean.random.is_nan() && s.mean.position.is_nan() && s.worst_position.is_nan());
    }
}
