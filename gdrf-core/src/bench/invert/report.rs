//! STEM.json, STEM.md, the plot and the figure: every method's points, means over objects
//! and noise seeds.
use crate::bench::write_json;
use crate::plot::{draw_panels, Panel, Series};
use crate::{Error, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use tch::Tensor;

use super::judge::Cell;
use super::{Method, PoseUsed};

/// STEM.json: the run's settings and every method's points.
#[derive(Serialize)]
pub struct Report {
    /// The generator, initialiser and probe as shown in committed figures.
    pub generator: String,
    pub init: Option<String>,
    pub dataset: String,
    /// The objects inverted (dataset files) and the first `skip` held-out ones passed over.
    pub objects: Vec<String>,
    pub skip: usize,
    pub noise_seeds: Vec<u64>,
    pub views: usize,
    pub resolution: i64,
    pub samples: usize,
    pub perceptual: String,
    /// The silhouette term's weight in every method but the paper's.
    pub silhouette_weight: f64,
    /// The seed of the restyled photos (`--restyle`), none for the dataset's own.
    pub restyle: Option<u64>,
    /// The framing file the photos were framed by, where there was one.
    pub framing: Option<String>,
    pub device: String,
    pub threads: usize,
    pub probe: String,
    /// The probe on the ground-truth novel views themselves: the best agreement it can give.
    pub structure_agreement_of_the_ground_truth_views: f64,
    pub points: Vec<Point>,
}

/// One measured point of one method: means over its objects and the noise seeds.
#[derive(Serialize, Clone)]
pub struct Point {
    pub method: String,
    pub start: String,
    pub pose: String,
    pub objects: usize,
    /// The step budget at this point and the steps actually run.
    pub steps: usize,
    /// Seconds from the photo to this point: the initialiser's prediction and the steps.
    pub seconds: f64,
    pub input_psnr: f64,
    pub novel_psnr: f64,
    /// The novel-view PSNR above the mean code's at the true pose (0 steps), on the same
    /// objects.
    pub novel_gain_db: f64,
    pub novel_perceptual: f64,
    pub silhouette_iou: f64,
    pub structure_agreement: f64,
    /// The pose at this point against the true one (the given one has none).
    pub pitch_error_deg: f64,
    pub yaw_error_deg: f64,
    pub median_yaw_error_deg: f64,
    /// The novel-view PSNR of each object (its mean over the noise seeds).
    pub novel_psnr_per_object: Vec<f64>,
    /// The novel-view PSNR of each noise seed (its mean over the objects).
    pub novel_psnr_per_noise_seed: Vec<f64>,
}

/// The means of one checkpoint over objects and seeds.
pub(super) fn summarise(m: &Method, steps: usize, cells: &[Vec<Cell>], baseline: &[f64]) -> Point {
    let all: Vec<&Cell> = cells.iter().flatten().collect();
    let avg = |f: &dyn Fn(&Cell) -> f64| all.iter().map(|c| f(c)).sum::<f64>() / all.len() as f64;
    let per_object: Vec<f64> =
        cells.iter().map(|o| o.iter().map(|c| c.scores[1]).sum::<f64>() / o.len() as f64).collect();
    let seeds = cells[0].len();
    let per_seed = (0..seeds).map(|s| cells.iter().map(|o| o[s].scores[1]).sum::<f64>() / cells.len() as f64).collect();
    let gain = per_object.iter().zip(baseline).map(|(p, b)| p - b).sum::<f64>() / per_object.len() as f64;
    let mut yaws: Vec<f64> = all.iter().map(|c| c.yaw_err).collect();
    yaws.sort_by(f64::total_cmp);
    let known = m.pose == PoseUsed::True;
    Point {
        method: m.name.clone(),
        start: format!("{:?}", m.from),
        pose: format!("{:?}", m.pose),
        objects: cells.len(),
        steps,
        seconds: avg(&|c| c.seconds),
        input_psnr: avg(&|c| c.scores[0]),
        novel_psnr: avg(&|c| c.scores[1]),
        novel_gain_db: gain,
        novel_perceptual: avg(&|c| c.scores[2]),
        silhouette_iou: avg(&|c| c.scores[3]),
        structure_agreement: avg(&|c| c.scores[4]),
        pitch_error_deg: if known { f64::NAN } else { avg(&|c| c.pitch_err) },
        yaw_error_deg: if known { f64::NAN } else { avg(&|c| c.yaw_err) },
        median_yaw_error_deg: if known { f64::NAN } else { crate::bench::median(&yaws) },
        novel_psnr_per_object: per_object,
        novel_psnr_per_noise_seed: per_seed,
    }
}

impl Report {
    /// The methods in the order they ran.
    fn methods(&self) -> Vec<String> {
        self.points.iter().fold(Vec::new(), |mut v, p| {
            if !v.contains(&p.method) {
                v.push(p.method.clone());
            }
            v
        })
    }

    /// Writes STEM.png, STEM.json, STEM.md and STEM-figure.png, and prints the table.
    pub(super) fn write(&self, out: &Path, figure_rows: &[Tensor]) -> Result<()> {
        let methods = self.methods();
        let series = |f: &dyn Fn(&Point) -> (f64, f64)| -> Vec<Series> {
            methods
                .iter()
                .map(|m| Series {
                    name: m.clone(),
                    points: self.points.iter().filter(|p| &p.method == m).map(f).collect(),
                })
                .collect()
        };
        let panel = |title: &str, f: &dyn Fn(&Point) -> (f64, f64)| Panel {
            title: title.into(),
            series: series(f),
            log_y: false,
            marks: vec![],
        };
        let panels = [
            panel("novel-view PSNR (dB) vs seconds", &|p| (p.seconds, p.novel_psnr)),
            panel("structure agreement vs seconds", &|p| (p.seconds, p.structure_agreement)),
        ];
        if let Some(dir) = out.parent() {
            std::fs::create_dir_all(dir).map_err(|err| Error::Io { path: dir.to_path_buf(), err })?;
        }
        let stem = out.display().to_string();
        crate::io::save_png(&PathBuf::from(format!("{stem}.png")), &draw_panels(&panels, 2, 480, 300)?)?;
        write_json(&PathBuf::from(format!("{stem}.json")), self)?;
        if !figure_rows.is_empty() {
            let fig = Tensor::cat(figure_rows, 1);
            let big =
                fig.unsqueeze(0).upsample_nearest2d([fig.size()[1] * 3, fig.size()[2] * 3], None, None).squeeze_dim(0);
            crate::io::save_png(&PathBuf::from(format!("{stem}-figure.png")), &crate::io::to_rgb8(&big, false)?)?;
        }
        let md = self.markdown();
        crate::paths::write_atomic(&PathBuf::from(format!("{stem}.md")), md.as_bytes())?;
        print!("{md}");
        let fig = if figure_rows.is_empty() { String::new() } else { format!(", {stem}-figure.png") };
        println!("wrote {stem}.json, {stem}.md, {stem}.png{fig}");
        Ok(())
    }

    /// Each method's last point (and its start), then every point.
    pub fn markdown(&self) -> String {
        let deg = |x: f64| if x.is_nan() { "—".to_string() } else { format!("{x:.1}°") };
        let row = |p: &Point| {
            format!(
                "| {} | {} | {} | {:.1} | {:.2} | {:+.2} | {:.3} | {:.3} | {:.3} | {} / {} ({}) |\n",
                p.method,
                p.objects,
                p.steps,
                p.seconds,
                p.novel_psnr,
                p.novel_gain_db,
                p.novel_perceptual,
                p.silhouette_iou,
                p.structure_agreement,
                deg(p.pitch_error_deg),
                deg(p.yaw_error_deg),
                deg(p.median_yaw_error_deg),
            )
        };
        let head = format!(
            "| method | objects | steps | seconds | novel PSNR | gain over the mean code | perceptual ({}) | silhouette IoU | structure | pose error pitch / yaw (median yaw) |\n|---|---|---|---|---|---|---|---|---|---|\n",
            self.perceptual
        );
        let mut md = format!(
            "{} held-out objects of {} (after the first {}), view 0 inverted, {} novel views each at {}², means over the objects and noise seeds {:?}. The gain is over the mean code at the true pose (0 steps) on the same objects. The probe agrees {:.3} with the ground-truth views themselves.\n\n",
            self.objects.len(),
            self.dataset,
            self.skip,
            self.views,
            self.resolution,
            self.noise_seeds,
            self.structure_agreement_of_the_ground_truth_views
        );
        md += &head;
        for m in self.methods() {
            let mine: Vec<&Point> = self.points.iter().filter(|p| p.method == m).collect();
            if mine[0].method.starts_with("mean code") || mine[0].method.starts_with("gdrf-invert") {
                md += &row(mine[0]).replacen(&mine[0].method, &format!("{} (start)", mine[0].method), 1);
            }
            md += &row(mine[mine.len() - 1]);
        }
        md += "\nEvery point:\n\n";
        md += &head;
        for p in &self.points {
            md += &row(p);
        }
        md
    }
}
