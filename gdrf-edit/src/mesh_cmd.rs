//! `gdrf-edit mesh`: an isosurface of a source's final density, coloured by the generator or
//! by each vertex's template-space position (x + Δx), so that corresponding parts of
//! different shapes get the same colour.
use crate::model::{open, resolve, Model, ModelArgs};
use anyhow::{bail, Context, Result};
use clap::Args;
use gdrf_core::camera::{camera_origins, normalize, Poses};
use gdrf_core::edit::{latents, Source};
use gdrf_core::field::generator::FieldOptions;
use gdrf_core::mesh::{isosurface, sample_density, template_colour, Grid, Mesh};
use gdrf_core::render::occupancy::camera_half_extent;
use gdrf_core::Latents;
use std::path::PathBuf;
use std::time::Instant;
use tch::{Kind, Tensor};

#[derive(Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Colour {
    /// The generator's colour, seen from the camera's mean pitch.
    Rgb,
    /// The vertex's template-space position x + Δx, mapped to RGB: correspondences.
    Template,
    /// No colour.
    None,
}

#[derive(Args)]
pub struct MeshArgs {
    /// The shape (and, with --colour rgb, the appearance): seed:N or a feature file.
    #[arg(long, value_name = "SOURCE")]
    source: Source,
    /// Where the appearance comes from instead (--colour rgb): texture transfer onto the
    /// shape through the shared template.
    #[arg(long, value_name = "SOURCE")]
    appearance_from: Option<Source>,
    #[command(flatten)]
    model: ModelArgs,
    /// Grid samples per axis over the camera's cube.
    #[arg(long, default_value_t = 128)]
    resolution: usize,
    /// Density softplus(σ) of the surface. Default: 10, or, when the grid's densities do not
    /// reach 10 (e.g. an untrained model), halfway through their range (printed).
    #[arg(long)]
    threshold: Option<f32>,
    /// Vertex colours.
    #[arg(long, value_enum, default_value = "rgb")]
    colour: Colour,
    /// Truncation ψ toward the mean mapping output (1 = none).
    #[arg(long, default_value_t = 1.0)]
    psi: f64,
    /// Output mesh: .ply or .obj.
    #[arg(long, short, default_value = "mesh.ply")]
    out: PathBuf,
}

pub fn mesh(a: MeshArgs) -> Result<()> {
    if !(8..=512).contains(&a.resolution) {
        bail!("--resolution {}: expected 8 to 512 samples per axis", a.resolution);
    }
    if let Some(t) = a.threshold {
        if !(t > 0.0 && t.is_finite()) {
            bail!("--threshold {t}: expected a positive density");
        }
    }
    let ext = a.out.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    if ext != "ply" && ext != "obj" {
        bail!("--out {}: expected a .ply or .obj file name", a.out.display());
    }
    let (model, threads) = open(&a.model)?;
    let g = &model.generator;
    let shape = resolve(&model, &a.source, "--source")?;
    // Without --appearance-from the source's own appearance: resolved once.
    let other = a.appearance_from.as_ref().map(|s| resolve(&model, s, "--appearance-from")).transpose()?;
    let trunc = g.truncation_at(a.psi);
    let lat = latents(g, &shape, other.as_ref().unwrap_or(&shape), trunc.as_ref());
    let start = Instant::now();
    let (mesh, threshold) = build(&model, &lat, (a.resolution, a.threshold), a.colour)?;
    mesh.save(&a.out).with_context(|| format!("writing --out {}", a.out.display()))?;
    println!(
        "{} vertices, {} triangles at density {} from a {}³ grid in {:.2} s ({threads} threads) -> {}",
        mesh.vertices.len(),
        mesh.triangles.len(),
        threshold,
        a.resolution,
        start.elapsed().as_secs_f64(),
        a.out.display()
    );
    Ok(())
}

/// The isosurface of `lat`'s density on a `resolution`³ grid over the camera's cube, at
/// density `threshold` (default: 10, or halfway through the densities' range when they do
/// not reach 10, said on stderr), with `colour` vertex colours; and the threshold used.
pub fn build(
    model: &Model,
    lat: &Latents,
    (resolution, threshold): (usize, Option<f32>),
    colour: Colour,
) -> Result<(Mesh, f32)> {
    let g = &model.generator;
    let half = camera_half_extent(&model.camera);
    let n = resolution;
    let values = sample_density(g, &lat.shape, FieldOptions::default(), half, n, 1 << 15)?;
    let spacing = (2.0 * half / (n - 1) as f64) as f32;
    let grid = Grid { values: &values, dims: [n; 3], origin: [-half as f32; 3], spacing };
    let (lo, hi) = values
        .iter()
        .filter(|v| v.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| (l.min(v), h.max(v)));
    let threshold = match threshold {
        Some(t) => t,
        None if lo < 10.0 && hi > 10.0 => 10.0,
        None => {
            let t = 0.5 * (lo + hi);
            eprintln!(
                "densities span {lo:.3e} to {hi:.3e}, not 10: the surface is at {t:.3e} (set --threshold to choose)"
            );
            t
        }
    };
    let mut mesh = isosurface(&grid, threshold)?;
    if mesh.triangles.is_empty() {
        bail!("no surface at density {threshold} (the grid's densities span {lo:.3e} to {hi:.3e}); pick --threshold inside that range");
    }
    if colour != Colour::None {
        let (kind, device) = g.kind_device();
        let flat: Vec<f32> = mesh.vertices.iter().flatten().copied().collect();
        let x = Tensor::from_slice(&flat).view([1, -1, 3]).to_kind(kind).to_device(device);
        let colours = tch::no_grad(|| {
            let d = g.density(&x, &lat.shape, FieldOptions::default());
            match colour {
                Colour::Template => template_colour(&d.x_template, half),
                _ => {
                    let pose = Poses::from_angles(&[(model.camera.v_mean, 0.0)], kind, device);
                    let dir = normalize(&-camera_origins(&pose, 1.0)).view([1, 1, 3]).expand_as(&x);
                    g.colour(&d.feature, &dir, &lat.appearance)
                }
            }
        });
        let c = Vec::<f32>::try_from(colours.to_kind(Kind::Float).view([-1]))?;
        mesh.colours = Some(c.chunks(3).map(|v| [v[0], v[1], v[2]]).collect());
    }
    Ok((mesh, threshold))
}
