//! Stamp and bitmap markers (docs/design.md#stamp): identity and absolute pose of
//! markers drawn as 0/1 bitmaps on the half-period grid.
//!
//! Two ways to find them, chosen from the bitmaps ([`StampSearch::Auto`]):
//! * **framed** (stamps: bitmaps with a solid border ring): every quadrilateral outline of a region
//!   brighter or darker than its surroundings is a candidate (`quads`), in the polarity of that
//!   region; around its centre a square window, its weighted mean removed (the window's own
//!   spectrum would otherwise swamp a faint grid) and apodised by the flat-top radial window
//!   (docs/design.md#stamp-window), goes through the phase engine; the frame's size must agree with
//!   the measured period; the bitmap thumbnail read along the phase planes (`thumbnail`) is matched
//!   against every bitmap in its 8 dihedral orientations and a few period shifts (`matching`); the
//!   reading must be confident ([`StampParams::min_decode_confidence`]) and the frame it predicts
//!   must lie where the frame was found ([`StampParams::max_frame_offset`]), or, where an
//!   occluder bent the outline found, where the image shows its edges; the pose follows. Any
//!   number of stamps per image, several with the same bitmap included (the original keeps one of
//!   them).
//! * **full image** (other bitmaps, e.g. an HP code layout seen as a bitmap): the phase engine on
//!   the whole image, then the same thumbnail and matching over every position of the bitmap,
//!   then a second, apodised measurement in a window on the bitmap found (the whole-image fit
//!   weighs an off-centre marker unevenly and leaks at its edges: ~1e-3 rad, 5e-3 px).
//!
//! Poses (docs/design.md#frames): the pattern origin is the bitmap's central dot; `alpha` is the
//! direction of the bitmap's x axis (increasing column) in the image, averaged with that of its
//! y axis turned back by 90° (forward for a mirrored view), and the pixel size the mean of the
//! two grid frequencies. The central dot's image position is where the two phase planes take
//! the values the match assigns to it, which is exact for any affine view. A mirrored marker (a
//! flipped image or optical path) gets the proper rigid pose of the pattern seen from behind,
//! as HP codes do: `gamma = −π`, a half turn (`cTp = Rz(α)·Rx(π)·Trans(x, y, 0)`, so its y axis
//! appears at `alpha − π/2`).
//!
//! Differences from the original, on purpose: no silent loss of same-ID stamps; the thumbnail
//! covers the whole bitmap (frame included) instead of its interior, so the period shift is pinned
//! by the frame; the original's period-shift sign slip (docs/design.md#defect-stamp-shift) cannot
//! occur (the match states where the origin is in the thumbnail); mirrored markers are recognised
//! and reported with their proper pose (or dropped with [`StampParams::allow_mirrored`] off); the
//! window is sized from the frame (largest `2^a·3^b` side inside the dot field) rather than fixed;
//! a reading that is a near tie or a pose that disagrees with the frame is dropped, never reported.

mod matching;
mod quads;
mod thumbnail;
mod tracking;

pub use quads::{Quad, QuadParams};

use crate::error::{Error, Result};
use crate::grey_image::{GreyImage, Polarity};
use crate::layout::BitmapLayout;
use crate::marker_tilt::{marker_tilt, MarkerTilt, TiltInput};
use crate::parallel;
use crate::phase::{
    fit_dot_field_against, fit_dot_field_tracked, wrap_angle, FieldFit, NodeMask, PhaseAnalysis,
    PhaseEngine, PhaseParams, PhasePlane, Rival, TiltStart, MIN_IMAGE_SIDE,
};
use crate::pose::Pose;
use matching::{best_match, Match, SearchRange, Template};
use nalgebra::{Matrix2, Matrix3, Vector2};
use quads::{Candidate, QuadFinder};
use std::f64::consts::{PI, TAU};

/// Largest bend of a frame outline ([`Quad::perspective_bend`]), in thumbnail cells, below
/// which the affine view is not read as well: the outline's view and the affine one then
/// sample every cell within its middle (each cell is read over ±1/6 of a cell) and give the
/// same reading.
const MAX_UNTESTED_BEND: f64 = 0.1;

/// How markers are searched for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum StampSearch {
    /// Framed when every bitmap has a solid border ring, full image when none has; a mix is an
    /// error.
    #[default]
    Auto,
    /// Find each marker by its frame (stamps); any number per image.
    Framed,
    /// One marker, measured on the whole image.
    FullImage,
}

/// Settings of [`StampDetector`].
#[derive(Clone, Debug)]
pub struct StampParams {
    /// Physical period `P` of the dot grid, pattern units (µm by convention). Must be > 0. The
    /// bitmaps' own periods are ignored.
    pub period: f64,
    /// The marker bitmaps; a marker's ID is the index of its bitmap here. Dimensions ≡ 1 (mod 4)
    /// (guaranteed by [`BitmapLayout`]), any mix of sizes.
    pub bitmaps: Vec<BitmapLayout>,
    /// Side of the square window analysed around each framed marker, pixels. Default `None`:
    /// the largest `2^a·3^b` that fits in the dot field inside the frame.
    pub window_size: Option<usize>,
    /// Dot polarity. `None` (default): frames of both polarities are searched and each
    /// marker is measured in its own (a stamp brighter or darker than its surroundings);
    /// `Some(p)` only accepts markers of polarity `p` (dark-dot images are inverted first).
    pub polarity: Option<Polarity>,
    /// Framed or full-image search.
    pub search: StampSearch,
    /// Frame (quadrilateral) search settings.
    pub quads: QuadParams,
    /// Exponent of the radial apodisation `(1 + cos(π·(d/ρ)^e))/2` of the window. Default 4
    /// (the original's flat top).
    pub apodization_exponent: f64,
    /// Smallest accepted correlation between thumbnail and bitmap, `[−1, 1]`. Default 0.5.
    pub min_correlation: f64,
    /// Smallest accepted decode confidence ([`StampDetection::decode_confidence`], `[0, 1]`).
    /// Default 0.5: on the cells that tell the reading from its closest rival (another
    /// bitmap, orientation or period shift), at least three quarters must read clearly as it
    /// predicts. A wrong reading is a near tie (≈ 0); a clean stamp scores ≈ 1, and dust or a
    /// hair over up to half of its distinguishing cells (no evidence either way) leaves 0.5.
    pub min_decode_confidence: f64,
    /// How far (in periods, along each axis) the window centre may be from the marker's
    /// central dot for the match to find it. Default 2 (the frame centre is much closer).
    pub max_center_offset: usize,
    /// Largest relative difference between a frame's size and the bitmap size times the
    /// measured period. Default 0.15.
    pub size_tolerance: f64,
    /// Largest distance between the centre of the frame found and that of the frame predicted
    /// by the fine pose (the bitmap's outline placed by the phase planes and the match), in
    /// grid periods. Default 0.5: the frame is what pins the period shift, so a pose one or
    /// more periods off (a grid matched at the wrong shift, a false marker beside a real one)
    /// is dropped, while the frame's edges are located to a small fraction of a period. Beyond
    /// it the outline found may have been bent by a hair or dust stuck to the frame, so the
    /// reading still stands if the image shows the frame's edges all round where the pose puts
    /// them rather than a period out (docs/design.md#stamp-matching). (The frame's size is
    /// checked by [`StampParams::size_tolerance`].)
    pub max_frame_offset: f64,
    /// Report mirrored markers (a flipped image or optical path), with their proper rigid pose
    /// (`gamma = −π`, see the module docs). Default true; false drops them (and mirrored
    /// readings are then no rivals of proper ones in the decode confidence).
    pub allow_mirrored: bool,
    /// After decoding, refine the planes on the bitmap's whole regular dot field, robustly
    /// (docs/design.md#field-fit): every dot with a plain periodic neighbourhood in the
    /// bitmap, dust and hair down-weighted. Default `true`; the window's planes give the pose
    /// when `false`.
    pub field_fit: bool,
    /// Threads running the whole-field fits of a frame's stamps in parallel (they are
    /// independent); 0 (default) = every core the system offers. Results do not depend on it.
    pub threads: usize,
    /// Phase-engine settings.
    pub phase: PhaseParams,
    /// Measure each stamp's out-of-plane angles `beta`, `gamma`
    /// ([`StampDetection::out_of_plane`], docs/design.md#pose-3d-markers) from its whole-field
    /// fit (its window's planes without one). Default `false`.
    pub pose_3d: bool,
    /// Focal length of a perspective camera, pixels (principal point at the image centre):
    /// with [`StampParams::pose_3d`], each stamp's depth `z` and the perspective solution.
    /// `None` (default): orthographic optics, `z` unknown.
    pub focal_length_px: Option<f64>,
}

impl StampParams {
    /// Defaults for `bitmaps` at physical period `period` (pattern units).
    pub fn new(period: f64, bitmaps: Vec<BitmapLayout>) -> Self {
        StampParams {
            period,
            bitmaps,
            window_size: None,
            polarity: None,
            search: StampSearch::Auto,
            quads: QuadParams::default(),
            apodization_exponent: 4.0,
            min_correlation: 0.5,
            min_decode_confidence: 0.5,
            max_center_offset: 2,
            size_tolerance: 0.15,
            max_frame_offset: 0.5,
            allow_mirrored: true,
            field_fit: true,
            threads: 0,
            phase: PhaseParams::default(),
            pose_3d: false,
            focal_length_px: None,
        }
    }

    /// Checks every field, naming the first invalid one; returns the resolved search mode.
    fn validate(&self) -> Result<StampSearch> {
        crate::marker_tilt::check_focal_length(self.focal_length_px)?;
        if !(self.period.is_finite() && self.period > 0.0) {
            return Err(Error::parameter(
                "period",
                format!("must be > 0, got {}", self.period),
            ));
        }
        if self.bitmaps.is_empty() {
            return Err(Error::parameter(
                "bitmaps",
                "at least one bitmap is required",
            ));
        }
        if let Some(size) = self.window_size {
            if size < MIN_IMAGE_SIDE {
                return Err(Error::parameter(
                    "window_size",
                    format!("must be ≥ {MIN_IMAGE_SIDE} pixels, got {size}"),
                ));
            }
        }
        if !(self.apodization_exponent.is_finite() && self.apodization_exponent > 0.0) {
            return Err(Error::parameter(
                "apodization_exponent",
                format!("must be > 0, got {}", self.apodization_exponent),
            ));
        }
        if !(-1.0..=1.0).contains(&self.min_correlation) {
            return Err(Error::parameter(
                "min_correlation",
                format!("must be in [−1, 1], got {}", self.min_correlation),
            ));
        }
        if self.max_center_offset > 64 {
            return Err(Error::parameter(
                "max_center_offset",
                format!("must be ≤ 64 periods, got {}", self.max_center_offset),
            ));
        }
        if !(self.size_tolerance > 0.0 && self.size_tolerance < 1.0) {
            return Err(Error::parameter(
                "size_tolerance",
                format!("must be in (0, 1), got {}", self.size_tolerance),
            ));
        }
        if !(0.0..=1.0).contains(&self.min_decode_confidence) {
            return Err(Error::parameter(
                "min_decode_confidence",
                format!("must be in [0, 1], got {}", self.min_decode_confidence),
            ));
        }
        if !(self.max_frame_offset.is_finite() && self.max_frame_offset > 0.0) {
            return Err(Error::parameter(
                "max_frame_offset",
                format!("must be > 0 periods, got {}", self.max_frame_offset),
            ));
        }
        validate_quads(&self.quads)?;
        self.phase.validate()?;
        self.resolved_search()
    }

    /// The search mode, `Auto` resolved from the bitmaps (all framed or none).
    fn resolved_search(&self) -> Result<StampSearch> {
        let framed = self
            .bitmaps
            .iter()
            .filter(|b| frame_thickness(b) > 0)
            .count();
        match self.search {
            StampSearch::Auto if framed == self.bitmaps.len() => Ok(StampSearch::Framed),
            StampSearch::Auto if framed == 0 => Ok(StampSearch::FullImage),
            StampSearch::Auto => Err(Error::parameter(
                "bitmaps",
                "mix of framed (stamp) and unframed bitmaps: choose the search mode explicitly",
            )),
            StampSearch::Framed if framed < self.bitmaps.len() => Err(Error::parameter(
                "bitmaps",
                "framed search needs bitmaps with a solid border ring (stamps)",
            )),
            mode => Ok(mode),
        }
    }
}

/// Checks the frame search's settings, naming the first invalid one.
fn validate_quads(q: &QuadParams) -> Result<()> {
    if q.threshold_window < 2 {
        return Err(Error::parameter(
            "threshold_window",
            format!("must be ≥ 2 pixels, got {}", q.threshold_window),
        ));
    }
    if !(q.min_side.is_finite() && q.min_side > 0.0) {
        return Err(Error::parameter(
            "min_side",
            format!("must be > 0 pixels, got {}", q.min_side),
        ));
    }
    if !(1..=8).contains(&q.decimation) {
        return Err(Error::parameter(
            "decimation",
            format!("must be in 1..=8, got {}", q.decimation),
        ));
    }
    if !(q.outline_tolerance.is_finite() && q.outline_tolerance >= 0.0) {
        return Err(Error::parameter(
            "outline_tolerance",
            format!("must be ≥ 0, got {}", q.outline_tolerance),
        ));
    }
    if q.levels > 5 {
        return Err(Error::parameter(
            "levels",
            format!("must be in 0..=5, got {}", q.levels),
        ));
    }
    Ok(())
}

/// One marker found.
#[derive(Clone, Debug)]
pub struct StampDetection {
    /// Index of the marker's bitmap in [`StampParams::bitmaps`].
    pub id: usize,
    /// Pose of the bitmap's pattern frame (origin at its central dot), see the module docs.
    pub pose: Pose,
    /// Image position `(col, row)` of the central dot, pixels.
    pub origin_px: Vector2<f64>,
    /// The marker is seen mirrored (see [`StampParams::allow_mirrored`]).
    pub mirrored: bool,
    /// Pearson correlation between the thumbnail and the bitmap, `[−1, 1]`, on the thumbnail's
    /// levels flattened for the light (docs/design.md#stamp-matching; raw levels for a bitmap
    /// without isolated dots or open gaps).
    pub correlation: f64,
    /// Confidence of the decoding, `[0, 1]`: on the bitmap cells where the winning hypothesis
    /// and a rival (the best other orientation or period shift, and every other bitmap) predict
    /// different values, the fraction of cells read as the winner predicts minus the fraction
    /// read as the rival predicts, each cell weighted by how well its 8 neighbours read as the
    /// winner predicts (a cell under dust or a hair is no evidence); the smallest over the
    /// rivals, clamped at 0.
    pub decode_confidence: f64,
    /// The frame outline, for framed markers.
    pub frame: Option<Quad>,
    /// Polarity the marker was measured in (the setting's, or found from its frame).
    pub polarity: Polarity,
    /// Image pixel `(col, row)` at the centre of the analysed window.
    pub window_center: (i64, i64),
    /// Side of the analysed square window, pixels (the image size for full-image search).
    pub window_size: usize,
    /// Phase-engine output of the analysed window (planes in the window's frame).
    pub analysis: PhaseAnalysis,
    /// The whole-field fit that gave the pose (docs/design.md#field-fit); `None` when the
    /// window's planes gave it ([`StampParams::field_fit`] off, or a field too small to fit).
    pub field: Option<FieldFit>,
    /// Standard deviation of the pattern-x and pattern-y phases at the origin, radians.
    pub phase_std: [f64; 2],
    /// Standard deviation of `pose.alpha` from the whole-field fit, radians; `None` without it.
    pub yaw_std: Option<f64>,
    /// The out-of-plane pose ([`StampParams::pose_3d`]); `None` when not asked for, or when
    /// the stamp's planes have no 3-D solution (logged).
    pub out_of_plane: Option<MarkerTilt>,
}

/// Finds stamp / bitmap markers and measures their absolute poses. Keeps FFT plans, the
/// apodisation windows and the frame-search buffers between frames.
///
/// # Example
///
/// ```
/// use vernier::layout::BitmapLayout;
/// use vernier::phase::wrap_to_pi;
/// use vernier::render::{render, RenderOptions};
/// use vernier::stamp::{StampDetector, StampParams};
/// use vernier::Pose;
///
/// # fn main() -> vernier::Result<()> {
/// // A 69 × 69-cell stamp: a 3-cell solid frame, a 1-cell gap, 31 × 31 dots on the even
/// // cells and a solid L-shaped glyph that breaks the symmetry.
/// let n = 69;
/// let rows: Vec<Vec<u8>> = (0..n)
///     .map(|r| {
///         (0..n)
///             .map(|c| {
///                 let frame = r < 3 || c < 3 || r >= n - 3 || c >= n - 3;
///                 let inside = (4..n - 4).contains(&r) && (4..n - 4).contains(&c);
///                 let dot = inside && r % 2 == 0 && c % 2 == 0;
///                 let glyph = ((8..19).contains(&r) && (50..53).contains(&c))
///                     || ((16..19).contains(&r) && (50..61).contains(&c));
///                 u8::from(frame || dot || glyph)
///             })
///             .collect()
///     })
///     .collect();
/// let bitmap = BitmapLayout::from_rows(10.0, &rows)?;
///
/// // 10 µm period at 2 µm per pixel: 5 px per period, a 173-px stamp turned by 0.25 rad.
/// let truth = Pose::planar(3.0, -2.0, 0.25, 2.0);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(256, 256) };
/// let image = render(&bitmap, &truth, &options)?;
///
/// let mut detector = StampDetector::new(StampParams::new(10.0, vec![bitmap]))?;
/// let stamps = detector.detect(&image)?;
/// assert_eq!(stamps.len(), 1);
/// let (stamp, tolerance) = (&stamps[0], 0.01 * truth.pixel_size);
/// assert_eq!(stamp.id, 0); // index of its bitmap
/// assert!((stamp.pose.x - truth.x).abs() < tolerance);
/// assert!((stamp.pose.y - truth.y).abs() < tolerance);
/// assert!(wrap_to_pi(stamp.pose.alpha - truth.alpha).abs() < 1e-4);
/// # Ok(())
/// # }
/// ```
pub struct StampDetector {
    params: StampParams,
    mode: StampSearch,
    engine: PhaseEngine,
    templates: Vec<Template>,
    /// Per bitmap: its `(cols, rows)` and dot-field side as a fraction of its side.
    shapes: Vec<([usize; 2], f64)>,
    /// Frame thickness over side, per bitmap.
    frame_fractions: Vec<f64>,
    finder: QuadFinder,
    windows: crate::lru::Lru<usize, Vec<f32>>,
    /// Windows measured in the current frame: centre, side and bright-dot analysis.
    measured: Vec<((i64, i64), usize, PhaseAnalysis)>,
}

/// Apodisation windows kept (one per window size in use).
const CACHED_WINDOWS: usize = 4;

/// A marker read in its window (bitmap matched, frame consistent), before its whole-field fit.
struct WindowReading {
    found: Match,
    /// The window's planes, frame of `origin`.
    planes: [PhasePlane; 2],
    /// The window's centre pixel, image coordinates.
    origin: Vector2<f64>,
    frame: Option<Quad>,
    center: (i64, i64),
    size: usize,
    analysis: PhaseAnalysis,
    polarity: Polarity,
}

/// One window's grid as the stages of [`StampDetector::read_window`] see it.
struct WindowGrid<'a> {
    image: &'a GreyImage,
    center: (i64, i64),
    /// The window's centre pixel, image coordinates (the planes' origin).
    origin: Vector2<f64>,
    planes: [PhasePlane; 2],
    /// Mean pixel period of the planes.
    period: f64,
    polarity: Polarity,
}

impl StampDetector {
    /// A detector with `params` (validated).
    pub fn new(params: StampParams) -> Result<Self> {
        // The shared physical ranges (vernier::limits) first, then the detector's own rules.
        crate::limits::check_period(params.period)?;
        if let Some(size) = params.window_size {
            crate::limits::check_window_size(size)?;
        }
        let mode = params.validate()?;
        let templates = params.bitmaps.iter().map(Template::new).collect();
        let side = |b: &BitmapLayout| b.cell_cols().min(b.cell_rows()) as f64;
        let shapes = params
            .bitmaps
            .iter()
            .map(|b| {
                let interior = side(b) - 2.0 * (frame_thickness(b) as f64 + 1.0);
                (
                    [b.cell_cols(), b.cell_rows()],
                    (interior / side(b)).max(0.0),
                )
            })
            .collect();
        let frame_fractions = params
            .bitmaps
            .iter()
            .map(|b| frame_thickness(b) as f64 / side(b))
            .collect();
        Ok(StampDetector {
            params,
            mode,
            engine: PhaseEngine::new(),
            templates,
            shapes,
            frame_fractions,
            finder: QuadFinder::default(),
            windows: crate::lru::Lru::new(CACHED_WINDOWS),
            measured: Vec::new(),
        })
    }

    /// Current settings.
    pub fn params(&self) -> &StampParams {
        &self.params
    }

    /// The search mode in use (never [`StampSearch::Auto`]).
    pub fn search(&self) -> StampSearch {
        self.mode
    }

    /// Detects every marker in `image`.
    ///
    /// Framed search: markers sorted by decreasing frame size; none found is an empty list.
    /// Full-image search: one marker, or [`Error::PatternNotFound`] when the grid or the bitmap
    /// is not recognised.
    pub fn detect(&mut self, image: &GreyImage) -> Result<Vec<StampDetection>> {
        // Phase analyses are shared within one image only.
        self.measured.clear();
        match self.mode {
            StampSearch::FullImage => {
                let image = image.as_bright_dots(self.params.polarity.unwrap_or_default());
                self.measure_full(&image).map(|d| vec![d])
            }
            _ => {
                let mut read: Vec<WindowReading> = Vec::new();
                for candidate in self.candidates(image) {
                    // Outermost only: a candidate inside an accepted frame is part of it.
                    let c = candidate.quad.center();
                    if read
                        .iter()
                        .filter_map(|r| r.frame.as_ref())
                        .any(|f| f.contains(c))
                    {
                        continue;
                    }
                    if let Some(r) = self.read_framed(image, candidate)? {
                        read.push(r);
                    }
                }
                // The whole-field fits, the costly part, one stamp per thread.
                let this = &*self;
                let mut workers = vec![(); parallel::thread_count(this.params.threads, read.len())];
                let fits = parallel::map_in_order(&mut workers, &read, |_, r| {
                    this.field_for(image, r, None)
                })
                .ok_or_else(|| {
                    Error::PatternNotFound("internal: a stamp-measuring thread panicked".into())
                })?;
                Ok(read
                    .into_iter()
                    .zip(fits)
                    .filter_map(|(r, fit)| this.finish(image, r, fit))
                    .collect())
            }
        }
    }

    /// Frame candidates of the polarities searched, refined, in the order to try them.
    fn candidates(&mut self, image: &GreyImage) -> Vec<Candidate> {
        let shapes: Vec<[usize; 2]> = self.shapes.iter().map(|s| s.0).collect();
        let found = self.finder.find(
            image,
            &self.params.quads,
            self.params.polarity,
            &self.frame_fractions,
            &|q| plausible_outline(q, &shapes),
        );
        log::debug!("stamp: {} frame candidates", found.len());
        for c in &found {
            log::trace!(
                "candidate {:?} centre {:.1?} sides {:.1?}",
                c.polarity,
                c.quad.center(),
                c.quad.sides()
            );
        }
        found
    }

    /// The polarities searched: the setting's, or both.
    fn polarities(&self) -> Vec<Polarity> {
        match self.params.polarity {
            Some(p) => vec![p],
            None => vec![Polarity::BrightDots, Polarity::DarkDots],
        }
    }

    /// Quadrilateral outlines (frame candidates, refined) of `image`, in the order they are
    /// tried (likely frames first, then largest first), before any check against the bitmaps
    /// (for display and diagnostics).
    pub fn find_frames(&mut self, image: &GreyImage) -> Vec<Quad> {
        self.candidates(image).into_iter().map(|c| c.quad).collect()
    }

    /// Measures a marker whose central dot is near the image pixel `center` (within
    /// [`StampParams::max_center_offset`] periods), in a `window_size` square window (default:
    /// [`StampParams::window_size`], else 256), without searching for its frame: for tracking
    /// a marker from frame to frame. `None` when no bitmap matches there.
    pub fn measure_at(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        window_size: Option<usize>,
    ) -> Result<Option<StampDetection>> {
        let size = window_size.or(self.params.window_size).unwrap_or(256);
        if size < MIN_IMAGE_SIDE {
            return Err(Error::parameter(
                "window_size",
                format!("must be ≥ {MIN_IMAGE_SIDE} pixels, got {size}"),
            ));
        }
        // A window entirely off the image sees nothing (and far-off centres would overflow).
        let (w, h) = (image.width() as i64, image.height() as i64);
        let reach = size as i64;
        if !(-reach..w + reach).contains(&center.0) || !(-reach..h + reach).contains(&center.1) {
            return Ok(None);
        }
        self.measured.clear();
        for polarity in self.polarities() {
            let reading = self.read_window(image, center, size, None, polarity)?;
            if let Some(d) = reading.and_then(|r| self.measured(image, r)) {
                return Ok(Some(d));
            }
        }
        Ok(None)
    }

    /// A framed candidate: window at the frame centre, sized to the dot field, read in the
    /// candidate's polarity.
    fn read_framed(
        &mut self,
        image: &GreyImage,
        candidate: Candidate,
    ) -> Result<Option<WindowReading>> {
        let quad = candidate.quad;
        let c = quad.center();
        let center = (c.x.round() as i64, c.y.round() as i64);
        let size = match self.params.window_size {
            Some(s) => s,
            None => {
                // The mean side: less sensitive than the shortest to where the outline's
                // corners fall (the size steps between fast FFT sizes).
                let side = quad.mean_side();
                let fraction = self
                    .shapes
                    .iter()
                    .map(|s| s.1)
                    .fold(f64::INFINITY, f64::min);
                crate::phase::fft_size::at_most((side * fraction).floor() as usize)
            }
        };
        if size < MIN_IMAGE_SIDE {
            return Ok(None);
        }
        self.read_window(image, center, size, Some(quad), candidate.polarity)
    }

    /// The `size` window of `image` centred on `center` as the phase engine gets it (bright
    /// dots): its window-weighted mean removed, apodised, 0 outside the image; with the
    /// variance of the source's rounding there (intensity units²).
    fn window_image(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        size: usize,
    ) -> Result<(GreyImage, f64)> {
        // The part of the window inside the image: window indices [lo, hi) on each axis, and
        // the image index of lo.
        let half = (size / 2) as i64;
        let span = |c: i64, len: usize| {
            let first = c - half;
            let lo = (-first).clamp(0, size as i64) as usize;
            let hi = ((len as i64 - first).clamp(0, size as i64) as usize).max(lo);
            (lo, hi, (first + lo as i64).max(0) as usize)
        };
        let (c0, c1, src_c) = span(center.0, image.width());
        let (r0, r1, src_r) = span(center.1, image.height());
        let mut pixels = vec![0.0f32; size * size];
        let weights = self.apodization(size);
        let src = image.pixels();
        let w = image.width();
        let (mut sum_w, mut sum_wv) = (0.0f64, 0.0f64);
        for r in r0..r1 {
            let from = (src_r + r - r0) * w + src_c;
            let row = &src[from..from + (c1 - c0)];
            let wrow = &weights[r * size + c0..r * size + c1];
            let (mut sw, mut swv) = (0.0f32, 0.0f32);
            for (&v, &k) in row.iter().zip(wrow) {
                sw += k;
                swv += k * v;
            }
            sum_w += sw as f64;
            sum_wv += swv as f64;
        }
        let mean = if sum_w > 0.0 {
            (sum_wv / sum_w) as f32
        } else {
            0.0
        };
        // Outside the image the window holds the mean (0 once removed): no step at the border.
        for r in r0..r1 {
            let from = (src_r + r - r0) * w + src_c;
            let row = &src[from..from + (c1 - c0)];
            let wrow = &weights[r * size + c0..r * size + c1];
            for ((o, &v), &k) in pixels[r * size + c0..r * size + c1]
                .iter_mut()
                .zip(row)
                .zip(wrow)
            {
                *o = (v - mean) * k;
            }
        }
        let window = GreyImage::new(size, size, pixels)?;
        // The source's rounding, which the apodisation (each pixel scaled by its weight) hides
        // from the window's own values; the weight is ~1 where the engine's sine-cubed weight
        // lies, so the window keeps the source's Δ²/12 (docs/design.md#uncertainty).
        let rounding = crate::phase::quantisation_variance_in(
            src,
            w,
            src_r..src_r + (r1 - r0),
            src_c..src_c + (c1 - c0),
        );
        Ok((window, rounding))
    }

    /// The bright-dot phase analysis of the `size` window at `center`: one measured already in
    /// this frame at nearly the same place (its centre within 2 % of the side: concentric
    /// candidates, such as a frame and the moat or threshold halo around it), its planes moved
    /// to `center`, or a new one. `None` when the engine finds no grid.
    fn analysis_at(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        size: usize,
        periods: Option<(f64, f64)>,
    ) -> Result<Option<PhaseAnalysis>> {
        let near = |c: &(i64, i64)| {
            let d = ((c.0 - center.0) as f64).hypot((c.1 - center.1) as f64);
            d <= 0.02 * size as f64
        };
        if let Some((c, _, a)) = self.measured.iter().find(|(c, s, _)| *s == size && near(c)) {
            let (dx, dy) = ((center.0 - c.0) as f64, (center.1 - c.1) as f64);
            log::debug!("stamp at {center:?}: phase planes of the window at {c:?} reused");
            let mut moved = a.clone();
            for p in moved.planes.iter_mut() {
                p.c += p.a * dx + p.b * dy;
            }
            return Ok(Some(moved));
        }
        let (window, rounding) = self.window_image(image, center, size)?;
        let mut params = self.params.phase.clone();
        params.rounding_variance = params.rounding_variance.max(rounding);
        if let Some((lo, hi)) = periods {
            // Lobes only where the frame says the grid is: a hair, JPEG blocks or a clutter
            // grid in the window cannot stand in for it.
            let band = (size as f64 / hi, size as f64 / lo);
            params.min_frequency = params.min_frequency.max(band.0);
            params.max_frequency = params.max_frequency.min(band.1);
            if params.max_frequency <= params.min_frequency {
                return Ok(None);
            }
        }
        let analysis = self.engine.analyze(&window, &params);
        match analysis {
            Ok(a) => {
                self.measured.push((center, size, a.clone()));
                Ok(Some(a))
            }
            Err(Error::PatternNotFound(why)) => {
                log::debug!("stamp at {center:?}: no grid ({why})");
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }

    /// Phase, frame-size check, match and frame consistency in a `size` window centred on
    /// `center`, for markers of `polarity`: the marker read, before its whole-field fit.
    fn read_window(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        size: usize,
        frame: Option<Quad>,
        polarity: Polarity,
    ) -> Result<Option<WindowReading>> {
        let periods = frame.as_ref().map(|q| self.expected_periods(q));
        let Some(mut analysis) = self.analysis_at(image, center, size, periods)? else {
            return Ok(None);
        };
        if polarity == Polarity::DarkDots {
            // The analysis of the negated window: every phase moves by π (dark dots at 0).
            for p in analysis
                .planes
                .iter_mut()
                .chain(&mut analysis.bandpass_planes)
            {
                p.c += PI;
            }
        }
        let planes = analysis.planes.map(|p| p.with_wrapped_offset());
        let period = analysis.mean_pixel_period();
        if let Some(q) = &frame {
            if !self.shapes.iter().any(|s| self.frame_fits(q, &planes, s.0)) {
                log::debug!(
                    "stamp at {center:?}: frame size does not fit the grid period {period:.2} px"
                );
                return Ok(None);
            }
        }
        let grid = WindowGrid {
            image,
            center,
            origin: Vector2::new(center.0 as f64, center.1 as f64),
            planes,
            period,
            polarity,
        };
        let Some(found) = self.read_bitmap(&grid, frame.as_ref()) else {
            return Ok(None);
        };
        let frame = match frame {
            None => None,
            Some(q) => match self.confirmed_frame(&grid, q, &found) {
                Some(q) => Some(q),
                None => return Ok(None),
            },
        };
        Ok(Some(WindowReading {
            found,
            planes,
            origin: grid.origin,
            frame,
            center,
            size,
            analysis,
            polarity,
        }))
    }

    /// The bitmap read in the window's thumbnail (through the frame's perspective where it
    /// bends the view), or `None` when no reading is accepted.
    fn read_bitmap(&self, grid: &WindowGrid, frame: Option<&Quad>) -> Option<Match> {
        let (center, planes, polarity) = (grid.center, &grid.planes, grid.polarity);
        // Thumbnail wide enough for the largest bitmap at the largest centre offset, plus a
        // margin of background.
        let reach = self
            .templates
            .iter()
            .map(|t| t.half[0].max(t.half[1]))
            .max()
            .unwrap_or(0);
        let half = reach + self.origin_reach() + 2;
        let thumb_at = |warp: Option<&Matrix3<f64>>| {
            self.matched_thumbnail(grid.image, grid.origin, planes, half, polarity, warp)
        };
        // Perspective: the frame's outline says how the affine view of the planes bends,
        // unless an occluder bent the outline (a hair or a dust speck stuck to the frame).
        // Where the bend moves cells and the outline's view reads nothing acceptable, the
        // affine view is read too, and stands if its reading is accepted.
        let cell_px = 0.5 * grid.period;
        let warp = frame.and_then(|q| Some((q.perspective_warp()?, q.perspective_bend()?)));
        let accepted = |m: &Match| self.reading_rejected(m).is_none();
        let found = match warp {
            None => thumb_at(None),
            Some((warp, bend)) => {
                let warped = thumb_at(Some(&warp));
                if !warped.as_ref().is_some_and(accepted) && bend > MAX_UNTESTED_BEND * cell_px {
                    thumb_at(None).filter(accepted).or(warped)
                } else {
                    warped
                }
            }
        };
        let found = found?;
        if let Some(why) = self.reading_rejected(&found) {
            log::debug!("stamp at {center:?}: {why}");
            return None;
        }
        Some(found)
    }

    /// The frame `q` found around the window if it fits bitmap `found` and sits where the
    /// pose puts it (or the predicted frame where the image shows one there: the outline
    /// was bent by an occluder); `None` rejects the reading.
    fn confirmed_frame(&self, grid: &WindowGrid, q: Quad, found: &Match) -> Option<Quad> {
        let (center, period) = (grid.center, grid.period);
        if !self.frame_fits(&q, &grid.planes, self.shapes[found.bitmap].0) {
            log::debug!(
                "stamp at {center:?}: frame size does not fit bitmap {}",
                found.bitmap
            );
            return None;
        }
        let predicted = self.predicted_frame(found, &grid.planes, grid.origin)?;
        // Centres, not corners: perspective bends the corners away from the affine view of
        // the phase planes (0.6 period on stamp1.png), not the centre.
        let offset = (q.center() - predicted.center()).norm() / period;
        let mut frame = q;
        if offset > self.params.max_frame_offset {
            // The outline found may be bent by an occluder stuck to the frame: the image
            // must then show the frame where the pose puts it, not a period away.
            // (A frame is drawn in the dots' material.)
            if !predicted.edges_confirmed(grid.image, grid.polarity, period) {
                log::debug!(
                    "stamp at {center:?}: the pose puts the frame {offset:.2} periods from \
                     the one found (max_frame_offset {}) and the image shows no frame there",
                    self.params.max_frame_offset
                );
                return None;
            }
            log::debug!(
                "stamp at {center:?}: the outline found is {offset:.2} periods off, the \
                 frame is where the pose puts it (outline bent by an occluder)"
            );
            frame = predicted;
        }
        log::debug!(
            "stamp at {center:?}: bitmap {} (correlation {:.3}, confidence {:.3}, frame \
             offset {offset:.2} periods)",
            found.bitmap,
            found.correlation,
            found.vote
        );
        Some(frame)
    }

    /// How far from the window centre the bitmap's central dot is searched for, thumbnail
    /// cells along each axis ([`StampParams::max_center_offset`] periods).
    fn origin_reach(&self) -> i64 {
        2 * self.params.max_center_offset as i64
    }

    /// The best reading of the thumbnail of `2·half + 1` cells a side sampled about the
    /// plane origin `origin` (image pixels), dots of `polarity`, every sample moved by `warp`
    /// (see [`thumbnail::sample`]); `None` when it leaves the image or nothing matches.
    fn matched_thumbnail(
        &self,
        image: &GreyImage,
        origin: Vector2<f64>,
        planes: &[PhasePlane; 2],
        half: i64,
        polarity: Polarity,
        warp: Option<&Matrix3<f64>>,
    ) -> Option<Match> {
        let len = (2 * half + 1) as usize;
        let mut thumb = thumbnail::sample(image, origin, planes, [-half, -half], [len, len], warp)?;
        if polarity == Polarity::DarkDots {
            // Dots (set cells) darker: the matching wants them high.
            for v in thumb.values.iter_mut().flatten() {
                *v = -*v;
            }
        }
        let shift = self.origin_reach();
        let range = SearchRange {
            origin: [[-shift, shift], [-shift, shift]],
            mirrored_allowed: self.params.allow_mirrored,
            min_overlap: 0.5,
        };
        best_match(&thumb, &self.templates, &range)
    }

    /// The detection of a marker read in its window, whole-field fit included.
    fn measured(&self, image: &GreyImage, reading: WindowReading) -> Option<StampDetection> {
        let field = self.field_for(image, &reading, None);
        self.finish(image, reading, field)
    }

    /// The whole-field fit of a marker read in its window, with its planes (frame of the
    /// reading's origin), when it beats the window's (`None`: the window's planes stand);
    /// started from `previous`, the last frame's fit of the marker, when tracking.
    fn field_for(
        &self,
        image: &GreyImage,
        reading: &WindowReading,
        previous: Option<&FieldFit>,
    ) -> Option<([PhasePlane; 2], FieldFit)> {
        let (icx, icy) = image.center();
        let at = Vector2::new(
            (reading.center.0 - icx as i64) as f64,
            (reading.center.1 - icy as i64) as f64,
        );
        let rival = Rival {
            phase_std: reading.analysis.phase_std,
            at: (at.x, at.y),
        };
        self.refine_on_field(image, reading, rival, previous)
            .filter(|(_, fit)| fit.beats(&rival))
    }

    /// The detection of a marker read in its window, with the planes of its whole-field fit
    /// when there is one.
    fn finish(
        &self,
        image: &GreyImage,
        reading: WindowReading,
        field: Option<([PhasePlane; 2], FieldFit)>,
    ) -> Option<StampDetection> {
        let planes = field.as_ref().map_or(reading.planes, |(p, _)| *p);
        let polarity = reading.polarity;
        let found = reading.found;
        self.detection(
            found,
            &planes,
            reading.origin,
            image,
            reading.frame,
            reading.center,
            reading.size,
            reading.analysis,
        )
        .map(|d| {
            let (icx, icy) = image.center();
            let at = d.origin_px - Vector2::new(icx as f64, icy as f64);
            let out_of_plane = match &field {
                Some((_, fit)) if self.params.pose_3d => {
                    let axes = found.orientation.matrix();
                    let input = TiltInput::from_field(fit, axes, at, found.orientation.mirrored);
                    self.tilt(&input, d.id)
                }
                _ => d.out_of_plane,
            };
            let (phase_std, yaw_std, field) = match field {
                Some((_, fit)) => {
                    let s =
                        in_pattern_order(found.orientation.matrix(), fit.phase_std_at(at.x, at.y));
                    (s, Some(fit.mean_direction_std()), Some(fit))
                }
                None => (d.phase_std, None, None),
            };
            StampDetection {
                polarity,
                field,
                phase_std,
                yaw_std,
                out_of_plane,
                ..d
            }
        })
    }

    /// The reading's planes (frame of its origin) refined on the matched bitmap's whole dot
    /// field (docs/design.md#field-fit), with the fit; `None` when
    /// [`StampParams::field_fit`] is off or the fit fails or cannot beat `rival`, the
    /// window's fit (the window's planes stand). With `previous`, the fit starts from the
    /// last frame's model ([`fit_dot_field_tracked`]).
    fn refine_on_field(
        &self,
        image: &GreyImage,
        reading: &WindowReading,
        rival: Rival,
        previous: Option<&FieldFit>,
    ) -> Option<([PhasePlane; 2], FieldFit)> {
        let (found, planes, origin) = (&reading.found, &reading.planes, reading.origin);
        if !self.params.field_fit {
            return None;
        }
        let template = self.templates.get(found.bitmap)?;
        // Planes in the image frame (origin at the centre pixel) and back.
        let (icx, icy) = image.center();
        let shift = Vector2::new(icx as f64, icy as f64) - origin;
        let moved = |p: &PhasePlane, s: f64| PhasePlane {
            c: p.c + s * (p.a * shift.x + p.b * shift.y),
            ..*p
        };
        // Node k (φ = 2πk) is thumbnail cell 2k, bitmap cell R·(2k − origin cell).
        let r = found.orientation.matrix();
        let o = found.origin_cell;
        let reach = template.half[0].max(template.half[1]) / 2 + 1;
        let (c1, c2) = (o[0].div_euclid(2), o[1].div_euclid(2));
        let mask = NodeMask::from_cells(
            c1 - reach..=c1 + reach,
            c2 - reach..=c2 + reach,
            |v1, v2| {
                let d = [v1 - o[0], v2 - o[1]];
                template.is_set([
                    r[0][0] * d[0] + r[0][1] * d[1],
                    r[1][0] * d[0] + r[1][1] * d[1],
                ])
            },
        );
        // The stamp's origin, the pose's, is node o/2: the fit measures the tilt about it.
        let centre = [o[0] as f64 / 2.0, o[1] as f64 / 2.0];
        let start = planes.map(|p| moved(&p, 1.0));
        let perspective = reading
            .frame
            .as_ref()
            .and_then(|outline| self.outline_perspective(found, planes, origin, outline, centre));
        let tilt = TiltStart {
            centre,
            perspective: perspective.unwrap_or_default(),
        };
        let fit = match previous {
            Some(previous) => {
                fit_dot_field_tracked(image, start, &mask, Some(rival), Some(tilt), previous)
            }
            None => fit_dot_field_against(image, start, &mask, Some(rival), Some(tilt)),
        }?;
        Some((fit.planes.map(|p| moved(&p, -1.0)), fit))
    }

    /// The out-of-plane pose of stamp `id` measured from `input`; `None` (logged) when its
    /// planes have no 3-D solution.
    fn tilt(&self, input: &TiltInput, id: usize) -> Option<MarkerTilt> {
        marker_tilt(input, self.params.period, self.params.focal_length_px)
            .map_err(|e| log::warn!("stamp {id}: no out-of-plane pose: {e}"))
            .ok()
    }

    /// Why a match is not reported (`None`: it is).
    fn reading_rejected(&self, found: &Match) -> Option<String> {
        let p = &self.params;
        if found.correlation < p.min_correlation {
            Some(format!(
                "bitmap {} correlation {:.3} < min_correlation {}",
                found.bitmap, found.correlation, p.min_correlation
            ))
        } else if found.orientation.mirrored && !p.allow_mirrored {
            Some(format!(
                "bitmap {} seen mirrored (allow_mirrored is off)",
                found.bitmap
            ))
        } else if found.vote < p.min_decode_confidence {
            Some(format!(
                "bitmap {} read with confidence {:.3} < min_decode_confidence {}",
                found.bitmap, found.vote, p.min_decode_confidence
            ))
        } else {
            None
        }
    }

    /// Full-image search: phase on the whole image, match over every bitmap position.
    fn measure_full(&mut self, image: &GreyImage) -> Result<StampDetection> {
        let analysis = self.engine.analyze(image, &self.params.phase)?;
        let planes = analysis.planes.map(|p| p.with_wrapped_offset());
        let (cx, cy) = image.center();
        let origin = Vector2::new(cx as f64, cy as f64);
        // Cell ranges covered by the image: phases at its corners.
        let corners = image.corners_from_center();
        let mut lo = [i64::MAX; 2];
        let mut hi = [i64::MIN; 2];
        for (x, y) in corners {
            for k in 0..2 {
                let i = planes[k].at(x, y) / PI;
                lo[k] = lo[k].min(i.floor() as i64 - 1);
                hi[k] = hi[k].max(i.ceil() as i64 + 1);
            }
        }
        let len = [(hi[0] - lo[0] + 1) as usize, (hi[1] - lo[1] + 1) as usize];
        let not_found = |why: &str| Error::PatternNotFound(format!("bitmap marker: {why}"));
        let thumb = thumbnail::sample(image, origin, &planes, lo, len, None)
            .ok_or_else(|| not_found("degenerate phase planes"))?;
        let range = SearchRange {
            origin: [[lo[0], hi[0]], [lo[1], hi[1]]],
            mirrored_allowed: self.params.allow_mirrored,
            min_overlap: 0.5,
        };
        let found = best_match(&thumb, &self.templates, &range)
            .ok_or_else(|| not_found("no bitmap position overlaps the image enough"))?;
        if let Some(why) = self.reading_rejected(&found) {
            return Err(not_found(&why));
        }
        let size = image.width().max(image.height());
        let coarse = self
            .detection(
                found,
                &planes,
                origin,
                image,
                None,
                (cx as i64, cy as i64),
                size,
                analysis,
            )
            .ok_or_else(|| not_found("degenerate phase planes"))?;
        // Second pass in an apodised window on the bitmap itself: the whole-image fit weighs
        // the marker by wherever it sits under the engine's window and leaks at its hard edges.
        let dims = self.shapes[coarse.id].0;
        let period_px = self.params.period / coarse.pose.pixel_size;
        let side = dims[0].min(dims[1]) as f64 * period_px / 2.0;
        let window = self
            .params
            .window_size
            .unwrap_or(crate::phase::fft_size::at_most(side as usize));
        if window < 32 {
            return Ok(coarse);
        }
        let center = (
            coarse.origin_px.x.round() as i64,
            coarse.origin_px.y.round() as i64,
        );
        // `image` is already bright-dot.
        let fine = self
            .read_window(image, center, window, None, Polarity::BrightDots)?
            .and_then(|reading| self.measured(image, reading));
        match fine {
            Some(fine) if fine.id == coarse.id && fine.mirrored == coarse.mirrored => {
                Ok(StampDetection {
                    polarity: coarse.polarity,
                    ..fine
                })
            }
            _ => Ok(coarse),
        }
    }

    /// Whether the frame's size along the two grid directions matches a `[cols, rows]` bitmap
    /// at the measured period (either way round).
    fn frame_fits(&self, quad: &Quad, planes: &[PhasePlane; 2], dims: [usize; 2]) -> bool {
        let measure = |p: &PhasePlane| {
            let f = p.frequency();
            let dir = Vector2::new(p.a, p.b) / f;
            // Extent in half periods (cells): extent_px / (π/f).
            quad.extent_along(dir) * f / PI
        };
        let (e1, e2) = (measure(&planes[0]), measure(&planes[1]));
        log::trace!(
            "frame extents {:.4} {:.4} of {dims:?}",
            e1 / dims[0] as f64,
            e2 / dims[1] as f64
        );
        let close = |e: f64, n: usize| (e / n as f64 - 1.0).abs() <= self.params.size_tolerance;
        (close(e1, dims[0]) && close(e2, dims[1])) || (close(e1, dims[1]) && close(e2, dims[0]))
    }

    /// Range of grid periods (pixels) that a frame outline allows: each side over half its
    /// number of cells, either way round for every bitmap, widened by 30 % (perspective, and
    /// the frame check that follows is the strict one).
    fn expected_periods(&self, quad: &Quad) -> (f64, f64) {
        let (mut lo, mut hi) = (f64::INFINITY, 0.0f64);
        for (dims, _) in &self.shapes {
            for side in quad.sides() {
                for n in dims {
                    let p = 2.0 * side / *n as f64;
                    lo = lo.min(p);
                    hi = hi.max(p);
                }
            }
        }
        (lo / 1.3, hi * 1.3)
    }

    /// The image point (pixels) of the thumbnail cell position `cell` (half periods along the
    /// two phases, fractional allowed), the planes being expressed about `plane_origin`.
    fn cell_to_image(
        planes: &[PhasePlane; 2],
        plane_origin: Vector2<f64>,
        cell: [f64; 2],
    ) -> Option<Vector2<f64>> {
        let inv = thumbnail::phase_jacobian(planes)?.try_inverse()?;
        let target = Vector2::new(PI * cell[0] - planes[0].c, PI * cell[1] - planes[1].c);
        Some(plane_origin + inv * target)
    }

    /// The outer outline of the matched bitmap (its frame) where the fine pose puts it.
    fn predicted_frame(
        &self,
        found: &Match,
        planes: &[PhasePlane; 2],
        plane_origin: Vector2<f64>,
    ) -> Option<Quad> {
        let mut corners = [Vector2::zeros(); 4];
        for (corner, cell) in corners.iter_mut().zip(self.frame_cells(found)?) {
            *corner = Self::cell_to_image(planes, plane_origin, cell)?;
        }
        Some(Quad { corners })
    }

    /// The thumbnail cells of the matched bitmap's outer outline's corners (half a cell beyond
    /// the outermost cell centres).
    fn frame_cells(&self, found: &Match) -> Option<[[f64; 2]; 4]> {
        let half = self.templates.get(found.bitmap)?.half;
        let (hx, hy) = (half[0] as f64 + 0.5, half[1] as f64 + 0.5);
        Some(
            [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(sx, sy)| {
                let i = found.orientation.inverse_apply([sx * hx, sy * hy]);
                [
                    found.origin_cell[0] as f64 + i[0],
                    found.origin_cell[1] as f64 + i[1],
                ]
            }),
        )
    }

    /// The perspective `p` per period about lattice point `centre` (periods; node `k` is
    /// thumbnail cell `2k`) that the frame's `outline` shows: the homography from lattice
    /// coordinates to the image that puts the outline's corners where they are, written about
    /// `centre` as `x_c + J·δ/(1 + p·δ)` (docs/design.md#tilt-centre). Each corner of the
    /// outline is paired with the nearest of the affine view's (`planes`, frame of
    /// `plane_origin`): a tilt bends corners by a fraction of a period, far less than the
    /// outline's side. `None` when the pairing is not one to one or the outline degenerate.
    fn outline_perspective(
        &self,
        found: &Match,
        planes: &[PhasePlane; 2],
        plane_origin: Vector2<f64>,
        outline: &Quad,
        centre: [f64; 2],
    ) -> Option<Vector2<f64>> {
        let cells = self.frame_cells(found)?;
        let affine = self.predicted_frame(found, planes, plane_origin)?;
        let mut lattice = [Vector2::zeros(); 4];
        let mut used = [false; 4];
        for (l, corner) in lattice.iter_mut().zip(&outline.corners) {
            let (j, _) = affine.corners.iter().enumerate().min_by(|a, b| {
                let (da, db) = ((a.1 - corner).norm(), (b.1 - corner).norm());
                da.total_cmp(&db)
            })?;
            if std::mem::replace(used.get_mut(j)?, true) {
                return None;
            }
            let c = cells.get(j)?;
            *l = Vector2::new(c[0] / 2.0, c[1] / 2.0);
        }
        // The unit square onto the outline, after the lattice onto the unit square (affine:
        // the outline is a rectangle of the lattice).
        let square = quads::square_to_quad(&outline.corners)?;
        let axes = Matrix2::from_columns(&[lattice[1] - lattice[0], lattice[3] - lattice[0]]);
        if (lattice[2] - (lattice[1] + lattice[3] - lattice[0])).norm() > 1e-9 {
            return None;
        }
        let to_square = axes.try_inverse()?;
        let shift = -(to_square * lattice[0]);
        let lattice_to_square = quads::affine_matrix(&to_square, shift);
        let h = square * lattice_to_square;
        // Row 3 of H at c + δ: s + r·δ, so p = r/s.
        let (r, s) = (
            Vector2::new(h[(2, 0)], h[(2, 1)]),
            h[(2, 0)] * centre[0] + h[(2, 1)] * centre[1] + h[(2, 2)],
        );
        let p = r / s;
        p.iter().all(|v| v.is_finite()).then_some(p)
    }

    /// Pose and bookkeeping of a match.
    #[allow(clippy::too_many_arguments)]
    fn detection(
        &self,
        found: Match,
        planes: &[PhasePlane; 2],
        plane_origin: Vector2<f64>,
        image: &GreyImage,
        frame: Option<Quad>,
        window_center: (i64, i64),
        window_size: usize,
        analysis: PhaseAnalysis,
    ) -> Option<StampDetection> {
        // Central dot: where the phases equal π·(its thumbnail cell).
        let cell = found.origin_cell.map(|c| c as f64);
        let origin_px = Self::cell_to_image(planes, plane_origin, cell)?;
        // Bitmap phases Φ = π·j0 + R·φ: their gradients from the planes'.
        let r = found.orientation.matrix();
        let g1 = Vector2::new(planes[0].a, planes[0].b);
        let g2 = Vector2::new(planes[1].a, planes[1].b);
        let gx = g1 * r[0][0] as f64 + g2 * r[0][1] as f64;
        let gy = g1 * r[1][0] as f64 + g2 * r[1][1] as f64;
        let (nx, ny) = (gx.norm(), gy.norm());
        if !(nx > 0.0 && ny > 0.0) {
            return None;
        }
        let u = gx / nx;
        let v = gy / ny;
        let mirrored = found.orientation.mirrored;
        // The y axis turned back onto the x axis: −90° for a proper view, +90° when mirrored.
        let v_on_x = if mirrored {
            Vector2::new(-v.y, v.x)
        } else {
            Vector2::new(v.y, -v.x)
        };
        let axis = u + v_on_x;
        let alpha = axis.y.atan2(axis.x);
        let pixel_size = self.params.period * (nx + ny) / 2.0 / TAU;
        let (icx, icy) = image.center();
        let from_center = origin_px - Vector2::new(icx as f64, icy as f64);
        let planar = Pose::from_origin_in_image(from_center, alpha, pixel_size);
        let pose = if mirrored {
            // cTp = Rz(α)·Rx(π)·Trans(x, y, 0): the origin at Rz(α)·(x, −y), so y flips sign.
            Pose {
                y: -planar.y,
                gamma: wrap_angle(PI),
                ..planar
            }
        } else {
            planar
        };
        let decode_confidence = found.vote.clamp(0.0, 1.0);
        let out_of_plane = if self.params.pose_3d {
            let phase_std = in_pattern_order(r, analysis.phase_std);
            let window = analysis.size.0.min(analysis.size.1) as f64;
            let input = TiltInput::from_window([gx, gy], phase_std, window, from_center, mirrored);
            self.tilt(&input, found.bitmap)
        } else {
            None
        };
        Some(StampDetection {
            id: found.bitmap,
            pose,
            origin_px,
            mirrored,
            correlation: found.correlation,
            decode_confidence,
            frame,
            polarity: self.params.polarity.unwrap_or_default(),
            window_center,
            window_size,
            phase_std: analysis.phase_std,
            analysis,
            field: None,
            yaw_std: None,
            out_of_plane,
        })
    }

    /// The radial apodisation window of a `size × size` snapshot (cached per size): the same
    /// weights as [`crate::snapshot::Snapshot::apodize`] with
    /// [`StampParams::apodization_exponent`].
    fn apodization(&mut self, size: usize) -> &[f32] {
        let exponent = self.params.apodization_exponent;
        self.windows
            .get_or_insert_with(size, || radial_window(size, exponent))
    }
}

/// Whether a quadrilateral can be the outline of a bitmap of one of the `[cols, rows]` shapes
/// seen from any angle (before measuring it): opposite sides within a factor 1.6 of each other
/// (a tilt of up to ~30° under strong perspective), and its two side lengths in the ratio of a
/// bitmap's sides within that factor too.
fn plausible_outline(quad: &Quad, shapes: &[[usize; 2]]) -> bool {
    const FACTOR: f64 = 1.6;
    let s = quad.sides();
    let within = |a: f64, b: f64| a <= FACTOR * b && b <= FACTOR * a;
    let (u, v) = ((s[0] + s[2]) / 2.0, (s[1] + s[3]) / 2.0);
    within(s[0], s[2])
        && within(s[1], s[3])
        && shapes.iter().any(|dims| {
            let aspect = dims[0] as f64 / dims[1] as f64;
            within(u, v * aspect) || within(v, u * aspect)
        })
}

/// `w(d) = (1 + cos(π·(d/ρ)^e))/2` for `d < ρ = size/2`, else 0; `d` from the centre index
/// `(size div 2, size div 2)`. Row-major `size × size`.
fn radial_window(size: usize, exponent: f64) -> Vec<f32> {
    let rho = size as f64 / 2.0;
    let c = (size / 2) as f64;
    let mut w = vec![0.0f32; size * size];
    for r in 0..size {
        for col in 0..size {
            let d = ((col as f64 - c).powi(2) + (r as f64 - c).powi(2)).sqrt();
            if d < rho {
                w[r * size + col] = (0.5 * (1.0 + (PI * (d / rho).powf(exponent)).cos())) as f32;
            }
        }
    }
    w
}

/// Number of complete solid rings around the bitmap (3 for the original's stamps, 0 when the
/// border is not solid).
pub fn frame_thickness(bitmap: &BitmapLayout) -> usize {
    let (rows, cols) = (bitmap.cell_rows(), bitmap.cell_cols());
    let mut t = 0;
    while 2 * (t + 1) < rows.min(cols) {
        let ring_solid = (t..cols - t).all(|c| bitmap.cell(t, c) && bitmap.cell(rows - 1 - t, c))
            && (t..rows - t).all(|r| bitmap.cell(r, t) && bitmap.cell(r, cols - 1 - t));
        if !ring_solid {
            break;
        }
        t += 1;
    }
    t
}

/// Per-plane values `[plane 1, plane 2]` in pattern-axis order `[x, y]` under the matched
/// orientation `r` (a signed permutation): swapped where pattern x runs along plane 2.
fn in_pattern_order(r: [[i64; 2]; 2], values: [f64; 2]) -> [f64; 2] {
    if r[0][0] == 0 {
        [values[1], values[0]]
    } else {
        values
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::snapshot::Snapshot;

    #[test]
    fn cached_window_equals_snapshot_apodization() {
        let size = 40;
        let ones = GreyImage::new(size, size, vec![1.0; size * size]).unwrap();
        let mut s = Snapshot::extract(&ones, (20, 20), size).unwrap();
        s.apodize(4.0);
        let w = radial_window(size, 4.0);
        for (a, b) in s.image.pixels().iter().zip(&w) {
            assert!((a - b).abs() < 1e-6);
        }
    }

    #[test]
    fn frame_thickness_of_a_ring() {
        let mut rows = vec![vec![1u8; 9]; 9];
        for r in rows.iter_mut().take(7).skip(2) {
            for v in r.iter_mut().take(7).skip(2) {
                *v = 0;
            }
        }
        let b = BitmapLayout::from_rows(1.0, &rows).unwrap();
        assert_eq!(frame_thickness(&b), 2);
        rows[0][4] = 0;
        let b = BitmapLayout::from_rows(1.0, &rows).unwrap();
        assert_eq!(frame_thickness(&b), 0);
    }
}
