//! Megarena absolute 2-D encoded dot grid (docs/design.md#layout-megarena).

use super::periodic::visit_grid_dots;
use super::{raised_cosine, Layout, Metadata, Rect};
use crate::error::{Error, Result};
use crate::megarena_sequence::LineSequence;

/// Square `L × L` dot grid whose rows and columns are switched on/off by a line sequence `s`
/// (docs/design.md#layout-megarena).
///
/// Dot `(r, c)` exists iff `s[r] = 1`, `s[c] = 1` and not (`r ≡ 0` and `c ≡ 0 (mod 3)`).
/// The **pattern origin is the centre of dot (0, 0)**: dot `(r, c)` is centred at pattern
/// coordinates `(c·P, r·P)`; the layout origin (top-left of the bounding box) is at pattern
/// `(−P/4, −P/4)`. All lengths are in pattern units.
///
/// A region of interest `(x₀, y₀, w, h)` (layout coordinates) restricts the exported
/// rectangles ([`Layout::visit_rects`]) to dot columns `int(x₀/P) ≤ c < int((x₀+w)/P)` and
/// likewise rows; it does not affect [`Layout::intensity`] or [`Layout::bounds`]. The default,
/// `(0, 0, L·P, L·P)`, keeps every dot (the bounding box itself, `L·P − P/2` wide, would drop
/// the last row and column under that rule).
#[derive(Clone, Debug, PartialEq)]
pub struct MegarenaLayout {
    period: f64,
    sequence: LineSequence,
    dot_size: f64,
    /// Region of interest in layout coordinates; all dots by default.
    region_of_interest: Rect,
    metadata: Metadata,
}

impl MegarenaLayout {
    /// The generated layout of code depth `code_depth` (4..=12) at `period` (pattern units,
    /// > 0), dots of side `period / 2`, region of interest = all dots.
    pub fn new(period: f64, code_depth: u32) -> Result<Self> {
        Self::from_sequence(period, LineSequence::generated(code_depth)?)
    }

    /// Layout from an explicit line sequence (generated or user-supplied), dots of side
    /// `period / 2`, region of interest = all dots.
    pub fn from_sequence(period: f64, sequence: LineSequence) -> Result<Self> {
        if !(period.is_finite() && period > 0.0) {
            return Err(Error::pattern(
                "period",
                format!("must be a positive number, got {period}"),
            ));
        }
        // `L·P` (not the width `L·P − P/2`): the truncating ROI rule
        // (docs/design.md#layout-megarena) then keeps the last row and column.
        let side = period * sequence.len() as f64;
        Ok(MegarenaLayout {
            period,
            sequence,
            dot_size: period / 2.0,
            region_of_interest: Rect::new(0.0, 0.0, side, side),
            metadata: Metadata::default(),
        })
    }

    /// Sets the dot side `dot_size` (pattern units, `0 < dot_size ≤ period`).
    pub fn with_dot_size(mut self, dot_size: f64) -> Result<Self> {
        if !(dot_size.is_finite() && dot_size > 0.0 && dot_size <= self.period) {
            return Err(Error::pattern(
                "dotSize",
                format!("must be in (0, period], got {dot_size}"),
            ));
        }
        self.dot_size = dot_size;
        Ok(self)
    }

    /// Sets the region of interest `(x₀, y₀, w, h)` in **layout coordinates** (origin at the
    /// top-left corner of the bounding box); `w, h ≥ 0`, all finite.
    pub fn with_region_of_interest(mut self, roi: Rect) -> Result<Self> {
        let finite = [roi.x, roi.y, roi.width, roi.height]
            .iter()
            .all(|v| v.is_finite());
        if !finite || roi.width < 0.0 || roi.height < 0.0 {
            return Err(Error::pattern(
                "regionOfInterest",
                format!(
                    "must be [x, y, w, h] with finite values and w, h ≥ 0, got [{}, {}, {}, {}]",
                    roi.x, roi.y, roi.width, roi.height
                ),
            ));
        }
        self.region_of_interest = roi;
        Ok(self)
    }

    /// Replaces the metadata (builder style).
    pub fn with_metadata(mut self, metadata: Metadata) -> Self {
        self.metadata = metadata;
        self
    }

    /// The line sequence `s`.
    pub fn sequence(&self) -> &LineSequence {
        &self.sequence
    }
    /// Code depth `d` of the line sequence.
    pub fn code_depth(&self) -> u32 {
        self.sequence.code_depth()
    }
    /// Number of dot rows = number of dot columns = `L`.
    pub fn n_dots(&self) -> usize {
        self.sequence.len()
    }
    /// Dot side, pattern units.
    pub fn dot_size(&self) -> f64 {
        self.dot_size
    }
    /// Region of interest `(x₀, y₀, w, h)`, layout coordinates.
    pub fn region_of_interest(&self) -> Rect {
        self.region_of_interest
    }
    /// Side of the square layout `L·P − P/2`, pattern units.
    pub fn width(&self) -> f64 {
        self.period * (self.n_dots() as f64 - 0.5)
    }
    /// True when dot `(row, col)` is fabricated (false outside the grid).
    pub fn dot_exists(&self, row: usize, col: usize) -> bool {
        self.sequence.is_set(row) && self.sequence.is_set(col) && !(row % 3 == 0 && col % 3 == 0)
    }

    /// Dot index range `[first, end)` of the region of interest along one axis
    /// (`start`, `length` in layout coordinates), as in docs/design.md#layout-megarena.
    fn roi_range(&self, start: f64, length: f64) -> (usize, usize) {
        let n = self.n_dots();
        // Saturating float→int casts: negative → 0, huge → usize::MAX, then clamped to n.
        let first = ((start / self.period).trunc().max(0.0) as usize).min(n);
        // The tolerance absorbs rounding in `(L·P)/P` for the default ROI.
        let end = (((start + length) / self.period + 1e-9).trunc().max(0.0) as usize).min(n);
        (first, end.max(first))
    }
}

impl Layout for MegarenaLayout {
    fn class_name(&self) -> &'static str {
        "MegarenaPattern"
    }
    fn period(&self) -> f64 {
        self.period
    }
    fn bounds(&self) -> Rect {
        let quarter = self.period / 4.0;
        Rect::new(-quarter, -quarter, self.width(), self.width())
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        let half = self.period / 2.0;
        if !(x >= -half && y >= -half) {
            return 0.0; // also rejects NaN
        }
        let col = (x / self.period + 0.5).floor();
        let row = (y / self.period + 0.5).floor();
        let n = self.n_dots() as f64;
        if col >= n || row >= n {
            return 0.0;
        }
        // Both are in [0, n) here, so the casts are exact.
        if self.dot_exists(row as usize, col as usize) {
            raised_cosine(x, y, self.period)
        } else {
            0.0
        }
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let roi = self.region_of_interest;
        let (c0, c1) = self.roi_range(roi.x, roi.width);
        let (r0, r1) = self.roi_range(roi.y, roi.height);
        // The helper iterates only the dots whose squares can meet `region`, so the cost is
        // proportional to the visited area, whatever L.
        let first = (c0 as f64 * self.period, r0 as f64 * self.period);
        visit_grid_dots(
            self.period,
            self.dot_size,
            first,
            (r1 - r0, c1 - c0),
            region,
            &mut |r, c| self.dot_exists(r + r0, c + c0),
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
    fn geometry_and_dot_rule() {
        let l = MegarenaLayout::new(10.0, 4).unwrap();
        assert_eq!(l.n_dots(), 54);
        assert_eq!(l.width(), 535.0);
        assert_eq!(l.origin(), (2.5, 2.5));
        assert!(!l.dot_exists(0, 0), "3×3 orientation rule");
        assert!(l.dot_exists(0, 1) && l.dot_exists(1, 0) && l.dot_exists(2, 2));
        assert!(!l.dot_exists(13, 2) && !l.dot_exists(2, 13), "s[13] = 0");
        assert!(!l.dot_exists(54, 1), "outside");
        assert_eq!(l.intensity(10.0, 0.0), 1.0);
        assert_eq!(l.intensity(0.0, 0.0), 0.0);
        assert_eq!(l.intensity(130.0, 10.0), 0.0);
        assert_eq!(l.intensity(-6.0, 10.0), 0.0);
    }

    #[test]
    fn rects_follow_dot_rule_and_roi() {
        let l = MegarenaLayout::new(4.0, 4).unwrap();
        let all = l.rects_in(&l.bounds());
        let expected: usize = (0..54)
            .flat_map(|r| (0..54).map(move |c| (r, c)))
            .filter(|&(r, c)| l.dot_exists(r, c))
            .count();
        assert_eq!(all.len(), expected);
        // Dot (0, 1) is centred at (P, 0).
        assert!(all.contains(&Rect::new(3.0, -1.0, 2.0, 2.0)));
        // ROI of layout [0, 12) × [0, 8): columns 0..3, rows 0..2.
        let roi = l
            .with_region_of_interest(Rect::new(0.0, 0.0, 12.0, 8.0))
            .unwrap();
        let rects = roi.rects_in(&roi.bounds());
        assert_eq!(rects.len(), 5, "6 dots minus (0, 0)");
    }

    #[test]
    fn twelve_bit_region_is_cheap() {
        let l = MegarenaLayout::new(14.0, 12).unwrap();
        assert_eq!(l.n_dots(), 12318);
        let mut count = 0usize;
        let region = Rect::new(100_000.0, 90_000.0, 140.0, 140.0);
        l.visit_rects(&region, &mut |r| {
            assert!(r.overlaps(&region));
            count += 1;
        });
        assert!(count > 0 && count <= 121, "{count}");
    }

    #[test]
    fn rejects_bad_parameters() {
        assert!(MegarenaLayout::new(0.0, 8).is_err());
        assert!(MegarenaLayout::new(1.0, 13).is_err());
        let l = MegarenaLayout::new(1.0, 4).unwrap();
        assert!(l.clone().with_dot_size(2.0).is_err());
        let e = l
            .with_region_of_interest(Rect::new(0.0, 0.0, -1.0, 1.0))
            .unwrap_err()
            .to_string();
        assert!(e.contains("regionOfInterest"), "{e}");
    }
}
