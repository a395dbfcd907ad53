//! Plain periodic dot grid (docs/design.md#layout-periodic).

use super::{raised_cosine, Layout, Metadata, Rect};
use crate::error::{Error, Result};

/// `n_rows × n_cols` grid of square dots at period `P`, centred on the central dot.
///
/// The top-left dot is omitted (orientation mark). Dot `(r, c)` is centred at pattern
/// coordinates `((c − (n_cols−1)/2)·P, (r − (n_rows−1)/2)·P)`.
#[derive(Clone, Debug, PartialEq)]
pub struct PeriodicLayout {
    period: f64,
    n_rows: usize,
    n_cols: usize,
    dot_size: f64,
    metadata: Metadata,
}

impl PeriodicLayout {
    /// Grid of `n_rows × n_cols` dots (both odd, ≥ 1) at `period` (pattern units, > 0) with
    /// dots of side `period / 2`.
    pub fn new(period: f64, n_rows: usize, n_cols: usize) -> Result<Self> {
        Self::with_dot_size(period, n_rows, n_cols, period / 2.0)
    }

    /// As [`PeriodicLayout::new`] with an explicit dot side `dot_size` (pattern units,
    /// `0 < dot_size ≤ period`).
    pub fn with_dot_size(period: f64, n_rows: usize, n_cols: usize, dot_size: f64) -> Result<Self> {
        if !(period.is_finite() && period > 0.0) {
            return Err(Error::pattern(
                "period",
                format!("must be a positive number, got {period}"),
            ));
        }
        for (key, n) in [("nRows", n_rows), ("nCols", n_cols)] {
            if n == 0 || n % 2 == 0 {
                return Err(Error::pattern(
                    key,
                    format!("must be a positive odd integer, got {n}"),
                ));
            }
        }
        if !(dot_size.is_finite() && dot_size > 0.0 && dot_size <= period) {
            return Err(Error::pattern(
                "dotSize",
                format!("must be in (0, period], got {dot_size}"),
            ));
        }
        Ok(PeriodicLayout {
            period,
            n_rows,
            n_cols,
            dot_size,
            metadata: Metadata::default(),
        })
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
    /// Dot side, pattern units.
    pub fn dot_size(&self) -> f64 {
        self.dot_size
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

/// Shared by every grid-based layout: visits the `dot_size` squares centred on the grid nodes
/// `(c·P + x0, r·P + y0)` for `r < n_rows`, `c < n_cols` that overlap `region` and pass `keep`.
pub(crate) fn visit_grid_dots(
    period: f64,
    dot_size: f64,
    (x0, y0): (f64, f64),
    (n_rows, n_cols): (usize, usize),
    region: &Rect,
    keep: &mut dyn FnMut(usize, usize) -> bool,
    visit: &mut dyn FnMut(Rect),
) {
    let half = dot_size / 2.0;
    // Index range of dots whose square can overlap the region.
    let range = |lo: f64, hi: f64, origin: f64, n: usize| -> (usize, usize) {
        let first = ((lo - origin - half) / period).floor().max(0.0);
        let last = ((hi - origin + half) / period).ceil().min(n as f64 - 1.0);
        if !(first.is_finite() && last.is_finite()) || last < first {
            return (1, 0);
        }
        (first as usize, last as usize)
    };
    let (c0, c1) = range(region.x, region.right(), x0, n_cols);
    let (r0, r1) = range(region.y, region.bottom(), y0, n_rows);
    if c1 < c0 || r1 < r0 {
        return;
    }
    for r in r0..=r1 {
        for c in c0..=c1 {
            if keep(r, c) {
                let dot = Rect::new(
                    x0 + c as f64 * period - half,
                    y0 + r as f64 * period - half,
                    dot_size,
                    dot_size,
                );
                if dot.overlaps(region) {
                    visit(dot);
                }
            }
        }
    }
}

impl Layout for PeriodicLayout {
    fn class_name(&self) -> &'static str {
        "PeriodicPattern"
    }
    fn period(&self) -> f64 {
        self.period
    }
    fn bounds(&self) -> Rect {
        let (w, h) = (self.width(), self.height());
        Rect::new(-w / 2.0, -h / 2.0, w, h)
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        let (w, h) = (self.width(), self.height());
        if x.abs() > w / 2.0 || y.abs() > h / 2.0 {
            return 0.0;
        }
        if x < -w / 2.0 + self.period && y < -h / 2.0 + self.period {
            return 0.0; // the missing top-left dot
        }
        raised_cosine(x, y, self.period)
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let first = (
            -((self.n_cols - 1) as f64) / 2.0 * self.period,
            -((self.n_rows - 1) as f64) / 2.0 * self.period,
        );
        visit_grid_dots(
            self.period,
            self.dot_size,
            first,
            (self.n_rows, self.n_cols),
            region,
            &mut |r, c| (r, c) != (0, 0),
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
    fn geometry_matches_spec() {
        let l = PeriodicLayout::new(10.0, 3, 5).unwrap();
        assert_eq!(l.width(), 45.0);
        assert_eq!(l.height(), 25.0);
        assert_eq!(l.origin(), (22.5, 12.5));
        let rects = l.rects_in(&l.bounds());
        assert_eq!(rects.len(), 14, "15 dots minus the top-left one");
        // The central dot is centred on the pattern origin.
        assert!(rects
            .iter()
            .any(|r| r.x == -2.5 && r.y == -2.5 && r.width == 5.0));
        assert_eq!(l.intensity(0.0, 0.0), 1.0);
        assert!(l.intensity(5.0, 0.0).abs() < 1e-15);
        assert_eq!(l.intensity(-20.0, -10.0), 0.0, "missing top-left dot");
        assert_eq!(l.intensity(30.0, 0.0), 0.0, "outside");
    }

    #[test]
    fn rejects_even_or_bad_sizes() {
        assert!(PeriodicLayout::new(10.0, 4, 5).is_err());
        assert!(PeriodicLayout::new(-1.0, 3, 5).is_err());
        assert!(PeriodicLayout::new(f64::NAN, 3, 5).is_err());
        let e = PeriodicLayout::new(10.0, 3, 0).unwrap_err().to_string();
        assert!(e.contains("nCols"), "{e}");
    }
}
