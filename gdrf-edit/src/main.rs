//! gdrf-edit: render a GDRF generator from any viewpoint, with shape and appearance
//! taken from different codes. `gdrf-edit --shape-from A --appearance-from B` is the swap.
mod mesh_cmd;
mod model;
mod serve;
mod swap;

use anyhow::{bail, Context, Result};
use clap::{Args, Parser, Subcommand};
use gdrf_core::camera::Poses;
use gdrf_core::field::generator::FieldOptions;
use gdrf_core::nn::mapping::seeded_randn;
use gdrf_core::render::Grids;
use gdrf_core::render::{Noise, OccupancyGrid, Renderer};
use gdrf_core::{io, RenderConfig};
use std::path::PathBuf;
use std::time::Instant;
use tch::{Kind, Tensor};

/// Render and edit GDRF generators: novel views, shape/appearance swaps.
///
/// Without a subcommand, `gdrf-edit --shape-from A --appearance-from B` renders the shape of
/// A with the appearance of B (the `swap` subcommand): a source is seed:N, a feature file
/// from gdrf-invert, or a photo (inverted on the fly). Every subcommand renders the shipped
/// model (models/chairs-campaign) unless --checkpoint names another, at the resolution and
/// samples per ray it learned at unless --resolution and --samples say otherwise.
#[derive(Parser)]
#[command(version, about, long_about, args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    swap: swap::SwapArgs,
    /// No progress bars, in this command and every subcommand (`render --quiet`), e.g. for
    /// logs, as gdrf-train's and gdrf-invert's.
    #[arg(long, global = true)]
    quiet: bool,
}

#[derive(Subcommand)]
enum Command {
    /// Render images for latent seeds from one or more viewpoints into a PNG grid
    /// (one row per seed, one column per view).
    Render(RenderArgs),
    /// Renderer benchmark: milliseconds per image against error (PSNR, max error, opacity
    /// error against a dense reference) for each configuration — the release's sampler,
    /// fewer samples, density-first shading, the occupancy grid and their combinations — on
    /// the trained model and on an analytic scene, with the PyTorch reference timed in the
    /// same run. Writes render.json, render.png (the Pareto plot) and render.md.
    Bench(gdrf_core::bench::render::Options),
    /// The shape of one source with the appearance of another, at one or more views:
    /// frame-NNN.png per view and strip.png. A source is seed:N, a feature file
    /// (.safetensors, from gdrf-invert or `features`) or a photo (inverted on the fly).
    Swap(swap::SwapArgs),
    /// A swap matrix over several sources: row i has the shape of source i, column j the
    /// appearance of source j. Each row's shape side is computed once and re-shaded.
    Matrix(swap::MatrixArgs),
    /// Write the feature file of a seed (the format gdrf-invert writes).
    Features(swap::FeaturesArgs),
    /// Interpolate the shape, the appearance or both between two sources at one view:
    /// frame-NNN.png, strip.png and sequence.gif.
    Interp(swap::InterpArgs),
    /// An isosurface of a source's density as a PLY or OBJ mesh, with the generator's colour
    /// (optionally another source's appearance: texture transfer) or the template-space
    /// position as vertex colour (correspondences across shapes).
    Mesh(mesh_cmd::MeshArgs),
    /// A local web server with a page to orbit a chair, choose its shape and its
    /// appearance apart (seeds, feature files, dropped photos), interpolate them and
    /// download the image, an orbit GIF, a mesh, features or a swap matrix. Listens on
    /// 127.0.0.1:8470 unless --host and --port say otherwise; prints the address.
    Serve(serve::ServeArgs),
    /// Frame times of `serve` over HTTP (median and 95th percentile) at several
    /// resolutions while orbiting, moving an appearance slider and moving a shape slider,
    /// then a load test (simulated users for a bounded time: requests, errors, latency,
    /// the server's peak memory). Writes STEM.json, STEM.png and STEM-load.json.
    ServeBench(serve::bench::BenchArgs),
}

#[derive(Args)]
struct RenderArgs {
    #[command(flatten)]
    model: model::ModelArgs,
    /// Latent seeds, comma separated: seed s draws z = randn(1, latent) after
    /// manual_seed(s), as the authors' scripts do (same z as PyTorch's CPU generator).
    #[arg(long, value_delimiter = ',', default_value = "0,1,2,3")]
    seeds: Vec<i64>,
    /// Appearance seeds (one per shape seed, or one for all): render each shape with
    /// another code's appearance. Default: the shape seed's own code.
    #[arg(long, value_delimiter = ',')]
    appearance_seeds: Vec<i64>,
    /// Where the camera stands, image size, samples per ray, truncation, ablations; the
    /// turntable's views are per seed.
    #[command(flatten)]
    view: gdrf_core::edit::view::ViewFlags,
    /// Run the networks' hidden layers in bfloat16 (integration stays float32). About 2×
    /// faster on GPUs and on CPUs with bfloat16 instructions (AVX512-BF16, AMX), slower
    /// elsewhere; it cost 0.7 dB against the dense reference in `gdrf-edit bench`.
    #[arg(long)]
    bf16: bool,
    #[command(flatten)]
    grid: gdrf_core::edit::view::GridFlags,
    /// What the renderer skips and how (the config's `[render]` keys as flags); the
    /// samples per ray come from --samples.
    #[command(flatten)]
    render: RenderConfig,
    /// Output PNG (the grid of images).
    #[arg(long, short, default_value = "render.png")]
    out: PathBuf,
    /// Columns of the grid (default: --views, i.e. one row per seed). With seeds
    /// 0,0,1,1 and appearance seeds 0,1,0,1, `--cols 2` lays out a swap matrix.
    #[arg(long)]
    cols: Option<i64>,
    /// Also write the normalised depth maps to this PNG.
    #[arg(long)]
    depth_out: Option<PathBuf>,
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    gdrf_core::progress::set_quiet(cli.quiet);
    match cli.command {
        None => swap::swap(cli.swap),
        Some(Command::Render(a)) => render(a),
        Some(Command::Bench(a)) => gdrf_core::bench::render::run(&a).map(drop).map_err(Into::into),
        Some(Command::Swap(a)) => swap::swap(a),
        Some(Command::Matrix(a)) => swap::matrix(a),
        Some(Command::Features(a)) => swap::features(a),
        Some(Command::Interp(a)) => swap::interp(a),
        Some(Command::Mesh(a)) => mesh_cmd::mesh(a),
        Some(Command::Serve(a)) => serve::serve(a),
        Some(Command::ServeBench(a)) => serve::bench::bench(a),
    }
}

fn render(mut a: RenderArgs) -> Result<()> {
    if a.seeds.is_empty() {
        bail!("--seeds: give at least one seed");
    }
    if !(a.appearance_seeds.is_empty() || a.appearance_seeds.len() == 1 || a.appearance_seeds.len() == a.seeds.len()) {
        bail!(
            "--appearance-seeds: {} seeds given, expected 1 or one per shape seed ({})",
            a.appearance_seeds.len(),
            a.seeds.len()
        );
    }
    a.view.check()?;
    let (model::Model { generator, camera, device: dev, learned, .. }, threads) = model::open(&a.model)?;
    a.view.settle(&learned);
    let resolution = a.view.res();
    let config = RenderConfig { num_steps: a.view.samples(), ..a.render.clone() };
    let mut renderer = Renderer::new(&generator, &camera, &config)?;
    renderer.field = FieldOptions { compute_kind: a.bf16.then_some(Kind::BFloat16), ..a.view.field() };

    let latent = generator.cfg.latent_dim as i64;
    let code = |s: i64| seeded_randn(&[1, latent], s).to_device(dev);
    let z_s = Tensor::cat(&a.seeds.iter().map(|&s| code(s)).collect::<Vec<_>>(), 0);
    let app_seeds: Vec<i64> = match a.appearance_seeds.len() {
        0 => a.seeds.clone(),
        1 => vec![a.appearance_seeds[0]; a.seeds.len()],
        _ => a.appearance_seeds.clone(),
    };
    let z_a = Tensor::cat(&app_seeds.iter().map(|&s| code(s)).collect::<Vec<_>>(), 0);
    let trunc = generator.truncation_at(a.view.psi);
    let latents = tch::no_grad(|| generator.latents(&z_s, &z_a, trunc.as_ref()))?;

    let views = a.view.turntable(&camera);
    let total = a.seeds.len() * views.len();
    let bar = gdrf_core::progress::bar(total as u64, "images", false);
    bar.set_prefix(format!("rendering {}×{}", resolution, resolution));
    let start = Instant::now();
    let mut rgb = Vec::with_capacity(total);
    let mut depth = Vec::with_capacity(total);
    let samples_per_shape = (views.len() as i64 * resolution * resolution) as f64 * config.samples_per_ray() as f64;
    let grid_cfg = a.grid.resolve(samples_per_shape)?;
    for i in 0..a.seeds.len() as i64 {
        let lat = latents.narrow(i, 1);
        // The grid depends on the shape alone: one per seed, shared by its views.
        let grid = match grid_cfg {
            Some(cfg) => Some(Grids::new(&renderer).occupancy_grid(&lat.shape, cfg).context("--grid")?),
            None => None,
        };
        let grids: Vec<&OccupancyGrid> = grid.iter().collect();
        for &v in &views {
            let poses = Poses::from_angles(&[v], Kind::Float, dev);
            let (img, _) =
                Grids::new(&renderer).render_image_in_grids(&lat, &poses, resolution, &Noise::default(), &grids)?;
            rgb.push(img.rgb);
            depth.push(img.depth);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    let rgb = Tensor::cat(&rgb, 0);
    let cols = a.cols.unwrap_or(views.len() as i64);
    if cols < 1 {
        bail!("--cols {cols}: expected at least 1");
    }
    let img = io::to_rgb8(&io::grid(&rgb, cols), false)?;
    io::save_png(&a.out, &img).with_context(|| format!("writing --out {}", a.out.display()))?;
    if let Some(p) = &a.depth_out {
        let d = io::grid(&io::depth_map(&Tensor::cat(&depth, 0), camera.ray_start, camera.ray_end), cols);
        io::save_png(p, &io::to_rgb8(&d, false)?).with_context(|| format!("writing --depth-out {}", p.display()))?;
    }
    let samples = total as f64 * (resolution * resolution) as f64 * config.samples_per_ray() as f64;
    println!(
        "rendered {total} image(s) of {r}×{r} with {s} samples/ray{g} on {dev:?} ({threads} threads) in {secs:.2} s \
         ({:.0} ms/image, {:.2} M samples/s) -> {}",
        1000.0 * secs / total as f64,
        samples / secs / 1e6,
        a.out.display(),
        r = resolution,
        s = config.samples_per_ray(),
        g = grid_note(grid_cfg),
    );
    Ok(())
}

/// How the renders were sampled, for the closing line: ", in the occupied cells of a 32³ grid".
pub(crate) fn grid_note(grid: Option<gdrf_core::render::GridConfig>) -> String {
    match grid {
        Some(g) if g.cells_only => format!(", in the occupied cells of a {}³ grid", g.resolution),
        Some(g) => format!(", between the first and last occupied cells of a {}³ grid", g.resolution),
        None => String::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;
    use gdrf_core::edit::Source;

    #[test]
    fn every_subcommand_takes_quiet() {
        assert_eq!(gdrf_core::progress::without_quiet(&mut Cli::command()), Vec::<String>::new());
        assert!(Cli::try_parse_from(["gdrf-edit", "render", "--seeds", "0", "--quiet"]).unwrap().quiet);
    }

    #[test]
    fn render_takes_the_samples_per_ray_as_steps_or_samples() {
        let steps = |flag: &str| match Cli::try_parse_from(["gdrf-edit", "render", flag, "8"]).unwrap().command {
            Some(Command::Render(a)) => a.view.samples,
            _ => unreachable!("parsed as render"),
        };
        assert_eq!((steps("--steps"), steps("--samples")), (Some(8), Some(8)));
    }

    #[test]
    fn renderer_flags_are_named_as_their_config_keys_and_keep_their_old_names() {
        let render =
            |args: &[&str]| match Cli::try_parse_from([&["gdrf-edit", "render"][..], args].concat()).unwrap().command {
                Some(Command::Render(a)) => a,
                _ => unreachable!("parsed as render"),
            };
        let d = RenderConfig::default();
        let a = render(&[]);
        assert_eq!(
            (a.render.shade_min_weight, a.render.importance_skip, a.render.importance_concentration),
            (d.shade_min_weight, d.importance_skip, d.importance_concentration)
        );
        assert_eq!(
            (a.render.importance_stride, a.render.chunk_points, a.render.jitter, a.render.force_last_white),
            (d.importance_stride, d.chunk_points, true, false)
        );
        for (new, old) in [
            ("--shade-min-weight", "--min-weight"),
            ("--importance-skip", "--skip-empty"),
            ("--importance-concentration", "--thin-concentrated"),
        ] {
            let get = |flag: &str| {
                let a = render(&[flag, "0.25"]);
                (a.render.shade_min_weight, a.render.importance_skip, a.render.importance_concentration)
            };
            assert_eq!(get(new), get(old), "{new} and {old}");
            assert_ne!(get(new), get("--termination"), "{new} sets something");
        }
        assert_eq!(render(&["--importance-stride", "3"]).render.importance_stride, 3);
        assert_eq!(render(&["--thin-stride", "3"]).render.importance_stride, 3);
        assert!(!render(&["--no-jitter"]).render.jitter);
        assert!(render(&["--force-last-white"]).render.force_last_white);
    }

    #[test]
    fn a_swap_needs_no_subcommand() {
        let cli = Cli::try_parse_from(["gdrf-edit", "--shape-from", "seed:0", "--appearance-from", "seed:1"]).unwrap();
        assert!(cli.command.is_none());
        assert_eq!(cli.swap.sources(), (Some(&Source::Seed(0)), Some(&Source::Seed(1))));
        // The subcommands stay, and a half-given swap is a usage error naming the missing flag.
        assert!(matches!(Cli::try_parse_from(["gdrf-edit", "render"]).unwrap().command, Some(Command::Render(_))));
        let e = Cli::try_parse_from(["gdrf-edit", "--shape-from", "seed:0"]).err().unwrap();
        assert_eq!(e.exit_code(), 2);
        assert!(e.to_string().contains("--appearance-from"), "{e}");
    }
}
