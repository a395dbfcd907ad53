//! Bitmap layouts: a 0/1 image on the half-period grid ([`BitmapLayout`],
//! docs/design.md#layout-bitmap; stamps are bitmaps) or one pixel per dot ([`FingerprintLayout`],
//! docs/design.md#layout-fingerprint).

use std::path::Path;

use super::periodic::visit_grid_dots;
use super::{raised_cosine, Layout, Metadata, Rect};
use crate::error::{Error, Result};

/// Checks that `period` is a positive finite number (key `period`).
fn check_period(period: f64) -> Result<()> {
    if period.is_finite() && period > 0.0 {
        Ok(())
    } else {
        Err(Error::pattern(
            "period",
            format!("must be a positive number, got {period}"),
        ))
    }
}

/// Flattens rows of 0/1 values into a row-major cell vector; errors (key `bitmap`) on an
/// empty bitmap, ragged rows or values other than 0/1. Returns `(n_rows, n_cols, cells)`.
fn flatten_rows<R: AsRef<[u8]>>(rows: &[R]) -> Result<(usize, usize, Vec<bool>)> {
    let n_cols = rows.first().map_or(0, |r| r.as_ref().len());
    if n_cols == 0 {
        return Err(Error::pattern(
            "bitmap",
            "must be a non-empty array of non-empty rows",
        ));
    }
    let mut cells = Vec::with_capacity(rows.len() * n_cols);
    for (i, row) in rows.iter().enumerate() {
        let row = row.as_ref();
        if row.len() != n_cols {
            return Err(Error::pattern(
                "bitmap",
                format!(
                    "row {i} has {} entries, expected {n_cols} like row 0",
                    row.len()
                ),
            ));
        }
        for (j, &v) in row.iter().enumerate() {
            if v > 1 {
                return Err(Error::pattern(
                    "bitmap",
                    format!("entry [{i}][{j}] must be 0 or 1, got {v}"),
                ));
            }
            cells.push(v == 1);
        }
    }
    Ok((rows.len(), n_cols, cells))
}

/// Row-major cells back into rows of 0/1 values.
fn cells_to_rows(n_cols: usize, cells: &[bool]) -> Vec<Vec<u8>> {
    cells
        .chunks(n_cols.max(1))
        .map(|row| row.iter().map(|&b| u8::from(b)).collect())
        .collect()
}

/// Binarises an image by the bitmap rule (docs/design.md#layout-bitmap): 8-bit grey (colour
/// converted to luma, alpha ignored, 16-bit scaled down), min-max normalised to [0, 1], set iff >
/// 0.5 (white = dot). Returns `(n_rows, n_cols, cells)` row-major. Errors on an empty or uniform
/// image.
pub(crate) fn binarize_image(image: &image::DynamicImage) -> Result<(usize, usize, Vec<bool>)> {
    let grey = image.to_luma8();
    let (n_cols, n_rows) = (grey.width() as usize, grey.height() as usize);
    let values = grey.as_raw();
    let (Some(&min), Some(&max)) = (values.iter().min(), values.iter().max()) else {
        return Err(Error::InvalidImage("layout image is empty".into()));
    };
    if min == max {
        return Err(Error::InvalidImage(format!(
            "layout image is uniform (all pixels = {min}): no dots can be told apart"
        )));
    }
    let range = f64::from(max - min);
    let cells = values
        .iter()
        .map(|&v| f64::from(v - min) / range > 0.5)
        .collect();
    Ok((n_rows, n_cols, cells))
}

/// Opens and decodes an image file (format guessed from its content), within the default
/// decode limits (100 MP, truncated files rejected).
pub(crate) fn read_image(path: &Path) -> Result<image::DynamicImage> {
    crate::image_file::decode_image_file(path, &crate::image_file::DecodeLimits::default())
}

/// Arbitrary binary image on the half-period grid: `n_rows × n_cols` cells of side `P/2` (both ≡ 1
/// mod 4), cell set = fabricated square (docs/design.md#layout-bitmap). Stamp markers are bitmaps.
///
/// The pattern origin is the centre of the central cell `((n_rows−1)/2, (n_cols−1)/2)`, a dot
/// position; cell `(row, col)` spans layout `[col·P/2, (col+1)·P/2) × [row·P/2, (row+1)·P/2)`.
/// Intensity is binary (no cosine profile). Well-formed periodic bitmaps put dots on even-even
/// cells and use odd cells only for solid features (finders, frames, glyphs).
#[derive(Clone, Debug, PartialEq)]
pub struct BitmapLayout {
    period: f64,
    n_rows: usize,
    n_cols: usize,
    /// Row-major, `n_rows · n_cols` cells.
    cells: Vec<bool>,
    metadata: Metadata,
}

impl BitmapLayout {
    /// Bitmap of `n_rows × n_cols` half-period cells (row-major `cells`, both dimensions ≡ 1
    /// mod 4) at `period` (pattern units, > 0). Errors name the `bitmap` or `period` key.
    pub fn new(period: f64, n_rows: usize, n_cols: usize, cells: Vec<bool>) -> Result<Self> {
        check_period(period)?;
        if n_rows % 4 != 1 || n_cols % 4 != 1 {
            return Err(Error::pattern(
                "bitmap",
                format!(
                    "dimensions must be ≡ 1 (mod 4) (e.g. 33, 37, 45, 69, 117), got {n_rows} rows × {n_cols} columns"
                ),
            ));
        }
        if cells.len() != n_rows * n_cols {
            return Err(Error::pattern(
                "bitmap",
                format!("{} cells given for {n_rows} × {n_cols}", cells.len()),
            ));
        }
        Ok(Self::from_cells_unchecked(period, n_rows, n_cols, cells))
    }

    /// Constructor for callers that already guarantee the invariants of [`BitmapLayout::new`].
    pub(crate) fn from_cells_unchecked(
        period: f64,
        n_rows: usize,
        n_cols: usize,
        cells: Vec<bool>,
    ) -> Self {
        BitmapLayout {
            period,
            n_rows,
            n_cols,
            cells,
            metadata: Metadata::default(),
        }
    }

    /// Bitmap from rows of 0/1 values (all rows the same length), as in the JSON `bitmap` key.
    pub fn from_rows<R: AsRef<[u8]>>(period: f64, rows: &[R]) -> Result<Self> {
        let (n_rows, n_cols, cells) = flatten_rows(rows)?;
        Self::new(period, n_rows, n_cols, cells)
    }

    /// Bitmap from an image, one pixel per half-period cell: grey, min-max normalised,
    /// pixel > 0.5 = set (white = dot).
    pub fn from_image(period: f64, image: &image::DynamicImage) -> Result<Self> {
        let (n_rows, n_cols, cells) = binarize_image(image)?;
        Self::new(period, n_rows, n_cols, cells)
    }

    /// Bitmap from an image file (PNG, JPEG, TIFF, PNM; 8/16-bit, grey/RGB/RGBA), see
    /// [`BitmapLayout::from_image`].
    pub fn from_image_file(period: f64, path: impl AsRef<Path>) -> Result<Self> {
        Self::from_image(period, &read_image(path.as_ref())?)
    }

    /// Replaces the metadata (builder style).
    pub fn with_metadata(mut self, metadata: Metadata) -> Self {
        self.metadata = metadata;
        self
    }

    /// Number of half-period cell rows `Hb`.
    pub fn cell_rows(&self) -> usize {
        self.n_rows
    }
    /// Number of half-period cell columns `Wb`.
    pub fn cell_cols(&self) -> usize {
        self.n_cols
    }
    /// Whether cell `(row, col)` is set; false outside the bitmap.
    pub fn cell(&self, row: usize, col: usize) -> bool {
        row < self.n_rows
            && col < self.n_cols
            && self.cells.get(row * self.n_cols + col) == Some(&true)
    }
    /// Row-major cells (`cell_rows() · cell_cols()` values).
    pub fn cells(&self) -> &[bool] {
        &self.cells
    }
    /// The cells as rows of 0/1 values (the JSON `bitmap` form).
    pub fn rows(&self) -> Vec<Vec<u8>> {
        cells_to_rows(self.n_cols, &self.cells)
    }
    /// Layout width `Wb·P/2`, pattern units.
    pub fn width(&self) -> f64 {
        self.n_cols as f64 * self.period / 2.0
    }
    /// Layout height `Hb·P/2`, pattern units.
    pub fn height(&self) -> f64 {
        self.n_rows as f64 * self.period / 2.0
    }
}

impl Layout for BitmapLayout {
    fn class_name(&self) -> &'static str {
        "BitmapPattern"
    }
    fn period(&self) -> f64 {
        self.period
    }
    fn bounds(&self) -> Rect {
        let (w, h) = (self.width(), self.height());
        Rect::new(-w / 2.0, -h / 2.0, w, h)
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        let half = self.period / 2.0;
        let col = ((x + self.width() / 2.0) / half).floor();
        let row = ((y + self.height() / 2.0) / half).floor();
        // `!(>= 0)` also rejects NaN; `as usize` saturates, and `cell` bounds-checks.
        if !(col >= 0.0 && row >= 0.0) {
            return 0.0;
        }
        if self.cell(row as usize, col as usize) {
            1.0
        } else {
            0.0
        }
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let half = self.period / 2.0;
        let first = (
            -self.width() / 2.0 + half / 2.0,
            -self.height() / 2.0 + half / 2.0,
        );
        visit_grid_dots(
            half,
            half,
            first,
            (self.n_rows, self.n_cols),
            region,
            &mut |r, c| self.cell(r, c),
            visit,
        );
    }
    fn metadata(&self) -> &Metadata {
        &self.metadata
    }
}

/// Binary image where **each pixel is one dot** of a period-`P` grid
/// (docs/design.md#layout-fingerprint): `n_rows × n_cols` dots (both odd), dot side `P/2`, set
/// pixel = dot present.
///
/// Geometry as [`super::PeriodicLayout`]: pattern origin at the centre of the central dot,
/// dot `(r, c)` centred at `((c − (n_cols−1)/2)·P, (r − (n_rows−1)/2)·P)`.
///
/// Differences from the original, on purpose: dimensions need only be **odd** (so that the
/// origin is a dot centre, where the raised-cosine phase is 0), not ≡ 1 (mod 4); and the
/// intensity is the raised cosine of period `P` (not `P/2`) over the `P × P` cell of each
/// present dot, 0 elsewhere — the periodic intensity with absent dots removed.
#[derive(Clone, Debug, PartialEq)]
pub struct FingerprintLayout {
    period: f64,
    n_rows: usize,
    n_cols: usize,
    /// Row-major, `n_rows · n_cols` dots.
    dots: Vec<bool>,
    metadata: Metadata,
}

impl FingerprintLayout {
    /// Fingerprint of `n_rows × n_cols` dots (row-major `dots`, both dimensions odd) at
    /// `period` (pattern units, > 0). Errors name the `bitmap` or `period` key.
    pub fn new(period: f64, n_rows: usize, n_cols: usize, dots: Vec<bool>) -> Result<Self> {
        check_period(period)?;
        if n_rows % 2 == 0 || n_cols % 2 == 0 {
            return Err(Error::pattern(
                "bitmap",
                format!(
                    "dimensions must be odd (the pattern origin is the central dot), got {n_rows} rows × {n_cols} columns"
                ),
            ));
        }
        if dots.len() != n_rows * n_cols {
            return Err(Error::pattern(
                "bitmap",
                format!("{} dots given for {n_rows} × {n_cols}", dots.len()),
            ));
        }
        Ok(FingerprintLayout {
            period,
            n_rows,
            n_cols,
            dots,
            metadata: Metadata::default(),
        })
    }

    /// Fingerprint from rows of 0/1 values (one per dot), as in the JSON `bitmap` key.
    pub fn from_rows<R: AsRef<[u8]>>(period: f64, rows: &[R]) -> Result<Self> {
        let (n_rows, n_cols, dots) = flatten_rows(rows)?;
        Self::new(period, n_rows, n_cols, dots)
    }

    /// Fingerprint from an image, one pixel per dot: grey, min-max normalised, > 0.5 = dot.
    pub fn from_image(period: f64, image: &image::DynamicImage) -> Result<Self> {
        let (n_rows, n_cols, dots) = binarize_image(image)?;
        Self::new(period, n_rows, n_cols, dots)
    }

    /// Fingerprint from an image file, see [`FingerprintLayout::from_image`].
    pub fn from_image_file(period: f64, path: impl AsRef<Path>) -> Result<Self> {
        Self::from_image(period, &read_image(path.as_ref())?)
    }

    /// Replaces the metadata (builder style).
    pub fn with_metadata(mut self, metadata: Metadata) -> Self {
        self.metadata = metadata;
        self
    }

    /// Number of dot rows.
    pub fn n_rows(&self) -> usize {
        self.n_rows
    }
    /// Number of dot columns.
    pub fn n_cols(&self) -> usize {
        self.n_cols
    }
    /// Whether dot `(row, col)` is present; false outside the grid.
    pub fn dot(&self, row: usize, col: usize) -> bool {
        row < self.n_rows
            && col < self.n_cols
            && self.dots.get(row * self.n_cols + col) == Some(&true)
    }
    /// The dots as rows of 0/1 values (the JSON `bitmap` form).
    pub fn rows(&self) -> Vec<Vec<u8>> {
        cells_to_rows(self.n_cols, &self.dots)
    }
    /// Dot side `P/2`, pattern units.
    pub fn dot_size(&self) -> f64 {
        self.period / 2.0
    }
    /// Layout width `P·(n_cols − ½)`, pattern units.
    pub fn width(&self) -> f64 {
        self.period * (self.n_cols as f64 - 0.5)
    }
    /// Layout height `P·(n_rows − ½)`, pattern units.
    pub fn height(&self) -> f64 {
        self.period * (self.n_rows as f64 - 0.5)
    }
}

impl Layout for FingerprintLayout {
    fn class_name(&self) -> &'static str {
        "FingerprintPattern"
    }
    fn period(&self) -> f64 {
        self.period
    }
    fn bounds(&self) -> Rect {
        let (w, h) = (self.width(), self.height());
        Rect::new(-w / 2.0, -h / 2.0, w, h)
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        if !(x.abs() <= self.width() / 2.0 && y.abs() <= self.height() / 2.0) {
            return 0.0; // also rejects NaN
        }
        // Nearest dot; non-negative inside the bounds.
        let col = (x / self.period + (self.n_cols - 1) as f64 / 2.0)
            .round()
            .max(0.0);
        let row = (y / self.period + (self.n_rows - 1) as f64 / 2.0)
            .round()
            .max(0.0);
        if self.dot(row as usize, col as usize) {
            raised_cosine(x, y, self.period)
        } else {
            0.0
        }
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let first = (
            -((self.n_cols - 1) as f64) / 2.0 * self.period,
            -((self.n_rows - 1) as f64) / 2.0 * self.period,
        );
        visit_grid_dots(
            self.period,
            self.dot_size(),
            first,
            (self.n_rows, self.n_cols),
            region,
            &mut |r, c| self.dot(r, c),
            visit,
        );
    }
    fn metadata(&self) -> &Metadata {
        &self.metadata
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn checkerboard(n_rows: usize, n_cols: usize) -> Vec<Vec<u8>> {
        (0..n_rows)
            .map(|r| {
                (0..n_cols)
                    .map(|c| u8::from(r % 2 == 0 && c % 2 == 0))
                    .collect()
            })
            .collect()
    }

    #[test]
    fn bitmap_geometry() {
        let mut rows = checkerboard(5, 9);
        rows[0][1] = 1; // a solid odd cell
        let l = BitmapLayout::from_rows(10.0, &rows).unwrap();
        assert_eq!((l.cell_rows(), l.cell_cols()), (5, 9));
        assert_eq!(l.bounds(), Rect::new(-22.5, -12.5, 45.0, 25.0));
        let rects = l.rects_in(&l.bounds());
        assert_eq!(rects.len(), 3 * 5 + 1);
        // The central cell (2, 4) is centred on the origin.
        assert!(rects.contains(&Rect::new(-2.5, -2.5, 5.0, 5.0)));
        assert_eq!(l.intensity(0.0, 0.0), 1.0);
        assert_eq!(l.intensity(5.0, 0.0), 0.0);
        assert_eq!(l.intensity(-16.0, -11.0), 1.0, "cell (0, 1)");
        assert_eq!(l.intensity(30.0, 0.0), 0.0);
        assert_eq!(l.rows(), rows);
    }

    #[test]
    fn bitmap_rejects_bad_input() {
        let e = BitmapLayout::from_rows(10.0, &checkerboard(5, 7))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`bitmap`") && e.contains("mod 4"), "{e}");
        let mut rows = checkerboard(5, 5);
        rows[2].pop();
        assert!(BitmapLayout::from_rows(10.0, &rows).is_err());
        rows[2].push(2);
        assert!(BitmapLayout::from_rows(10.0, &rows).is_err());
        assert!(BitmapLayout::from_rows(10.0, &Vec::<Vec<u8>>::new()).is_err());
        assert!(BitmapLayout::from_rows(-1.0, &checkerboard(5, 5)).is_err());
    }

    #[test]
    fn image_binarisation() {
        let mut grey = image::GrayImage::new(5, 5);
        grey.put_pixel(0, 0, image::Luma([200]));
        grey.put_pixel(4, 0, image::Luma([100]));
        grey.put_pixel(2, 2, image::Luma([101]));
        let l = BitmapLayout::from_image(1.0, &image::DynamicImage::ImageLuma8(grey)).unwrap();
        assert!(l.cell(0, 0) && l.cell(2, 2) && !l.cell(0, 4) && !l.cell(1, 1));
        let flat = image::DynamicImage::ImageLuma8(image::GrayImage::new(5, 5));
        assert!(BitmapLayout::from_image(1.0, &flat).is_err());
    }

    #[test]
    fn fingerprint_geometry() {
        let mut rows = vec![vec![1u8; 3]; 3];
        rows[1][2] = 0;
        let l = FingerprintLayout::from_rows(10.0, &rows).unwrap();
        assert_eq!(l.bounds(), Rect::new(-12.5, -12.5, 25.0, 25.0));
        let rects = l.rects_in(&l.bounds());
        assert_eq!(rects.len(), 8);
        assert!(rects.contains(&Rect::new(-12.5, -12.5, 5.0, 5.0)));
        assert_eq!(l.intensity(0.0, 0.0), 1.0);
        assert_eq!(l.intensity(10.0, 0.0), 0.0, "absent dot");
        assert!((l.intensity(-10.0, 0.0) - 1.0).abs() < 1e-12);
        assert!(l.intensity(5.0, 0.0).abs() < 1e-12, "period P, not P/2");
        assert!(FingerprintLayout::from_rows(10.0, &[vec![1u8; 4]]).is_err());
        assert!(FingerprintLayout::from_rows(10.0, &[vec![1u8; 3]]).is_ok());
    }
}
