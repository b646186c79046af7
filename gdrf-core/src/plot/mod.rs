//! Line plots and captions drawn into an [`image::RgbImage`] with `plotters`.
//!
//! Two faces, subsets of DejaVu Sans and DejaVu Sans Mono committed with their licence
//! (`assets/fonts/`), rendered in pure Rust by plotters' `ab_glyph` backend: `gdrf-train
//! plot` works on a headless training box with no system font libraries and no Python, and
//! the same binary draws the same pixels everywhere. The monospace face keeps the evaluation
//! report's columns aligned. The workspace's `image` writes the PNG.

mod canvas;
mod charts;

use image::{Rgb, RgbImage};
use plotters::coord::ranged1d::{Ranged, ValueFormatter};
use plotters::coord::types::RangedCoordf64;
use plotters::coord::Shift;
use plotters::prelude::*;

use crate::error::Result;
use canvas::MARK;
pub use canvas::{draw_dashes, draw_text, fill, text_width, Lettering, TABLE, TEXT};
use canvas::{drawing, fit, font, rgb, Canvas, DASH, TITLE};
pub use charts::{draw_bars, draw_scatter, Bars, ScatterAxes, ScatterPanel};

/// One curve: a name (shown in the legend) and (x, y) points; non-finite y values are
/// skipped (gaps), not drawn as spikes.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// One panel: a title, its curves (each drawn in its own colour from a fixed palette),
/// whether the y axis is logarithmic (only positive values are plotted then), and x
/// positions marked by a dashed vertical line (where a training schedule changed, say); a
/// mark outside the curves' x range is not drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub title: String,
    pub series: Vec<Series>,
    pub log_y: bool,
    pub marks: Vec<f64>,
}

const WHITE_PX: Rgb<u8> = Rgb([255, 255, 255]);
const INK: RGBColor = RGBColor(20, 20, 20);
const FRAME: RGBColor = RGBColor(70, 70, 70);
const GRID: RGBColor = RGBColor(225, 225, 225);
const LEGEND_BORDER: RGBColor = RGBColor(180, 180, 180);
/// Matplotlib's "tab10": ten distinct colours that readers already associate with curves.
#[rustfmt::skip]
const PALETTE: [RGBColor; 10] = [
    RGBColor(31, 119, 180), RGBColor(255, 127, 14), RGBColor(44, 160, 44), RGBColor(214, 39, 40),
    RGBColor(148, 103, 189), RGBColor(140, 86, 75), RGBColor(227, 119, 194), RGBColor(127, 127, 127),
    RGBColor(188, 189, 34), RGBColor(23, 190, 207),
];
/// Curve thickness in pixels.
const LINE_W: u32 = 2;
/// At most about this many labelled ticks per axis (plotters picks round steps under it).
const TICKS: usize = 7;
/// Below this many pixels a panel has no room for axes and labels and stays blank.
const MIN_PANEL: (u32, u32) = (120, 90);

/// Draws panels in a grid of `cols` columns, each panel `panel_w × panel_h` pixels, white
/// background, and returns the image. `cols` is clamped to 1..=panels.len() so the image has
/// no empty columns; zero panels give one blank panel-sized image.
pub fn draw_panels(panels: &[Panel], cols: usize, panel_w: u32, panel_h: u32) -> Result<RgbImage> {
    let (pw, ph) = (panel_w.max(1), panel_h.max(1));
    if panels.is_empty() {
        return Ok(RgbImage::from_pixel(pw, ph, WHITE_PX));
    }
    let cols = cols.clamp(1, panels.len());
    let rows = panels.len().div_ceil(cols);
    let mut img = RgbImage::from_pixel(pw.saturating_mul(cols as u32), ph.saturating_mul(rows as u32), WHITE_PX);
    if pw < MIN_PANEL.0 || ph < MIN_PANEL.1 {
        return Ok(img);
    }
    {
        let root = Canvas::on(&mut img);
        for (p, area) in panels.iter().zip(root.split_evenly((rows, cols))) {
            draw_panel(&area, p)?;
        }
        root.present().map_err(drawing)?;
    }
    Ok(img)
}

/// The points of `s` as plotted, split into runs of consecutive valid points (a gap at
/// every non-finite value, and at non-positive values on a log axis).
fn runs(s: &Series, log_y: bool) -> Vec<Vec<(f64, f64)>> {
    let mut out = vec![Vec::new()];
    for &q in &s.points {
        if valid(q, log_y) {
            out.last_mut().expect("one run at least").push(q);
        } else if !out.last().expect("one run at least").is_empty() {
            out.push(Vec::new());
        }
    }
    out.retain(|r| !r.is_empty());
    out
}

fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, p: &Panel) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let (w, h) = area.dim_in_pixel();
    let pts: Vec<(f64, f64)> =
        p.series.iter().flat_map(|s| s.points.iter().copied()).filter(|&q| valid(q, p.log_y)).collect();
    let x = data_range(pts.iter().map(|q| q.0), 0.0, false);
    let ly = data_range(pts.iter().map(|q| if p.log_y { q.1.log10() } else { q.1 }), 0.05, p.log_y);
    // Under two decades a log axis would label one tick or none: the positive values then
    // go on a linear axis.
    let log_axis = p.log_y && ly.1 - ly.0 >= 2.0;
    let y = if p.log_y { (10f64.powf(ly.0), 10f64.powf(ly.1)) } else { ly };
    let title = fit(&p.title, w as i64 - 8, TITLE)?;
    let spans_ok = (x.1 - x.0).is_finite() && (y.1 - y.0).is_finite() && y.0 < y.1 && y.0.is_finite();
    let gutter = ["-0.0000", "2.5e-5"].iter().map(|s| text_width(s, TEXT)).collect::<Result<Vec<_>>>()?;
    let mut chart = ChartBuilder::on(area);
    chart
        .caption(title, font(TITLE)?.color(&INK))
        .margin_left(4)
        .margin_right(12)
        .margin_top(4)
        .margin_bottom(4)
        .x_label_area_size(TEXT.px as u32 + 10)
        .y_label_area_size(gutter.into_iter().max().unwrap_or(40) as u32 + 10);
    let note = |text: &str| -> Result<()> {
        let tw = text_width(text, TEXT)?;
        let at = ((w as i64 - tw) / 2, h as i64 / 2);
        area.draw(&Text::new(text.to_string(), (at.0 as i32, at.1 as i32), font(TEXT)?.color(&INK))).map_err(drawing)
    };
    if pts.is_empty() || !spans_ok {
        let mut c = chart.build_cartesian_2d(0f64..1f64, 0f64..1f64).map_err(drawing)?;
        mesh(&mut c, false, None)?;
        return note(if pts.is_empty() { "no data" } else { "range too large to plot" });
    }
    // The legend's size as a share of the plot area (plotters' box: a 22 px swatch, the
    // widest name, a row of text a series, margins), to find the corner where it hides least.
    let widest = p.series.iter().map(|s| text_width(&s.name, TEXT)).collect::<Result<Vec<_>>>()?;
    let plot = ((w as f64 - 60.0).max(1.0), (h as f64 - TITLE.px - TEXT.px - 30.0).max(1.0));
    let legend = (
        (widest.into_iter().max().unwrap_or(0) as f64 + 40.0) / plot.0,
        (p.series.len() as f64 * (TEXT.px + 6.0) + 12.0) / plot.1,
    );
    let axis_y = |v: f64| if log_axis { v.log10() } else { v };
    let span = (x, if log_axis { ly } else { y });
    let corner = legend_corner(p, span, axis_y, legend);
    if log_axis {
        let c = chart.build_cartesian_2d(x.0..x.1, (y.0..y.1).log_scale()).map_err(drawing)?;
        curves(c, p, y, corner)
    } else {
        let c = chart.build_cartesian_2d(x.0..x.1, y.0..y.1).map_err(drawing)?;
        curves(c, p, y, corner)
    }
}

/// The corner whose legend-sized box (`size`, shares of the plot's width and height) covers
/// the least of the curves, walked along each segment so that a line crossing the box counts
/// as well as its points: the legend is drawn last, on white, and hides what lies under it.
/// Ties go to the upper right, where a plot with room there keeps it. `span` is the axes'
/// ranges, y as the axis draws it (`axis_y`: log10 on a log axis).
fn legend_corner(
    p: &Panel,
    span: ((f64, f64), (f64, f64)),
    axis_y: impl Fn(f64) -> f64,
    size: (f64, f64),
) -> SeriesLabelPosition {
    let ((x0, x1), (y0, y1)) = span;
    let at = |(x, y): (f64, f64)| ((x - x0) / (x1 - x0), (axis_y(y) - y0) / (y1 - y0));
    let mut walked = Vec::new();
    for s in &p.series {
        for run in runs(s, p.log_y) {
            let run: Vec<(f64, f64)> = run.into_iter().map(at).collect();
            walked.extend(run.first().copied());
            for w in run.windows(2) {
                walked.extend((1..=16).map(|k| {
                    let t = k as f64 / 16.0;
                    (w[0].0 + t * (w[1].0 - w[0].0), w[0].1 + t * (w[1].1 - w[0].1))
                }));
            }
        }
    }
    let (right, upper) = (1.0 - size.0, 1.0 - size.1);
    let corners = [
        (SeriesLabelPosition::UpperRight, (right, 1.0), (upper, 1.0)),
        (SeriesLabelPosition::UpperLeft, (0.0, size.0), (upper, 1.0)),
        (SeriesLabelPosition::LowerRight, (right, 1.0), (0.0, size.1)),
        (SeriesLabelPosition::LowerLeft, (0.0, size.0), (0.0, size.1)),
    ];
    let covered = |(xs, ys): ((f64, f64), (f64, f64))| {
        walked.iter().filter(|q| (xs.0..=xs.1).contains(&q.0) && (ys.0..=ys.1).contains(&q.1)).count()
    };
    // min_by_key keeps the first of equals: the upper right.
    corners.into_iter().min_by_key(|&(_, xs, ys)| covered((xs, ys))).map(|c| c.0).expect("four corners")
}

/// Grid, axes and compact tick labels ([`fmt_num`]).
fn mesh<'a, DB: DrawingBackend + 'a, X, Y>(
    c: &mut ChartContext<'a, DB, Cartesian2d<X, Y>>,
    labels: bool,
    desc: Option<(&str, &str)>,
) -> Result<()>
where
    DB::ErrorType: 'static,
    X: Ranged<ValueType = f64> + ValueFormatter<f64>,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    let (xf, yf) = (|v: &f64| fmt_num(*v), |v: &f64| fmt_num(*v));
    let (xl, yl) = if labels { (TICKS, TICKS) } else { (0, 0) };
    let mut m = c.configure_mesh();
    m.x_labels(xl)
        .y_labels(yl)
        .max_light_lines(0)
        .bold_line_style(GRID)
        .axis_style(FRAME)
        .x_label_formatter(&xf)
        .y_label_formatter(&yf)
        .label_style(font(TEXT)?.color(&INK));
    if let Some((x, y)) = desc {
        m.x_desc(x).y_desc(y).axis_desc_style(font(TEXT)?.color(&INK));
    }
    m.draw().map_err(drawing)
}

/// The panel's marks, curves (a dot for a lone point) and legend, on axes built for it.
fn curves<'a, DB: DrawingBackend + 'a, Y>(
    mut c: ChartContext<'a, DB, Cartesian2d<RangedCoordf64, Y>>,
    p: &Panel,
    y: (f64, f64),
    corner: SeriesLabelPosition,
) -> Result<()>
where
    DB::ErrorType: 'static,
    Y: Ranged<ValueType = f64> + ValueFormatter<f64>,
{
    mesh(&mut c, true, None)?;
    let xr = c.x_range();
    for &m in p.marks.iter().filter(|m| (xr.start..=xr.end).contains(*m)) {
        let style = ShapeStyle::from(rgb(MARK)).stroke_width(1);
        c.draw_series(DashedLineSeries::new([(m, y.0), (m, y.1)], DASH as i32, DASH as i32, style)).map_err(drawing)?;
    }
    for (i, s) in p.series.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        let style = Color::stroke_width(&colour, LINE_W);
        let runs = runs(s, p.log_y);
        let first = runs.first().cloned().unwrap_or_default();
        // The first run carries the legend entry (an empty one for a series with no points,
        // so that the legend still names it).
        c.draw_series(LineSeries::new(first, style))
            .map_err(drawing)?
            .label(s.name.clone())
            .legend(move |(lx, ly)| PathElement::new([(lx, ly), (lx + 14, ly)], Color::stroke_width(&colour, LINE_W)));
        for run in runs.iter().skip(1) {
            c.draw_series(LineSeries::new(run.iter().copied(), style)).map_err(drawing)?;
        }
        let lone = runs.iter().filter(|r| r.len() == 1).map(|r| Circle::new(r[0], LINE_W + 1, colour.filled()));
        c.draw_series(lone).map_err(drawing)?;
    }
    if !p.series.is_empty() {
        // Last, on a white box, so curves never hide the names; in the corner where it hides
        // the least of them.
        c.configure_series_labels()
            .position(corner)
            .legend_area_size(22)
            .margin(6)
            .background_style(WHITE)
            .border_style(LEGEND_BORDER)
            .label_font(font(TEXT)?.color(&INK))
            .draw()
            .map_err(drawing)?;
    }
    Ok(())
}

/// Moving average over a window of `k` points (k = 1 returns the input), used to smooth
/// noisy GAN losses. The window is centred (no lag against the raw curve) and shrinks at the
/// ends so the output keeps every x. Non-finite y values stay non-finite (gaps survive
/// smoothing) and are left out of their neighbours' averages.
pub fn smooth(points: &[(f64, f64)], k: usize) -> Vec<(f64, f64)> {
    if k <= 1 {
        return points.to_vec();
    }
    let (before, after) = (k / 2, (k - 1) / 2);
    (0..points.len())
        .map(|i| {
            let (x, y) = points[i];
            if !y.is_finite() {
                return (x, y);
            }
            let win = &points[i.saturating_sub(before)..(i + after + 1).min(points.len())];
            let (sum, n) = win.iter().filter(|q| q.1.is_finite()).fold((0.0, 0.0), |(s, n), q| (s + q.1, n + 1.0));
            (x, sum / n)
        })
        .collect()
}

/// A point as plotted: x finite and y finite (and positive on a log axis).
fn valid((x, y): (f64, f64), log_y: bool) -> bool {
    x.is_finite() && y.is_finite() && (!log_y || y > 0.0)
}

/// Min/max of `vals` widened by `pad` × span. A zero span (one point, flat curve) is padded
/// so the axes never have zero length; no values at all give [0, 1]. On a log axis the
/// values are log10's.
fn data_range(vals: impl Iterator<Item = f64>, pad: f64, log_y: bool) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return (0.0, 1.0);
    }
    let span = hi - lo;
    if !span.is_finite() {
        return (lo, hi); // overflowing span: refused by the caller
    }
    if span <= 1e-12 * lo.abs().max(hi.abs()) {
        let d = if log_y {
            0.5
        } else if lo == 0.0 {
            1.0
        } else {
            0.1 * lo.abs()
        };
        return (lo - d, hi + d);
    }
    (lo - span * pad, hi + span * pad)
}

/// Trims trailing fractional zeros ("1.500" → "1.5", "2.000" → "2").
fn trim(s: &str) -> &str {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.')
    } else {
        s
    }
}

/// Four significant digits at most, fixed-point.
fn fmt_plain(v: f64) -> String {
    let decimals = (3 - v.abs().log10().floor() as i32).max(0) as usize;
    trim(&format!("{v:.decimals$}")).to_string()
}

/// Compact tick label: "0", "500", "1.5k", "20k", "2.5M", "0.001", "1e-4", "-2.5"; short
/// enough to keep the y-label gutter narrow.
fn fmt_num(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 || !v.is_finite() {
        return if v == 0.0 { "0".into() } else { format!("{v}") };
    }
    if !(1e-3..1e9).contains(&a) {
        let s = format!("{v:.2e}");
        let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
        return format!("{}e{e}", trim(m));
    }
    match a {
        a if a >= 1e6 => format!("{}M", fmt_plain(v / 1e6)),
        a if a >= 1e3 => format!("{}k", fmt_plain(v / 1e3)),
        _ => fmt_plain(v),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn series(name: &str, points: Vec<(f64, f64)>) -> Series {
        Series { name: name.into(), points }
    }
    fn panel(series: Vec<Series>, log_y: bool) -> Panel {
        Panel { title: "g_adv".into(), series, log_y, marks: vec![] }
    }
    fn is(c: &Rgb<u8>, k: RGBColor) -> bool {
        c.0 == [k.0, k.1, k.2]
    }
    /// Columns of `img` that hold at least `n` pixels of colour `k`.
    fn columns_of(img: &RgbImage, k: RGBColor, n: usize) -> Vec<u32> {
        (0..img.width()).filter(|&x| (0..img.height()).filter(|&y| is(img.get_pixel(x, y), k)).count() >= n).collect()
    }

    #[test]
    fn image_is_a_grid_of_panels() {
        let ps = vec![panel(vec![], false); 3];
        assert_eq!(draw_panels(&ps, 2, 360, 240).unwrap().dimensions(), (720, 480));
        assert_eq!(draw_panels(&ps, 0, 100, 50).unwrap().dimensions(), (100, 150));
        assert_eq!(draw_panels(&ps, 9, 100, 50).unwrap().dimensions(), (300, 50));
        let blank = draw_panels(&[], 2, 40, 30).unwrap();
        assert_eq!(blank.dimensions(), (40, 30));
        assert!(blank.pixels().all(|p| *p == WHITE_PX));
    }

    #[test]
    fn a_mark_is_a_dashed_column_inside_the_x_range_and_absent_outside_it() {
        let mut p = panel(vec![series("loss", vec![(0.0, 0.0), (10.0, 1.0)])], false);
        p.marks = vec![5.0, 12.0, -1.0];
        let img = draw_panels(std::slice::from_ref(&p), 1, 360, 240).unwrap();
        // One dashed column (the mark inside [0, 10]); at 5 of 10 it sits mid-way between
        // the curve's ends, which are the x range's.
        let marked = columns_of(&img, rgb(MARK), 20);
        assert_eq!(marked.len(), 1, "{marked:?}");
        let curve = columns_of(&img, PALETTE[0], 1);
        let mid = (curve[0] + curve[curve.len() - 1]) as f64 / 2.0;
        assert!((marked[0] as f64 - mid).abs() <= 3.0, "mark at {} for a plot centred at {mid}", marked[0]);
        // Dashed: gaps between its pixels, and none longer than a dash and a gap.
        let ys: Vec<u32> = (0..240).filter(|&y| is(img.get_pixel(marked[0], y), rgb(MARK))).collect();
        assert!(ys.windows(2).any(|w| w[1] - w[0] > 1), "a dashed line has gaps");
        p.marks.clear();
        assert!(columns_of(&draw_panels(&[p], 1, 360, 240).unwrap(), rgb(MARK), 20).is_empty());
    }

    #[test]
    fn a_curve_is_drawn_in_its_colour_and_named_in_the_legend() {
        let p = panel(
            vec![series("loss", vec![(0.0, 0.0), (10.0, 10.0)]), series("other", vec![(0.0, 5.0), (10.0, 5.0)])],
            false,
        );
        let img = draw_panels(std::slice::from_ref(&p), 1, 360, 240).unwrap();
        let count = |k: RGBColor| img.pixels().filter(|c| is(c, k)).count();
        // A diagonal across a ~300 px wide plot, two pixels thick; the flat line likewise.
        assert!(count(PALETTE[0]) > 300, "{}", count(PALETTE[0]));
        assert!(count(PALETTE[1]) > 300, "{}", count(PALETTE[1]));
        assert_eq!(count(PALETTE[2]), 0);
        // The diagonal rises: its pixels' rows fall (image y down) as columns grow.
        let ink: Vec<(u32, u32)> =
            img.enumerate_pixels().filter(|(_, _, c)| is(c, PALETTE[0])).map(|(x, y, _)| (x, y)).collect();
        let (left, right) = (ink.iter().min_by_key(|p| p.0).unwrap(), ink.iter().max_by_key(|p| p.0).unwrap());
        assert!(left.1 > right.1 + 100, "{left:?} {right:?}");
        // Text (title, ticks, legend) is drawn in ink, antialiased: dark pixels.
        assert!(img.pixels().filter(|c| c.0.iter().all(|&v| v < 100)).count() > 100);
    }

    #[test]
    fn the_legend_goes_to_the_corner_it_hides_least() {
        let rising = panel(vec![series("psnr", vec![(0.0, 0.0), (10.0, 10.0)])], false);
        let span = ((0.0, 10.0), (0.0, 10.0));
        let at = |p: &Panel| legend_corner(p, span, |v| v, (0.3, 0.2));
        // A rising curve ends in the upper right and starts in the lower left.
        assert!(matches!(at(&rising), SeriesLabelPosition::UpperLeft));
        // A falling one, from the upper left: the upper right is free again.
        let falling = panel(vec![series("loss", vec![(0.0, 10.0), (10.0, 0.0)])], false);
        assert!(matches!(at(&falling), SeriesLabelPosition::UpperRight));
        // Two points far apart whose segment crosses the upper right still count there.
        let crossing = panel(vec![series("x", vec![(0.0, 9.5), (10.0, 9.5), (10.0, 0.0)])], false);
        assert!(matches!(at(&crossing), SeriesLabelPosition::LowerLeft));
    }

    #[test]
    fn degenerate_inputs_do_not_panic_and_nan_leaves_a_gap() {
        let gap = panel(vec![series("d_r1", vec![(0.0, 0.0), (1.0, f64::NAN), (2.0, 0.0), (3.0, 0.0)])], false);
        assert_eq!(runs(&gap.series[0], false), vec![vec![(0.0, 0.0)], vec![(2.0, 0.0), (3.0, 0.0)]]);
        let neg = series("log", vec![(0.0, -1.0), (1.0, 2.0), (2.0, 0.0), (3.0, 1.0), (4.0, 2.0)]);
        assert_eq!(runs(&neg, true), vec![vec![(1.0, 2.0)], vec![(3.0, 1.0), (4.0, 2.0)]]);
        let ps = vec![
            panel(vec![], false),
            panel(vec![series("empty", vec![])], true),
            panel(vec![series("one", vec![(3.0, 7.0)])], false),
            panel(
                vec![series("flat", vec![(0.0, 2.0), (5.0, 2.0)]), series("zero", vec![(0.0, 0.0), (1.0, 0.0)])],
                false,
            ),
            panel(vec![series("bad", vec![(0.0, f64::INFINITY), (f64::NAN, 1.0), (2.0, -f64::INFINITY)])], false),
            panel(vec![series("log", vec![(0.0, -1.0), (1.0, 0.0), (2.0, 1e-3), (3.0, 0.1)])], true),
            panel(vec![series("neg", vec![(0.0, -1.0), (1.0, 0.0)])], true),
            panel(vec![series("huge", vec![(-1e308, -1e308), (1e308, 1e308)])], false),
            gap,
        ];
        for (w, h) in [(360, 240), (120, 90), (10, 10), (1, 1)] {
            assert_eq!(draw_panels(&ps, 5, w, h).unwrap().dimensions(), (5 * w, 2 * h));
        }
        // A lone point is a dot in the curve's colour.
        let one = draw_panels(&[panel(vec![series("one", vec![(3.0, 7.0)])], false)], 1, 360, 240).unwrap();
        assert!(one.pixels().filter(|c| is(c, PALETTE[0])).count() >= 5);
    }

    #[test]
    fn text_is_drawn_where_asked_and_measured() {
        let mut img = RgbImage::from_pixel(200, 40, WHITE_PX);
        draw_text(&mut img, 10, 10, "step 205046 ²×°", Rgb([0, 0, 0]), TEXT).unwrap();
        let inked: Vec<(u32, u32)> =
            img.enumerate_pixels().filter(|(_, _, c)| c.0[0] < 128).map(|(x, y, _)| (x, y)).collect();
        let (x0, x1) = (inked.iter().map(|p| p.0).min().unwrap(), inked.iter().map(|p| p.0).max().unwrap());
        let (y0, y1) = (inked.iter().map(|p| p.1).min().unwrap(), inked.iter().map(|p| p.1).max().unwrap());
        let w = text_width("step 205046 ²×°", TEXT).unwrap();
        assert!((10..=12).contains(&x0), "{x0}");
        assert!((x1 as i64 - 10 - w).abs() <= 8, "ink to {x1}, measured {w}");
        assert!(y0 >= 8 && y1 <= 10 + TEXT.px as u32 + 2, "{y0}..{y1}");
        // The table's face is monospace, every character advancing the same; the text's is not.
        assert_eq!(text_width("iiii", TABLE).unwrap(), text_width("MMMM", TABLE).unwrap());
        assert!(text_width("iiii", TEXT).unwrap() < text_width("MMMM", TEXT).unwrap());
        assert_eq!(fit("images/s", text_width("imag", TEXT).unwrap(), TEXT).unwrap(), "imag");
    }

    #[test]
    fn smooth_is_a_centred_moving_average() {
        assert_eq!(smooth(&[(0.0, 3.0); 6], 4), vec![(0.0, 3.0); 6]);
        let ramp: Vec<_> = (0..5).map(|i| (i as f64, i as f64)).collect();
        assert_eq!(smooth(&ramp, 1), ramp);
        assert_eq!(smooth(&ramp, 0), ramp);
        let ys: Vec<f64> = smooth(&ramp, 3).iter().map(|p| p.1).collect();
        assert_eq!(ys, [0.5, 1.0, 2.0, 3.0, 3.5]);
        let s = smooth(&[(0.0, 1.0), (1.0, f64::NAN), (2.0, 3.0)], 3);
        assert_eq!((s[0].1, s[2].1), (1.0, 3.0));
        assert!(s[1].1.is_nan());
        assert!(smooth(&[], 5).is_empty());
    }

    #[test]
    fn labels_are_compact() {
        #[rustfmt::skip]
        let cases = [
            (0.0, "0"), (-0.0, "0"), (500.0, "500"), (1500.0, "1.5k"), (20000.0, "20k"),
            (2.5e6, "2.5M"), (0.001, "0.001"), (1e-4, "1e-4"), (2.5e-5, "2.5e-5"), (-2.5, "-2.5"),
            (0.1 + 0.2, "0.3"), (7.5, "7.5"), (3e9, "3e9"), (123.456, "123.5"),
        ];
        for (v, s) in cases {
            assert_eq!(fmt_num(v), s, "{v}");
        }
    }
}
