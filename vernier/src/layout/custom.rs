//! Free list of rectangles, not periodic (docs/design.md#layout-custom), with its CSV reader.

use std::path::Path;

use super::{Layout, Metadata, Rect};
use crate::error::{Error, Result};

/// One rectangle of a [`CustomLayout`]: geometry in pattern coordinates (pattern units) and
/// an intensity value that is stored and written back but not used for rendering (as in the
/// original).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CustomDot {
    /// Rectangle, pattern coordinates.
    pub rect: Rect,
    /// Stored intensity (the original's CSV writer writes 1).
    pub intensity: f64,
}

impl CustomDot {
    /// Rectangle `(x, y, width, height)` (pattern units) with stored `intensity`.
    pub const fn new(x: f64, y: f64, width: f64, height: f64, intensity: f64) -> Self {
        CustomDot {
            rect: Rect::new(x, y, width, height),
            intensity,
        }
    }
}

/// Free list of rectangles in pattern coordinates, pattern origin = layout origin = `(0, 0)`
/// when all rectangles have `x, y ≥ 0` (docs/design.md#layout-custom).
///
/// The bounding box spans `[min(0, min x), max(x + w)] × [min(0, min y), max(y + h)]`.
/// The layout is not periodic: [`Layout::period`] returns 0.
///
/// Intensity: sum over the rectangles whose extended box `[x − w/2, x + 1.5w] × [y − h/2,
/// y + 1.5h]` contains the point of `(1 + cos(π(X − cx)/w))·(1 + cos(π(Y − cy)/h))/4`, with
/// `(cx, cy)` the rectangle centre, clamped to 1 where rectangles overlap.
#[derive(Clone, Debug, PartialEq)]
pub struct CustomLayout {
    /// In the order given (kept for writing files back identically).
    dots: Vec<CustomDot>,
    /// Indices into `dots` sorted by `rect.x`, for range queries.
    by_x: Vec<usize>,
    /// Largest rectangle width: bounds how far left of a query a relevant rectangle starts.
    max_width: f64,
    bounds: Rect,
    metadata: Metadata,
}

impl CustomLayout {
    /// Layout from a non-empty list of rectangles (finite coordinates, `w, h > 0`, finite
    /// intensity). Errors name the `dots` key and the entry index.
    pub fn new(dots: Vec<CustomDot>) -> Result<Self> {
        if dots.is_empty() {
            return Err(Error::pattern("dots", "must hold at least one rectangle"));
        }
        for (i, d) in dots.iter().enumerate() {
            let r = d.rect;
            let finite = [r.x, r.y, r.width, r.height, d.intensity]
                .iter()
                .all(|v| v.is_finite());
            if !finite || r.width <= 0.0 || r.height <= 0.0 {
                return Err(Error::pattern(
                    "dots",
                    format!(
                        "entry {i} must be finite [x, y, w, h, intensity] with w, h > 0, got [{}, {}, {}, {}, {}]",
                        r.x, r.y, r.width, r.height, d.intensity
                    ),
                ));
            }
        }
        let rects = || dots.iter().map(|d| d.rect);
        let left = rects().map(|r| r.x).fold(0.0, f64::min);
        let top = rects().map(|r| r.y).fold(0.0, f64::min);
        let right = rects().map(|r| r.right()).fold(f64::NEG_INFINITY, f64::max);
        let bottom = rects()
            .map(|r| r.bottom())
            .fold(f64::NEG_INFINITY, f64::max);
        let max_width = rects().map(|r| r.width).fold(0.0, f64::max);
        let mut by_x: Vec<usize> = (0..dots.len()).collect();
        by_x.sort_by(|&a, &b| dots[a].rect.x.total_cmp(&dots[b].rect.x));
        Ok(CustomLayout {
            bounds: Rect::new(left, top, right - left, bottom - top),
            dots,
            by_x,
            max_width,
            metadata: Metadata::default(),
        })
    }

    /// Layout from CSV text (docs/design.md#layout-custom): a header line (skipped), then one
    /// rectangle per line `x;y;width;height;intensity`. Blank lines are ignored.
    pub fn from_csv_str(text: &str) -> Result<Self> {
        let mut dots = Vec::new();
        for (index, line) in text.lines().enumerate().skip(1) {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let values: Vec<f64> = line
                .split(';')
                .map(|field| field.trim().parse::<f64>())
                .collect::<std::result::Result<_, _>>()
                .map_err(|e| {
                    Error::pattern("dots", format!("CSV line {}: `{line}`: {e}", index + 1))
                })?;
            let [x, y, w, h, intensity] = values[..] else {
                return Err(Error::pattern(
                    "dots",
                    format!(
                        "CSV line {}: expected 5 `;`-separated numbers x;y;width;height;intensity, got {}",
                        index + 1,
                        values.len()
                    ),
                ));
            };
            dots.push(CustomDot::new(x, y, w, h, intensity));
        }
        Self::new(dots)
    }

    /// Layout from a CSV file, see [`CustomLayout::from_csv_str`].
    pub fn from_csv_file(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|source| Error::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_csv_str(&text)
    }

    /// Replaces the metadata (builder style).
    pub fn with_metadata(mut self, metadata: Metadata) -> Self {
        self.metadata = metadata;
        self
    }

    /// The rectangles in their original order.
    pub fn dots(&self) -> &[CustomDot] {
        &self.dots
    }

    /// Rectangles whose left edge lies in `[lo, hi]`, in increasing `x`.
    fn dots_with_left_in(&self, lo: f64, hi: f64) -> impl Iterator<Item = &CustomDot> {
        let start = self.by_x.partition_point(|&i| self.dots[i].rect.x < lo);
        self.by_x[start..]
            .iter()
            .map(|&i| &self.dots[i])
            .take_while(move |d| d.rect.x <= hi)
    }
}

impl Layout for CustomLayout {
    fn class_name(&self) -> &'static str {
        "CustomPattern"
    }
    /// Not periodic: 0.
    fn period(&self) -> f64 {
        0.0
    }
    fn bounds(&self) -> Rect {
        self.bounds
    }
    fn intensity(&self, x: f64, y: f64) -> f64 {
        // A rectangle contributes when x ∈ [rx − w/2, rx + 1.5w], so rx ∈ [x − 1.5w, x + w/2].
        let lo = x - 1.5 * self.max_width;
        let hi = x + 0.5 * self.max_width;
        let mut sum = 0.0;
        for d in self.dots_with_left_in(lo, hi) {
            let r = d.rect;
            let inside_x = x >= r.x - r.width / 2.0 && x <= r.x + 1.5 * r.width;
            let inside_y = y >= r.y - r.height / 2.0 && y <= r.y + 1.5 * r.height;
            if inside_x && inside_y {
                let cx = r.x + r.width / 2.0;
                let cy = r.y + r.height / 2.0;
                let fx = 1.0 + (std::f64::consts::PI * (x - cx) / r.width).cos();
                let fy = 1.0 + (std::f64::consts::PI * (y - cy) / r.height).cos();
                sum += fx * fy / 4.0;
            }
        }
        sum.clamp(0.0, 1.0)
    }
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect)) {
        let lo = region.x - self.max_width;
        for d in self.dots_with_left_in(lo, region.right()) {
            if d.rect.overlaps(region) {
                visit(d.rect);
            }
        }
    }
    fn metadata(&self) -> &Metadata {
        &self.metadata
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_geometry_and_intensity() {
        let csv = "x;y;width;height:intensity\n0;0;5;5;1\n10; 0;5;5;1\r\n\n0;10;5;5;1\n";
        let l = CustomLayout::from_csv_str(csv).unwrap();
        assert_eq!(l.dots().len(), 3);
        assert_eq!(l.bounds(), Rect::new(0.0, 0.0, 15.0, 15.0));
        assert_eq!(l.origin(), (0.0, 0.0));
        assert_eq!(l.intensity(2.5, 2.5), 1.0);
        assert!((l.intensity(5.0, 2.5) - 0.5).abs() < 1e-12, "edge");
        assert!(l.intensity(7.5, 2.5) < 1e-12, "between");
        assert_eq!(l.intensity(12.5, 12.5), 0.0);
        let region = Rect::new(9.0, -1.0, 2.0, 2.0);
        assert_eq!(l.rects_in(&region), vec![Rect::new(10.0, 0.0, 5.0, 5.0)]);
        assert_eq!(l.rects_in(&l.bounds()).len(), 3);
    }

    #[test]
    fn csv_errors_name_the_line() {
        let e = CustomLayout::from_csv_str("h\n0;0;5;5;1\n1;2;3\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 3") && e.contains("got 3"), "{e}");
        let e = CustomLayout::from_csv_str("h\n0;a;5;5;1\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2"), "{e}");
        assert!(CustomLayout::from_csv_str("h\n0;0;0;5;1\n").is_err());
        assert!(CustomLayout::from_csv_str("h\n").is_err());
    }
}
