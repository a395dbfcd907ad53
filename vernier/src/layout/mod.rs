//! Marker layouts: where the fabricated dots are (docs/design.md#layouts).
//!
//! Two frames are used (both y down, as in the layout's PNG/SVG):
//! * **layout coordinates** `(u, v)`: origin at the top-left corner of the bounding box;
//! * **pattern coordinates** `(x, y) = (u − origin_x, v − origin_y)`: the frame poses refer to
//!   (centre of the central dot for periodic/HP/bitmap/stamp, centre of dot (0, 0) for Megarena).
//!
//! All lengths are in the pattern unit (the unit of the period, µm by convention).

mod bitmap;
mod custom;
mod hpcode;
mod megarena;
mod periodic;

pub use bitmap::{BitmapLayout, FingerprintLayout};
pub use custom::{CustomDot, CustomLayout};
pub use hpcode::HpCodeLayout;
pub use megarena::MegarenaLayout;
pub use periodic::PeriodicLayout;

/// Axis-aligned rectangle: top-left corner `(x, y)` and size, in pattern units.
///
/// The frame (layout or pattern coordinates) is stated where a `Rect` is used.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rect {
    /// Left edge (smallest x).
    pub x: f64,
    /// Top edge (smallest y, y down).
    pub y: f64,
    /// Width, ≥ 0.
    pub width: f64,
    /// Height, ≥ 0.
    pub height: f64,
}

impl Rect {
    /// Rectangle from its top-left corner and size.
    pub const fn new(x: f64, y: f64, width: f64, height: f64) -> Self {
        Rect {
            x,
            y,
            width,
            height,
        }
    }
    /// Right edge.
    pub fn right(&self) -> f64 {
        self.x + self.width
    }
    /// Bottom edge.
    pub fn bottom(&self) -> f64 {
        self.y + self.height
    }
    /// True when the two closed rectangles overlap with positive area.
    pub fn overlaps(&self, other: &Rect) -> bool {
        self.x < other.right()
            && other.x < self.right()
            && self.y < other.bottom()
            && other.y < self.bottom()
    }
    /// The same rectangle moved by `(dx, dy)`.
    pub fn translated(&self, dx: f64, dy: f64) -> Rect {
        Rect::new(self.x + dx, self.y + dy, self.width, self.height)
    }
}

/// Margins added around a layout at export time (pattern units).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Margins {
    /// Left margin.
    pub left: f64,
    /// Right margin.
    pub right: f64,
    /// Top margin.
    pub top: f64,
    /// Bottom margin.
    pub bottom: f64,
}

/// Descriptive fields shared by all layouts (docs/design.md#layouts, docs/design.md#pattern-file).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Metadata {
    /// Free text.
    pub description: String,
    /// Creation date, free text (`YYYY-MM-DD HH:MM:SS` when generated).
    pub date: String,
    /// Author.
    pub author: String,
    /// Name of the length unit of the period (metadata only, e.g. "um").
    pub unit: String,
    /// Export margins.
    pub margins: Margins,
}

/// A marker layout: the set of fabricated rectangles and its analytic intensity.
///
/// Implementors must make [`Layout::visit_rects`] cost proportional to the number of rectangles
/// visited, so that huge layouts (a 12-bit Megarena holds 10⁸ dots) can be rendered and exported
/// by region.
pub trait Layout: Send + Sync {
    /// Class name as used in JSON pattern files (`"PeriodicPattern"`, `"MegarenaPattern"`, ...).
    fn class_name(&self) -> &'static str;

    /// Physical period `P` of the dot grid, pattern units.
    fn period(&self) -> f64;

    /// Bounding box in **pattern coordinates**: `(-origin_x, -origin_y, width, height)`.
    fn bounds(&self) -> Rect;

    /// Analytic intensity `I(x, y) ∈ [0, 1]` (docs/design.md#layouts) at pattern point `(x, y)`
    /// (bright dots = 1, background = 0). Used by the point-sampled renderer and PNG export.
    fn intensity(&self, x: f64, y: f64) -> f64;

    /// Calls `visit` with every fabricated rectangle (in **pattern coordinates**) that
    /// overlaps `region` (pattern coordinates). Rectangles may be visited in any order; a
    /// rectangle that only touches `region` may or may not be visited.
    fn visit_rects(&self, region: &Rect, visit: &mut dyn FnMut(Rect));

    /// Descriptive metadata and margins.
    fn metadata(&self) -> &Metadata;

    /// Pattern-frame origin in layout coordinates `(origin_x, origin_y)`.
    fn origin(&self) -> (f64, f64) {
        let b = self.bounds();
        (-b.x, -b.y)
    }

    /// All rectangles overlapping `region` (pattern coordinates), collected into a vector.
    fn rects_in(&self, region: &Rect) -> Vec<Rect> {
        let mut out = Vec::new();
        self.visit_rects(region, &mut |r| out.push(r));
        out
    }
}

/// The separable raised-cosine dot profile (docs/design.md#layouts):
/// `(1 + cos(2πx/P))(1 + cos(2πy/P))/4`, 1 at dot centres (multiples of `period`).
pub fn raised_cosine(x: f64, y: f64, period: f64) -> f64 {
    let k = std::f64::consts::TAU / period;
    (1.0 + (k * x).cos()) * (1.0 + (k * y).cos()) / 4.0
}
