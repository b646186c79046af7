//! Isosurfaces of a density grid as triangle meshes (marching tetrahedra: each cube split
//! into six tetrahedra along its main diagonal, so that neighbouring cubes cut their shared
//! faces the same way and the surface is closed wherever the level set is), with vertices
//! shared between triangles, and their PLY and OBJ files.
use crate::paths::write_atomic;
use crate::{Error, Result};
use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

/// A triangle mesh with optional per-vertex colours in [0, 1].
#[derive(Debug, Clone, Default)]
pub struct Mesh {
    pub vertices: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
    pub colours: Option<Vec<[f32; 3]>>,
}

/// A regular grid of samples: `values[(i·ny + j)·nz + k]` at `origin + spacing·(i, j, k)`.
#[derive(Debug, Clone, Copy)]
pub struct Grid<'a> {
    pub values: &'a [f32],
    pub dims: [usize; 3],
    pub origin: [f32; 3],
    pub spacing: f32,
}

/// Cube corners as (di, dj, dk), and the six tetrahedra sharing the diagonal 0–6.
const CORNERS: [[usize; 3]; 8] =
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]];
const TETRAHEDRA: [[usize; 4]; 6] =
    [[0, 6, 1, 2], [0, 6, 2, 3], [0, 6, 3, 7], [0, 6, 7, 4], [0, 6, 4, 5], [0, 6, 5, 1]];

/// The surface where the values cross `iso`, oriented with normals toward lower values
/// (out of a density). Errors name a grid whose size does not match its values, or a
/// non-finite level.
pub fn isosurface(grid: &Grid, iso: f32) -> Result<Mesh> {
    let [nx, ny, nz] = grid.dims;
    if nx * ny * nz != grid.values.len() || nx < 2 || ny < 2 || nz < 2 || !iso.is_finite() {
        return Err(Error::Invalid(format!(
            "isosurface of a {nx}×{ny}×{nz} grid with {} values at level {iso}: expected at least 2 samples per axis, one value each and a finite level",
            grid.values.len()
        )));
    }
    let index = |p: [usize; 3]| (p[0] * ny + p[1]) * nz + p[2];
    // NaN counts as outside (below the level).
    let value = |p: [usize; 3]| {
        let v = grid.values[index(p)];
        if v.is_nan() {
            f32::NEG_INFINITY
        } else {
            v
        }
    };
    let mut mesh = Mesh::default();
    let mut edges: HashMap<(usize, usize), u32> = HashMap::new();
    let mut vertex = |a: [usize; 3], b: [usize; 3], mesh: &mut Mesh| -> u32 {
        let (ia, ib) = (index(a), index(b));
        let key = (ia.min(ib), ia.max(ib));
        *edges.entry(key).or_insert_with(|| {
            let (va, vb) = (value(a), value(b));
            let t =
                if (vb - va).abs() > 0.0 && va.is_finite() && vb.is_finite() { (iso - va) / (vb - va) } else { 0.5 };
            let t = t.clamp(0.0, 1.0);
            let p = |c: usize| grid.origin[c] + grid.spacing * (a[c] as f32 + t * (b[c] as f32 - a[c] as f32));
            mesh.vertices.push([p(0), p(1), p(2)]);
            (mesh.vertices.len() - 1) as u32
        })
    };
    for i in 0..nx - 1 {
        for j in 0..ny - 1 {
            for k in 0..nz - 1 {
                let corner = |c: usize| [i + CORNERS[c][0], j + CORNERS[c][1], k + CORNERS[c][2]];
                let inside: Vec<bool> = (0..8).map(|c| value(corner(c)) > iso).collect();
                if inside.iter().all(|&x| x) || inside.iter().all(|&x| !x) {
                    continue;
                }
                for tet in TETRAHEDRA {
                    let p: Vec<[usize; 3]> = tet.iter().map(|&c| corner(c)).collect();
                    let ins: Vec<bool> = tet.iter().map(|&c| inside[c]).collect();
                    polygonise_tetrahedron(&p, &ins, &mut mesh, &mut vertex);
                }
            }
        }
    }
    Ok(mesh)
}

/// Triangles of one tetrahedron `p` whose corners are inside where `ins`, with normals from
/// the inside corners to the outside ones. The orientation comes from the sign of the
/// corners' integer determinant, never from the (possibly degenerate) triangle itself.
fn polygonise_tetrahedron(
    p: &[[usize; 3]],
    ins: &[bool],
    mesh: &mut Mesh,
    vertex: &mut impl FnMut([usize; 3], [usize; 3], &mut Mesh) -> u32,
) {
    let inside: Vec<usize> = (0..4).filter(|&c| ins[c]).collect();
    let outside: Vec<usize> = (0..4).filter(|&c| !ins[c]).collect();
    // det(q1 − q0, q2 − q0, q3 − q0) > 0: the corners in that order are positively oriented.
    let positive = |q: [usize; 4]| {
        let d = |i: usize| [0, 1, 2].map(|c| p[q[i]][c] as i64 - p[q[0]][c] as i64);
        let (u, v, w) = (d(1), d(2), d(3));
        u[0] * (v[1] * w[2] - v[2] * w[1]) - u[1] * (v[0] * w[2] - v[2] * w[0]) + u[2] * (v[0] * w[1] - v[1] * w[0]) > 0
    };
    let push =
        |t: [u32; 3], flip: bool, mesh: &mut Mesh| mesh.triangles.push(if flip { [t[0], t[2], t[1]] } else { t });
    match inside.len() {
        1 | 3 => {
            // One corner apart from the other three: the triangle across the edges to it
            // faces away from the corner when the four are positively oriented.
            let (lone, o) = if inside.len() == 1 { (inside[0], &outside) } else { (outside[0], &inside) };
            let t = [0, 1, 2].map(|k| vertex(p[lone], p[o[k]], mesh));
            let away = positive([lone, o[0], o[1], o[2]]);
            // Inside lone corner: the normal must face away from it; outside: toward it.
            push(t, away != (inside.len() == 1), mesh);
        }
        2 => {
            // Two and two: the quad across the four edges between the pairs, as two
            // triangles facing the outside pair when (a, b, c, d) is positively oriented.
            let (a, b, c, d) = (inside[0], inside[1], outside[0], outside[1]);
            let (ac, ad) = (vertex(p[a], p[c], mesh), vertex(p[a], p[d], mesh));
            let (bd, bc) = (vertex(p[b], p[d], mesh), vertex(p[b], p[c], mesh));
            let flip = !positive([a, b, c, d]);
            push([ac, ad, bd], flip, mesh);
            push([ac, bd, bc], flip, mesh);
        }
        _ => {}
    }
}

/// Densities softplus(σ) of `field` for shape modulation `shape` (one image) on the n³ grid
/// over `[−half, half]³`, in [`Grid`] order, `chunk` points at a time.
pub fn sample_density<F: crate::field::RadianceField>(
    field: &F,
    shape: &crate::Film,
    opts: crate::field::generator::FieldOptions,
    half: f64,
    n: usize,
    chunk: usize,
) -> Result<Vec<f32>> {
    if n < 2 || !(half > 0.0 && half.is_finite()) {
        return Err(Error::Invalid(format!(
            "a density grid of {n} samples per axis over ±{half}: expected n ≥ 2 and a positive extent"
        )));
    }
    let (kind, device) = field.kind_device();
    let h = 2.0 * half / (n - 1) as f64;
    let axis = tch::Tensor::arange(n as i64, (kind, device)) * h - half;
    let ni = n as i64;
    let pts = tch::Tensor::stack(
        &[
            axis.view([ni, 1, 1]).expand([ni, ni, ni], false),
            axis.view([1, ni, 1]).expand([ni, ni, ni], false),
            axis.view([1, 1, ni]).expand([ni, ni, ni], false),
        ],
        3,
    )
    .reshape([1, ni * ni * ni, 3]);
    let total = ni * ni * ni;
    let mut out = Vec::with_capacity(total as usize);
    tch::no_grad(|| -> Result<()> {
        let mut start = 0;
        while start < total {
            let len = (chunk.max(1) as i64).min(total - start);
            let (sigma, _) = field.sigma_feature(&pts.narrow(1, start, len), shape, opts);
            out.extend(Vec::<f32>::try_from(sigma.to_kind(tch::Kind::Float).softplus().view([-1]))?);
            start += len;
        }
        Ok(())
    })?;
    Ok(out)
}

/// Correspondence colours: template-space positions `x_t: (…, 3)` (x + Δx) within the
/// cube `[−half, half]³` mapped to RGB in [0, 1]. A function of the template point alone, so
/// corresponding points of different shapes get the same colour.
pub fn template_colour(x_template: &tch::Tensor, half: f64) -> tch::Tensor {
    ((x_template / half + 1.0) * 0.5).clamp(0.0, 1.0)
}

impl Mesh {
    /// ASCII PLY with per-vertex colours (8-bit) when there are colours.
    pub fn to_ply(&self) -> String {
        let mut s = format!("ply\nformat ascii 1.0\ncomment gdrf isosurface\nelement vertex {}\n", self.vertices.len());
        s += "property float x\nproperty float y\nproperty float z\n";
        if self.colours.is_some() {
            s += "property uchar red\nproperty uchar green\nproperty uchar blue\n";
        }
        s += &format!("element face {}\nproperty list uchar int vertex_indices\nend_header\n", self.triangles.len());
        for (i, v) in self.vertices.iter().enumerate() {
            let _ = write!(s, "{} {} {}", v[0], v[1], v[2]);
            if let Some(c) = &self.colours {
                let b = |x: f32| (x.clamp(0.0, 1.0) * 255.0).round() as u8;
                let _ = write!(s, " {} {} {}", b(c[i][0]), b(c[i][1]), b(c[i][2]));
            }
            s.push('\n');
        }
        for t in &self.triangles {
            let _ = writeln!(s, "3 {} {} {}", t[0], t[1], t[2]);
        }
        s
    }

    /// OBJ, with colours as the common `v x y z r g b` extension when there are colours.
    pub fn to_obj(&self) -> String {
        let mut s = String::from("# gdrf isosurface\n");
        for (i, v) in self.vertices.iter().enumerate() {
            let _ = write!(s, "v {} {} {}", v[0], v[1], v[2]);
            if let Some(c) = &self.colours {
                let _ = write!(s, " {} {} {}", c[i][0], c[i][1], c[i][2]);
            }
            s.push('\n');
        }
        for t in &self.triangles {
            let _ = writeln!(s, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1);
        }
        s
    }

    /// Writes `.ply` or `.obj` (by extension), atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
        let text = match ext.as_str() {
            "ply" => self.to_ply(),
            "obj" => self.to_obj(),
            _ => return Err(Error::Invalid(format!("{}: expected a .ply or .obj file name", path.display()))),
        };
        write_atomic(path, text.as_bytes())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sphere of radius r as a density (r − |x| > 0 inside) on an n³ grid over [−1, 1]³.
    fn sphere(n: usize, r: f32) -> (Vec<f32>, Grid<'static>) {
        let h = 2.0 / (n - 1) as f32;
        let mut v = Vec::with_capacity(n * n * n);
        for i in 0..n {
            for j in 0..n {
                for k in 0..n {
                    let p = [i, j, k].map(|c| -1.0 + h * c as f32);
                    v.push(r - (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt());
                }
            }
        }
        let g = Grid { values: &[], dims: [n; 3], origin: [-1.0; 3], spacing: h };
        (v, g)
    }

    #[test]
    fn a_sphere_is_closed_outward_and_of_its_radius() {
        let (values, g) = sphere(41, 0.6);
        let mesh = isosurface(&Grid { values: &values, ..g }, 0.0).unwrap();
        assert!(mesh.triangles.len() > 1000);
        // Closed: every edge belongs to exactly two triangles, once in each direction.
        let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
        for t in &mesh.triangles {
            for (a, b) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *edges.entry((a, b)).or_default() += 1;
            }
        }
        for (&(a, b), &n) in &edges {
            assert_eq!(n, 1, "edge {a}-{b} used {n} times in one direction");
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} has no opposite");
        }
        // On the sphere: every vertex within a small fraction of a cell of radius 0.6.
        let worst = mesh
            .vertices
            .iter()
            .map(|v| ((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() - 0.6).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 0.2 * g.spacing, "vertex {worst} off the sphere");
        // Outward: the signed volume (divergence theorem) is the sphere's, not its negative.
        let vol: f32 = mesh
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
                (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
                    + a[2] * (b[0] * c[1] - b[1] * c[0]))
                    / 6.0
            })
            .sum();
        let want = 4.0 / 3.0 * std::f32::consts::PI * 0.6f32.powi(3);
        assert!((vol - want).abs() < 0.01 * want, "volume {vol} vs {want}");
    }

    /// Two shapes deform differently; points of each that land on the same template point
    /// (found by a fixed-point iteration x ← t − Δx(x)) get the same correspondence colour,
    /// while the same target points of the two shapes do not.
    #[test]
    fn corresponding_points_of_two_shapes_share_colours() {
        use crate::field::generator::{FieldOptions, Generator};
        use tch::{nn, Device, Kind, Tensor};
        tch::manual_seed(11);
        let vs = nn::VarStore::new(Device::Cpu);
        let cfg = crate::GeneratorConfig::tiny();
        let mut g = Generator::new(&vs.root(), &cfg).unwrap();
        tch::no_grad(|| {
            let _ = g.deform.head.weight.uniform_(-0.003, 0.003);
        });
        let z = Tensor::randn([2, 8], (Kind::Float, Device::Cpu));
        let lat = tch::no_grad(|| g.latents(&z, &z, None)).unwrap();
        let (a, b) = (lat.shape.narrow(0, 1), lat.shape.narrow(1, 1));
        let x_a = Tensor::rand([1, 50, 3], (Kind::Float, Device::Cpu)) - 0.5;
        let opts = FieldOptions::default();
        let t = tch::no_grad(|| g.density(&x_a, &a, opts).x_template);
        let mut x_b = t.copy();
        for _ in 0..50 {
            x_b = tch::no_grad(|| &t - g.density(&x_b, &b, opts).dx);
        }
        let t_b = tch::no_grad(|| g.density(&x_b, &b, opts).x_template);
        let dx_gap = f64::try_from((&x_b - &x_a).abs().max()).unwrap();
        assert!(dx_gap > 1e-3, "the two shapes deform alike ({dx_gap})");
        let (ca, cb) = (template_colour(&t, 0.8), template_colour(&t_b, 0.8));
        assert!(f64::try_from((&ca - &cb).abs().max()).unwrap() < 1e-5);
        let same_target = tch::no_grad(|| template_colour(&g.density(&x_a, &b, opts).x_template, 0.8));
        assert!(f64::try_from((&ca - same_target).abs().max()).unwrap() > 1e-4);
    }

    #[test]
    fn ply_and_obj_files_hold_the_mesh() {
        let (values, g) = sphere(9, 0.5);
        let mut mesh = isosurface(&Grid { values: &values, ..g }, 0.0).unwrap();
        mesh.colours = Some(vec![[1.0, 0.5, 0.0]; mesh.vertices.len()]);
        let ply = mesh.to_ply();
        assert!(ply.starts_with("ply\nformat ascii 1.0"));
        assert!(ply.contains(&format!("element vertex {}", mesh.vertices.len())));
        assert!(ply.contains(&format!("element face {}", mesh.triangles.len())));
        let body: Vec<&str> = ply.split("end_header\n").nth(1).unwrap().lines().collect();
        assert_eq!(body.len(), mesh.vertices.len() + mesh.triangles.len());
        assert!(body[0].ends_with(" 255 128 0"));
        let obj = mesh.to_obj();
        assert_eq!(obj.lines().filter(|l| l.starts_with("v ")).count(), mesh.vertices.len());
        let faces: Vec<&str> = obj.lines().filter(|l| l.starts_with("f ")).collect();
        assert_eq!(faces.len(), mesh.triangles.len());
        // 1-based indices, all in range.
        let max = faces.iter().flat_map(|f| f[2..].split(' ').map(|x| x.parse::<usize>().unwrap())).max().unwrap();
        assert!(max <= mesh.vertices.len());
        assert!(mesh.save(Path::new("mesh.stl")).unwrap_err().to_string().contains(".ply or .obj"));
        let bad = Grid { values: &values[..10], ..g };
        assert!(isosurface(&bad, 0.0).is_err());
    }
}
