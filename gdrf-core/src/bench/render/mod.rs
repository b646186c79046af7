//! `gdrf-edit bench`: run time against error for each renderer configuration, on the
//! trained model and on an analytic scene with exact surfaces, beside the PyTorch
//! reference renderer timed in the same run.
use super::{median, peak_rss_mb, run_reference, write_json};
use crate::camera::Poses;
use crate::checkpoint::load_generator;
use crate::data::synth::{analytic::AnalyticField, sample_object, Category};
use crate::error::Context;
use crate::eval::fidelity::psnr_all;
use crate::field::generator::FieldOptions;
use crate::field::RadianceField;
use crate::nn::mapping::seeded_randn;
use crate::paths::write_atomic;
use crate::render::Grids;
use crate::render::{GridConfig, Image, Noise, OccupancyGrid, Renderer};
use crate::{device, CameraConfig, Error, Latents, RenderConfig, Result};
use std::path::PathBuf;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

mod report;

pub use report::{PyTorchRun, Report, Row};

/// The flags of `gdrf-edit bench`.
#[derive(clap::Args)]
pub struct Options {
    /// Generator checkpoint benchmarked beside the analytic scene; default: the shipped
    /// models/chairs-campaign. --generator is the same.
    #[arg(long, visible_alias = "generator", value_name = "FILE")]
    pub checkpoint: Option<PathBuf>,
    /// Image sizes (square).
    #[arg(long, value_delimiter = ',', default_value = "64,128")]
    pub resolutions: Vec<i64>,
    /// Latent seeds of the model (z = randn after manual_seed, as `render`), and object
    /// seeds of the analytic scene (procedural chairs).
    #[arg(long, value_delimiter = ',', default_value = "0,1")]
    pub seeds: Vec<i64>,
    /// Views per seed (yaw spread over 360° at the camera's mean pitch); an occupancy grid
    /// is built once per seed and reused by its views.
    #[arg(long, default_value_t = 2)]
    pub views: usize,
    /// Timed repetitions (after one warm-up); times are medians.
    #[arg(long, default_value_t = 3)]
    pub repeats: usize,
    /// Coarse samples N of the dense reference that errors are measured against
    /// (N stratified + N importance, no jitter).
    #[arg(long, default_value_t = 256)]
    pub reference_steps: usize,
    /// Run only the configurations whose name contains one of these (e.g. `grid,thin`);
    /// the release's sampler always runs, as the baseline of the speed-ups.
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<String>,
    /// Skip the PyTorch reference (it needs the project's Python: scripts/setup.sh).
    #[arg(long)]
    pub no_pytorch: bool,
    /// Output folder: render.json, render.png (time against error) and render.md (table).
    #[arg(long, default_value = "bench")]
    pub out: PathBuf,
    /// auto, cpu, cuda or cuda:N.
    #[arg(long, default_value = "auto")]
    pub device: String,
}

impl Options {
    /// --checkpoint, else the shipped model (found from any working folder).
    fn checkpoint(&self) -> PathBuf {
        self.checkpoint.clone().unwrap_or_else(crate::paths::shipped_generator)
    }
}

/// One renderer configuration.
struct Setting {
    name: String,
    /// What the renderer skips, and how many samples it places (no jitter: deterministic
    /// renders).
    render: RenderConfig,
    grid: Option<GridConfig>,
    /// The networks' hidden layers in bfloat16 (integration stays float32); the model only.
    bf16: bool,
}

/// The release trains and renders with N = 36 at 64² and N = 64 at 128².
fn release_steps(res: i64) -> usize {
    if res <= 64 {
        36
    } else {
        64
    }
}

fn settings(res: i64) -> Vec<Setting> {
    let n = release_steps(res);
    // family, N, density-first threshold, termination, importance skip, grid
    let s = |family: &str, steps: usize, min_weight: f64, termination: f64, importance_skip: f64, grid: bool| Setting {
        name: format!("{family} N={steps}"),
        render: RenderConfig {
            num_steps: steps,
            jitter: false,
            shade_min_weight: min_weight,
            termination,
            importance_skip,
            importance_stride: 1,
            ..Default::default()
        },
        grid: grid.then(GridConfig::default),
        bf16: false,
    };
    let bf16 = |mut s: Setting| {
        s.name = s.name.replacen(' ', "+bf16 ", 1);
        s.bf16 = true;
        s
    };
    // A grid of another resolution, sampling the first-to-last interval or (cells) only
    // the occupied cells.
    let fine = |mut s: Setting, resolution: i64, cells_only: bool| {
        let family = if cells_only { "cells" } else { "grid" };
        s.name = s.name.replacen("grid", &format!("{family}{resolution}"), 1);
        s.grid = Some(GridConfig { cells_only, resolution, ..GridConfig::default() });
        s
    };
    let cells = |s: Setting, resolution: i64| fine(s, resolution, true);
    // Grids are built coarse to fine (from 16³ up, only inside the coarser grid's occupied
    // cells); `flat` evaluates every lattice point, to show what that build gives up.
    let flat = |mut s: Setting| {
        s.name = s.name.replacen(' ', "/flat ", 1);
        s.grid = s.grid.map(|g| GridConfig { coarse_to_fine: false, ..g });
        s
    };
    let thin = |mut s: Setting, concentration: f64, stride: usize| {
        s.name = format!(
            "{}+thin/{stride}@{concentration} N={}",
            s.name.split(' ').next().unwrap_or(""),
            s.render.num_steps
        );
        s.render.importance_concentration = concentration;
        s.render.importance_stride = stride;
        s
    };
    vec![
        s("reference", n, 0.0, 0.0, 0.0, false),
        s("reference", 24, 0.0, 0.0, 0.0, false),
        s("reference", 12, 0.0, 0.0, 0.0, false),
        s("density-first", n, 1e-3, 0.0, 0.0, false),
        s("density-first", 24, 1e-3, 0.0, 0.0, false),
        s("early-termination", n, 0.0, 1e-3, 0.0, false),
        s("skip-empty", n, 0.0, 0.0, 1e-3, false),
        s("skip-empty", 24, 0.0, 0.0, 1e-3, false),
        s("grid", n, 0.0, 0.0, 0.0, true),
        s("grid", 24, 0.0, 0.0, 0.0, true),
        s("grid", 12, 0.0, 0.0, 0.0, true),
        s("grid", 8, 0.0, 0.0, 0.0, true),
        s("grid+density-first", 24, 1e-3, 0.0, 0.0, true),
        s("grid+density-first", 12, 1e-3, 0.0, 0.0, true),
        s("grid+skip-empty", 24, 0.0, 0.0, 1e-3, true),
        s("grid+skip-empty", 12, 0.0, 0.0, 1e-3, true),
        s("grid+skip-empty+density-first", 12, 1e-3, 0.0, 1e-3, true),
        thin(s("reference", 24, 0.0, 0.0, 0.0, false), 0.9, 2),
        thin(s("reference", 24, 0.0, 0.0, 0.0, false), 0.9, 4),
        thin(s("density-first", 24, 1e-3, 0.0, 0.0, false), 0.9, 4),
        cells(s("grid", 24, 0.0, 0.0, 0.0, true), 32),
        cells(s("grid", 12, 0.0, 0.0, 0.0, true), 32),
        cells(s("grid", 8, 0.0, 0.0, 0.0, true), 32),
        cells(s("grid", 12, 0.0, 0.0, 0.0, true), 64),
        cells(s("grid", 8, 0.0, 0.0, 0.0, true), 64),
        cells(s("grid", 6, 0.0, 0.0, 0.0, true), 64),
        cells(s("grid", 4, 0.0, 0.0, 0.0, true), 64),
        fine(s("grid", 12, 0.0, 0.0, 0.0, true), 64, false),
        fine(s("grid", 8, 0.0, 0.0, 0.0, true), 64, false),
        cells(s("grid", 8, 0.0, 0.0, 0.0, true), 128),
        cells(s("grid", 6, 0.0, 0.0, 0.0, true), 128),
        cells(s("grid+density-first", 8, 1e-3, 0.0, 0.0, true), 64),
        flat(cells(s("grid", 12, 0.0, 0.0, 0.0, true), 32)),
        flat(cells(s("grid", 12, 0.0, 0.0, 0.0, true), 64)),
        flat(cells(s("grid", 8, 0.0, 0.0, 0.0, true), 128)),
        bf16(s("reference", n, 0.0, 0.0, 0.0, false)),
        bf16(s("density-first", 24, 1e-3, 0.0, 0.0, false)),
    ]
}

/// Stratified importance uniforms (k + ½)/N and no jitter: deterministic renders that
/// the PyTorch reference reproduces.
fn noise(b: i64, r: i64, n: usize, device: Device) -> Noise {
    let n = n as i64;
    let u = ((Tensor::arange(n, (Kind::Float, device)) + 0.5) / n as f64).view([1, 1, n]).expand([b, r, n], false);
    Noise { jitter: None, importance: Some(u.contiguous()) }
}

struct Scene<'a, F: RadianceField> {
    name: &'static str,
    fields: Vec<&'a F>,
    latents: Vec<Latents>,
}

/// Runs the benchmark and writes render.json, render.md and render.png into `--out`.
pub fn run(a: &Options) -> Result<Report> {
    if a.seeds.is_empty() || a.views == 0 || a.repeats == 0 || a.resolutions.is_empty() {
        return Err(Error::Invalid(
            "--seeds, --views, --repeats and --resolutions need at least one value each".into(),
        ));
    }
    if let Some(r) = a.resolutions.iter().find(|r| !(8..=1024).contains(*r)) {
        return Err(Error::Invalid(format!("--resolutions: {r} is outside 8..=1024")));
    }
    let threads = device::init_threads();
    let dev = device::select(&a.device)?;
    let loaded = load_generator(&a.checkpoint(), dev, Kind::Float)
        .with_context(|| format!("loading --checkpoint {}", a.checkpoint().display()))?;
    let camera = loaded.header.camera.clone().unwrap_or_default();
    let latent = loaded.generator.cfg.latent_dim as i64;
    let poses = crate::camera::turntable(camera.v_mean, 0.4, a.views);
    let model = Scene {
        name: "model",
        fields: vec![&loaded.generator; a.seeds.len()],
        latents: a
            .seeds
            .iter()
            .map(|&s| {
                let z = seeded_randn(&[1, latent], s).to_device(dev);
                tch::no_grad(|| loaded.generator.latents(&z, &z, None))
            })
            .collect::<Result<_>>()?,
    };
    let objects: Vec<AnalyticField> = a
        .seeds
        .iter()
        .map(|&s| {
            let (shape, app) = sample_object(Category::Chairs, s as u64);
            AnalyticField::new(&shape, &app, &camera, 500.0, 0.004)
        })
        .collect::<Result<_>>()?;
    let analytic = Scene {
        name: "analytic",
        fields: objects.iter().collect(),
        latents: objects.iter().map(|f| f.latents(1)).collect(),
    };

    println!(
        "gdrf-edit bench: {} seed(s) × {} view(s) at {:?} on {dev:?} ({threads} threads); errors against N={} + {} without jitter",
        a.seeds.len(),
        a.views,
        a.resolutions,
        a.reference_steps,
        a.reference_steps
    );
    let mut results = Vec::new();
    let mut pytorch = Vec::new();
    for &res in &a.resolutions {
        let (rows, images) = run_scene(&model, &camera, &poses, res, a)?;
        results.extend(rows);
        if !a.no_pytorch {
            pytorch.push(pytorch_reference(a, &poses, res, &images)?);
        }
        let (rows, _) = run_scene(&analytic, &camera, &poses, res, a)?;
        results.extend(rows);
    }
    let report = Report {
        title: "renderer: time against error",
        checkpoint: crate::paths::shown(&a.checkpoint()),
        device: format!("{dev:?}"),
        threads,
        seeds: a.seeds.clone(),
        views: a.views,
        repeats: a.repeats,
        reference_steps: a.reference_steps,
        results,
        pytorch,
    };
    std::fs::create_dir_all(&a.out).with_context(|| format!("creating --out {}", a.out.display()))?;
    let json_path = a.out.join("render.json");
    write_json(&json_path, &report)?;
    let md = report.markdown();
    write_atomic(&a.out.join("render.md"), md.as_bytes())?;
    let png = a.out.join("render.png");
    crate::io::save_png(&png, &report.chart()?)?;
    println!("{md}");
    println!("wrote {}, {} and {}", json_path.display(), png.display(), a.out.join("render.md").display());
    Ok(report)
}

fn max_abs(t: &Tensor) -> f64 {
    f64::try_from(t.abs().max().to_kind(Kind::Double)).unwrap_or(f64::NAN)
}

/// Every configuration (after --only) on `scene` at `res`², and the `(S·V, 3, res, res)`
/// images of the release's sampler (the PyTorch reference's comparison).
fn run_scene<F: RadianceField>(
    scene: &Scene<F>,
    camera: &CameraConfig,
    poses: &[(f64, f64)],
    res: i64,
    a: &Options,
) -> Result<(Vec<Row>, Tensor)> {
    let (_, dev) = scene.fields[0].kind_device();
    let render_all = |rc: &RenderConfig, opts: FieldOptions, grids: &[Option<OccupancyGrid>]| {
        render_all(scene, camera, poses, res, (rc, opts), grids)
    };
    let n_images = (scene.fields.len() * poses.len()) as f64;
    eprintln!("{} {res}²: dense reference (N={} + {}) …", scene.name, a.reference_steps, a.reference_steps);
    let dense_rc = RenderConfig { num_steps: a.reference_steps, jitter: false, ..Default::default() };
    let no_grids: Vec<Option<OccupancyGrid>> = scene.fields.iter().map(|_| None).collect();
    let (dense, _) = render_all(&dense_rc, FieldOptions::default(), &no_grids)?;

    let baseline = format!("reference N={}", release_steps(res));
    let list: Vec<Setting> = settings(res)
        .into_iter()
        .filter(|s| s.name == baseline || a.only.is_empty() || a.only.iter().any(|o| s.name.contains(o.as_str())))
        // The analytic field has no networks to run in bfloat16.
        .filter(|s| !(s.bf16 && scene.name == "analytic"))
        .collect();
    let bar = crate::progress::bar(list.len() as u64, "configurations", false);
    bar.set_prefix(format!("{} {res}²", scene.name));
    let mut rows = Vec::new();
    let mut reference_images = Tensor::zeros([0], (Kind::Float, dev));
    for s in &list {
        let rc = &s.render;
        let opts = FieldOptions { compute_kind: s.bf16.then_some(Kind::BFloat16), ..Default::default() };
        // Grids are built once per shape, timed apart from the renders that reuse them.
        let (grids, grid_ms, grid_queries) = match s.grid {
            Some(cfg) => build_grids(scene, camera, (rc, opts), cfg)?,
            None => (no_grids.iter().map(|_| None).collect(), 0.0, 0),
        };
        let mut times = Vec::new();
        let mut out = None;
        for rep in 0..=a.repeats {
            let t = Instant::now();
            let o = render_all(rc, opts, &grids)?;
            if rep > 0 {
                times.push(1000.0 * t.elapsed().as_secs_f64() / n_images);
            }
            out = Some(o);
        }
        let (img, (dq, cq)) = out.expect("rendered");
        if s.name == baseline {
            reference_images = img.rgb.shallow_clone();
        }
        let ms = median(&times);
        rows.push(Row {
            scene: scene.name,
            resolution: res,
            config: s.name.clone(),
            steps: rc.num_steps,
            min_weight: rc.shade_min_weight,
            termination: rc.termination,
            importance_skip: rc.importance_skip,
            importance_concentration: rc.importance_concentration,
            importance_stride: rc.importance_stride,
            bf16: s.bf16,
            grid: s.grid,
            ms_per_image: ms,
            grid_ms_per_shape: grid_ms,
            ms_per_image_with_grid_build: ms + grid_ms / poses.len() as f64,
            density_queries_per_image: dq as f64 / n_images,
            colour_queries_per_image: cq as f64 / n_images,
            grid_queries_per_shape: grid_queries,
            psnr_db: psnr_all(&img.rgb, &dense.rgb)?,
            max_abs_error: max_abs(&((&img.rgb - &dense.rgb) * 0.5)),
            opacity_error: max_abs(&(&img.opacity - &dense.opacity)),
            peak_rss_mb_so_far: peak_rss_mb(),
            ms_per_image_runs: times,
        });
        bar.inc(1);
    }
    bar.finish_and_clear();
    for row in &rows {
        eprintln!(
            "  {:<8} {res:>4}² {:<26} {:>8.1} ms/image {:>6.1} dB  opacity err {:.1e}",
            scene.name, row.config, row.ms_per_image, row.psnr_db, row.opacity_error
        );
    }
    Ok((rows, reference_images))
}

/// Every field of `scene` at every pose, rendered with `rc` and `opts` in its grid (where
/// `grids` has one), concatenated; and the density and colour queries made.
fn render_all<F: RadianceField>(
    scene: &Scene<F>,
    camera: &CameraConfig,
    poses: &[(f64, f64)],
    res: i64,
    (rc, opts): (&RenderConfig, FieldOptions),
    grids: &[Option<OccupancyGrid>],
) -> Result<(Image, (i64, i64))> {
    let (_, dev) = scene.fields[0].kind_device();
    let r = res * res;
    let mut parts = Vec::new();
    let (mut dq, mut cq) = (0, 0);
    for (i, (field, lat)) in scene.fields.iter().zip(&scene.latents).enumerate() {
        let mut renderer = Renderer::new(*field, camera, rc)?;
        renderer.field = opts;
        let grid: Vec<&OccupancyGrid> = grids[i].iter().collect();
        for &pose in poses {
            let pose = Poses::from_angles(&[pose], Kind::Float, dev);
            let noise = noise(1, r, rc.num_steps, dev);
            let (img, (d, c)) = Grids::new(&renderer).render_image_in_grids(lat, &pose, res, &noise, &grid)?;
            parts.push(img);
            dq += d;
            cq += c;
        }
    }
    let cat = |f: &dyn Fn(&Image) -> &Tensor| Tensor::cat(&parts.iter().map(f).collect::<Vec<_>>(), 0);
    Ok((Image { rgb: cat(&|i| &i.rgb), depth: cat(&|i| &i.depth), opacity: cat(&|i| &i.opacity) }, (dq, cq)))
}

/// One occupancy grid per shape of `scene` for `cfg`, the milliseconds a grid took and the
/// density queries it made (means over the shapes).
fn build_grids<F: RadianceField>(
    scene: &Scene<F>,
    camera: &CameraConfig,
    (rc, opts): (&RenderConfig, FieldOptions),
    cfg: GridConfig,
) -> Result<(Vec<Option<OccupancyGrid>>, f64, i64)> {
    let t = Instant::now();
    let grids = scene
        .fields
        .iter()
        .zip(&scene.latents)
        .map(|(f, l)| {
            let mut r = Renderer::new(*f, camera, rc)?;
            r.field = opts;
            Grids::new(&r).occupancy_grid(&l.shape, cfg).map(Some)
        })
        .collect::<Result<Vec<_>>>()?;
    let ms = 1000.0 * t.elapsed().as_secs_f64() / scene.fields.len() as f64;
    let q = grids.iter().flatten().map(|g| g.evaluated).sum::<i64>() / scene.fields.len() as i64;
    Ok((grids, ms, q))
}

/// The PyTorch reference sampler on the same checkpoint, seeds, poses and uniforms; its
/// `(S·V, 3, res, res)` images are compared with the Rust reference configuration's.
fn pytorch_reference(a: &Options, poses: &[(f64, f64)], res: i64, rust_images: &Tensor) -> Result<PyTorchRun> {
    let tmp = std::env::temp_dir().join(format!("gdrf-bench-render-{}-{res}.safetensors", std::process::id()));
    let n = release_steps(res);
    let args: Vec<String> = vec![
        a.checkpoint().display().to_string(),
        "--seeds".into(),
        a.seeds.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(","),
        "--poses".into(),
        poses.iter().map(|(p, y)| format!("{p}:{y}")).collect::<Vec<_>>().join(","),
        "--resolution".into(),
        res.to_string(),
        "--num-steps".into(),
        n.to_string(),
        "--repeats".into(),
        a.repeats.to_string(),
        "--images-out".into(),
        tmp.display().to_string(),
    ];
    let measured = run_reference("bench_render.py", &args)?;
    let images =
        Tensor::read_safetensors(&tmp).with_context(|| format!("reading the reference's images {}", tmp.display()))?;
    let _ = std::fs::remove_file(&tmp);
    let theirs = images
        .into_iter()
        .find(|(k, _)| k == "images")
        .map(|(_, t)| t)
        .ok_or_else(|| Error::Data { path: tmp.clone(), reason: "no 'images' in the reference's output".into() })?;
    let diff = max_abs(&((theirs.to_device(rust_images.device()) - rust_images) * 0.5));
    let run = PyTorchRun {
        measured,
        resolution: res,
        config: format!("reference N={n}"),
        max_abs_difference_from_rust: diff,
    };
    eprintln!(
        "  pytorch  {res:>4}² reference N={n}: {:.1} ms/image, images within {diff:.1e} of Rust's",
        run.ms_per_image()
    );
    Ok(run)
}
