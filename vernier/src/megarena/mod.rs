//! Megarena absolute encoded grids (docs/design.md#megarena): absolute position of the image centre
//! over the whole pattern, full-turn orientation, and the out-of-plane pose
//! (docs/design.md#pose-3d).
//!
//! Pipeline (one way, image → planes → lattice → code → pose):
//! 1. the phase engine measures the two phase planes (sub-pixel lattice, modulo one period);
//! 2. `thumbnail`: the dot contrast is sampled at every lattice node the planes predict;
//! 3. `orientation`: the 3×3 missing-dot rule gives, per lattice axis, the coding residue and
//!    the direction of the layout index;
//! 4. `refine`: the planes are corrected dot by dot (the grid's holes bias the engine's
//!    whole-image fit by a few 1e-3 px);
//! 5. `decoding`: every visible coding line gives one soft bit; the bits are located in the
//!    sequence with an O(1) window table, tolerating a few wrong bits;
//! 6. the planes, re-expressed as absolute pattern phases `2π·(pattern coordinate)/P`, give the
//!    pose (and, on request, the out-of-plane angles, [`pose3d`]).

mod decoding;
mod orientation;
pub mod pose3d;
mod refine;
mod thumbnail;

pub use decoding::{Located, WindowIndex};
pub use orientation::Orientation;
pub use thumbnail::Thumbnail;

use crate::error::{Error, Result};
use crate::grey_image::{GreyImage, Polarity};
use crate::layout::MegarenaLayout;
use crate::megarena_sequence::LineSequence;
use crate::phase::{PhaseAnalysis, PhaseEngine, PhaseParams, PhasePlane};
use crate::pose::Pose;
use nalgebra::Vector2;
use std::f64::consts::TAU;

/// Settings of [`MegarenaDetector`].
#[derive(Clone, Debug, PartialEq)]
pub struct MegarenaParams {
    /// Physical period `P` of the grid, pattern units (µm by convention). Must be > 0.
    pub period: f64,
    /// Line sequence of the pattern (generated from a code depth, or user-supplied).
    pub sequence: LineSequence,
    /// Dot polarity of the images (dark dots are inverted first).
    pub polarity: Polarity,
    /// Phase-engine settings.
    pub phase: PhaseParams,
    /// Also measure the out-of-plane angles (docs/design.md#pose-3d): every detection then
    /// carries [`MegarenaDetection::out_of_plane`], the orthographic solutions with the
    /// perspective cue's choice (`z = 0` without [`Self::focal_length_px`]). Costs one demodulation pass over
    /// the image. Default `false`.
    pub pose_3d: bool,
    /// Focal length of a perspective camera, pixels: with `pose_3d`, the depth
    /// `z = pixel_size·focal` of the pattern point on the optical axis (the image centre).
    /// `None` (default): `z` unknown (0).
    pub focal_length_px: Option<f64>,
}

impl MegarenaParams {
    /// Defaults for the generated pattern of code depth `code_depth` (4..=12) and physical
    /// period `period` (pattern units).
    pub fn new(period: f64, code_depth: u32) -> Result<Self> {
        Ok(Self::with_sequence(
            period,
            LineSequence::generated(code_depth)?,
        ))
    }

    /// Defaults for a pattern with the line sequence `sequence`.
    pub fn with_sequence(period: f64, sequence: LineSequence) -> Self {
        MegarenaParams {
            period,
            sequence,
            polarity: Polarity::BrightDots,
            phase: PhaseParams::default(),
            pose_3d: false,
            focal_length_px: None,
        }
    }

    /// Defaults matching a layout (period and sequence).
    pub fn from_layout(layout: &MegarenaLayout) -> Self {
        Self::with_sequence(
            crate::layout::Layout::period(layout),
            layout.sequence().clone(),
        )
    }
}

/// Absolute phase planes: `φ_x = 2π·x_p/P` and `φ_y = 2π·y_p/P` as functions of the image frame
/// (pixels from the centre pixel, y down), `(x_p, y_p)` being the pattern point seen there.
pub type PatternPlanes = [PhasePlane; 2];

/// Decoding details of one pattern axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisDecoding {
    /// Thumbnail (phase-engine) axis that carries this pattern axis: 0 or 1.
    pub lattice_axis: usize,
    /// +1 when the pattern coordinate grows with that plane's phase, −1 otherwise.
    pub direction: i64,
    /// Where the read bits lie in the coding sequence.
    pub located: Located,
}

/// One Megarena measurement.
#[derive(Clone, Debug)]
pub struct MegarenaDetection {
    /// Absolute planar pose: `(−x, −y)` is the pattern point at the image centre pixel
    /// (pattern units, origin at dot (0, 0)), `alpha ∈ [−π, π)`, pixel size in pattern units.
    pub pose: Pose,
    /// Image position `(col, row)` of the pattern origin (centre of dot (0, 0)), pixels; usually
    /// far outside the image.
    pub origin_px: Vector2<f64>,
    /// Absolute phase planes of the pattern x and y axes.
    pub pattern_planes: PatternPlanes,
    /// Fraction of the read coding bits (both axes) that agree with the decoded position.
    pub decode_confidence: f64,
    /// Decoding of the pattern x axis (dot columns) and y axis (dot rows).
    pub axes: [AxisDecoding; 2],
    /// Orientation found from the 3×3 rule.
    pub orientation: Orientation,
    /// Phase-engine output the pose was computed from.
    pub analysis: PhaseAnalysis,
    /// Physical period `P` the pose was computed with, pattern units.
    pub period: f64,
    /// Dots measured by the dot-wise plane refinement (0 when too few were found and the
    /// phase engine's planes were kept).
    pub refined_dots: usize,
    /// Out-of-plane pose ([`MegarenaDetection::out_of_plane`] of the analysed image, `z = 0`)
    /// when [`MegarenaParams::pose_3d`] is set; `None` otherwise.
    pub out_of_plane: Option<pose3d::OutOfPlanePose>,
}

impl MegarenaDetection {
    /// Out-of-plane pose (docs/design.md#pose-3d): the two orthographic solutions and the one the
    /// perspective cue of `image` (the analysed image, same polarity as given to `detect`)
    /// favours. `focal_px`: focal length in pixels for `z = pixel_size·focal`, `None` for
    /// `z = 0`. See [`pose3d`].
    pub fn out_of_plane(
        &self,
        image: &GreyImage,
        focal_px: Option<f64>,
    ) -> Result<pose3d::OutOfPlanePose> {
        pose3d::out_of_plane(image, &self.pattern_planes, self.period, focal_px)
    }
}

/// Measures the absolute pose of a Megarena pattern filling the image. Keeps FFT plans, the
/// window table and the thumbnail buffers between calls.
///
/// # Example
///
/// ```
/// use vernier::layout::MegarenaLayout;
/// use vernier::megarena::{MegarenaDetector, MegarenaParams};
/// use vernier::phase::wrap_to_pi;
/// use vernier::render::{render, RenderOptions};
/// use vernier::Pose;
///
/// # fn main() -> vernier::Result<()> {
/// // A 6-bit Megarena (204 × 204 dots) of 10 µm period at 1.25 µm per pixel. The image
/// // centre sees pattern point (812.5, 655) µm, i.e. near dot column 81, row 65.
/// let layout = MegarenaLayout::new(10.0, 6)?;
/// let truth = Pose::planar(-812.5, -655.0, 2.0, 1.25);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(256, 256) };
/// let image = render(&layout, &truth, &options)?;
///
/// let mut detector = MegarenaDetector::new(MegarenaParams::new(10.0, 6)?)?;
/// let found = detector.detect(&image)?;
/// let tolerance = 0.01 * truth.pixel_size; // absolute position to 1/100 px
/// assert!((found.pose.x - truth.x).abs() < tolerance);
/// assert!((found.pose.y - truth.y).abs() < tolerance);
/// assert!(wrap_to_pi(found.pose.alpha - truth.alpha).abs() < 1e-4); // full turn
/// assert_eq!(found.decode_confidence, 1.0); // every coding bit read agrees
/// # Ok(())
/// # }
/// ```
pub struct MegarenaDetector {
    params: MegarenaParams,
    index: WindowIndex,
    engine: PhaseEngine,
    thumbnail: Thumbnail,
}

impl MegarenaDetector {
    /// A detector with `params` (validated).
    pub fn new(params: MegarenaParams) -> Result<Self> {
        crate::limits::check_period(params.period)?;
        params.phase.validate()?;
        let index = WindowIndex::new(&params.sequence)?;
        Ok(MegarenaDetector {
            params,
            index,
            engine: PhaseEngine::new(),
            thumbnail: Thumbnail::default(),
        })
    }

    /// Current settings.
    pub fn params(&self) -> &MegarenaParams {
        &self.params
    }

    /// The thumbnail (node levels and contrasts) of the last analysed image, for display and
    /// diagnosis.
    pub fn thumbnail(&self) -> &Thumbnail {
        &self.thumbnail
    }

    /// Measures `image`.
    ///
    /// Errors: those of the phase engine ([`Error::PatternNotFound`] without a grid), and
    /// [`Error::Decode`] when too few periods are visible to read the code ("not enough
    /// periods to decode") or the bits are inconsistent or ambiguous.
    pub fn detect(&mut self, image: &GreyImage) -> Result<MegarenaDetection> {
        let image = &*image.as_bright_dots(self.params.polarity);
        let analysis = self.engine.analyze(image, &self.params.phase)?;
        self.thumbnail.sample(image, &analysis.planes)?;
        let orientation = orientation::find_orientation(&self.thumbnail)?;
        self.thumbnail.subtract_background(&orientation);
        let white = orientation.dot_contrast;
        // Dot-wise refinement of the planes (removes the bias of the grid's holes).
        let (planes, refined_dots) =
            match refine::refine_on_dots(image, &analysis.planes, &self.thumbnail, white) {
                Some(r) => (r.planes, r.dots),
                None => (analysis.planes, 0),
            };
        // Decode each lattice axis: the absolute plane 2π·(layout index) and its decoding.
        let decode_axis = |k: usize| self.decode_axis(&orientation, &planes, white, k);
        let (mut first, mut second) = (decode_axis(0)?, decode_axis(1)?);
        // The pattern frame is right-handed in the image (y_p = x_p turned by +90°), so the
        // axis whose gradient turns positively into the other's is x.
        let cross = first.0.a * second.0.b - first.0.b * second.0.a;
        if cross < 0.0 {
            std::mem::swap(&mut first, &mut second);
        }
        let pattern_planes = [first.0, second.0];
        let axes = [first.1, second.1];
        let read: usize = axes.iter().map(|a| a.located.read).sum();
        let agreeing: usize = axes.iter().map(|a| a.located.agreeing).sum();
        let pose = pose_from_planes(&pattern_planes, self.params.period);
        let (cx, cy) = image.center();
        let origin_px = Vector2::new(cx as f64, cy as f64)
            + origin_offset(&pattern_planes).unwrap_or_else(|| pose.origin_in_image());
        let out_of_plane = if self.params.pose_3d {
            Some(pose3d::out_of_plane(
                image,
                &pattern_planes,
                self.params.period,
                self.params.focal_length_px,
            )?)
        } else {
            None
        };
        Ok(MegarenaDetection {
            pose,
            origin_px,
            pattern_planes,
            decode_confidence: agreeing as f64 / read.max(1) as f64,
            axes,
            orientation,
            analysis,
            period: self.params.period,
            refined_dots,
            out_of_plane,
        })
    }

    /// The absolute plane `2π·(layout index)` of lattice axis `k` (0 or 1) and its decoding:
    /// the axis's coding lines read in the thumbnail and located in the sequence.
    fn decode_axis(
        &self,
        orientation: &orientation::Orientation,
        planes: &[PhasePlane; 2],
        white: f64,
        k: usize,
    ) -> Result<(PhasePlane, AxisDecoding)> {
        let bits = decoding::read_lines(&self.thumbnail, orientation, k, white);
        let direction = orientation.direction[k];
        let mut soft = bits.soft.clone();
        if direction < 0 {
            soft.reverse(); // layout order
        }
        let located = self.index.locate(&soft).map_err(|e| match e {
            Error::Decode(msg) => Error::Decode(format!("lattice axis {}: {msg}", k + 1)),
            other => other,
        })?;
        // Layout index of the line with phase order n: direction·n + offset.
        let first_layout_line = 3 * located.start as i64 + 1;
        let offset = if direction > 0 {
            first_layout_line - bits.first_line
        } else {
            let last_line = bits.first_line + 3 * (bits.soft.len() as i64 - 1);
            first_layout_line + last_line
        };
        let (p, d) = (planes[k.min(1)], direction as f64);
        let plane = PhasePlane {
            a: d * p.a,
            b: d * p.b,
            c: d * p.c + TAU * offset as f64,
        };
        let axis = AxisDecoding {
            lattice_axis: k,
            direction,
            located,
        };
        Ok((plane, axis))
    }
}

/// Planar pose from the absolute planes (docs/design.md#megarena-pose): `x = −P·c_x/2π`,
/// `y = −P·c_y/2π`, `alpha` = direction of the x phase gradient, pixel size `P·|∇φ_x|/2π`.
pub fn pose_from_planes(planes: &PatternPlanes, period: f64) -> Pose {
    let [px, py] = planes;
    Pose::planar(
        -period * px.c / TAU,
        -period * py.c / TAU,
        px.angle(),
        period * px.frequency() / TAU,
    )
}

/// Image position of the pattern origin (both absolute phases 0), pixels from the centre pixel;
/// `None` for degenerate planes.
fn origin_offset(planes: &PatternPlanes) -> Option<Vector2<f64>> {
    let [px, py] = planes;
    let det = px.a * py.b - px.b * py.a;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let (u, v) = (-px.c, -py.c);
    Some(Vector2::new(
        (py.b * u - px.b * v) / det,
        (-py.a * u + px.a * v) / det,
    ))
}
