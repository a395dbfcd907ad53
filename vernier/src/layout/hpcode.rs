//! HP code: QR-like marker made of a periodic dot grid, three finder squares and an ID
//! (docs/design.md#layout-hpcode).

use super::bitmap::BitmapLayout;
use super::periodic::visit_grid_dots;
use super::{raised_cosine, Layout, Metadata, Rect};
use crate::error::{Error, Result};

/// Side of a finder square, in half-period cells.
const FINDER_CELLS: usize = 7;
/// Dot columns `0..ID_FIRST_DOT_COL` of the top row belong to the top-left finder (+ gap).
const ID_FIRST_DOT_COL: usize = 4;
/// Smallest supported number of dots per side: the three finders (7 cells each) must not
/// overlap and leave room for at least one ID bit.
const MIN_SIZE: usize = 9;

/// HP code marker: `n × n` dots at period `P` (n odd), plus three QR-style finder squares
/// (top-left, top-right, bottom-left) and an ID written in the top dot row.
///
/// In the half-period grid (cells of side `P/2`) the marker is `W = 2n − 1` cells wide; dots
/// sit on even-even cells. The pattern origin is the centre of the central dot (= marker
/// centre); dot `(r, c)` is centred at pattern coordinates `((c − (n−1)/2)·P, (r − (n−1)/2)·P)`
/// and cell `(row, col)` spans layout `[col·P/2, (col+1)·P/2) × [row·P/2, (row+1)·P/2)`.
///
/// **ID encoding**: bit `k` (k = 0 least significant) is the dot of row 0 at dot column
/// `c = n − 5 − k`, for `k < n − 8` (= `(W − 15)/2` bits); a **missing** dot means bit = 1.
///
/// Unlike the original, the exported rectangles include the top-left finder's corner cell,
/// all three finders are always drawn, and rectangles and intensity describe the same cells.
#[derive(Clone, Debug, PartialEq)]
pub struct HpCodeLayout {
    period: f64,
    size: usize,
    id: u64,
    metadata: Metadata,
}

impl HpCodeLayout {
    /// Marker with `size` dots per side (odd, ≥ 9; JSON key `size`) at `period` (pattern
    /// units, > 0), ID 0.
    pub fn new(period: f64, size: usize) -> Result<Self> {
        if !(period.is_finite() && period > 0.0) {
            return Err(Error::pattern(
                "period",
                format!("must be a positive number, got {period}"),
            ));
        }
        if size % 2 == 0 || size < MIN_SIZE {
            return Err(Error::pattern(
                "size",
                format!("must be an odd integer ≥ {MIN_SIZE} (dots per side), got {size}"),
            ));
        }
        Ok(HpCodeLayout {
            period,
            size,
            id: 0,
            metadata: Metadata::default(),
        })
    }

    /// Marker `code_size` cells wide (`W = 2n − 1`, the detector's "numberHalfPeriods";
    /// `W ≡ 1 (mod 4)`, ≥ 17, e.g. 33 or 37) at `period` (pattern units), ID 0.
    pub fn from_code_size(period: f64, code_size: usize) -> Result<Self> {
        if code_size % 4 != 1 || code_size < 2 * MIN_SIZE - 1 {
            return Err(Error::pattern(
                "numberHalfPeriods",
                format!(
                    "must be ≡ 1 (mod 4) and ≥ {}, got {code_size}",
                    2 * MIN_SIZE - 1
                ),
            ));
        }
        Self::new(period, code_size.div_ceil(2))
    }

    /// Sets the marker ID; errors (key `id`) when `id` does not fit in
    /// [`HpCodeLayout::id_bit_count`] bits.
    pub fn with_id(mut self, id: u64) -> Result<Self> {
        let bits = self.id_bit_count();
        if bits < 64 && id >> bits != 0 {
            return Err(Error::pattern(
                "id",
                format!(
                    "{id} does not fit in the {bits} ID bits of a {}-cell marker (max {})",
                    self.code_size(),
                    (1u64 << bits) - 1
                ),
            ));
        }
        self.id = id;
        Ok(self)
    }

    /// Replaces the metadata (builder style).
    pub fn with_metadata(mut self, metadata: Metadata) -> Self {
        self.metadata = metadata;
        self
    }

    /// Number of dots per side `n`.
    pub fn size(&self) -> usize {
        self.size
    }
    /// Width in half-period cells `W = 2n − 1`.
    pub fn code_size(&self) -> usize {
        2 * self.size - 1
    }
    /// Marker ID.
    pub fn id(&self) -> u64 {
        self.id
    }
    /// Number of ID bits `n − 8 = (W − 15)/2`.
    pub fn id_bit_count(&self) -> usize {
        self.size - 8
    }
    /// Half-period cell `(row, col)` holding ID bit `k` (`k < id_bit_count()`): row 0,
    /// column `2·(n − 5 − k)`. `None` when `k` is out of range.
    pub fn id_bit_cell(&self, k: usize) -> Option<(usize, usize)> {
        (k < self.id_bit_count()).then(|| (0, 2 * (self.size - 5 - k)))
    }
    /// Side `P·(n − ½)` of the square layout, pattern units.
    pub fn width(&self) -> f64 {
        self.period * (self.size as f64 - 0.5)
    }

    /// True when dot `(row, col)` is removed to encode an ID bit equal to 1.
    fn is_id_cleared(&self, row: usize, col: usize) -> bool {
        if row != 0 || col < ID_FIRST_DOT_COL || col > self.size - 5 {
            return false;
        }
        let k = self.size - 5 - col;
        k < 64 && (self.id >> k) & 1 == 1
    }

    /// `Some(true)` on a finder ring or centre cell, `Some(false)` in a finder's gap, `None`
    /// outside the three finder squares.
    fn finder_cell(&self, row: usize, col: usize) -> Option<bool> {
        let far = self.code_size() - FINDER_CELLS;
        [(0, 0), (0, far), (far, 0)]
            .into_iter()
            .find(|&(r0, c0)| {
                (r0..r0 + FINDER_CELLS).contains(&row) && (c0..c0 + FINDER_CELLS).contains(&col)
            })
            .map(|(r0, c0)| {
                let (r, c) = (row - r0, col - c0);
                let ring = r == 0 || r == 6 || c == 0 || c == 6;
                let centre = (2..=4).contains(&r) && (2..=4).contains(&c);
                ring || centre
            })
    }

    /// True when half-period cell `(row, col)` (`< W`) is fabricated material: finder ring or
    /// centre, or a dot on an even-even cell that no ID bit removes. False outside the marker.
    pub fn cell_is_set(&self, row: usize, col: usize) -> bool {
        let w = self.code_size();
        if row >= w || col >= w {
            return false;
        }
        match self.finder_cell(row, col) {
            Some(set) => set,
            None => row % 2 == 0 && col % 2 == 0 && !self.is_id_cleared(row / 2, col / 2),
        }
    }

    /// The marker as a `W × W` half-period [`BitmapLayout`] (same period and metadata), the
    /// form used to edit markers or build bitmap templates.
    pub fn to_bitmap(&self) -> BitmapLayout {
        let w = self.code_size();
        let cells = (0..w * w).map(|i| self.cell_is_set(i / w, i % w)).collect();
        BitmapLayout::from_cells_unchecked(self.period, w, w, cells)
            .with_metadata(self.metadata.clone())
    }
}

impl Layout for HpCodeLayout {
    fn class_name(&self) -> &'static str {
        "HPCodePattern"
    }
    fn period(&self) -> f64 {
        self.period
    }
    fn bounds(&self) -> Rect {
        let w = self.width();
        Rect::new(-w / 2.0, -w / 2.0, w, w)
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        let half_width = self.width() / 2.0;
        if !(x.abs() <= half_width && y.abs() <= half_width) {
            return 0.0; // also rejects NaN
        }
        let p = self.period;
        // Half-period cell under the point (docs/design.md#layout-hpcode); in [0, W] here.
        let cell = |v: f64| ((v + half_width - p / 4.0) / (p / 2.0)).round().max(0.0) as usize;
        if self.finder_cell(cell(y), cell(x)) == Some(true) {
            return 1.0;
        }
        // Nearest dot; an ID-cleared dot leaves its whole period cell dark.
        let centre = (self.size - 1) as f64 / 2.0;
        let dot = |v: f64| (v / p + centre).round().max(0.0) as usize;
        if self.is_id_cleared(dot(y), dot(x)) {
            return 0.0;
        }
        raised_cosine(x, y, p)
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let half = self.period / 2.0;
        let first = -self.width() / 2.0 + half / 2.0;
        let w = self.code_size();
        // Rectangles are exactly the set half-period cells, so they agree with the intensity.
        visit_grid_dots(
            half,
            half,
            (first, first),
            (w, w),
            region,
            &mut |r, c| self.cell_is_set(r, c),
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

    #[test]
    fn geometry_and_rect_count() {
        let l = HpCodeLayout::new(10.0, 17).unwrap();
        assert_eq!(l.code_size(), 33);
        assert_eq!(l.width(), 165.0);
        assert_eq!(l.id_bit_count(), 9);
        let rects = l.rects_in(&l.bounds());
        // All 17² dots (the top-left one is the finder corner) + 17 extra cells per finder.
        assert_eq!(rects.len(), 17 * 17 + 3 * 17);
        assert!(
            rects.contains(&Rect::new(-82.5, -82.5, 5.0, 5.0)),
            "corner cell"
        );
        assert_eq!(l.intensity(0.0, 0.0), 1.0);
        assert_eq!(l.intensity(-80.0, -75.0), 1.0, "finder ring odd cell");
        assert!(
            (l.intensity(80.0, 80.0) - 1.0).abs() < 1e-12,
            "no bottom-right finder"
        );
        assert!(
            l.intensity(-75.0, -75.0).abs() < 1e-12,
            "finder gap keeps the cosine"
        );
        assert_eq!(l.intensity(90.0, 0.0), 0.0);
    }

    #[test]
    fn id_clears_top_row_dots() {
        let l = HpCodeLayout::from_code_size(8.0, 37)
            .unwrap()
            .with_id(0b101)
            .unwrap();
        assert_eq!(l.size(), 19);
        assert_eq!(l.id_bit_cell(0), Some((0, 28)));
        assert_eq!(l.id_bit_cell(10), Some((0, 8)));
        assert_eq!(l.id_bit_cell(11), None);
        assert!(!l.cell_is_set(0, 28) && l.cell_is_set(0, 26) && !l.cell_is_set(0, 24));
        assert_eq!(l.rects_in(&l.bounds()).len(), 19 * 19 + 3 * 17 - 2);
        // Dot (0, 14) is cleared: dark at its centre.
        let (x, y) = ((14.0 - 9.0) * 8.0, -9.0 * 8.0);
        assert_eq!(l.intensity(x, y), 0.0);
        assert!((l.intensity(x - 8.0, y) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_parameters() {
        assert!(HpCodeLayout::new(10.0, 18).is_err());
        assert!(HpCodeLayout::new(10.0, 7).is_err());
        assert!(HpCodeLayout::new(0.0, 17).is_err());
        assert!(HpCodeLayout::from_code_size(10.0, 35).is_err());
        let l = HpCodeLayout::from_code_size(10.0, 33).unwrap();
        assert!(l.clone().with_id(511).is_ok());
        let e = l.with_id(512).unwrap_err().to_string();
        assert!(e.contains("`id`") && e.contains("9 ID bits"), "{e}");
    }
}
