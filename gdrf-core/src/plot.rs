//! Training curves drawn straight into an [`image::RgbImage`].
//!
//! Deliberately self-contained (a 5×7 bitmap font, Bresenham lines, "nice" ticks) so that
//! `gdrf-train plot` works on a headless training box with no plotting crate, no system
//! fonts and no Python: the only dependency is `image`, which also writes the PNG.

use image::{Rgb, RgbImage};

/// One curve: a name (shown in the legend) and (x, y) points; non-finite y values are
/// skipped (gaps), not drawn as spikes.
#[derive(Debug, Clone, PartialEq)]
pub struct Series {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// One panel: a title, its curves (each drawn in its own colour from a fixed palette),
/// whether the y axis is log10 (only positive values are plotted then), and x positions
/// marked by a dashed vertical line (where a training schedule changed, say); a mark outside
/// the curves' x range is not drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct Panel {
    pub title: String,
    pub series: Vec<Series>,
    pub log_y: bool,
    pub marks: Vec<f64>,
}

const WHITE: Rgb<u8> = Rgb([255, 255, 255]);
const INK: Rgb<u8> = Rgb([20, 20, 20]);
const FRAME: Rgb<u8> = Rgb([70, 70, 70]);
const GRID: Rgb<u8> = Rgb([225, 225, 225]);
/// Dashed x marks: darker than the grid so they read as events, lighter than the curves.
const MARK: Rgb<u8> = Rgb([150, 150, 150]);
/// A dashed mark paints `DASH` pixels of every `2 × DASH`.
const DASH: i64 = 4;
/// Matplotlib's "tab10": ten distinct colours that readers already associate with curves.
#[rustfmt::skip]
const PALETTE: [Rgb<u8>; 10] = [
    Rgb([31, 119, 180]), Rgb([255, 127, 14]), Rgb([44, 160, 44]), Rgb([214, 39, 40]),
    Rgb([148, 103, 189]), Rgb([140, 86, 75]), Rgb([227, 119, 194]), Rgb([127, 127, 127]),
    Rgb([188, 189, 34]), Rgb([23, 190, 207]),
];
/// Tick and legend text scale. 5×7 glyphs at ×1 are legible at 100 % zoom and keep the
/// y-label gutter narrow enough for a 360×240 panel.
const SCALE: u32 = 1;
/// Titles are doubled so that a grid of panels can be scanned at a glance.
const TITLE_SCALE: u32 = 2;
/// Curve thickness: every Bresenham step paints a `LINE_W`×`LINE_W` square.
const LINE_W: i64 = 2;
/// At most this many ticks per axis.
const TICKS: usize = 5;

/// 5×7 glyphs, one byte per row, bit 4 = leftmost column. Lookup tries the exact character
/// first and then its lower case, so upper case letters (except `M`, kept for "2.5M"
/// labels so it cannot be misread as milli) draw as lower case.
#[rustfmt::skip]
const FONT: &[(char, [u8; 7])] = &[
    ('0', [0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E]), ('1', [0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('2', [0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F]), ('3', [0x1F, 0x02, 0x04, 0x02, 0x01, 0x11, 0x0E]),
    ('4', [0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02]), ('5', [0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E]),
    ('6', [0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E]), ('7', [0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08]),
    ('8', [0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E]), ('9', [0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C]),
    ('a', [0x00, 0x00, 0x0E, 0x01, 0x0F, 0x11, 0x0F]), ('b', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x1E]),
    ('c', [0x00, 0x00, 0x0E, 0x10, 0x10, 0x11, 0x0E]), ('d', [0x01, 0x01, 0x0D, 0x13, 0x11, 0x11, 0x0F]),
    ('e', [0x00, 0x00, 0x0E, 0x11, 0x1F, 0x10, 0x0E]), ('f', [0x06, 0x09, 0x08, 0x1C, 0x08, 0x08, 0x08]),
    ('g', [0x00, 0x00, 0x0F, 0x11, 0x0F, 0x01, 0x0E]), ('h', [0x10, 0x10, 0x16, 0x19, 0x11, 0x11, 0x11]),
    ('i', [0x04, 0x00, 0x0C, 0x04, 0x04, 0x04, 0x0E]), ('j', [0x02, 0x00, 0x06, 0x02, 0x02, 0x12, 0x0C]),
    ('k', [0x10, 0x10, 0x12, 0x14, 0x18, 0x14, 0x12]), ('l', [0x0C, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E]),
    ('m', [0x00, 0x00, 0x1A, 0x15, 0x15, 0x11, 0x11]), ('n', [0x00, 0x00, 0x16, 0x19, 0x11, 0x11, 0x11]),
    ('o', [0x00, 0x00, 0x0E, 0x11, 0x11, 0x11, 0x0E]), ('p', [0x00, 0x00, 0x1E, 0x11, 0x1E, 0x10, 0x10]),
    ('q', [0x00, 0x00, 0x0D, 0x13, 0x0F, 0x01, 0x01]), ('r', [0x00, 0x00, 0x16, 0x19, 0x10, 0x10, 0x10]),
    ('s', [0x00, 0x00, 0x0E, 0x10, 0x0E, 0x01, 0x1E]), ('t', [0x08, 0x08, 0x1C, 0x08, 0x08, 0x09, 0x06]),
    ('u', [0x00, 0x00, 0x11, 0x11, 0x11, 0x13, 0x0D]), ('v', [0x00, 0x00, 0x11, 0x11, 0x11, 0x0A, 0x04]),
    ('w', [0x00, 0x00, 0x11, 0x11, 0x15, 0x15, 0x0A]), ('x', [0x00, 0x00, 0x11, 0x0A, 0x04, 0x0A, 0x11]),
    ('y', [0x00, 0x00, 0x11, 0x11, 0x0F, 0x01, 0x0E]), ('z', [0x00, 0x00, 0x1F, 0x02, 0x04, 0x08, 0x1F]),
    ('M', [0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11]), (' ', [0x00; 7]),
    ('.', [0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C]), (',', [0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08]),
    ('-', [0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00]), ('+', [0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00]),
    ('_', [0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x1F]), ('/', [0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00]),
    ('(', [0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02]), (')', [0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08]),
    (':', [0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00]), ('=', [0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00]),
    ('%', [0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03]), ('²', [0x0C, 0x02, 0x04, 0x08, 0x0E, 0x00, 0x00]),
    ('×', [0x00, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x00]), ('^', [0x04, 0x0A, 0x11, 0x00, 0x00, 0x00, 0x00]),
];
/// Unknown characters render as a hollow box: visibly missing rather than silently dropped.
const BOX: [u8; 7] = [0x1F, 0x11, 0x11, 0x11, 0x11, 0x11, 0x1F];

fn glyph(c: char) -> [u8; 7] {
    let find = |c: char| FONT.iter().find(|(g, _)| *g == c).map(|(_, rows)| *rows);
    find(c).or_else(|| find(c.to_ascii_lowercase())).unwrap_or(BOX)
}

pub(crate) fn text_width(s: &str, scale: u32) -> i64 {
    (s.chars().count() as i64 * 6 - 1).max(0) * scale as i64
}

/// Longest prefix of `s` that fits in `max_w` pixels.
fn fit(s: &str, max_w: i64, scale: u32) -> String {
    let n = ((max_w + scale as i64) / (6 * scale as i64)).max(0) as usize;
    s.chars().take(n).collect()
}

/// Fills a rectangle, clipped to the image (so callers never need bounds checks).
pub(crate) fn fill(img: &mut RgbImage, x: i64, y: i64, w: i64, h: i64, c: Rgb<u8>) {
    let (iw, ih) = (img.width() as i64, img.height() as i64);
    for yy in y.max(0)..(y + h).min(ih) {
        for xx in x.max(0)..(x + w).min(iw) {
            img.put_pixel(xx as u32, yy as u32, c);
        }
    }
}

/// A mark one pixel wide and `len` long from (x, y), down or to the right: `DASH` pixels
/// on, `DASH` off, clipped to the image.
pub(crate) fn draw_dashes(img: &mut RgbImage, x: i64, y: i64, len: i64, down: bool) {
    for o in (0..len).step_by(2 * DASH as usize) {
        let d = DASH.min(len - o);
        if down {
            fill(img, x, y + o, 1, d, MARK);
        } else {
            fill(img, x + o, y, d, 1, MARK);
        }
    }
}

/// Draws `s` with its top-left corner at (x, y).
pub(crate) fn draw_text(img: &mut RgbImage, x: i64, y: i64, s: &str, c: Rgb<u8>, scale: u32) {
    let sc = scale as i64;
    for (i, ch) in s.chars().enumerate() {
        let gx = x + i as i64 * 6 * sc;
        for (r, bits) in glyph(ch).iter().enumerate() {
            for col in 0..5 {
                if (bits >> (4 - col)) & 1 == 1 {
                    fill(img, gx + col * sc, y + r as i64 * sc, sc, sc, c);
                }
            }
        }
    }
}

/// Pixel rectangle with inclusive bounds.
#[derive(Debug, Clone, Copy)]
struct Rect {
    l: i64,
    t: i64,
    r: i64,
    b: i64,
}

/// One-pixel border along the inside of `r`.
fn outline(img: &mut RgbImage, r: Rect, c: Rgb<u8>) {
    let (w, h) = (r.r - r.l + 1, r.b - r.t + 1);
    for (x, y, fw, fh) in [(r.l, r.t, w, 1), (r.l, r.b, w, 1), (r.l, r.t, 1, h), (r.r, r.t, 1, h)] {
        fill(img, x, y, fw, fh, c);
    }
}

/// A `size`×`size` square at (x, y), clipped to `clip`.
fn dot(img: &mut RgbImage, x: i64, y: i64, size: i64, c: Rgb<u8>, clip: Rect) {
    let (x0, y0) = ((x - (size - 1) / 2).max(clip.l), (y - (size - 1) / 2).max(clip.t));
    let (x1, y1) = ((x - (size - 1) / 2 + size - 1).min(clip.r), (y - (size - 1) / 2 + size - 1).min(clip.b));
    fill(img, x0, y0, x1 - x0 + 1, y1 - y0 + 1, c);
}

/// Bresenham line of `LINE_W`-pixel squares; no anti-aliasing keeps palette colours exact.
fn line(img: &mut RgbImage, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb<u8>, clip: Rect) {
    let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
    let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
    let (mut x, mut y, mut err) = (x0, y0, dx + dy);
    loop {
        dot(img, x, y, LINE_W, c, clip);
        if x == x1 && y == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// A point as plotted: x finite and y finite (and positive, then log10'd, on a log axis).
fn valid((x, y): (f64, f64), log_y: bool) -> Option<(f64, f64)> {
    let ok = x.is_finite() && y.is_finite() && (!log_y || y > 0.0);
    ok.then(|| (x, if log_y { y.log10() } else { y }))
}

/// Min/max of `vals` widened by `pad` × span. A zero span (one point, flat curve) is padded
/// so the mapping never divides by zero; no values at all give [0, 1].
fn data_range(vals: impl Iterator<Item = f64>, pad: f64, log_y: bool) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if lo > hi {
        return (0.0, 1.0);
    }
    let span = hi - lo;
    if !span.is_finite() {
        return (lo, hi); // overflowing span: plot squashed, but never NaN coordinates
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

/// Ticks at multiples of the smallest step m·10^e (m in `mantissas`, e ≥ `min_exp`) that
/// puts at most [`TICKS`] ticks inside [lo, hi]. Values are computed as i·m / 10^-e so that
/// e.g. 0.3 comes out as 0.3, not 0.30000000000000004.
fn ticks_with(lo: f64, hi: f64, mantissas: &[f64], min_exp: i32) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite() && hi > lo && (hi - lo).is_finite()) {
        return Vec::new();
    }
    let start = (((hi - lo) / TICKS as f64).log10().floor() as i32 - 1).max(min_exp);
    for e in start..start + 40 {
        for &m in mantissas {
            let scale = |i: f64| {
                if e < 0 {
                    i * m / 10f64.powi(-e)
                } else {
                    i * m * 10f64.powi(e)
                }
            };
            let step = scale(1.0);
            let (i0, i1) = ((lo / step - 1e-9).ceil(), (hi / step + 1e-9).floor());
            if i1 - i0 + 1.0 <= TICKS as f64 {
                return (i0 as i64..=i1 as i64).map(|i| scale(i as f64) + 0.0).collect();
            }
        }
    }
    Vec::new()
}

/// Linear ticks: steps of 1, 2, 2.5 or 5 × 10^k (2.5 gives the familiar 0/250/500/750/1000).
fn nice_ticks(lo: f64, hi: f64) -> Vec<f64> {
    ticks_with(lo, hi, &[1.0, 2.0, 2.5, 5.0], i32::MIN)
}

/// Log ticks (in log10 units) at whole decades, stepping 1, 2, 5… decades; a range under two
/// decades falls back to linear nice ticks of the values themselves.
fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let t = ticks_with(lo, hi, &[1.0, 2.0, 5.0], 0);
    if t.len() >= 2 {
        return t;
    }
    let lin = nice_ticks(10f64.powf(lo), 10f64.powf(hi));
    lin.into_iter().filter(|v| *v > 0.0).map(f64::log10).collect()
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

/// Data-to-pixel mapping of one panel's plot area.
struct Axes {
    area: Rect,
    x: (f64, f64),
    y: (f64, f64),
}

impl Axes {
    /// Pixel of a (x, transformed y) point. Every plotted point lies in the data range by
    /// construction; the clamp only guards against pathological (overflowing) spans.
    fn map(&self, (x, y): (f64, f64)) -> (i64, i64) {
        let a = self.area;
        let fx = (x - self.x.0) / (self.x.1 - self.x.0) * (a.r - a.l) as f64;
        let fy = (y - self.y.0) / (self.y.1 - self.y.0) * (a.b - a.t) as f64;
        ((a.l + fx.round() as i64).clamp(a.l - 1, a.r + 1), (a.b - fy.round() as i64).clamp(a.t - 1, a.b + 1))
    }
}

/// Panel geometry: axes, x ticks, y ticks (log10 units when `log_y`), their labels, and
/// whether any point is plottable.
struct Layout {
    axes: Axes,
    xt: Vec<f64>,
    yt: Vec<f64>,
    ylabels: Vec<String>,
    has_data: bool,
}

fn layout(p: &Panel, ox: i64, oy: i64, w: i64, h: i64) -> Layout {
    let pts: Vec<(f64, f64)> =
        p.series.iter().flat_map(|s| s.points.iter()).filter_map(|&q| valid(q, p.log_y)).collect();
    let x = data_range(pts.iter().map(|q| q.0), 0.0, false);
    let y = data_range(pts.iter().map(|q| q.1), 0.05, p.log_y);
    let (xt, yt) = (nice_ticks(x.0, x.1), if p.log_y { log_ticks(y.0, y.1) } else { nice_ticks(y.0, y.1) });
    let ylabels: Vec<String> = yt.iter().map(|&t| fmt_num(if p.log_y { 10f64.powf(t) } else { t })).collect();
    let gutter = ylabels.iter().map(|s| text_width(s, SCALE)).max().unwrap_or(0).max(16) + 8;
    let (l, t) = (ox + gutter, oy + 7 * TITLE_SCALE as i64 + 12);
    let (r, b) = ((ox + w - 12).max(l + 1), (oy + h - 7 * SCALE as i64 - 8).max(t + 1));
    let axes = Axes { area: Rect { l, t, r, b }, x, y };
    Layout { axes, xt, yt, ylabels, has_data: !pts.is_empty() }
}

fn draw_panel(img: &mut RgbImage, p: &Panel, ox: i64, oy: i64, w: i64, h: i64) {
    let lay = layout(p, ox, oy, w, h);
    let (ax, a) = (&lay.axes, lay.axes.area);
    let title = fit(&p.title, w - 8, TITLE_SCALE);
    draw_text(img, ox + (w - text_width(&title, TITLE_SCALE)) / 2, oy + 5, &title, INK, TITLE_SCALE);
    let ch = 7 * SCALE as i64;
    for &t in &lay.xt {
        let (x, _) = ax.map((t, ax.y.0));
        fill(img, x, a.t, 1, a.b - a.t, GRID);
        fill(img, x, a.b, 1, 4, FRAME);
        let s = fmt_num(t);
        let lx = (x - text_width(&s, SCALE) / 2).clamp(ox, (ox + w - text_width(&s, SCALE)).max(ox));
        draw_text(img, lx, a.b + 5, &s, INK, SCALE);
    }
    for (&t, s) in lay.yt.iter().zip(&lay.ylabels) {
        let (_, y) = ax.map((ax.x.0, t));
        fill(img, a.l, y, a.r - a.l, 1, GRID);
        fill(img, a.l - 3, y, 3, 1, FRAME);
        draw_text(img, a.l - 5 - text_width(s, SCALE), y - ch / 2, s, INK, SCALE);
    }
    if lay.has_data {
        for &m in p.marks.iter().filter(|m| (ax.x.0..=ax.x.1).contains(*m)) {
            let (x, _) = ax.map((m, ax.y.0));
            draw_dashes(img, x, a.t, a.b - a.t, true);
        }
    }
    outline(img, a, FRAME);
    if !lay.has_data {
        let s = "no data";
        draw_text(img, (a.l + a.r - text_width(s, SCALE)) / 2, (a.t + a.b - ch) / 2, s, INK, SCALE);
        return;
    }
    for (i, s) in p.series.iter().enumerate() {
        let c = PALETTE[i % PALETTE.len()];
        // A run is a stretch of consecutive valid points; a lone-point run gets a visible dot.
        let (mut last, mut run) = (None, 0usize);
        for q in s.points.iter().map(|&q| valid(q, p.log_y)).chain([None]) {
            match q.map(|q| ax.map(q)) {
                Some(pt) => {
                    line(img, last.unwrap_or(pt), pt, c, a);
                    (last, run) = (Some(pt), run + 1);
                }
                None => {
                    if let (Some((x, y)), 1) = (last, run) {
                        dot(img, x, y, LINE_W + 2, c, a);
                    }
                    (last, run) = (None, 0);
                }
            }
        }
    }
    // Legend last, on a white box, so curves never hide the names.
    let row = 10 * SCALE as i64;
    let n = (p.series.len() as i64).min((a.b - a.t - 6) / row).max(0) as usize;
    let names: Vec<String> = p.series.iter().take(n).map(|s| fit(&s.name, (a.r - a.l) / 2, SCALE)).collect();
    if n > 0 {
        let lw = names.iter().map(|s| text_width(s, SCALE)).max().unwrap_or(0) + 26;
        let (lx, ly) = (a.r - lw - 3, a.t + 3);
        let lb = Rect { l: lx, t: ly, r: lx + lw - 1, b: ly + n as i64 * row + 3 };
        fill(img, lx, ly, lw, lb.b - ly + 1, WHITE);
        outline(img, lb, Rgb([180, 180, 180]));
        for (i, s) in names.iter().enumerate() {
            let y = ly + 3 + i as i64 * row;
            fill(img, lx + 4, y + ch / 2 - 1, 14, 2, PALETTE[i % PALETTE.len()]);
            draw_text(img, lx + 22, y, s, INK, SCALE);
        }
    }
}

/// Draws panels in a grid of `cols` columns, each panel `panel_w × panel_h` pixels, white
/// background, and returns the image. `cols` is clamped to 1..=panels.len() so the image has
/// no empty columns; zero panels give one blank panel-sized image.
pub fn draw_panels(panels: &[Panel], cols: usize, panel_w: u32, panel_h: u32) -> RgbImage {
    let (pw, ph) = (panel_w.max(1), panel_h.max(1));
    if panels.is_empty() {
        return RgbImage::from_pixel(pw, ph, WHITE);
    }
    let cols = cols.clamp(1, panels.len());
    let rows = panels.len().div_ceil(cols);
    let mut img = RgbImage::from_pixel(pw.saturating_mul(cols as u32), ph.saturating_mul(rows as u32), WHITE);
    for (i, p) in panels.iter().enumerate() {
        let (ox, oy) = ((i % cols) as i64 * pw as i64, (i / cols) as i64 * ph as i64);
        draw_panel(&mut img, p, ox, oy, pw as i64, ph as i64);
    }
    img
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

#[cfg(test)]
mod tests {
    use super::*;

    fn series(name: &str, points: Vec<(f64, f64)>) -> Series {
        Series { name: name.into(), points }
    }
    fn panel(series: Vec<Series>, log_y: bool) -> Panel {
        Panel { title: "g_adv".into(), series, log_y, marks: vec![] }
    }

    #[test]
    fn image_is_a_grid_of_panels() {
        let ps = vec![panel(vec![], false); 3];
        assert_eq!(draw_panels(&ps, 2, 360, 240).dimensions(), (720, 480));
        assert_eq!(draw_panels(&ps, 0, 100, 50).dimensions(), (100, 150));
        assert_eq!(draw_panels(&ps, 9, 100, 50).dimensions(), (300, 50));
        let blank = draw_panels(&[], 2, 40, 30);
        assert_eq!(blank.dimensions(), (40, 30));
        assert!(blank.pixels().all(|p| *p == WHITE));
    }

    #[test]
    fn a_mark_is_a_dashed_column_inside_the_x_range_and_absent_outside_it() {
        let mut p = panel(vec![series("loss", vec![(0.0, 0.0), (10.0, 1.0)])], false);
        p.marks = vec![5.0, 12.0, -1.0];
        let img = draw_panels(std::slice::from_ref(&p), 1, 360, 240);
        let lay = layout(&p, 0, 0, 360, 240);
        let (a, (x, _)) = (lay.axes.area, lay.axes.map((5.0, 0.0)));
        let marked: Vec<(u32, u32)> =
            img.enumerate_pixels().filter(|(_, _, c)| **c == MARK).map(|(x, y, _)| (x, y)).collect();
        // Only the mark inside [0, 10] is drawn, one pixel wide.
        assert!(marked.iter().all(|&(mx, _)| mx as i64 == x), "{marked:?}");
        // Dashed: DASH pixels on, DASH off, from the top of the plot area down (the curve
        // crosses the column once, and may hide a few).
        let on = |y: i64| marked.contains(&(x as u32, y as u32));
        let (dashes, gaps) = (a.t..a.b).partition::<Vec<i64>, _>(|y| (y - a.t) % (2 * DASH) < DASH);
        assert!(dashes.iter().filter(|&&y| on(y)).count() + 6 >= dashes.len(), "{marked:?}");
        assert!(gaps.iter().all(|&y| !on(y)));
        p.marks.clear();
        assert!(!draw_panels(&[p], 1, 360, 240).pixels().any(|c| *c == MARK));
    }

    #[test]
    fn diagonal_is_drawn_and_far_corners_stay_white() {
        let p = panel(vec![series("loss", vec![(0.0, 0.0), (10.0, 10.0)])], false);
        let img = draw_panels(std::slice::from_ref(&p), 1, 360, 240);
        let lay = layout(&p, 0, 0, 360, 240);
        let a = lay.axes.area;
        // Stop at t = 8: the legend box covers the top-right end of the diagonal.
        for i in 0..=16 {
            let (x, y) = lay.axes.map((i as f64 * 0.5, i as f64 * 0.5));
            assert!((a.l..=a.r).contains(&x) && (a.t..=a.b).contains(&y));
            let hit =
                (-1..=1).any(|dx| (-1..=1).any(|dy| *img.get_pixel((x + dx) as u32, (y + dy) as u32) == PALETTE[0]));
            assert!(hit, "no curve pixel near ({x}, {y})");
        }
        assert_eq!(*img.get_pixel(a.l as u32 + 3, a.t as u32 + 3), WHITE);
        assert_eq!(*img.get_pixel(a.r as u32 - 3, a.b as u32 - 3), WHITE);
        // The title and tick labels put ink outside the plot area.
        assert!((0..a.t as u32).any(|y| (0..360).any(|x| *img.get_pixel(x, y) == INK)));
        assert!((0..a.l as u32).any(|x| (a.t as u32..a.b as u32).any(|y| *img.get_pixel(x, y) == INK)));
    }

    #[test]
    fn degenerate_inputs_do_not_panic_and_nan_leaves_a_gap() {
        let gap = panel(vec![series("d_r1", vec![(0.0, 0.0), (1.0, f64::NAN), (2.0, 0.0)])], false);
        let img = draw_panels(std::slice::from_ref(&gap), 1, 360, 240);
        let lay = layout(&gap, 0, 0, 360, 240);
        let (x, y) = lay.axes.map((1.0, 0.0));
        assert_ne!(*img.get_pixel(x as u32, y as u32), PALETTE[0], "NaN must not be bridged");
        let (x, y) = lay.axes.map((0.0, 0.0));
        assert_eq!(*img.get_pixel(x as u32 + 1, y as u32), PALETTE[0], "lone point drawn as a dot");
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
        ];
        for (w, h) in [(360, 240), (10, 10), (1, 1)] {
            assert_eq!(draw_panels(&ps, 4, w, h).dimensions(), (4 * w, 2 * h));
        }
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
    fn ticks_are_nice() {
        assert_eq!(nice_ticks(0.0, 1000.0), [0.0, 250.0, 500.0, 750.0, 1000.0]);
        assert_eq!(nice_ticks(0.0, 0.4), [0.0, 0.1, 0.2, 0.3, 0.4]);
        assert_eq!(nice_ticks(-0.5, 10.5), [0.0, 2.5, 5.0, 7.5, 10.0]);
        assert_eq!(nice_ticks(3.0, 17.0), [5.0, 7.5, 10.0, 12.5, 15.0]);
        assert_eq!(nice_ticks(-3.0, 1.0), [-3.0, -2.0, -1.0, 0.0, 1.0]);
        assert_eq!(nice_ticks(0.0, 20000.0), [0.0, 5000.0, 10000.0, 15000.0, 20000.0]);
        assert!(nice_ticks(1.0, 1.0).is_empty() && nice_ticks(f64::NAN, 1.0).is_empty());
        assert_eq!(log_ticks(-4.2, -0.8), [-4.0, -3.0, -2.0, -1.0]);
        assert_eq!(log_ticks(-12.0, 0.0), [-10.0, -5.0, 0.0]);
        // Under two decades: linear ticks 1.5, 2, 2.5, 3 of the values 10^0.1 … 10^0.5.
        let t: Vec<f64> = log_ticks(0.1, 0.5).iter().map(|t| 10f64.powf(*t)).collect();
        assert_eq!(t.len(), 4);
        assert!(t.iter().zip([1.5, 2.0, 2.5, 3.0]).all(|(a, b)| (a - b).abs() < 1e-12));
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

    #[test]
    fn font_covers_label_characters() {
        for c in "abcdefghijklmnopqrstuvwxyz0123456789.,-+_/():=%²×^M".chars() {
            assert_ne!(glyph(c), BOX, "{c:?}");
        }
        assert_eq!(glyph('G'), glyph('g'));
        assert_eq!(glyph('@'), BOX);
        assert_eq!(glyph(' '), [0; 7]);
        assert_eq!(text_width("1e-4", 2), 46);
        assert_eq!(fit("images/s", 23, 1), "imag");
    }
}
