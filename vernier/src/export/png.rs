//! PNG export (docs/design.md#export-png): 8-bit grey, one pixel per half-period cell, white = dot.

use image::GrayImage;

use super::geometry::ExportFrame;
use crate::error::{Error, Result};
use crate::pattern_file::Pattern;

/// Largest PNG written, pixels (a whole 12-bit Megarena, 24 636² px, still fits).
pub const MAX_PNG_PIXELS: u64 = 1 << 30;

/// The layout image: pixel `(row, col)` covers the half-period cell whose layout-coordinate
/// centre is `(frame.x + col·P/2 + P/4, frame.y + row·P/2 + P/4)`; it is 255 where the
/// layout intensity there exceeds 0.5, else 0.
///
/// Size: `(2·n_rows − 1) × (2·n_cols − 1)` for periodic, HP code and fingerprint layouts,
/// the bitmap itself for bitmaps and stamps, `2·(r₁ − r₀) × 2·(c₁ − c₀)` for the dot rows and
/// columns of a Megarena region of interest. Margins are not drawn (as in the original).
/// HP codes include all three complete finders and the ID.
///
/// Errors: a `CustomPattern` (not periodic, no half-period grid), or an image larger than
/// [`MAX_PNG_PIXELS`].
pub fn layout_image(pattern: &Pattern) -> Result<GrayImage> {
    if let Pattern::Custom(_) = pattern {
        return Err(Error::parameter(
            "format",
            "PNG export needs a periodic layout (one pixel per half-period cell); \
             CustomPattern has no period: export it as SVG, GDS or OASIS",
        ));
    }
    let layout = pattern.layout();
    let frame = ExportFrame::of(pattern);
    let half = layout.period() / 2.0;
    let cells = |length: f64| (length / half).round();
    let (w, h) = (cells(frame.frame.width), cells(frame.frame.height));
    if !(w >= 1.0 && h >= 1.0) || w * h > MAX_PNG_PIXELS as f64 {
        return Err(Error::parameter(
            "export",
            format!(
                "PNG of {w} × {h} pixels: must hold 1 to {MAX_PNG_PIXELS} pixels \
                 (for a Megarena, choose a smaller region of interest)"
            ),
        ));
    }
    let (w, h) = (w as u32, h as u32);
    let (ox, oy) = frame.origin;
    let x0 = frame.frame.x + half / 2.0 - ox;
    let y0 = frame.frame.y + half / 2.0 - oy;
    Ok(GrayImage::from_fn(w, h, |col, row| {
        let value = layout.intensity(x0 + f64::from(col) * half, y0 + f64::from(row) * half);
        image::Luma([if value > 0.5 { 255 } else { 0 }])
    }))
}

/// [`layout_image`] encoded as a PNG file.
pub fn write_png(pattern: &Pattern) -> Result<Vec<u8>> {
    let image = layout_image(pattern)?;
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .map_err(|e| Error::ImageWrite {
            path: "<memory>".into(),
            reason: e.to_string(),
        })?;
    Ok(bytes)
}
