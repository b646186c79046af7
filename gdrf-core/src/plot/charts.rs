//! The benchmarks' two charts: grouped bars (seconds per phase, one bar per implementation)
//! and time against error (one panel per scene and size, a point per configuration, the
//! Pareto front and reference lines).
use image::RgbImage;
use plotters::coord::combinators::BindKeyPoints;
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use plotters::coord::ranged1d::{Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;

use super::canvas::{drawing, fit, font, Canvas, TITLE};
use super::{fmt_num, mesh, Lettering, INK, LEGEND_BORDER, PALETTE, TEXT};
use crate::error::Result;

/// Bars in groups: `groups` along x (the phases), in each a bar per series (an
/// implementation), its height and value printed above it.
#[derive(Debug, Clone, PartialEq)]
pub struct Bars {
    pub title: String,
    pub y_label: String,
    pub groups: Vec<String>,
    /// (name, one value per group); a non-finite value leaves its bar out.
    pub series: Vec<(String, Vec<f64>)>,
}

/// One panel of a time-against-error chart.
#[derive(Debug, Clone, PartialEq)]
pub struct ScatterPanel {
    pub title: String,
    /// (family, x, y, note): each family its own colour and marker, the note beside it.
    pub points: Vec<(String, f64, f64, String)>,
    /// Drawn through in order, dashed (the Pareto front).
    pub front: Vec<(f64, f64)>,
    /// Vertical reference lines (name, x), dotted grey.
    pub verticals: Vec<(String, f64)>,
    /// A horizontal threshold, dotted red.
    pub threshold: Option<f64>,
}

/// A scatter chart's title above its panels, its axis names, and whether x is logarithmic.
#[derive(Debug, Clone, PartialEq)]
pub struct ScatterAxes {
    pub title: String,
    pub x: String,
    pub y: String,
    pub log_x: bool,
}

/// Draws `b` into a `w × h` image.
pub fn draw_bars(b: &Bars, w: u32, h: u32) -> Result<RgbImage> {
    let mut img = RgbImage::from_pixel(w.max(1), h.max(1), image::Rgb([255, 255, 255]));
    {
        let root = Canvas::on(&mut img);
        let values = b.series.iter().flat_map(|s| s.1.iter().copied()).filter(|v| v.is_finite());
        let top = values.fold(0f64, f64::max).max(1e-12) * 1.15;
        let n = b.groups.len().max(1) as f64;
        // Benchmark titles carry their settings: the text size, not the title size.
        let title = fit(&b.title, w as i64 - 16, TEXT)?;
        let mut chart = ChartBuilder::on(&root)
            .caption(title, font(TEXT)?.color(&INK))
            .margin(8)
            .x_label_area_size(TEXT.px as u32 + 12)
            .y_label_area_size(56)
            .build_cartesian_2d(0f64..n, 0f64..top)
            .map_err(drawing)?;
        chart
            .configure_mesh()
            .x_labels(0)
            .y_labels(6)
            .disable_x_mesh()
            .max_light_lines(0)
            .y_desc(b.y_label.as_str())
            .y_label_formatter(&|v| fmt_num(*v))
            .label_style(font(TEXT)?.color(&INK))
            .axis_desc_style(font(TEXT)?.color(&INK))
            .draw()
            .map_err(drawing)?;
        let k = b.series.len().max(1) as f64;
        let width = 0.8 / k;
        let above = font(TEXT)?.color(&INK).pos(Pos::new(HPos::Center, VPos::Bottom));
        for (i, (name, vals)) in b.series.iter().enumerate() {
            let colour = PALETTE[i % PALETTE.len()];
            let x0 = |g: usize| g as f64 + 0.1 + i as f64 * width;
            let bars = vals
                .iter()
                .enumerate()
                .filter(|(_, v)| v.is_finite())
                .map(|(g, &v)| Rectangle::new([(x0(g), 0.0), (x0(g) + width * 0.95, v)], colour.filled()));
            chart
                .draw_series(bars)
                .map_err(drawing)?
                .label(name.clone())
                .legend(move |(x, y)| Rectangle::new([(x, y - 5), (x + 12, y + 5)], colour.filled()));
            let labels = vals
                .iter()
                .enumerate()
                .filter(|(_, v)| v.is_finite())
                .map(|(g, &v)| Text::new(fmt_num(v), (x0(g) + width / 2.0, v), above.clone()));
            chart.draw_series(labels).map_err(drawing)?;
        }
        let below = font(TEXT)?.color(&INK).pos(Pos::new(HPos::Center, VPos::Top));
        for (g, name) in b.groups.iter().enumerate() {
            let (x, y) = chart.backend_coord(&(g as f64 + 0.5, 0.0));
            root.draw(&Text::new(name.clone(), (x, y + 6), below.clone())).map_err(drawing)?;
        }
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .legend_area_size(22)
            .background_style(WHITE)
            .border_style(LEGEND_BORDER)
            .label_font(font(TEXT)?.color(&INK))
            .draw()
            .map_err(drawing)?;
        root.present().map_err(drawing)?;
    }
    Ok(img)
}

/// Draws `panels` in a grid of `cols` columns, each `w × h`, with one legend beside them
/// (inside a panel it would hide points): each family, the front, the reference lines.
pub fn draw_scatter(panels: &[ScatterPanel], axes: &ScatterAxes, cols: usize, w: u32, h: u32) -> Result<RgbImage> {
    let legend_w = 240u32;
    let cols = cols.clamp(1, panels.len().max(1));
    let rows = panels.len().div_ceil(cols).max(1);
    let mut families: Vec<String> = Vec::new();
    for (f, ..) in panels.iter().flat_map(|p| p.points.iter()) {
        if !families.contains(f) {
            families.push(f.clone());
        }
    }
    let title_h = (TITLE.px * 2.0) as u32;
    let full_w = w * cols as u32 + legend_w;
    let mut img = RgbImage::from_pixel(full_w, h * rows as u32 + title_h, image::Rgb([255, 255, 255]));
    {
        let root = Canvas::on(&mut img);
        let title = fit(&axes.title, full_w as i64 - 16, TEXT)?;
        let centred = font(TEXT)?.color(&INK).pos(Pos::new(HPos::Center, VPos::Center));
        root.draw(&Text::new(title, (full_w as i32 / 2, title_h as i32 / 2), centred)).map_err(drawing)?;
        let (_, body) = root.split_vertically(title_h);
        let (plots, side) = body.split_horizontally(w * cols as u32);
        for (p, area) in panels.iter().zip(plots.split_evenly((rows, cols))) {
            scatter_panel(&area, p, axes, &families)?;
        }
        let mut entries: Vec<(String, Swatch)> =
            families.iter().enumerate().map(|(i, f)| (f.clone(), Swatch::Marker(i))).collect();
        entries.push(("Pareto front".into(), Swatch::Line(BLACK)));
        let mut refs: Vec<&String> = Vec::new();
        for (name, _) in panels.iter().flat_map(|p| p.verticals.iter()) {
            if !refs.contains(&name) {
                refs.push(name);
            }
        }
        entries.extend(refs.into_iter().map(|n| (n.clone(), Swatch::Line(REFERENCE))));
        let row = (TEXT.px * 1.6) as i32;
        let top = (h as i32 * rows as i32 - row * entries.len() as i32) / 2;
        let left = font(TEXT)?.color(&INK).pos(Pos::new(HPos::Left, VPos::Center));
        for (k, (name, swatch)) in entries.iter().enumerate() {
            let y = top + k as i32 * row + row / 2;
            match swatch {
                Swatch::Marker(i) => draw_marker(&side, *i, (14, y))?,
                Swatch::Line(c) => {
                    side.draw(&PathElement::new([(6, y), (22, y)], c.stroke_width(1))).map_err(drawing)?
                }
            }
            side.draw(&Text::new(fit(name, legend_w as i64 - 34, TEXT)?, (30, y), left.clone())).map_err(drawing)?;
        }
        root.present().map_err(drawing)?;
    }
    Ok(img)
}

/// Ticks of a log axis over [lo, hi]: 1, 2 and 5 × 10^k, or only the decades where those
/// would be more than ten.
fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let (a, b) = (lo.log10().floor() as i32, hi.log10().ceil() as i32);
    let all = |ms: &[f64]| -> Vec<f64> {
        (a..=b).flat_map(|e| ms.iter().map(move |m| m * 10f64.powi(e))).filter(|v| (lo..=hi).contains(v)).collect()
    };
    let fine = all(&[1.0, 2.0, 5.0]);
    if fine.len() > 10 {
        all(&[1.0])
    } else {
        fine
    }
}

/// Dotted reference lines (the PyTorch reference's time).
const REFERENCE: RGBColor = RGBColor(140, 140, 140);
/// The threshold line (40 dB).
const THRESHOLD: RGBColor = RGBColor(214, 39, 40);

enum Swatch {
    Marker(usize),
    Line(RGBColor),
}

/// Family `i`'s marker at pixel `at` of `area`, in the family's colour: a circle, triangle,
/// square or cross, in turn.
fn draw_marker<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, i: usize, at: (i32, i32)) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let c = PALETTE[i % PALETTE.len()];
    let (x, y) = at;
    match (i / PALETTE.len() + i) % 4 {
        0 => area.draw(&Circle::new(at, 4, c.filled())),
        1 => area.draw(&TriangleMarker::new(at, 6, c.filled())),
        2 => area.draw(&Rectangle::new([(x - 4, y - 4), (x + 4, y + 4)], c.filled())),
        _ => area.draw(&Cross::new(at, 4, c.stroke_width(2))),
    }
    .map_err(drawing)
}

fn scatter_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    p: &ScatterPanel,
    axes: &ScatterAxes,
    families: &[String],
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let ok_x = |x: &f64| x.is_finite() && (!axes.log_x || *x > 0.0);
    let xs = p.points.iter().map(|q| q.1).chain(p.verticals.iter().map(|v| v.1)).filter(ok_x);
    let ys = p.points.iter().map(|q| q.2).chain(p.threshold).filter(|y| y.is_finite());
    let (x0, x1) = xs.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let (y0, y1) = ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    let title = fit(&p.title, area.dim_in_pixel().0 as i64 - 8, TITLE)?;
    let mut b = ChartBuilder::on(area);
    b.caption(title, font(TITLE)?.color(&INK)).margin(8).x_label_area_size(36).y_label_area_size(56);
    if !(x0 <= x1 && y0 <= y1 && (x1 - x0).is_finite() && (y1 - y0).is_finite()) {
        let mut c = b.build_cartesian_2d(0f64..1f64, 0f64..1f64).map_err(drawing)?;
        return mesh(&mut c, false, None);
    }
    let pad = 0.06 * (y1 - y0).max(1.0);
    let y = (y0 - pad, y1 + pad);
    if axes.log_x {
        let (lo, hi) = (x0 / 1.3, x1 * 1.3);
        let c =
            b.build_cartesian_2d((lo..hi).log_scale().with_key_points(log_ticks(lo, hi)), y.0..y.1).map_err(drawing)?;
        scatter_into(area, c, p, axes, families, y)
    } else {
        let pad = 0.06 * (x1 - x0).max(1e-9);
        let c = b.build_cartesian_2d(x0 - pad..x1 + pad, y.0..y.1).map_err(drawing)?;
        scatter_into(area, c, p, axes, families, y)
    }
}

fn scatter_into<'a, DB: DrawingBackend + 'a, X>(
    area: &DrawingArea<DB, Shift>,
    mut c: ChartContext<'a, DB, Cartesian2d<X, RangedCoordf64>>,
    p: &ScatterPanel,
    axes: &ScatterAxes,
    families: &[String],
    y: (f64, f64),
) -> Result<()>
where
    DB::ErrorType: 'static,
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    mesh(&mut c, true, Some((&axes.x, &axes.y)))?;
    let xr = c.x_range();
    if let Some(t) = p.threshold {
        c.draw_series(DashedLineSeries::new([(xr.start, t), (xr.end, t)], 2, 3, THRESHOLD.stroke_width(1)))
            .map_err(drawing)?;
    }
    for (_, x) in &p.verticals {
        c.draw_series(DashedLineSeries::new([(*x, y.0), (*x, y.1)], 2, 3, REFERENCE.stroke_width(1)))
            .map_err(drawing)?;
    }
    c.draw_series(DashedLineSeries::new(p.front.iter().copied(), 6, 4, BLACK.stroke_width(1))).map_err(drawing)?;
    let base = area.get_base_pixel();
    let note = font(Lettering { px: 10.0, mono: false })?.color(&INK);
    for (family, x, yv, text) in &p.points {
        if !(x.is_finite() && yv.is_finite()) {
            continue;
        }
        let i = families.iter().position(|f| f == family).unwrap_or(0);
        let (px, py) = c.backend_coord(&(*x, *yv));
        let at = (px - base.0, py - base.1);
        draw_marker(area, i, at)?;
        area.draw(&Text::new(text.clone(), (at.0 + 5, at.1 - 12), note.clone())).map_err(drawing)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn is(c: &image::Rgb<u8>, k: RGBColor) -> bool {
        c.0 == [k.0, k.1, k.2]
    }
    /// The tallest run of colour `k` standing on row `base` in columns `xs` (a bar's height;
    /// the legend's swatch stands on nothing).
    fn bar_height(img: &RgbImage, k: RGBColor, xs: std::ops::Range<u32>, base: u32) -> u32 {
        xs.map(|x| (0..=base).rev().take_while(|&y| is(img.get_pixel(x, y), k)).count() as u32).max().unwrap_or(0)
    }

    #[test]
    fn bars_stand_as_tall_as_their_values() {
        let b = Bars {
            title: "step".into(),
            y_label: "median seconds".into(),
            groups: vec!["a".into(), "b".into()],
            series: vec![("gdrf".into(), vec![1.0, 2.0]), ("reference".into(), vec![4.0, f64::NAN])],
        };
        let img = draw_bars(&b, 600, 400).unwrap();
        assert_eq!(img.dimensions(), (600, 400));
        // Bars grow up from one baseline: each series' columns, in group a's half and b's.
        let (a, bb) = (0..300, 300..600);
        let base = (0..400).rev().find(|&y| (0..600).any(|x| is(img.get_pixel(x, y), PALETTE[0]))).unwrap();
        let height = |k, xs| bar_height(&img, k, xs, base);
        let (g_a, g_b, r_a) = (height(PALETTE[0], a.clone()), height(PALETTE[0], bb.clone()), height(PALETTE[1], a));
        assert!((g_b as f64 / g_a as f64 - 2.0).abs() < 0.05, "{g_a} {g_b}");
        assert!((r_a as f64 / g_a as f64 - 4.0).abs() < 0.1, "{g_a} {r_a}");
        // The NaN bar is left out: the reference's colour in group b is only its legend swatch.
        let legend_only = (300..600)
            .flat_map(|x| (0..400).map(move |y| (x, y)))
            .filter(|&(x, y)| is(img.get_pixel(x, y), PALETTE[1]))
            .count();
        assert!(legend_only < 200, "{legend_only}");
    }

    #[test]
    fn a_scatter_marks_each_family_and_draws_the_front_and_references() {
        let panel = ScatterPanel {
            title: "model, 16×16".into(),
            points: vec![
                ("reference".into(), 10.0, 50.0, "N=36".into()),
                ("grid".into(), 3.0, 42.0, "N=12".into()),
                ("grid".into(), 5.0, 45.0, "N=24".into()),
            ],
            front: vec![(3.0, 42.0), (5.0, 45.0), (10.0, 50.0)],
            verticals: vec![("PyTorch reference".into(), 40.0)],
            threshold: Some(40.0),
        };
        let axes = ScatterAxes { title: "renderer".into(), x: "ms".into(), y: "dB".into(), log_x: true };
        let img = draw_scatter(&[panel.clone(), panel], &axes, 1, 400, 300).unwrap();
        let title_h = (TITLE.px * 2.0) as u32;
        assert_eq!(img.dimensions(), (400 + 240, 600 + title_h));
        let count = |k: RGBColor, xs: std::ops::Range<u32>| {
            xs.flat_map(|x| (0..img.height()).map(move |y| (x, y))).filter(|&(x, y)| is(img.get_pixel(x, y), k)).count()
        };
        // Each family's markers in the panels, and its swatch in the legend beside them.
        for k in [PALETTE[0], PALETTE[1]] {
            assert!(count(k, 0..400) >= 40, "{k:?}");
            assert!(count(k, 400..640) >= 10, "{k:?}");
        }
        assert!(count(BLACK, 0..400) > 40, "the dashed front");
        assert!(count(THRESHOLD, 0..400) > 100, "the 40 dB line");
        assert!(count(REFERENCE, 0..400) > 40, "the reference's time");
    }

    #[test]
    fn log_ticks_are_one_two_five_or_decades() {
        assert_eq!(log_ticks(3.0, 40.0), [5.0, 10.0, 20.0]);
        assert_eq!(log_ticks(0.9, 2.1), [1.0, 2.0]);
        assert_eq!(log_ticks(0.5, 5e4), [1.0, 10.0, 100.0, 1000.0, 10000.0]);
    }
}
