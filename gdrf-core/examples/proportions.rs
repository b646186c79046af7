//! Proportions of generated chairs against the dataset's: the bounding box (height, width,
//! depth, where it sits) of each chair's largest connected piece of density ≥ 10 on a grid,
//! measured the same way on a generator's seeds and on the dataset's own objects (their
//! exact signed distance as a radiance field), plus the dataset objects' exact boxes from
//! their primitives. It asks whether a bias that a pose reader sees in every generated
//! image (docs/campaign-log.md, "Where the pitch error comes from") is in the geometry.
//!
//! `cargo run --release -p gdrf-core --example proportions -- GENERATOR DATASET_DIR [N] [GRID]`
//! writes one JSON line per chair to stdout and a summary to stderr.
use gdrf_core::checkpoint::load_generator;
use gdrf_core::data::synth::analytic::AnalyticField;
use gdrf_core::data::synth::render::{fit_radius, Scene};
use gdrf_core::data::synth::{image_record, SynthOptions};
use gdrf_core::edit::{latents, Features};
use gdrf_core::field::generator::FieldOptions;
use gdrf_core::mesh::sample_density;
use std::collections::VecDeque;
use tch::{Device, Kind};

/// Half the side of the measured cube: the dataset scales every object into a sphere of
/// radius fit_radius (0.38 for the chairs camera), so ±0.45 holds every chair.
const HALF: f64 = 0.45;
const SURFACE: f32 = 10.0;

/// Box (min, max per axis), centroid and voxel count of the largest 26-connected piece of
/// `values ≥ SURFACE` on the n³ grid (x slowest, z fastest, as `sample_density` orders it),
/// and the share of all occupied voxels it holds.
fn largest_piece(values: &[f32], n: usize) -> Option<([f64; 6], [f64; 3], usize, f64)> {
    let idx = |x: usize, y: usize, z: usize| (x * n + y) * n + z;
    let occupied: Vec<bool> = values.iter().map(|v| *v >= SURFACE).collect();
    let total = occupied.iter().filter(|o| **o).count();
    let mut label = vec![0u32; values.len()];
    let mut best: Option<(u32, usize)> = None;
    let mut next = 0u32;
    for start in 0..values.len() {
        if !occupied[start] || label[start] != 0 {
            continue;
        }
        next += 1;
        let mut count = 0;
        let mut queue = VecDeque::from([start]);
        label[start] = next;
        while let Some(i) = queue.pop_front() {
            count += 1;
            let (x, y, z) = (i / (n * n), (i / n) % n, i % n);
            for dx in -1i64..=1 {
                for dy in -1i64..=1 {
                    for dz in -1i64..=1 {
                        let (a, b, c) = (x as i64 + dx, y as i64 + dy, z as i64 + dz);
                        if a < 0 || b < 0 || c < 0 || a >= n as i64 || b >= n as i64 || c >= n as i64 {
                            continue;
                        }
                        let j = idx(a as usize, b as usize, c as usize);
                        if occupied[j] && label[j] == 0 {
                            label[j] = next;
                            queue.push_back(j);
                        }
                    }
                }
            }
        }
        if best.is_none_or(|(_, c)| count > c) {
            best = Some((next, count));
        }
    }
    let (id, count) = best?;
    let h = 2.0 * HALF / (n - 1) as f64;
    let mut bbox = [f64::MAX, f64::MIN, f64::MAX, f64::MIN, f64::MAX, f64::MIN];
    let mut sum = [0.0; 3];
    for (i, l) in label.iter().enumerate() {
        if *l != id {
            continue;
        }
        let p = [(i / (n * n)) as f64 * h - HALF, ((i / n) % n) as f64 * h - HALF, (i % n) as f64 * h - HALF];
        for a in 0..3 {
            bbox[2 * a] = bbox[2 * a].min(p[a]);
            bbox[2 * a + 1] = bbox[2 * a + 1].max(p[a]);
            sum[a] += p[a];
        }
    }
    Some((bbox, sum.map(|s| s / count as f64), count, count as f64 / total as f64))
}

/// The measures of one box: height, width, depth, their ratios and where it sits.
fn measures(bbox: [f64; 6], centroid: [f64; 3]) -> Vec<(&'static str, f64)> {
    let (w, h, d) = (bbox[1] - bbox[0], bbox[3] - bbox[2], bbox[5] - bbox[4]);
    vec![
        ("height", h),
        ("width", w),
        ("depth", d),
        ("height/width", h / w),
        ("height/depth", h / d),
        ("width/depth", w / d),
        ("y_min", bbox[2]),
        ("y_max", bbox[3]),
        ("z_centre", 0.5 * (bbox[4] + bbox[5])),
        ("centroid_y", centroid[1]),
        ("centroid_z", centroid[2]),
    ]
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    anyhow::ensure!(args.len() >= 3, "usage: proportions GENERATOR DATASET_DIR [N] [GRID]");
    let n_chairs: usize = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(32);
    let grid: usize = args.get(4).map(|s| s.parse()).transpose()?.unwrap_or(96);
    tch::set_num_threads(1);
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(std::path::Path::new(&args[2]).join("metadata.json"))?)?;
    let opts: SynthOptions = serde_json::from_value(meta["options"].clone())?;
    let loaded = load_generator(std::path::Path::new(&args[1]), Device::Cpu, Kind::Float)?;
    let g = &loaded.generator;
    let mut sums: std::collections::BTreeMap<(String, &'static str), Vec<f64>> = Default::default();
    let mut record = |source: &str, i: usize, m: Vec<(&'static str, f64)>, extra: String| {
        let fields: Vec<String> = m.iter().map(|(k, v)| format!("\"{k}\": {v:.5}")).collect();
        println!("{{\"source\": \"{source}\", \"index\": {i}, {}{extra}}}", fields.join(", "));
        for (k, v) in m {
            sums.entry((source.to_string(), k)).or_default().push(v);
        }
    };
    for i in 0..n_chairs {
        // Held-out objects chose nothing; the generator's seeds are 10 000 + i.
        let rec = image_record(&opts, opts.count - 1 - i);
        let scene = Scene::new(&rec.shape.geometry(), &rec.appearance, fit_radius(&opts.camera))?;
        let mut exact = [f64::MAX, f64::MIN, f64::MAX, f64::MIN, f64::MAX, f64::MIN];
        for p in scene.prims() {
            let (lo, hi) = p.aabb();
            for (a, (l, h)) in [(lo.x, hi.x), (lo.y, hi.y), (lo.z, hi.z)].into_iter().enumerate() {
                exact[2 * a] = exact[2 * a].min(l as f64);
                exact[2 * a + 1] = exact[2 * a + 1].max(h as f64);
            }
        }
        let field = AnalyticField::new(&rec.shape, &rec.appearance, &opts.camera, 500.0, 0.002)?;
        let lat = field.latents(1);
        let values = sample_density(&field, &lat.shape, FieldOptions::default(), HALF, grid, 1 << 15)?;
        let (bbox, c, count, share) = largest_piece(&values, grid).ok_or_else(|| anyhow::anyhow!("empty object"))?;
        record("dataset", i, measures(bbox, c), format!(", \"voxels\": {count}, \"share\": {share:.4}"));
        // A box has no mass: its centroid columns are its centre.
        let centre = [0.5 * (exact[0] + exact[1]), 0.5 * (exact[2] + exact[3]), 0.5 * (exact[4] + exact[5])];
        record("dataset_exact", i, measures(exact, centre), String::new());

        let f = Features::from_seed(g, 10_000 + i as i64);
        let lat = latents(g, &f, &f, None);
        let values = sample_density(g, &lat.shape, FieldOptions::default(), HALF, grid, 1 << 15)?;
        match largest_piece(&values, grid) {
            Some((bbox, c, count, share)) => {
                record("generated", i, measures(bbox, c), format!(", \"voxels\": {count}, \"share\": {share:.4}"))
            }
            None => eprintln!("seed {}: no density ≥ {SURFACE}", 10_000 + i),
        }
        eprint!("\r{}/{n_chairs}", i + 1);
    }
    eprintln!();
    let stat = |v: &[f64]| {
        let m = v.iter().sum::<f64>() / v.len() as f64;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1).max(1) as f64).sqrt();
        (m, sd / (v.len() as f64).sqrt())
    };
    let keys: Vec<&'static str> = measures([0.0; 6], [0.0; 3]).into_iter().map(|(k, _)| k).collect();
    eprintln!("{:<14} {:>18} {:>18} {:>18}", "", "dataset (grid)", "dataset (exact)", "generated");
    for k in keys {
        let cell = |s: &str| {
            sums.get(&(s.to_string(), k)).map(|v| stat(v)).map(|(m, e)| format!("{m:.4} ± {e:.4}")).unwrap_or_default()
        };
        eprintln!("{k:<14} {:>18} {:>18} {:>18}", cell("dataset"), cell("dataset_exact"), cell("generated"));
    }
    Ok(())
}
