//! `gdrf-edit swap`, `matrix` and `features`: the shape of one source with the appearance of
//! another, a swap matrix over several sources, and feature files of seeds. Density never
//! depends on the appearance, so the shape side of each (shape, view) is computed once and
//! only the colour branch runs again for each appearance.
use crate::model::{open, resolve, ModelArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use gdrf_core::camera::{Poses, Rays};
use gdrf_core::edit::matrix::MatrixView;
use gdrf_core::edit::view::{GridFlags, ViewArgs};
use gdrf_core::edit::{interpolate, latents, Features, Interpolate, Source};
use gdrf_core::io;
use gdrf_core::render::Grids;
use gdrf_core::render::Renderer;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::{Kind, Tensor};

#[derive(Args)]
pub struct SwapArgs {
    /// Where the shape comes from: seed:N, a feature file (.safetensors) or a photo.
    #[arg(long, value_name = "SOURCE", required = true)]
    shape_from: Option<Source>,
    /// Where the appearance comes from: seed:N, a feature file or a photo.
    #[arg(long, value_name = "SOURCE", required = true)]
    appearance_from: Option<Source>,
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    view: ViewArgs,
    /// Output folder: frame-NNN.png per view, strip.png with all views and, for more than
    /// one view, sequence.gif.
    #[arg(long, short, default_value = "swap")]
    out: PathBuf,
    /// Write into an output folder that already holds files.
    #[arg(long)]
    force: bool,
    /// Also write depth-NNN.png (near to far over the camera's ray range) and
    /// opacity-NNN.png, through the viridis colour map.
    #[arg(long)]
    maps: bool,
    #[command(flatten)]
    grid: GridFlags,
}

#[derive(Args)]
pub struct MatrixArgs {
    /// Sources (seed:N, feature files), comma separated: row i has the shape of source i,
    /// column j the appearance of source j; the diagonal is the sources themselves.
    #[arg(long, value_delimiter = ',', required = true)]
    sources: Vec<Source>,
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    view: ViewArgs,
    /// Output PNG (one matrix per view, side by side).
    #[arg(long, short, default_value = "swap-matrix.png")]
    out: PathBuf,
    /// Render every cell in full instead of shading each row's kept shape side (for
    /// timing the difference; the images agree within 1e-5).
    #[arg(long)]
    no_cache: bool,
}

#[derive(Args)]
pub struct FeaturesArgs {
    /// The seed whose features to write (z = randn after manual_seed, as `render`).
    #[arg(long)]
    seed: i64,
    #[command(flatten)]
    model: ModelArgs,
    /// Output feature file (.safetensors).
    #[arg(long, short)]
    out: PathBuf,
}

impl SwapArgs {
    /// The shape's and the appearance's source as given.
    pub fn sources(&self) -> (Option<&Source>, Option<&Source>) {
        (self.shape_from.as_ref(), self.appearance_from.as_ref())
    }
}

pub fn swap(mut a: SwapArgs) -> Result<()> {
    a.view.check()?;
    let (shape_from, appearance_from) = match a.sources() {
        (Some(s), Some(p)) => (s.clone(), p.clone()),
        _ => bail!("a swap needs both --shape-from and --appearance-from"),
    };
    let (model, threads) = open(&a.model)?;
    a.view = a.view.resolved(&model.learned);
    let (shape, appearance) =
        (resolve(&model, &shape_from, "--shape-from")?, resolve(&model, &appearance_from, "--appearance-from")?);
    gdrf_core::io::output_dir(&a.out, a.force, "--out")?;
    let g = &model.generator;
    let trunc = g.truncation_at(a.view.flags.psi);
    let lat = latents(g, &shape, &appearance, trunc.as_ref());
    let rc = a.view.render_config();
    let mut renderer = Renderer::new(g, &model.camera, &rc)?;
    renderer.field = a.view.field();
    let start = Instant::now();
    let views = a.view.poses(&model.camera);
    let pixels = a.view.res() * a.view.res();
    // One grid for the shape, shared by its views (density never depends on the appearance).
    let grid_cfg = a.grid.resolve((views.len() as i64 * pixels) as f64 * rc.samples_per_ray() as f64)?;
    let grid = match grid_cfg {
        Some(cfg) => Some(Grids::new(&renderer).occupancy_grid(&lat.shape, cfg).context("--grid")?),
        None => None,
    };
    let grids: Vec<_> = grid.iter().collect();
    let mut frames = Vec::new();
    for (k, &pose) in views.iter().enumerate() {
        let poses = Poses::from_angles(&[pose], Kind::Float, model.device);
        let noise = a.view.noise(k, pixels, model.device);
        let (img, _) = Grids::new(&renderer).render_image_in_grids(&lat, &poses, a.view.res(), &noise, &grids)?;
        let path = a.out.join(format!("frame-{k:03}.png"));
        io::save_png(&path, &io::to_rgb8(&img.rgb.get(0), false)?)
            .with_context(|| format!("writing {}", path.display()))?;
        if a.maps {
            let depth = io::depth_map(&img.depth.get(0), model.camera.ray_start, model.camera.ray_end);
            io::save_png(&a.out.join(format!("depth-{k:03}.png")), &io::to_rgb8(&depth, false)?)?;
            io::save_png(
                &a.out.join(format!("opacity-{k:03}.png")),
                &io::to_rgb8(&io::colour_map(&img.opacity.get(0)), false)?,
            )?;
        }
        frames.push(img.rgb);
    }
    write_sequence(&a.out, &frames)?;
    println!(
        "shape of {:?} with the appearance of {:?}: {} view(s) of {r}×{r}{} in {:.2} s ({threads} threads) -> {}",
        shape_from,
        appearance_from,
        frames.len(),
        crate::grid_note(grid_cfg),
        start.elapsed().as_secs_f64(),
        a.out.display(),
        r = a.view.res()
    );
    Ok(())
}

pub fn matrix(mut a: MatrixArgs) -> Result<()> {
    a.view.check()?;
    let (model, threads) = open(&a.model)?;
    a.view = a.view.resolved(&model.learned);
    let g = &model.generator;
    let features: Vec<Features> = a
        .sources
        .iter()
        .enumerate()
        .map(|(i, s)| resolve(&model, s, &format!("--sources (entry {})", i + 1)))
        .collect::<Result<_>>()?;
    let k = features.len() as i64;
    let trunc = g.truncation_at(a.view.flags.psi);
    let rc = a.view.render_config();
    let mut renderer = Renderer::new(g, &model.camera, &rc)?;
    renderer.field = a.view.field();
    let res = a.view.res();
    let start = Instant::now();
    let mut blocks = Vec::new();
    for (v, &pose) in a.view.poses(&model.camera).iter().enumerate() {
        let poses = Poses::from_angles(&[pose], Kind::Float, model.device);
        let noise = a.view.noise(v, res * res, model.device);
        let view = MatrixView {
            renderer: &renderer,
            features: &features,
            poses: &poses,
            res,
            noise: &noise,
            trunc: trunc.as_ref(),
        };
        let cells = if a.no_cache { view.full()? } else { view.cached()? };
        blocks.push(io::grid(&Tensor::cat(&cells, 0), k));
    }
    let secs = start.elapsed().as_secs_f64();
    let out = io::grid(&Tensor::stack(&blocks, 0), blocks.len() as i64);
    io::save_png(&a.out, &io::to_rgb8(&out, false)?).with_context(|| format!("writing --out {}", a.out.display()))?;
    println!(
        "{k}×{k} swap matrix, {} view(s) of {res}×{res}, {} in {secs:.2} s ({:.0} ms/image, {threads} threads) -> {}",
        blocks.len(),
        if a.no_cache { "every cell in full" } else { "one shape side per row" },
        1000.0 * secs / (k * k) as f64 / blocks.len() as f64,
        a.out.display()
    );
    Ok(())
}

/// strip.png with every frame `(1, 3, H, W)` in a row and, for more than one, the animated
/// sequence.gif.
fn write_sequence(dir: &Path, frames: &[Tensor]) -> Result<()> {
    let strip = io::grid(&Tensor::cat(frames, 0), frames.len() as i64);
    io::save_png(&dir.join("strip.png"), &io::to_rgb8(&strip, false)?)?;
    if frames.len() > 1 {
        let imgs = frames.iter().map(|f| io::to_rgb8(&f.get(0), false)).collect::<gdrf_core::Result<Vec<_>>>()?;
        io::save_gif(&dir.join("sequence.gif"), &imgs, 120)?;
    }
    Ok(())
}

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum What {
    Shape,
    Appearance,
    Both,
}

#[derive(Args)]
pub struct InterpArgs {
    /// The first source (seed:N or a feature file).
    #[arg(long, value_name = "SOURCE")]
    from: Source,
    /// The last source.
    #[arg(long, value_name = "SOURCE")]
    to: Source,
    /// What moves from the first source to the last: the shape, the appearance or both
    /// (the rest stays the first source's). Codes of seeds are slerped, features lerped.
    #[arg(long, value_enum, default_value = "both")]
    what: What,
    /// Frames, both ends included.
    #[arg(long, default_value_t = 8)]
    frames: usize,
    #[command(flatten)]
    model: ModelArgs,
    #[command(flatten)]
    view: ViewArgs,
    /// Output folder: frame-NNN.png, strip.png and sequence.gif.
    #[arg(long, short, default_value = "interp")]
    out: PathBuf,
    /// Write into an output folder that already holds files.
    #[arg(long)]
    force: bool,
}

pub fn interp(mut a: InterpArgs) -> Result<()> {
    a.view.check()?;
    if !(2..=240).contains(&a.frames) {
        bail!("--frames {}: expected 2 to 240", a.frames);
    }
    let (model, threads) = open(&a.model)?;
    a.view = a.view.resolved(&model.learned);
    let g = &model.generator;
    let (from, to) = (resolve(&model, &a.from, "--from")?, resolve(&model, &a.to, "--to")?);
    gdrf_core::io::output_dir(&a.out, a.force, "--out")?;
    let what = match a.what {
        What::Shape => Interpolate::Shape,
        What::Appearance => Interpolate::Appearance,
        What::Both => Interpolate::Both,
    };
    let trunc = g.truncation_at(a.view.flags.psi);
    let rc = a.view.render_config();
    let mut renderer = Renderer::new(g, &model.camera, &rc)?;
    renderer.field = a.view.field();
    let pose = a.view.poses(&model.camera)[0];
    let poses = Poses::from_angles(&[pose], Kind::Float, model.device);
    let noise = a.view.noise(0, a.view.res() * a.view.res(), model.device);
    let start = Instant::now();
    // Only the appearance moves: one shape side, re-shaded per frame.
    let sides = if what == Interpolate::Appearance {
        let rays = Rays::from_poses(&poses, a.view.res(), model.camera.fov_deg);
        Some(renderer.staged().shape_sides(&latents(g, &from, &from, trunc.as_ref()).shape, &rays, &noise, 0.0)?)
    } else {
        None
    };
    let mut frames = Vec::new();
    for k in 0..a.frames {
        let t = k as f64 / (a.frames - 1) as f64;
        let f = interpolate(g, &from, &to, t, what);
        let lat = latents(g, &f, &f, trunc.as_ref());
        let rgb = match &sides {
            Some(sides) => {
                let res = a.view.res();
                renderer.staged().shade_chunks(sides, &lat.appearance)?.permute([0, 2, 1]).reshape([1, 3, res, res])
                    * 2.0
                    - 1.0
            }
            None => renderer.render_image(&lat, &poses, a.view.res(), &noise)?.rgb,
        };
        let path = a.out.join(format!("frame-{k:03}.png"));
        io::save_png(&path, &io::to_rgb8(&rgb.get(0), false)?)
            .with_context(|| format!("writing {}", path.display()))?;
        frames.push(rgb);
    }
    write_sequence(&a.out, &frames)?;
    println!(
        "{} frames from {:?} to {:?} in {:.2} s ({threads} threads) -> {}",
        a.frames,
        a.from,
        a.to,
        start.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

pub fn features(a: FeaturesArgs) -> Result<()> {
    let (model, _) = open(&a.model)?;
    let f = Features::from_seed(&model.generator, a.seed);
    f.save(&a.out, &model.id).with_context(|| format!("writing --out {}", a.out.display()))?;
    println!("features of seed {} for generator {} -> {}", a.seed, model.id, a.out.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use gdrf_core::edit::view::ViewFlags;
    use gdrf_core::field::generator::Generator;
    use gdrf_core::{CameraConfig, GeneratorConfig, RenderConfig};
    use tch::{nn, Device};

    #[test]
    fn samples_is_the_samples_per_ray_flag_as_in_gdrf_invert() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            view: ViewArgs,
        }
        let steps = |args: &[&str]| <Cli as clap::Parser>::try_parse_from(args).unwrap().view.flags.samples;
        assert_eq!(steps(&["x"]), None, "default: where the model learned");
        assert_eq!(steps(&["x", "--steps", "8"]), Some(8));
        assert_eq!(steps(&["x", "--samples", "8"]), Some(8));
    }

    #[test]
    fn photo_sources_invert_where_the_generator_learned() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            model: ModelArgs,
        }
        let photo_cfg = |args: &[&str]| {
            let cli = <Cli as clap::Parser>::try_parse_from(args).unwrap();
            let (model, _) = open(&cli.model).unwrap();
            let c = &model.photo.cfg;
            (c.resolution, c.samples, c.steps)
        };
        // The shipped generator's header records 64² and 24 samples per ray.
        let shipped = gdrf_core::paths::shipped_generator();
        let shipped = shipped.to_str().unwrap();
        assert_eq!(photo_cfg(&["x", "--checkpoint", shipped, "--photo-steps", "7", "--device", "cpu"]), (64, 12, 7));
        // Without --checkpoint: the shipped generator.
        assert_eq!(photo_cfg(&["x", "--device", "cpu"]).0, 64);
        // A random generator has no training record: gdrf-invert's plain defaults.
        let d = gdrf_core::invert::InvertConfig::default();
        assert_eq!(photo_cfg(&["x", "--random-init", "--device", "cpu"]), (d.resolution, d.samples, d.steps));
    }

    fn small() -> (nn::VarStore, Generator) {
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = GeneratorConfig::tiny();
        // A deformation head with weights, so that shapes differ.
        let g = gdrf_core::rng::with_global_seed(5, || {
            let mut g = Generator::new(&vs.root(), &cfg).unwrap();
            tch::no_grad(|| {
                let _ = g.deform.head.weight.uniform_(-0.05, 0.05);
            });
            g
        });
        (vs, g)
    }

    fn view() -> ViewArgs {
        ViewArgs {
            flags: ViewFlags {
                resolution: Some(12),
                views: 1,
                pitch: None,
                yaw: 30.0,
                samples: Some(6),
                psi: 1.0,
                no_deformation: false,
                no_correction: false,
            },
            noise_seed: 3,
            preset: None,
            ellipse: false,
        }
    }

    /// Disentanglement is structural: the appearance never reaches density, so "shape A +
    /// appearance B" has exactly the opacity and depth of "shape A + appearance A".
    #[test]
    fn the_appearance_never_changes_geometry() {
        let (_vs, g) = small();
        let cam = CameraConfig::chair();
        let v = view();
        let rc = v.render_config();
        let r = Renderer::new(&g, &cam, &rc).unwrap();
        let (a, b) = (Features::from_seed(&g, 1), Features::from_seed(&g, 2));
        let poses = Poses::from_angles(&v.poses(&cam), Kind::Float, Device::Cpu);
        let noise = v.noise(0, 144, Device::Cpu);
        let aa = r.render_image(&latents(&g, &a, &a, None), &poses, 12, &noise).unwrap();
        let ab = r.render_image(&latents(&g, &a, &b, None), &poses, 12, &noise).unwrap();
        assert!(aa.opacity.equal(&ab.opacity) && aa.depth.equal(&ab.depth));
        assert!(!aa.rgb.equal(&ab.rgb), "the appearance changed nothing");
    }

    /// Each row's kept shape side, re-shaded, gives the full renders within 1e-5.
    #[test]
    fn the_cached_matrix_equals_the_full_one() {
        let (_vs, g) = small();
        let cam = CameraConfig::chair();
        let v = view();
        let rc = RenderConfig { chunk_points: 200, ..v.render_config() };
        let r = Renderer::new(&g, &cam, &rc).unwrap();
        let features: Vec<Features> = (0..3).map(|s| Features::from_seed(&g, s)).collect();
        let poses = Poses::from_angles(&v.poses(&cam), Kind::Float, Device::Cpu);
        let noise = v.noise(0, 144, Device::Cpu);
        let t = g.truncation(0.7, 100, 0);
        for trunc in [None, Some(&t)] {
            let view = MatrixView { renderer: &r, features: &features, poses: &poses, res: 12, noise: &noise, trunc };
            let (full, cached) = (view.full().unwrap(), view.cached().unwrap());
            for (i, (f, c)) in full.iter().zip(&cached).enumerate() {
                let err = f64::try_from((f - c).abs().max()).unwrap();
                assert!(err <= 1e-5, "cell {i}: {err}");
            }
            // Rows share shape, columns appearance: the cells differ.
            assert!(!full[1].equal(&full[0]) && !full[3].equal(&full[0]));
        }
    }

    #[test]
    fn the_ellipse_path_is_the_releases() {
        let mut v = ViewArgs { ellipse: true, ..view() };
        v.flags.views = 5;
        let cam = CameraConfig::chair();
        let p = v.poses(&cam);
        assert_eq!(p.len(), 5);
        // a = 0, π/2, π, 3π/2, 2π: yaw h_mean + h_std·cos a, pitch v_mean + v_std·sin a.
        assert!((p[0].1 - cam.h_std).abs() < 1e-12 && (p[0].0 - cam.v_mean).abs() < 1e-12);
        assert!((p[1].0 - (cam.v_mean + cam.v_std)).abs() < 1e-12 && p[1].1.abs() < 1e-9);
        assert!((p[4].1 - p[0].1).abs() < 1e-9);
        // CARLA's spherical-uniform pitch: arccos(1 − 2v/π) (v_mean 0.7418 → 1.0148 rad).
        let carla = v.poses(&CameraConfig::carla());
        assert!((carla[0].0 - 1.0148).abs() < 1e-4, "{}", carla[0].0);
    }

    #[test]
    fn bad_views_are_refused() {
        let bad = |f: &dyn Fn(&mut ViewArgs), flag: &str| {
            let mut v = view();
            f(&mut v);
            let e = v.check().unwrap_err().to_string();
            assert!(e.contains(flag), "{flag}: {e}");
        };
        bad(&|v| v.flags.resolution = Some(4), "--resolution");
        bad(&|v| v.flags.views = 0, "--views");
        bad(&|v| v.flags.pitch = Some(200.0), "--pitch");
        bad(&|v| v.flags.psi = -1.0, "--psi");
    }
}
