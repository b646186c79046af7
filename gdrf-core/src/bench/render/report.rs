//! render.json, its table (render.md) and its chart (render.png).
use crate::render::GridConfig;
use crate::Result;
use serde::Serialize;

/// render.json: the run's settings and one row per scene, resolution and configuration.
#[derive(Serialize)]
pub struct Report {
    pub title: &'static str,
    /// The checkpoint as shown in committed figures (relative to the repository).
    pub checkpoint: String,
    pub device: String,
    pub threads: usize,
    pub seeds: Vec<i64>,
    pub views: usize,
    pub repeats: usize,
    pub reference_steps: usize,
    pub results: Vec<Row>,
    /// The PyTorch reference sampler, one run per resolution (none with --no-pytorch).
    pub pytorch: Vec<PyTorchRun>,
}

/// One renderer configuration on one scene at one resolution; times and queries are per
/// image (medians over the repeats), errors against the dense reference.
#[derive(Serialize)]
pub struct Row {
    /// `model` or `analytic`.
    pub scene: &'static str,
    pub resolution: i64,
    pub config: String,
    pub steps: usize,
    pub min_weight: f64,
    pub termination: f64,
    pub importance_skip: f64,
    pub importance_concentration: f64,
    pub importance_stride: usize,
    pub bf16: bool,
    pub grid: Option<GridConfig>,
    pub ms_per_image: f64,
    pub ms_per_image_runs: Vec<f64>,
    pub grid_ms_per_shape: f64,
    /// The grid's build spread over the views that reuse it.
    pub ms_per_image_with_grid_build: f64,
    pub density_queries_per_image: f64,
    pub colour_queries_per_image: f64,
    pub grid_queries_per_shape: i64,
    pub psnr_db: f64,
    pub max_abs_error: f64,
    pub opacity_error: f64,
    pub peak_rss_mb_so_far: f64,
}

/// What scripts/reference/bench_render.py measured, and where this bench placed it.
#[derive(Serialize)]
pub struct PyTorchRun {
    /// The script's own JSON (its keys are the script's business; `ms_per_image` is read).
    #[serde(flatten)]
    pub measured: serde_json::Value,
    pub resolution: i64,
    pub config: String,
    /// Largest difference of its images from the Rust reference configuration's, in
    /// colour units of `[0, 1]`.
    pub max_abs_difference_from_rust: f64,
}

/// The points (time, PSNR) that no faster one matches in PSNR, by time: the Pareto front.
fn pareto(points: impl Iterator<Item = (f64, f64)>) -> Vec<(f64, f64)> {
    let mut pts: Vec<(f64, f64)> = points.filter(|p| p.0.is_finite() && p.1.is_finite()).collect();
    pts.sort_by(|a, b| a.0.total_cmp(&b.0).then(b.1.total_cmp(&a.1)));
    let mut best = f64::NEG_INFINITY;
    pts.into_iter()
        .filter(|p| {
            p.1 > best && {
                best = p.1;
                true
            }
        })
        .collect()
}

impl PyTorchRun {
    /// The script's median milliseconds per image (NaN when it gave none).
    pub(super) fn ms_per_image(&self) -> f64 {
        self.measured["ms_per_image"].as_f64().unwrap_or(f64::NAN)
    }
}

impl Report {
    /// Time against error: a panel per scene and resolution (the model's first), a point
    /// per configuration (ms per image, PSNR against the dense reference) coloured by its
    /// family (the name before " N="), the Pareto front through the points no other beats
    /// on both, the PyTorch reference's time as a vertical line, 40 dB dotted.
    pub fn chart(&self) -> Result<image::RgbImage> {
        let mut keys: Vec<(&str, i64)> = Vec::new();
        for r in &self.results {
            if !keys.contains(&(r.scene, r.resolution)) {
                keys.push((r.scene, r.resolution));
            }
        }
        keys.sort_by_key(|&(scene, res)| (scene != "model", res));
        let cols = keys.iter().map(|k| k.1).collect::<std::collections::BTreeSet<_>>().len();
        let family = |r: &Row| r.config.split(" N=").next().unwrap_or(&r.config).to_string();
        let panels: Vec<crate::plot::ScatterPanel> = keys
            .iter()
            .map(|&(scene, res)| {
                let rows: Vec<&Row> = self.results.iter().filter(|r| r.scene == scene && r.resolution == res).collect();
                let points: Vec<(String, f64, f64, String)> =
                    rows.iter().map(|r| (family(r), r.ms_per_image, r.psnr_db, format!("N={}", r.steps))).collect();
                let verticals = self
                    .pytorch
                    .iter()
                    .filter(|p| scene == "model" && p.resolution == res)
                    .filter_map(|p| Some((format!("PyTorch {}", p.config), p.measured["ms_per_image"].as_f64()?)))
                    .collect();
                crate::plot::ScatterPanel {
                    title: format!("{scene}, {res}×{res}"),
                    front: pareto(points.iter().map(|p| (p.1, p.2))),
                    points,
                    verticals,
                    threshold: Some(40.0),
                }
            })
            .collect();
        let axes = crate::plot::ScatterAxes {
            title: format!("{} — {}, {} threads", self.title, self.device, self.threads),
            x: "ms per image (median)".into(),
            y: "PSNR vs dense reference (dB)".into(),
            log_x: true,
        };
        crate::plot::draw_scatter(&panels, &axes, cols, 560, 420)
    }

    /// The table of docs/benchmarks.md, "Renderer: time against error": per scene and
    /// resolution, each configuration's time, speed-up over the release's sampler in this
    /// binary, queries and errors; the PyTorch
    /// reference's time. A grid's time is given twice: per image when many views reuse it,
    /// and for one view per shape (a single swap or render), its build included.
    pub fn markdown(&self) -> String {
        let mut s = String::from(
            "| scene | size | configuration | ms/image | speed-up | grid build ms/shape | speed-up at one view per shape | density / colour queries per image | PSNR (dB) | max error | opacity error |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
        );
        for row in &self.results {
            let base = self
                .results
                .iter()
                .find(|r| {
                    r.scene == row.scene
                        && r.resolution == row.resolution
                        && r.config == format!("reference N={}", super::release_steps(row.resolution))
                })
                .map_or(f64::NAN, |r| r.ms_per_image);
            let (build, one_view) = match row.grid {
                Some(_) => (
                    format!("{:.1}", row.grid_ms_per_shape),
                    format!("{:.2}×", base / (row.ms_per_image + row.grid_ms_per_shape)),
                ),
                None => (String::new(), format!("{:.2}×", base / row.ms_per_image)),
            };
            s += &format!(
                "| {} | {}² | {} | {:.1} | {:.2}× | {build} | {one_view} | {:.0} / {:.0} | {:.1} | {:.3} | {:.1e} |\n",
                row.scene,
                row.resolution,
                row.config,
                row.ms_per_image,
                base / row.ms_per_image,
                row.density_queries_per_image,
                row.colour_queries_per_image,
                row.psnr_db,
                row.max_abs_error,
                row.opacity_error,
            );
        }
        for p in &self.pytorch {
            s += &format!(
                "| model | {}² | PyTorch reference, {} | {:.1} | | | | | | | |\n",
                p.resolution,
                p.config,
                p.ms_per_image()
            );
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::pareto;

    #[test]
    fn the_front_keeps_the_points_no_faster_one_matches() {
        let pts = [(5.0, 40.0), (3.0, 42.0), (4.0, 41.0), (9.0, 50.0), (9.0, 45.0), (7.0, 49.0), (f64::NAN, 60.0)];
        assert_eq!(pareto(pts.into_iter()), [(3.0, 42.0), (7.0, 49.0), (9.0, 50.0)]);
    }
}
