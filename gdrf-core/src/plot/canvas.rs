//! Where the plots draw: plotters' bitmap backend over an [`image::RgbImage`], with its
//! text drawn here (glyphs placed at their own bounds: plotters 0.3.7's ab_glyph drawing
//! drops each glyph's left side bearing), the committed faces, and the pixel helpers the
//! report and the filmstrip use.
use std::sync::OnceLock;

use ab_glyph::{Font, FontRef, PxScale, ScaleFont};
use image::{Rgb, RgbImage};
use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, VPos};
use plotters::style::FontTransform;
use plotters_backend::{BackendColor, BackendCoord, BackendStyle, BackendTextStyle, DrawingErrorKind};

use crate::error::{Error, Result};

const SANS: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans-subset.ttf");
const MONO: &[u8] = include_bytes!("../../assets/fonts/DejaVuSansMono-subset.ttf");
/// Dashed marks: darker than the grid so they read as events, lighter than the curves.
pub(crate) const MARK: Rgb<u8> = Rgb([150, 150, 150]);
/// A dashed mark paints `DASH` pixels of every `2 × DASH`.
pub(super) const DASH: i64 = 4;
/// A text's size in pixels and face.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Lettering {
    pub px: f64,
    pub mono: bool,
}
/// Tick, legend and caption text: legible at 100 % zoom in a 360×240 panel.
pub const TEXT: Lettering = Lettering { px: 12.0, mono: false };
/// Columns of figures that must line up (the evaluation report's table).
pub const TABLE: Lettering = Lettering { px: 12.0, mono: true };
/// Panel titles, larger so that a grid of panels can be scanned at a glance.
pub(super) const TITLE: Lettering = Lettering { px: 15.0, mono: false };
/// The committed faces under plotters' sans-serif (its default for every text) and
/// monospace families, registered once per process.
pub(super) fn font(l: Lettering) -> Result<FontDesc<'static>> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        let reg = |family, bytes| plotters::style::register_font(family, FontStyle::Normal, bytes).is_ok();
        reg("sans-serif", SANS) && reg("monospace", MONO)
    });
    if !ok {
        return Err(Error::Invalid("the plots' embedded fonts (assets/fonts) do not parse".into()));
    }
    let family = if l.mono { FontFamily::Monospace } else { FontFamily::SansSerif };
    Ok(FontDesc::new(family, l.px, FontStyle::Normal))
}

pub(super) fn rgb(c: Rgb<u8>) -> RGBColor {
    RGBColor(c.0[0], c.0[1], c.0[2])
}

pub(super) fn drawing<E: std::error::Error + Send + Sync + 'static>(e: DrawingAreaErrorKind<E>) -> Error {
    Error::While { what: "drawing a plot".into(), err: Box::new(e) }
}

/// The bitmap backend over an RGB buffer, with text drawn by [`glyphs`] (every other
/// primitive is the bitmap backend's own).
pub(super) struct Canvas<'a>(BitMapBackend<'a>);

impl<'a> Canvas<'a> {
    pub(super) fn on(img: &'a mut RgbImage) -> DrawingArea<Self, Shift> {
        let dims = img.dimensions();
        Canvas(BitMapBackend::with_buffer(img, dims)).into_drawing_area()
    }
}

/// The face a text style names: monospace, or the sans face for any other family.
fn face(family: &str) -> Result<FontRef<'static>> {
    // Parsed once per process: every label and measurement of every chart asks for one.
    static FACES: OnceLock<Option<(FontRef<'static>, FontRef<'static>)>> = OnceLock::new();
    let parse = || Some((FontRef::try_from_slice(SANS).ok()?, FontRef::try_from_slice(MONO).ok()?));
    let (sans, mono) = FACES
        .get_or_init(parse)
        .as_ref()
        .ok_or_else(|| Error::Invalid("the plots' embedded fonts (assets/fonts) do not parse".into()))?;
    Ok(if family == "monospace" { mono.clone() } else { sans.clone() })
}

/// Calls `dot(x, y, coverage)` for every pixel of `text` at `px` pixels, its box's top-left
/// corner at (0, 0): glyphs on one baseline at `ascent`, each advanced and kerned from the
/// last and drawn at its own bounds (side bearings included). Returns the box's width.
fn glyphs(font: &FontRef<'_>, px: f64, text: &str, mut dot: impl FnMut(i32, i32, f32)) -> f32 {
    let scaled = font.as_scaled(PxScale::from(px as f32));
    let mut x = 0f32;
    let mut prev = None;
    for c in text.chars() {
        let id = scaled.glyph_id(c);
        if let Some(p) = prev {
            x += scaled.kern(p, id);
        }
        let glyph = id.with_scale_and_position(scaled.scale(), ab_glyph::point(x, scaled.ascent()));
        if let Some(outlined) = font.outline_glyph(glyph) {
            let b = outlined.px_bounds();
            outlined.draw(|gx, gy, cov| dot(b.min.x as i32 + gx as i32, b.min.y as i32 + gy as i32, cov));
        }
        x += scaled.h_advance(id);
        prev = Some(id);
    }
    x
}

impl DrawingBackend for Canvas<'_> {
    type ErrorType = <BitMapBackend<'static> as DrawingBackend>::ErrorType;

    fn get_size(&self) -> (u32, u32) {
        self.0.get_size()
    }
    fn ensure_prepared(&mut self) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.ensure_prepared()
    }
    fn present(&mut self) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.present()
    }
    fn draw_pixel(
        &mut self,
        p: BackendCoord,
        c: BackendColor,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_pixel(p, c)
    }
    fn draw_line<S: BackendStyle>(
        &mut self,
        from: BackendCoord,
        to: BackendCoord,
        style: &S,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_line(from, to, style)
    }
    fn draw_rect<S: BackendStyle>(
        &mut self,
        a: BackendCoord,
        b: BackendCoord,
        style: &S,
        fill: bool,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_rect(a, b, style, fill)
    }
    fn draw_path<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        path: I,
        style: &S,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_path(path, style)
    }
    fn draw_circle<S: BackendStyle>(
        &mut self,
        centre: BackendCoord,
        radius: u32,
        style: &S,
        fill: bool,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.draw_circle(centre, radius, style, fill)
    }
    fn fill_polygon<S: BackendStyle, I: IntoIterator<Item = BackendCoord>>(
        &mut self,
        vert: I,
        style: &S,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.fill_polygon(vert, style)
    }
    fn blit_bitmap(
        &mut self,
        pos: BackendCoord,
        dims: (u32, u32),
        src: &[u8],
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        self.0.blit_bitmap(pos, dims, src)
    }
    fn draw_text<T: BackendTextStyle>(
        &mut self,
        text: &str,
        style: &T,
        pos: BackendCoord,
    ) -> std::result::Result<(), DrawingErrorKind<Self::ErrorType>> {
        let colour = style.color();
        if colour.alpha == 0.0 {
            return Ok(());
        }
        if !matches!(style.transform(), FontTransform::None) {
            return self.0.draw_text(text, style, pos); // rotated text: none is drawn here
        }
        let font = face(style.family().as_str()).map_err(|e| DrawingErrorKind::FontError(Box::new(e)))?;
        let px = style.size();
        let width = glyphs(&font, px, text, |_, _, _| {}).round() as i32;
        let dx = match style.anchor().h_pos {
            HPos::Left => 0,
            HPos::Right => -width,
            HPos::Center => -width / 2,
        };
        let dy = match style.anchor().v_pos {
            VPos::Top => 0,
            VPos::Center => -(px as i32) / 2,
            VPos::Bottom => -(px as i32),
        };
        let (w, h) = self.get_size();
        let mut result = Ok(());
        glyphs(&font, px, text, |x, y, cov| {
            let (x, y) = (pos.0 + dx + x, pos.1 + dy + y);
            if result.is_ok() && x >= 0 && y >= 0 && x < w as i32 && y < h as i32 {
                result = self.0.draw_pixel((x, y), colour.mix(cov.clamp(0.0, 1.0) as f64));
            }
        });
        result
    }
}

/// Width in pixels of `s` in lettering `l`.
pub fn text_width(s: &str, l: Lettering) -> Result<i64> {
    let family = if l.mono { "monospace" } else { "sans-serif" };
    Ok(glyphs(&face(family)?, l.px, s, |_, _, _| {}).round() as i64)
}

/// Longest prefix of `s` that fits in `max_w` pixels in lettering `l`.
pub(super) fn fit(s: &str, max_w: i64, l: Lettering) -> Result<String> {
    let mut out = String::new();
    for c in s.chars() {
        out.push(c);
        if text_width(&out, l)? > max_w {
            out.pop();
            break;
        }
    }
    Ok(out)
}

/// Draws `s` with its top-left corner at (x, y) in lettering `l`.
pub fn draw_text(img: &mut RgbImage, x: i64, y: i64, s: &str, c: Rgb<u8>, l: Lettering) -> Result<()> {
    let root = Canvas::on(img);
    let colour = rgb(c);
    root.draw(&Text::new(s.to_string(), (x as i32, y as i32), font(l)?.color(&colour))).map_err(drawing)?;
    root.present().map_err(drawing)
}

/// Fills a rectangle, clipped to the image (so callers never need bounds checks).
pub fn fill(img: &mut RgbImage, x: i64, y: i64, w: i64, h: i64, c: Rgb<u8>) {
    let (iw, ih) = (img.width() as i64, img.height() as i64);
    for yy in y.max(0)..(y + h).min(ih) {
        for xx in x.max(0)..(x + w).min(iw) {
            img.put_pixel(xx as u32, yy as u32, c);
        }
    }
}

/// A mark one pixel wide and `len` long from (x, y), down or to the right: `DASH` pixels
/// on, `DASH` off, clipped to the image; the same dashes as the panels' marks.
pub fn draw_dashes(img: &mut RgbImage, x: i64, y: i64, len: i64, down: bool) {
    for o in (0..len).step_by(2 * DASH as usize) {
        let d = DASH.min(len - o);
        if down {
            fill(img, x, y + o, 1, d, MARK);
        } else {
            fill(img, x + o, y, d, 1, MARK);
        }
    }
}
