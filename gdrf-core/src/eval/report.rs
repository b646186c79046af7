//! The evaluation as people read it: the scores as text, the one-page `report.png`
//! (scores, samples, class histograms, the swap matrix with its verdicts), and `eval.json`.
use super::result::{Calibrated, EvalResult};
use crate::paths::write_atomic;
use crate::{io, Error, Result};
use std::path::Path;

/// `", model truncated to ψ = 0.7"` where the model's codes were truncated, else nothing.
pub(crate) fn truncation_note(psi: f64) -> String {
    if psi == 1.0 {
        String::new()
    } else {
        format!(", model truncated to ψ = {psi}")
    }
}

/// The scores as text, one line per score.
pub fn summary(r: &EvalResult) -> String {
    let mut s = format!(
        "{} images at {}² ({} samples/ray{}), features: {}\n",
        r.images,
        r.resolution,
        r.samples_per_ray,
        truncation_note(r.psi),
        r.features
    );
    s += &format!("{:<26} {:>10} {:>10} {:>10} {:>9}\n", "score", "model", "real", "random", "position");
    for (name, c) in score_rows(r) {
        s += &format!("{name:<26} {:>10.4} {:>10.4} {:>10.4} {:>9.2}\n", c.model, c.real, c.random, c.position);
    }
    let o = &r.yaw_frame_offset_deg;
    s += &format!(
        "yaw in its own frame: turned by (probe − rendered) {:.1}° model, {:.1}° real, {:.1}° random\n",
        o.model, o.real, o.random
    );
    let o = &r.pitch_bias_deg;
    s += &format!(
        "pitch read high by (probe − rendered, mean) {:.1}° model, {:.1}° real, {:.1}° random\n",
        o.model, o.real, o.random
    );
    if let Some(line) = low_resolution_line(r) {
        s += &line;
        s.push('\n');
    }
    for w in &r.warnings {
        s += &format!("warning: {w}\n");
    }
    s
}

/// What the real images score at the lower resolution, in one line, when it was asked for.
fn low_resolution_line(r: &EvalResult) -> Option<String> {
    r.real_at_resolution.as_ref().map(|l| {
        format!(
            "real images at {}² (down and back up): frechet {:.4}, kernel {:.4}, coverage tv {:.4}, shape {:.4}, \
             appearance {:.4}, yaw {:.1}° ({:.1}° in its own frame), pitch {:.1}° (read high by {:.1}°)",
            l.resolution,
            l.frechet,
            l.kernel,
            l.coverage_tv,
            l.shape_follows,
            l.appearance_follows,
            l.pose_yaw_error_deg,
            l.pose_yaw_error_in_frame_deg,
            l.pose_pitch_error_deg,
            l.pitch_bias_deg
        )
    })
}

pub(crate) fn score_rows(r: &EvalResult) -> Vec<(&'static str, &Calibrated)> {
    vec![
        ("frechet distance", &r.frechet),
        ("kernel distance", &r.kernel),
        ("coverage tv", &r.coverage_tv),
        ("shape follows i", &r.shape_follows),
        ("appearance follows j", &r.appearance_follows),
        ("pose yaw error deg", &r.pose_yaw_error_deg),
        ("  in its own frame", &r.pose_yaw_error_in_frame_deg),
        ("pose pitch error deg", &r.pose_pitch_error_deg),
    ]
}

const CLASSES_CAPTION: &str = "classes: grey held-out truth, blue model, orange random generator";
const SWAP_CAPTION: &str = "swap matrix: row = shape, column = appearance";
// Apart from the line above: together they ran past the right edge of a 640-px report.
const BARS_CAPTION: &str = "bars: structure (left) and colour (right). green yes, red no, grey not counted";

/// The one-page report: scores, sample grid, class histograms (reference / model /
/// random), and the swap matrix with the probe's verdicts (a green or red bar under each
/// off-diagonal cell: left half structure follows the row, right half colour follows the
/// column).
pub fn report_image(r: &EvalResult) -> Result<image::RgbImage> {
    use crate::plot::{draw_text, fill, text_width, TABLE, TEXT};
    use image::Rgb;
    let s = r.resolution;
    let cols = 8;
    let grid = io::to_rgb8(&io::grid(&r.samples, cols), false)?;
    let k = r.swap_side;
    let cell = s + 6;
    // Wide enough for the grids and for every fixed caption, which would otherwise be cut.
    let captions = [CLASSES_CAPTION, SWAP_CAPTION, BARS_CAPTION];
    let text = captions.iter().map(|c| text_width(c, TEXT)).collect::<Result<Vec<_>>>()?.into_iter().max().unwrap_or(0);
    let width = (grid.width() as i64).max(k * cell + 20).max(text + 10).max(620) + 20;
    let hist_h = 150;
    let low_lines = if r.real_at_resolution.is_some() { 2 } else { 0 };
    let height = 20 + 14 * (12 + low_lines) + 20 + grid.height() as i64 + 30 + hist_h + 44 + k * cell + 20;
    let mut img = image::RgbImage::from_pixel(width as u32, height as u32, Rgb([255, 255, 255]));
    let black = Rgb([0, 0, 0]);
    let mut y = 10;
    draw_text(&mut img, 10, y, &format!("gdrf eval: {} images at {}x{}", r.images, s, s), black, TEXT)?;
    y += 14;
    draw_text(
        &mut img,
        10,
        y,
        &format!("{:<24}{:>10}{:>10}{:>10}{:>10}", "score", "model", "real", "random", "position"),
        black,
        TABLE,
    )?;
    for (name, c) in score_rows(r) {
        y += 14;
        draw_text(
            &mut img,
            10,
            y,
            &format!("{name:<24}{:>10.4}{:>10.4}{:>10.4}{:>10.2}", c.model, c.real, c.random, c.position),
            black,
            TABLE,
        )?;
    }
    y += 14;
    let o = &r.yaw_frame_offset_deg;
    let line = format!(
        "yaw in its own frame: turned {:.1} (model) {:.1} (real) {:.1} (random) deg",
        o.model, o.real, o.random
    );
    draw_text(&mut img, 10, y, &line, black, TEXT)?;
    y += 14;
    let o = &r.pitch_bias_deg;
    let line = format!("pitch read high by {:.1} (model) {:.1} (real) {:.1} (random) deg", o.model, o.real, o.random);
    draw_text(&mut img, 10, y, &line, black, TEXT)?;
    if let Some(l) = &r.real_at_resolution {
        let lines = [
            format!(
                "real at {}x{}: frechet {:.2} kernel {:.4} coverage {:.3} shape {:.3} appearance {:.3}",
                l.resolution, l.resolution, l.frechet, l.kernel, l.coverage_tv, l.shape_follows, l.appearance_follows
            ),
            format!(
                "  yaw {:.1} ({:.1} in its own frame) pitch {:.1} (read high by {:.1}) deg",
                l.pose_yaw_error_deg, l.pose_yaw_error_in_frame_deg, l.pose_pitch_error_deg, l.pitch_bias_deg
            ),
        ];
        for line in lines {
            y += 14;
            draw_text(&mut img, 10, y, &line, black, TEXT)?;
        }
    }
    y += 24;
    draw_text(&mut img, 10, y, "samples", black, TEXT)?;
    y += 12;
    image::imageops::overlay(&mut img, &grid, 10, y);
    y += grid.height() as i64 + 16;
    draw_text(&mut img, 10, y, CLASSES_CAPTION, black, TEXT)?;
    y += 14;
    let colours = [Rgb([90, 90, 90]), Rgb([40, 110, 220]), Rgb([220, 120, 40])];
    let mut x = 10;
    let bar_w = 5;
    for t in &r.classes {
        draw_text(&mut img, x, y + hist_h - 10, &t.factor, black, TEXT)?;
        for (c, _) in t.classes.iter().enumerate() {
            for (series, v) in [&t.reference, &t.model, &t.random].iter().enumerate() {
                let h = (v[c] * (hist_h - 24) as f64).round() as i64;
                fill(&mut img, x, y + hist_h - 14 - h, bar_w, h, colours[series]);
                x += bar_w;
            }
            x += 4;
        }
        x += 16;
    }
    y += hist_h + 12;
    draw_text(&mut img, 10, y, SWAP_CAPTION, black, TEXT)?;
    y += 14;
    draw_text(&mut img, 10, y, BARS_CAPTION, black, TEXT)?;
    y += 14;
    let sw = io::to_rgb8(&io::grid(&r.swap_images, k), false)?;
    for i in 0..k {
        for j in 0..k {
            let tile = image::imageops::crop_imm(&sw, (j * s) as u32, (i * s) as u32, s as u32, s as u32).to_image();
            let (tx, ty) = (10 + j * cell, y + i * cell);
            image::imageops::overlay(&mut img, &tile, tx, ty);
            if i != j {
                let (shape_ok, colour_ok) = r.swap_verdicts[(i * k + j) as usize];
                let c = |v: Option<bool>| match v {
                    Some(true) => Rgb([30, 170, 60]),
                    Some(false) => Rgb([210, 40, 40]),
                    None => Rgb([190, 190, 190]),
                };
                fill(&mut img, tx, ty + s + 1, s / 2 - 1, 3, c(shape_ok));
                fill(&mut img, tx + s / 2 + 1, ty + s + 1, s / 2 - 1, 3, c(colour_ok));
            }
        }
    }
    Ok(img)
}

/// Writes `eval.json` and `report.png` into `dir` (created; files written atomically).
pub fn write(dir: &Path, r: &EvalResult) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|source| Error::Io { path: dir.to_path_buf(), err: source })?;
    let json = serde_json::to_string_pretty(r)?;
    write_atomic(&dir.join("eval.json"), json.as_bytes())?;
    io::save_png(&dir.join("report.png"), &report_image(r)?)
}
