//! `gdrf-bench shared-grid`: how much of the training rays a grid shared by all shape codes
//! would let a step skip, before anyone builds one. nerfacc's training-time grid serves one
//! scene; a generator's is the union over its codes (the maximum over random codes). For
//! 1, 2, 4, … codes this takes the union of their own occupancy grids (the renderer's
//! [`OccupancyGrid`], coarse to fine, at each threshold) and walks a batch of training
//! rays (camera poses drawn as training draws them) through it: the share of rays that
//! meet it (a ray that does not costs one sample instead of 2N) and the share of the
//! camera's ray interval the grid keeps (where the coarse samples would go). One code's own
//! grid, the per-instance grid of gdrf-edit, is the first row.
use super::write_json;
use crate::camera::{Poses, Rays};
use crate::checkpoint::load_generator;
use crate::error::Context;
use crate::nn::mapping::seeded_randn;
use crate::render::occupancy::camera_half_extent;
use crate::render::{GridConfig, OccupancyGrid};
use crate::rng::{Purpose, StepRng};
use crate::{Error, Result};
use serde::Serialize;
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};

/// The flags of `gdrf-bench shared-grid` (the JSON records the settings, not the paths).
#[derive(clap::Args, Debug, Clone, Serialize)]
pub struct Options {
    /// Generator checkpoint; default: the shipped model.
    #[arg(long, visible_alias = "generator", value_name = "FILE")]
    #[serde(skip)]
    pub checkpoint: Option<PathBuf>,
    /// Codes in the largest union (z = randn after manual_seed of seeds 0, 1, …, as
    /// `gdrf-edit render`); the unions of the first 1, 2, 4, … of them are measured.
    #[arg(long, default_value_t = 64)]
    pub codes: i64,
    /// Grid cells per side.
    #[arg(long, default_value_t = 32)]
    pub grid: i64,
    /// Densities softplus(σ) the grid promises to keep (the renderer's default is 0.5).
    #[arg(long, value_delimiter = ',', default_value = "0.5,2,8")]
    pub thresholds: Vec<f64>,
    /// Camera poses of the training rays, drawn from the checkpoint's camera.
    #[arg(long, default_value_t = 32)]
    pub views: i64,
    /// Pixels per side of each view's rays.
    #[arg(long, default_value_t = 64)]
    pub resolution: i64,
    /// Output stem: writes STEM.json and STEM.png.
    #[arg(long, default_value = "shared-grid")]
    #[serde(skip)]
    pub out: PathBuf,
}

/// One union of codes at one threshold.
#[derive(Debug, Clone, Serialize)]
pub struct Row {
    pub threshold: f64,
    pub codes: i64,
    /// Share of the cells occupied.
    pub occupied: f64,
    /// Share of the rays that meet an occupied cell.
    pub rays_hit: f64,
    /// The largest share of one view's rays that do (a batch padded to its fullest image).
    pub rays_hit_max_view: f64,
    /// Mean over all rays of the share of the camera's interval between a ray's first and
    /// last occupied cell (0 for a ray that meets none).
    pub interval_kept: f64,
    /// Density queries a grid build spent (one code's own grid; 0 for a union, which
    /// reuses its codes' grids).
    pub queries: f64,
}

#[derive(Serialize)]
struct Doc<'a> {
    title: String,
    checkpoint: String,
    settings: &'a Options,
    /// One code's own grid, averaged over the codes (the per-instance grid).
    own_grid: Vec<Row>,
    unions: Vec<Row>,
}

/// What `occupied` (a `(G, G, G)` grid over the camera's cube) keeps of `rays`.
fn measure(grid: &OccupancyGrid, rays: &Rays, range: (f64, f64), (threshold, codes): (f64, i64)) -> Row {
    let queries = grid.evaluated as f64;
    let (bounds, hit) = grid.clip(rays, range.0, range.1);
    let hit = hit.to_kind(Kind::Float);
    let kept = (bounds.select(2, 1) - bounds.select(2, 0)).clamp_min(0.0) * &hit / (range.1 - range.0);
    let scalar = |t: Tensor| f64::try_from(t).unwrap_or(f64::NAN);
    Row {
        threshold,
        codes,
        occupied: scalar(grid.occupied.to_kind(Kind::Float).mean(Kind::Float)),
        rays_hit: scalar(hit.mean(Kind::Float)),
        rays_hit_max_view: scalar(hit.mean_dim(&[1i64][..], false, Kind::Float).max()),
        interval_kept: scalar(kept.mean(Kind::Float)),
        queries,
    }
}

/// Measures, prints the table and writes `--out`.json and .png.
pub fn run(a: &Options) -> Result<(Vec<Row>, Vec<Row>)> {
    if a.codes < 1 || a.views < 1 || a.resolution < 1 || a.thresholds.is_empty() {
        return Err(Error::Invalid(format!(
            "--codes {}, --views {}, --resolution {} and --thresholds ({} given) must each be at least 1",
            a.codes,
            a.views,
            a.resolution,
            a.thresholds.len()
        )));
    }
    let path = a.checkpoint.clone().unwrap_or_else(crate::paths::shipped_generator);
    let g =
        load_generator(&path, Device::Cpu, Kind::Float).with_context(|| format!("--checkpoint {}", path.display()))?;
    let camera = g.header.camera.clone().ok_or_else(|| Error::Data {
        path: path.clone(),
        reason: "records no camera, and the grid's cube and the rays are the camera's".into(),
    })?;
    let range = (camera.ray_start, camera.ray_end);
    let poses =
        Poses::sample_from(&camera, a.views, &mut StepRng::new(0, 0, Purpose::GenPoses, Kind::Float, Device::Cpu));
    let rays = Rays::from_poses(&poses, a.resolution, camera.fov_deg);
    let z = Tensor::cat(
        &(0..a.codes).map(|s| seeded_randn(&[1, g.generator.cfg.latent_dim as i64], s)).collect::<Vec<_>>(),
        0,
    );
    let latents = g.generator.latents(&z, &z, None)?;
    let counts: Vec<i64> =
        (0..).map(|k| 1i64 << k).take_while(|&n| n < a.codes).chain(std::iter::once(a.codes)).collect();
    let bar = crate::progress::bar(a.codes as u64 * a.thresholds.len() as u64, "grids", false);
    bar.set_prefix("occupancy grids");
    let (mut own, mut unions) = (Vec::new(), Vec::new());
    for &threshold in &a.thresholds {
        let cfg = GridConfig { resolution: a.grid, threshold, ..GridConfig::default() };
        cfg.validate()?;
        let mut union: Option<Tensor> = None;
        let mut own_rows = Vec::new();
        for i in 0..a.codes {
            let grid = OccupancyGrid::build(
                &g.generator,
                &latents.shape.narrow(i, 1),
                Default::default(),
                &camera,
                cfg,
                1 << 16,
            )?;
            own_rows.push(measure(&grid, &rays, range, (threshold, 1)));
            union = Some(match union {
                None => grid.occupied,
                Some(u) => u.logical_or(&grid.occupied),
            });
            if counts.contains(&(i + 1)) {
                let occupied = union.as_ref().map(|u| u.shallow_clone()).expect("a grid was built");
                let shared = OccupancyGrid { cfg, half: camera_half_extent(&camera), occupied, evaluated: 0 };
                unions.push(measure(&shared, &rays, range, (threshold, i + 1)));
            }
            bar.inc(1);
        }
        let mean = |f: fn(&Row) -> f64| own_rows.iter().map(f).sum::<f64>() / own_rows.len() as f64;
        own.push(Row {
            threshold,
            codes: 1,
            occupied: mean(|r| r.occupied),
            rays_hit: mean(|r| r.rays_hit),
            rays_hit_max_view: mean(|r| r.rays_hit_max_view),
            interval_kept: mean(|r| r.interval_kept),
            queries: mean(|r| r.queries),
        });
    }
    bar.finish_and_clear();
    println!(
        "{:>9} {:>7} {:>9} {:>9} {:>13} {:>14} {:>11}",
        "threshold", "codes", "occupied", "rays hit", "fullest view", "interval kept", "queries"
    );
    let labelled =
        own.iter().map(|r| (r, "1 (own)".to_string())).chain(unions.iter().map(|r| (r, r.codes.to_string())));
    for (r, codes) in labelled {
        println!(
            "{:>9} {:>7} {:>9.3} {:>9.3} {:>13.3} {:>14.3} {:>11.0}",
            r.threshold, codes, r.occupied, r.rays_hit, r.rays_hit_max_view, r.interval_kept, r.queries
        );
    }
    let stem = a.out.display().to_string();
    let (json, png) = (PathBuf::from(format!("{stem}.json")), PathBuf::from(format!("{stem}.png")));
    if let Some(dir) = json.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    let title = format!(
        "A {g}³ grid shared by n codes: {v} training views at {r}², {p}",
        g = a.grid,
        v = a.views,
        r = a.resolution,
        p = path.display()
    );
    write_json(
        &json,
        &Doc {
            title: title.clone(),
            checkpoint: path.display().to_string(),
            settings: a,
            own_grid: own.clone(),
            unions: unions.clone(),
        },
    )?;
    // One code's own grid at the first threshold, as a level: what a per-instance grid keeps.
    let panel = |name: &str, f: fn(&Row) -> f64| crate::plot::Panel {
        title: format!("{name}, against the number of codes in the union"),
        series: a
            .thresholds
            .iter()
            .map(|&t| crate::plot::Series {
                name: format!("density > {t}"),
                points: unions.iter().filter(|r| r.threshold == t).map(|r| (r.codes as f64, f(r))).collect(),
            })
            .chain(std::iter::once(crate::plot::Series {
                name: format!("one code's own grid, density > {}", own[0].threshold),
                points: vec![(1.0, f(&own[0])), (a.codes as f64, f(&own[0]))],
            }))
            .collect(),
        log_y: false,
        marks: Vec::new(),
    };
    let panels = [
        panel("Share of rays that meet the grid", |r| r.rays_hit),
        panel("Share of the ray interval kept", |r| r.interval_kept),
    ];
    crate::io::save_png(&png, &crate::plot::draw_panels(&panels, 2, 520, 360)?)?;
    println!("{title}\nwrote {} and {}", json.display(), png.display());
    Ok((own, unions))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::TempDir;
    use crate::{CameraConfig, Generator, GeneratorConfig};

    /// The union never shrinks as codes join it, and each figure is a share.
    #[test]
    fn unions_grow_and_every_figure_is_a_share() {
        tch::manual_seed(2);
        let dir = TempDir::new("shared-grid").unwrap();
        let vs = tch::nn::VarStore::new(Device::Cpu);
        let g = Generator::new(&vs.root(), &GeneratorConfig::tiny()).unwrap();
        let header = crate::checkpoint::Header::generator(g.cfg.clone(), Some(CameraConfig::chair()));
        let file = dir.path("g.safetensors");
        crate::checkpoint::save_generator(&file, &vs, &header).unwrap();
        let a = Options {
            checkpoint: Some(file),
            codes: 3,
            grid: 16,
            thresholds: vec![0.5, 4.0],
            views: 2,
            resolution: 8,
            out: dir.path("out"),
        };
        let (own, unions) = run(&a).unwrap();
        assert_eq!(own.len(), 2);
        for t in [0.5, 4.0] {
            let rows: Vec<&Row> = unions.iter().filter(|r| r.threshold == t).collect();
            assert_eq!(rows.iter().map(|r| r.codes).collect::<Vec<_>>(), [1, 2, 3]);
            for w in rows.windows(2) {
                assert!(w[1].occupied >= w[0].occupied && w[1].rays_hit >= w[0].rays_hit, "{t}: {w:?}");
            }
            for r in &rows {
                for v in [r.occupied, r.rays_hit, r.rays_hit_max_view, r.interval_kept] {
                    assert!((0.0..=1.0).contains(&v), "{r:?}");
                }
            }
        }
        assert!(dir.path("out.json").exists() && dir.path("out.png").exists());
        let bad = Options { codes: 0, ..a };
        assert!(run(&bad).unwrap_err().to_string().contains("--codes 0"));
    }
}
