//! Stamp and bitmap markers (METHOD.md §1.5, §5.3, §5.4): identity and absolute pose of
//! markers drawn as 0/1 bitmaps on the half-period grid.
//!
//! Two ways to find them, chosen from the bitmaps ([`StampSearch::Auto`]):
//! * **framed** (stamps: bitmaps with a solid border ring): every quadrilateral outline of a
//!   bright region is a candidate ([`quads`]); around its centre a square window, apodised by
//!   the flat-top radial window of METHOD.md §5.3.2, goes through the phase engine; the frame's
//!   size must agree with the measured period; the bitmap thumbnail read along the phase planes
//!   (`thumbnail`) is matched against every bitmap in its 8 dihedral orientations and a few
//!   period shifts (`matching`); the pose follows. Any number of stamps per image, several
//!   with the same bitmap included (the original keeps one of them).
//! * **full image** (other bitmaps, e.g. an HP code layout seen as a bitmap): the phase engine on
//!   the whole image, then the same thumbnail and matching over every position of the bitmap,
//!   then a second, apodised measurement in a window on the bitmap found (the whole-image fit
//!   weighs an off-centre marker unevenly and leaks at its edges: ~1e-3 rad, 5e-3 px).
//!
//! Poses (METHOD.md §6): the pattern origin is the bitmap's central dot; `alpha` is the
//! direction of the bitmap's x axis (increasing column) in the image, averaged with that of its
//! y axis turned back by 90°, and the pixel size the mean of the two grid frequencies. The
//! central dot's image position is where the two phase planes take the values the match assigns
//! to it, which is exact for any affine view.
//!
//! Differences from the original, on purpose: no silent loss of same-ID stamps; the thumbnail
//! covers the whole bitmap (frame included) instead of its interior, so the period shift is
//! pinned by the frame; the period-shift sign slip of METHOD.md §9.12 cannot occur (the match
//! states where the origin is in the thumbnail); mirrored markers (a flipped image) are
//! recognised, and reported only when [`StampParams::allow_mirrored`] is set, so they never
//! come out with a wrong pose; the window is sized from the frame (largest `2^a·3^b` side
//! inside the dot field) rather than fixed.

mod matching;
pub mod quads;
mod thumbnail;

pub use quads::{Quad, QuadParams};

use crate::error::{Error, Result};
use crate::grey_image::{GreyImage, Polarity};
use crate::layout::BitmapLayout;
use crate::phase::{PhaseAnalysis, PhaseEngine, PhaseParams, PhasePlane, MIN_IMAGE_SIDE};
use crate::pose::Pose;
use crate::snapshot::Snapshot;
use matching::{best_match, Match, SearchRange, Template};
use nalgebra::Vector2;
use quads::QuadFinder;
use std::f64::consts::{PI, TAU};

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
    /// How far (in periods, along each axis) the window centre may be from the marker's
    /// central dot for the match to find it. Default 2 (the frame centre is much closer).
    pub max_center_offset: usize,
    /// Largest relative difference between a frame's size and the bitmap size times the
    /// measured period. Default 0.15.
    pub size_tolerance: f64,
    /// Report mirrored markers (seen through a flipped optical path). Their pose gives the
    /// bitmap's x axis direction and central dot; their y axis points the other way
    /// (`alpha − π/2`). Default false: mirrored markers are dropped.
    pub allow_mirrored: bool,
    /// Phase-engine settings.
    pub phase: PhaseParams,
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
            max_center_offset: 2,
            size_tolerance: 0.15,
            allow_mirrored: false,
            phase: PhaseParams::default(),
        }
    }

    /// Checks every field, naming the first invalid one; returns the resolved search mode.
    fn validate(&self) -> Result<StampSearch> {
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
        let q = &self.quads;
        if q.threshold_window < 2 {
            return Err(Error::parameter(
                "threshold_window",
                format!("must be ≥ 2 pixels, got {}", q.threshold_window),
            ));
        }
        if !(q.threshold_offset.is_finite() && q.threshold_offset >= 0.0) {
            return Err(Error::parameter(
                "threshold_offset",
                format!("must be ≥ 0, got {}", q.threshold_offset),
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
        self.phase.validate()?;
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
    /// Correlation between the thumbnail and the bitmap, `[−1, 1]`.
    pub correlation: f64,
    /// Confidence of the decoding, `[0, 1]`: on the bitmap cells where the winning hypothesis
    /// and a rival (the best other orientation or period shift, and every other bitmap) predict
    /// different values, the fraction of cells read as the winner predicts minus the fraction
    /// read as the rival predicts; the smallest over the rivals, clamped at 0.
    pub decode_confidence: f64,
    /// The frame outline, for framed markers.
    pub frame: Option<Quad>,
    /// Polarity the marker was measured in (the setting's, or found from its frame).
    pub polarity: Polarity,
    /// Image pixel `(col, row)` at the centre of the analysed window.
    pub window_center: (i64, i64),
    /// Side of the analysed square window, pixels (the image size for full-image search).
    pub window_size: usize,
    /// Phase-engine output the pose was computed from (planes in the window's frame).
    pub analysis: PhaseAnalysis,
}

/// Finds stamp / bitmap markers and measures their absolute poses. Keeps FFT plans, the
/// apodisation windows and the frame-search buffers between frames.
pub struct StampDetector {
    params: StampParams,
    mode: StampSearch,
    engine: PhaseEngine,
    templates: Vec<Template>,
    /// Per bitmap: its `(cols, rows)` and dot-field side as a fraction of its side.
    shapes: Vec<([usize; 2], f64)>,
    finder: QuadFinder,
    windows: Vec<(usize, Vec<f32>)>,
}

/// Apodisation windows kept (one per window size in use).
const CACHED_WINDOWS: usize = 4;

impl StampDetector {
    /// A detector with `params` (validated).
    pub fn new(params: StampParams) -> Result<Self> {
        let mode = params.validate()?;
        let templates = params.bitmaps.iter().map(Template::new).collect();
        let shapes = params
            .bitmaps
            .iter()
            .map(|b| {
                let (cols, rows) = (b.cell_cols(), b.cell_rows());
                let side = cols.min(rows) as f64;
                let interior = side - 2.0 * (frame_thickness(b) as f64 + 1.0);
                ([cols, rows], (interior / side).max(0.0))
            })
            .collect();
        Ok(StampDetector {
            params,
            mode,
            engine: PhaseEngine::new(),
            templates,
            shapes,
            finder: QuadFinder::default(),
            windows: Vec::new(),
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
        match self.mode {
            StampSearch::FullImage => {
                let image = image.as_bright_dots(self.params.polarity.unwrap_or_default());
                self.measure_full(&image).map(|d| vec![d])
            }
            _ => {
                let mut found: Vec<StampDetection> = Vec::new();
                for polarity in self.polarities() {
                    let image = image.as_bright_dots(polarity);
                    self.detect_framed(&image, polarity, &mut found)?;
                }
                Ok(found)
            }
        }
    }

    /// The polarities searched: the setting's, or both.
    fn polarities(&self) -> Vec<Polarity> {
        match self.params.polarity {
            Some(p) => vec![p],
            None => vec![Polarity::BrightDots, Polarity::DarkDots],
        }
    }

    /// Framed markers of one polarity (`image` already made bright-dot), appended to `found`
    /// unless inside a frame already accepted.
    fn detect_framed(
        &mut self,
        image: &GreyImage,
        polarity: Polarity,
        found: &mut Vec<StampDetection>,
    ) -> Result<()> {
        let quads = self.finder.find(image, &self.params.quads);
        for quad in quads {
            // Outermost only: a candidate inside an accepted frame is part of it.
            let c = quad.center();
            if found
                .iter()
                .filter_map(|d| d.frame.as_ref())
                .any(|f| f.contains(c))
            {
                continue;
            }
            if let Some(mut d) = self.measure_framed(image, quad)? {
                d.polarity = polarity;
                found.push(d);
            }
        }
        Ok(())
    }

    /// Quadrilateral outlines (frame candidates) of `image`, largest first, before any check
    /// against the bitmaps (for display and diagnostics).
    pub fn find_frames(&mut self, image: &GreyImage) -> Vec<Quad> {
        let mut quads = Vec::new();
        for polarity in self.polarities() {
            let image = image.as_bright_dots(polarity);
            quads.extend(self.finder.find(&image, &self.params.quads));
        }
        quads
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
        for polarity in self.polarities() {
            let image = image.as_bright_dots(polarity);
            if let Some(mut d) = self.measure_window(&image, center, size, None)? {
                d.polarity = polarity;
                return Ok(Some(d));
            }
        }
        Ok(None)
    }

    /// A framed candidate: window at the frame centre, sized to the dot field.
    fn measure_framed(&mut self, image: &GreyImage, quad: Quad) -> Result<Option<StampDetection>> {
        let c = quad.center();
        let center = (c.x.round() as i64, c.y.round() as i64);
        let size = match self.params.window_size {
            Some(s) => s,
            None => {
                let side = quad.sides().iter().copied().fold(f64::INFINITY, f64::min);
                let fraction = self
                    .shapes
                    .iter()
                    .map(|s| s.1)
                    .fold(f64::INFINITY, f64::min);
                fast_size_at_most((side * fraction).floor() as usize)
            }
        };
        if size < MIN_IMAGE_SIDE {
            return Ok(None);
        }
        self.measure_window(image, center, size, Some(quad))
    }

    /// Phase, frame-size check, match and pose in a `size` window centred on `center`.
    fn measure_window(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        size: usize,
        frame: Option<Quad>,
    ) -> Result<Option<StampDetection>> {
        let mut snapshot = Snapshot::extract(image, center, size)?;
        let window = self.apodization(size);
        for (v, w) in snapshot.image.pixels_mut().iter_mut().zip(window) {
            *v *= w;
        }
        let analysis = match self.engine.analyze(&snapshot.image, &self.params.phase) {
            Ok(a) => a,
            Err(Error::PatternNotFound(_)) => return Ok(None),
            Err(e) => return Err(e),
        };
        let planes = analysis.planes.map(|p| p.with_wrapped_offset());
        if let Some(q) = &frame {
            if !self.shapes.iter().any(|s| self.frame_fits(q, &planes, s.0)) {
                return Ok(None);
            }
        }
        // Thumbnail wide enough for the largest bitmap at the largest centre offset, plus a
        // margin of background.
        let reach = self
            .templates
            .iter()
            .map(|t| t.half[0].max(t.half[1]))
            .max()
            .unwrap_or(0);
        let shift = 2 * self.params.max_center_offset as i64;
        let half = reach + shift + 2;
        let origin = Vector2::new(center.0 as f64, center.1 as f64);
        let len = (2 * half + 1) as usize;
        let Some(thumb) = thumbnail::sample(image, origin, &planes, [-half, -half], [len, len])
        else {
            return Ok(None);
        };
        let range = SearchRange {
            origin: [[-shift, shift], [-shift, shift]],
            mirrored_allowed: self.params.allow_mirrored,
            min_overlap: 0.5,
        };
        let Some(found) = best_match(&thumb, &self.templates, &range) else {
            return Ok(None);
        };
        if found.correlation < self.params.min_correlation
            || (found.orientation.mirrored && !self.params.allow_mirrored)
        {
            return Ok(None);
        }
        if let Some(q) = &frame {
            if !self.frame_fits(q, &planes, self.shapes[found.bitmap].0) {
                return Ok(None);
            }
        }
        Ok(self.detection(found, &planes, origin, image, frame, center, size, analysis))
    }

    /// Full-image search: phase on the whole image, match over every bitmap position.
    fn measure_full(&mut self, image: &GreyImage) -> Result<StampDetection> {
        let analysis = self.engine.analyze(image, &self.params.phase)?;
        let planes = analysis.planes.map(|p| p.with_wrapped_offset());
        let (cx, cy) = image.center();
        let origin = Vector2::new(cx as f64, cy as f64);
        // Cell ranges covered by the image: phases at its corners.
        let corners = [
            (-(cx as f64), -(cy as f64)),
            ((image.width() - 1 - cx) as f64, -(cy as f64)),
            (-(cx as f64), (image.height() - 1 - cy) as f64),
            (
                (image.width() - 1 - cx) as f64,
                (image.height() - 1 - cy) as f64,
            ),
        ];
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
        let thumb = thumbnail::sample(image, origin, &planes, lo, len)
            .ok_or_else(|| not_found("degenerate phase planes"))?;
        let range = SearchRange {
            origin: [[lo[0], hi[0]], [lo[1], hi[1]]],
            mirrored_allowed: self.params.allow_mirrored,
            min_overlap: 0.5,
        };
        let found = best_match(&thumb, &self.templates, &range)
            .ok_or_else(|| not_found("no bitmap position overlaps the image enough"))?;
        if found.correlation < self.params.min_correlation {
            return Err(not_found(&format!(
                "best correlation {:.2} is below min_correlation {:.2}",
                found.correlation, self.params.min_correlation
            )));
        }
        if found.orientation.mirrored && !self.params.allow_mirrored {
            return Err(not_found(
                "the bitmap is seen mirrored (allow_mirrored is off)",
            ));
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
            .unwrap_or(fast_size_at_most(side as usize));
        if window < 32 {
            return Ok(coarse);
        }
        let center = (
            coarse.origin_px.x.round() as i64,
            coarse.origin_px.y.round() as i64,
        );
        match self.measure_window(image, center, window, None)? {
            Some(fine) if fine.id == coarse.id && fine.mirrored == coarse.mirrored => Ok(fine),
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
        let close = |e: f64, n: usize| (e / n as f64 - 1.0).abs() <= self.params.size_tolerance;
        (close(e1, dims[0]) && close(e2, dims[1])) || (close(e1, dims[1]) && close(e2, dims[0]))
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
        let jac = thumbnail::phase_jacobian(planes)?;
        let inv = jac.try_inverse()?;
        // Central dot: where the phases equal π·(its thumbnail cell).
        let cell = found.origin_cell;
        let target = Vector2::new(
            PI * cell[0] as f64 - planes[0].c,
            PI * cell[1] as f64 - planes[1].c,
        );
        let origin_px = plane_origin + inv * target;
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
        // The y axis turned back onto the x axis: −90° for a proper view, +90° when mirrored.
        let v_on_x = if found.orientation.mirrored {
            Vector2::new(-v.y, v.x)
        } else {
            Vector2::new(v.y, -v.x)
        };
        let axis = u + v_on_x;
        let alpha = axis.y.atan2(axis.x);
        let pixel_size = self.params.period * (nx + ny) / 2.0 / TAU;
        let (icx, icy) = image.center();
        let from_center = origin_px - Vector2::new(icx as f64, icy as f64);
        let pose = Pose::from_origin_in_image(from_center, alpha, pixel_size);
        let decode_confidence = found.vote.clamp(0.0, 1.0);
        Some(StampDetection {
            id: found.bitmap,
            pose,
            origin_px,
            mirrored: found.orientation.mirrored,
            correlation: found.correlation,
            decode_confidence,
            frame,
            polarity: self.params.polarity.unwrap_or_default(),
            window_center,
            window_size,
            analysis,
        })
    }

    /// The radial apodisation window of a `size × size` snapshot (cached per size): the same
    /// weights as [`Snapshot::apodize`] with [`StampParams::apodization_exponent`].
    fn apodization(&mut self, size: usize) -> &[f32] {
        if let Some(pos) = self.windows.iter().position(|(s, _)| *s == size) {
            let w = self.windows.remove(pos);
            self.windows.push(w);
        } else {
            if self.windows.len() >= CACHED_WINDOWS {
                self.windows.remove(0);
            }
            self.windows
                .push((size, radial_window(size, self.params.apodization_exponent)));
        }
        let last = self.windows.len() - 1;
        &self.windows[last].1
    }
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

/// Largest `2^a·3^b ≤ n` (fast FFT sizes); 0 for `n = 0`.
fn fast_size_at_most(n: usize) -> usize {
    let mut best = 0;
    let mut p3 = 1usize;
    while p3 <= n {
        let mut v = p3;
        while v * 2 <= n {
            v *= 2;
        }
        best = best.max(v);
        p3 *= 3;
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_sizes_at_most() {
        assert_eq!(fast_size_at_most(0), 0);
        assert_eq!(fast_size_at_most(1), 1);
        assert_eq!(fast_size_at_most(473), 432);
        assert_eq!(fast_size_at_most(500), 486);
        assert_eq!(fast_size_at_most(512), 512);
    }

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
