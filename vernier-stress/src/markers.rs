//! Marker families, the markers placed in a scene and their ground truth.
//!
//! Truth convention (exactly what `vernier::MarkerPose::origin_px` reports): the image
//! position `(col, row)` of the marker's pattern origin, with pixel `(c, r)` centred on
//! `(c, r)`: the centre of the central dot for HP codes (`W ≡ 1 mod 4`) and stamps (the
//! bitmap's central cell). Markers are rendered with
//! `Pose::from_origin_in_image(origin − centre, alpha, pixel_size)`, which puts the origin
//! there; under perspective the truth is the homography image of that plane point.

use crate::bound::PositionBound;
use crate::data::StampSet;
use crate::error::Result;
use crate::geometry::{rotate, Homography, OrientedRect};
use nalgebra::Vector2;
use vernier::layout::{HpCodeLayout, Layout};

/// Physical period of every marker, pattern units (µm): what the user gives the detector.
pub const PERIOD: f64 = 10.0;

/// The marker families under test.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Family {
    /// HP code markers (W = 33 or 37 half periods), ID = the decoded bits.
    HpCode,
    /// Stamp markers (69 × 69 cell bitmaps), ID = index in [`crate::data::STAMP_NAMES`].
    Stamp,
}

impl Family {
    /// Both families.
    pub const ALL: [Family; 2] = [Family::HpCode, Family::Stamp];

    /// Lower-case name (`hpcode`, `stamp`).
    pub fn name(self) -> &'static str {
        match self {
            Family::HpCode => "hpcode",
            Family::Stamp => "stamp",
        }
    }

    /// Parses `hpcode` / `stamp`.
    pub fn parse(s: &str) -> Option<Family> {
        match s {
            "hpcode" | "hp" => Some(Family::HpCode),
            "stamp" => Some(Family::Stamp),
            _ => None,
        }
    }
}

/// What the detector is expected to do with a marker.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Expectation {
    /// Of the scene's family and wholly visible: must be found with its ID.
    Expected,
    /// Of the scene's family but cut by the image border: a detection on it counts neither
    /// as found nor as false.
    Ignored,
    /// Of the other family (clutter): a detection on it is a false marker.
    Foreign,
}

impl Expectation {
    /// Lower-case name for reports.
    pub fn name(self) -> &'static str {
        match self {
            Expectation::Expected => "expected",
            Expectation::Ignored => "ignored",
            Expectation::Foreign => "foreign",
        }
    }
}

/// Which marker is drawn.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MarkerKind {
    /// HP code `code_size` cells wide with its ID.
    HpCode {
        /// Width in half-period cells (33 or 37).
        code_size: usize,
        /// Encoded ID (`(W − 15)/2` bits).
        id: u64,
    },
    /// Stamp with bitmap `index` of [`crate::data::STAMP_NAMES`].
    Stamp {
        /// Bitmap index = ID.
        index: usize,
    },
}

impl MarkerKind {
    /// The marker's family.
    pub fn family(&self) -> Family {
        match self {
            MarkerKind::HpCode { .. } => Family::HpCode,
            MarkerKind::Stamp { .. } => Family::Stamp,
        }
    }

    /// The ID the detector should report.
    pub fn id(&self) -> u64 {
        match *self {
            MarkerKind::HpCode { id, .. } => id,
            MarkerKind::Stamp { index } => index as u64,
        }
    }

    /// Side of the marker in half-period cells (HP: `W`; stamps: 69).
    pub fn cells(&self) -> usize {
        match *self {
            MarkerKind::HpCode { code_size, .. } => code_size,
            MarkerKind::Stamp { .. } => STAMP_CELLS,
        }
    }

    /// The layout to render.
    pub fn layout(&self, stamps: &StampSet) -> Result<Box<dyn Layout>> {
        Ok(match *self {
            MarkerKind::HpCode { code_size, id } => {
                Box::new(HpCodeLayout::from_code_size(PERIOD, code_size)?.with_id(id)?)
            }
            MarkerKind::Stamp { index } => match stamps.layouts.get(index) {
                Some(l) => Box::new(l.clone()),
                None => {
                    return Err(crate::error::StressError::new(format!(
                        "no stamp bitmap {index}"
                    )))
                }
            },
        })
    }
}

/// Side of the stamp bitmaps in half-period cells.
pub const STAMP_CELLS: usize = 69;

/// Side of a finder square / thickness of the stamp frame, cells.
const FINDER_CELLS: f64 = 7.0;
const FRAME_CELLS: f64 = 2.0;

/// A marker as placed on the (untilted) marker plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placed {
    /// Which marker.
    pub kind: MarkerKind,
    /// Plane position of the pattern origin, pixels.
    pub origin: Vector2<f64>,
    /// Direction of the pattern x axis on the plane, radians.
    pub alpha: f64,
    /// Pattern units per plane pixel.
    pub pixel_size: f64,
    /// Seen from its back (a half turn about its x axis): its y axis points the other way.
    pub mirrored: bool,
    /// Detector expectation.
    pub expectation: Expectation,
}

/// Areas of a marker that dust and hair must respect, in half-period cell coordinates
/// `(col, row)` from the marker's top-left corner: rectangles `[c0, c1) × [r0, r1)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Zones {
    /// Finder squares (HP code) or frame sides (stamp): at most one may be touched.
    pub finders: Vec<[f64; 4]>,
    /// ID strips (HP code top row and left column between the finders): never touched.
    pub id_strips: Vec<[f64; 4]>,
}

impl Placed {
    /// Marker side on the plane, pixels.
    pub fn side_px(&self) -> f64 {
        self.kind.cells() as f64 * PERIOD / 2.0 / self.pixel_size
    }

    /// Grid period on the plane, pixels.
    pub fn period_px(&self) -> f64 {
        PERIOD / self.pixel_size
    }

    /// The marker's square outline on the plane.
    pub fn footprint(&self) -> OrientedRect {
        OrientedRect::square(self.origin, self.side_px(), self.alpha)
    }

    /// Plane pixel `p` in cell coordinates `(col, row)` from the marker's top-left corner.
    pub fn to_cells(&self, p: Vector2<f64>) -> Vector2<f64> {
        let mut local = rotate(p - self.origin, -self.alpha) * self.pixel_size / (PERIOD / 2.0);
        if self.mirrored {
            local.y = -local.y;
        }
        local + Vector2::repeat(self.kind.cells() as f64 / 2.0)
    }

    /// A plane length in pixels as cells.
    pub fn px_to_cells(&self, length: f64) -> f64 {
        length * self.pixel_size / (PERIOD / 2.0)
    }

    /// The dust/hair constraint zones.
    pub fn zones(&self) -> Zones {
        let n = self.kind.cells() as f64;
        match self.kind {
            MarkerKind::HpCode { .. } => {
                let f = FINDER_CELLS;
                Zones {
                    finders: vec![[0.0, f, 0.0, f], [n - f, n, 0.0, f], [0.0, f, n - f, n]],
                    // Top dot row and left dot column between the finders, half a period
                    // around them.
                    id_strips: vec![[f, n - f, -1.0, 2.0], [-1.0, 2.0, f, n - f]],
                }
            }
            MarkerKind::Stamp { .. } => {
                let t = FRAME_CELLS;
                Zones {
                    finders: vec![
                        [0.0, n, 0.0, t],
                        [0.0, n, n - t, n],
                        [0.0, t, 0.0, n],
                        [n - t, n, 0.0, n],
                    ],
                    id_strips: Vec::new(),
                }
            }
        }
    }

    /// The zones a disc of radius `radius` pixels at plane point `p` touches:
    /// `(finder bit mask, touches an ID strip)`.
    pub fn touches(&self, p: Vector2<f64>, radius: f64) -> (u32, bool) {
        let q = self.to_cells(p);
        let r = self.px_to_cells(radius);
        let hit = |z: &[f64; 4]| {
            let dx = (z[0] - q.x).max(0.0).max(q.x - z[1]);
            let dy = (z[2] - q.y).max(0.0).max(q.y - z[3]);
            dx * dx + dy * dy < r * r || (dx == 0.0 && dy == 0.0)
        };
        let zones = self.zones();
        let mask = zones
            .finders
            .iter()
            .enumerate()
            .filter(|(_, z)| hit(z))
            .fold(0u32, |m, (i, _)| m | 1 << i);
        (mask, zones.id_strips.iter().any(hit))
    }

    /// Ground truth in the image seen through `homography`; `None` if the origin is beyond
    /// the horizon.
    pub fn truth(&self, homography: &Homography) -> Option<TruthMarker> {
        let origin = homography.apply(self.origin)?;
        let j = homography.jacobian(self.origin)?;
        let ax = j * rotate(Vector2::x(), self.alpha);
        let ay = j * rotate(Vector2::y(), self.alpha);
        // Mean direction of the pattern x axis and of the y axis turned back by 90° (`ay` is
        // the direction 90° on from x in the plane; a mirrored marker's y axis is its
        // opposite, and its angle is still that of its x axis).
        let a1 = ax.y.atan2(ax.x);
        let a2 = ay.y.atan2(ay.x) - std::f64::consts::FRAC_PI_2;
        let angle = vernier::phase::wrap_angle(a1 + vernier::phase::wrap_to_pi(a2 - a1) / 2.0);
        let scale = j.determinant().abs().sqrt();
        Some(TruthMarker {
            family: self.kind.family(),
            code_size: match self.kind {
                MarkerKind::HpCode { code_size, .. } => Some(code_size),
                MarkerKind::Stamp { .. } => None,
            },
            id: self.kind.id(),
            origin_px: [origin.x, origin.y],
            angle,
            pixel_size: self.pixel_size / scale,
            period_px: self.period_px() * scale,
            mirrored: self.mirrored,
            expectation: self.expectation,
            position_bound: None,
        })
    }
}

/// Ground truth of one marker in the final image.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthMarker {
    /// Family.
    pub family: Family,
    /// HP code width in half periods (`None` for stamps).
    pub code_size: Option<usize>,
    /// The ID the detector should report.
    pub id: u64,
    /// Image position `(col, row)` of the pattern origin, pixels.
    pub origin_px: [f64; 2],
    /// Direction of the pattern x axis in the image, radians in `[−π, π)` (under perspective:
    /// the local mean direction of both axes at the origin).
    pub angle: f64,
    /// Pattern units per pixel at the origin.
    pub pixel_size: f64,
    /// Grid period at the origin, pixels.
    pub period_px: f64,
    /// Seen from its back: the detector must say so (`gamma = −π`).
    pub mirrored: bool,
    /// What the detector should do with it.
    pub expectation: Expectation,
    /// Cramér–Rao bound of its origin's radial error (or its JPEG model; [`crate::bound`]),
    /// where the scene has one.
    pub position_bound: Option<PositionBound>,
}
