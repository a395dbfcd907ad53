//! HP code detector (docs/design.md#hpcode): every HP code marker in an image, with its ID and
//! absolute pose.
//!
//! Pipeline, one module per step:
//! 1. `finders`: finder squares as nested regions (centre in gap in ring) of the scale-free
//!    local binarisation ([`crate::binarize`]) at three threshold levels, each with its own
//!    polarity, coarse to fine on a pyramid of 2×2-binned copies;
//! 2. `grouping`: triples of finders that fit the marker geometry (right angle, equal legs
//!    `W − 7` modules long); leftovers are ignored;
//! 3. a window holding only the marker's dot grid (inside the marker, clear of the finders)
//!    around the coarse centre, [`PhaseEngine::analyze`] (refined planes); a radial Hann
//!    apodisation only for windows larger than the marker (the original's 256/512 px);
//! 4. `fine`: planes assigned to the pattern axes seen by the finders (full `(−π, π]`
//!    orientation), marker width measured in whole periods, centre = grid point nearest to the
//!    coarse centre (no half-period limit); then a second analysis on the window the measured
//!    centre and size call for, so the result does not depend on the coarse stage;
//! 5. `marker_id`: ID read at the measured dot positions; a mirrored marker (seen from its
//!    back, or a flipped image) is recognised from where its ID dots are.
//!
//! Poses follow docs/design.md#frames: `(x, y) = Rz(−α)·(camera-frame position of the centre dot)`,
//! pattern units. A mirrored marker is reported with `gamma = −π` (rotation by π about the
//! pattern x axis: the marker seen from behind), which keeps `cTp` a proper rigid transform.

mod dot_homography;
mod finders;
pub(crate) mod fine;
mod grouping;
pub(crate) mod marker_id;

pub use finders::Finder;
pub use grouping::{
    candidate_triples, disjoint_triples, group_finders, pair_hypotheses, FinderTriple,
};

use crate::error::{Error, Result};
use crate::grey_image::{GreyImage, Polarity};
use crate::marker_tilt::{marker_tilt, MarkerTilt, TiltInput};
use crate::phase::{
    wrap_angle, FieldFit, LobePrior, PhaseAnalysis, PhaseEngine, PhaseParams, Rival,
};
use crate::pose::{rotate2, Pose};
use finders::FinderScanner;
use marker_id::ReadingView;
use nalgebra::Vector2;
use std::f64::consts::{FRAC_PI_2, PI, TAU};

/// Smallest [`marker_id::grid_precheck`] score for a candidate to be analysed (½ on texture
/// that is not a grid, ~1 on a dot field; dust and hair may spoil some dots).
const MIN_PRECHECK: f64 = 0.7;
/// Most two-finder hypotheses tried per image (each costs one window analysis).
const MAX_HYPOTHESES: usize = 48;
/// Most finder triples measured per image ([`HpCodeDetector::detect`]), a bound on the cost of
/// hostile input (a texture of finder-like shapes): a triple that is no marker mostly fails
/// the grid pre-check (a few hundred samples), at worst one window analysis. The real images
/// and stress scenes have at most a few dozen candidate triples, all of which are tried.
const MAX_TRIPLES: usize = 256;
/// Smallest fraction of the marker's dots and gaps that must look right
/// ([`marker_id::grid_support`]); dust and hair may spoil the rest.
const MIN_GRID_SUPPORT: f64 = 0.75;
/// Largest distance between the centre the pose is computed from (the window's planes, or the
/// whole-field fit's) and the centre of the grid fitted to the dots, periods, beyond the
/// planes' bias under a tilt and [`CENTRE_SIGMAS`] standard deviations of the two
/// (docs/design.md#hp-dot-homography). The window's planes over dust moved the pose of stress
/// scene 62907 by 0.05 period while every check on the dots passed, and no whole-field fit
/// replaced them; elsewhere the window's planes agree within 0.008 period (110 candidates of
/// 100 stress scenes, every category), and a whole-field fit corrects planes 0.026 period off
/// (stress scene 64778).
const MAX_CENTRE_DISAGREEMENT: f64 = 0.02;
/// Standard deviations of the two centres allowed on top of [`MAX_CENTRE_DISAGREEMENT`].
const CENTRE_SIGMAS: f64 = 5.0;

/// Search radius of the guided lobe search, fraction of the expected frequency: finder module
/// (~5 %), axis angle (~0.05 rad) and foreshortening of a 25° tilt (10 %).
const LOBE_TOLERANCE: f64 = 0.2;
/// Prominence a lobe needs where the finders expect it. White noise reaches 2 in a disc of a
/// few dozen bins with a probability of ~1e-8; a wrong lobe still fails the fine checks.
const GUIDED_PROMINENCE: f64 = 2.0;

/// Smallest analysis window side, pixels.
const MIN_WINDOW: usize = 32;
/// Clearance kept by the automatic window from the finders and the marker edge, modules.
const WINDOW_CLEARANCE: f64 = 0.5;

/// Settings of [`HpCodeDetector`] (docs/design.md#settings).
#[derive(Clone, Debug, PartialEq)]
pub struct HpCodeParams {
    /// Physical period `P` of the dot grid, pattern units (µm by convention). Must be > 0.
    pub period: f64,
    /// Nominal marker width in half-period cells `W = 2n − 1` (the original's
    /// "numberHalfPeriods", CLI `--code-size`): `W ≡ 1 (mod 4)`, ≥ 17; 33 and 37 in practice.
    /// A prior: markers whose finders are `W' − 7` modules apart for any odd `W'` within 8
    /// cells of `W` are accepted, and `W'` is measured (reported in
    /// [`HpCodeMarker::code_size`]); the ID layout follows `W'`.
    pub code_size: usize,
    /// Side of the square window analysed around each marker, pixels (even, ≥ 32). `None`
    /// (default) sizes it for each marker: the largest FFT-friendly size (`2^a·3^b·5^c`) that
    /// stays inside the marker and clear of its finders at the marker's angle (0.55–0.7 marker
    /// widths), so the window holds nothing but the marker's dot grid.
    /// The original's examples use 256 or 512 (more than the marker: background and clutter
    /// enter, hence [`HpCodeParams::apodize`]).
    pub window_size: Option<usize>,
    /// Multiply the window by the radial Hann window `(1 + cos(π·d/ρ))/2`, `ρ` = half the side
    /// (docs/design.md#hp-window). `None` (default): only when the window is larger than the
    /// automatic one, i.e. reaches beyond the marker (without it, the background and clutter of
    /// e.g. a 512-px window on Image96 hide the marker's grid). Inside the marker the phase
    /// engine's refinement applies its own separable window, and the radial Hann on top of it
    /// degrades the orientation from ~1e-8 to ~1e-5 rad on noise-free renders (measured).
    /// The original's band-pass planes need it ([`HpCodeParams::original`]).
    pub apodize: Option<bool>,
    /// Dot polarity. `None` (default) takes each marker's polarity from its finder squares;
    /// `Some(p)` only accepts markers of polarity `p`.
    pub polarity: Option<Polarity>,
    /// Smallest local contrast (max − min over a neighbourhood) that the finder search
    /// binarises, intensity units (`[0, 1]` images). `None` (default) chooses it per image:
    /// 6 noise standard deviations (measured in the quietest blocks), at least 0.015.
    pub min_contrast: Option<f64>,
    /// Markers whose ID is read with a confidence below this are dropped (`[0, 1]`, the
    /// smallest margin of an ID or left-column dot, `marker_id::bit_margin`: a present dot's
    /// height above the present/absent threshold in half contrasts; a missing dot's depth
    /// below the middle of the lower half, in quarter contrasts, since a hidden present dot
    /// may sit anywhere below the threshold; each also no more than how clearly no fibre or
    /// blob over the ID strip made the reading, docs/design.md#hp-id-occluders). Default 0.2:
    /// a present dot 10 % of the contrast above the threshold, a missing one 30 % below it.
    pub min_id_confidence: f64,
    /// Phase-engine settings used on each window.
    pub phase: PhaseParams,
    /// How orientation, pixel size and position follow from the two planes.
    pub pose_formula: PoseFormula,
    /// Threads measuring the candidate markers of a frame in parallel (they are independent);
    /// 0 (default) = every core the system offers. Results do not depend on it.
    pub threads: usize,
    /// After decoding, refine the planes on the marker's whole regular dot field, robustly
    /// (docs/design.md#field-fit): every plain dot of the layout with plain neighbours, dust and
    /// hair down-weighted. Default `true`; the window's planes give the pose when `false`
    /// (and with [`HpCodeParams::original`]).
    pub field_fit: bool,
    /// Measure each marker's out-of-plane angles `beta`, `gamma` ([`HpCodeMarker::out_of_plane`],
    /// docs/design.md#pose-3d-markers) from its whole-field fit. Default `false`.
    pub pose_3d: bool,
    /// Focal length of a perspective camera, pixels (principal point at the image centre):
    /// with [`HpCodeParams::pose_3d`], each marker's depth `z` and the perspective solution.
    /// `None` (default): orthographic optics, `z` unknown.
    pub focal_length_px: Option<f64>,
}

/// How the pose of a marker follows from its two phase planes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PoseFormula {
    /// Symmetric in the two grid axes, hence covariant under image rotations and flips
    /// (default): final window placed symmetrically about the pixel corner nearest the
    /// measured centre, `alpha` the mean direction of the two pattern axes (a quarter turn
    /// apart), pixel size from the mean frequency of both planes, centre where both planes take
    /// the centre's phase.
    #[default]
    Symmetric,
    /// The original's formulas (docs/design.md#hp-fine): window centred on the
    /// truncated coarse centre, `alpha` and pixel size from the
    /// engine's plane 1 (the lobe whose direction is in `[0, π/2)`, whichever marker axis it
    /// is), position `ps·Rz(−α)·(window centre) − P·c/2π`, here with the whole-period shift
    /// of the centre added. Use with [`HpCodeParams::original`] to reproduce its numbers.
    Original,
}

impl HpCodeParams {
    /// Defaults for markers `code_size` cells wide with physical period `period`.
    pub fn new(period: f64, code_size: usize) -> Self {
        HpCodeParams {
            period,
            code_size,
            window_size: None,
            apodize: None,
            polarity: None,
            min_contrast: None,
            min_id_confidence: 0.2,
            phase: PhaseParams::default(),
            pose_formula: PoseFormula::Symmetric,
            threads: 0,
            field_fit: true,
            pose_3d: false,
            focal_length_px: None,
        }
    }

    /// Settings that reproduce the original's numbers (docs/design.md#hp-fine): window of
    /// `window_size` pixels, band-pass phase planes without refinement
    /// (docs/design.md#phase-bandpass, ring band-pass from 20 bins) and [`PoseFormula::Original`].
    /// Its result moves by up to ~3e-3 rad with the window size on real images (Image96: 320 to 640
    /// px), about 10 times more than the default's.
    pub fn original(period: f64, code_size: usize, window_size: usize) -> Self {
        let mut p = HpCodeParams::new(period, code_size);
        p.window_size = Some(window_size);
        p.apodize = Some(true);
        p.phase.refine_iterations = 0;
        p.phase.min_frequency = 20.0;
        p.pose_formula = PoseFormula::Original;
        p.field_fit = false;
        p
    }

    /// Checks every field, naming the first invalid one.
    pub fn validate(&self) -> Result<()> {
        if !(self.period.is_finite() && self.period > 0.0) {
            return Err(Error::parameter(
                "period",
                format!("must be > 0, got {}", self.period),
            ));
        }
        if self.code_size % 4 != 1 || self.code_size < 17 {
            return Err(Error::parameter(
                "code_size",
                format!(
                    "HP code width in half periods must be ≡ 1 (mod 4) and ≥ 17 (33, 37, ...), got {}",
                    self.code_size
                ),
            ));
        }
        if let Some(s) = self.window_size {
            if s % 2 != 0 || s < MIN_WINDOW {
                return Err(Error::parameter(
                    "window_size",
                    format!("must be even and ≥ {MIN_WINDOW} pixels, got {s}"),
                ));
            }
        }
        if let Some(t) = self.min_contrast {
            if !(t.is_finite() && t > 0.0 && t < 1.0) {
                return Err(Error::parameter(
                    "min_contrast",
                    format!("must be in (0, 1), got {t}"),
                ));
            }
        }
        if !(0.0..=1.0).contains(&self.min_id_confidence) {
            return Err(Error::parameter(
                "min_id_confidence",
                format!("must be in [0, 1], got {}", self.min_id_confidence),
            ));
        }
        crate::marker_tilt::check_focal_length(self.focal_length_px)?;
        self.phase.validate()
    }
}

/// One HP code marker found in an image.
#[derive(Clone, Debug)]
pub struct HpCodeMarker {
    /// Decoded ID: bit `k` is 1 when the top-row dot `k` places from the top-right finder is
    /// missing (docs/design.md#hp-id-encoding).
    pub id: u64,
    /// Measured marker width in half-period cells `W` (odd; the setting is only a prior).
    pub code_size: usize,
    /// Pose of the marker (docs/design.md#frames). Pattern origin: the marker centre, i.e. the
    /// centre dot (`W ≡ 1 mod 4`) or the gap between the four central dots (`W ≡ 3 mod 4`).
    pub pose: Pose,
    /// Image position `(col, row)` of the marker centre, pixels.
    pub origin_px: Vector2<f64>,
    /// Polarity of the marker (from its finders, or the setting).
    pub polarity: Polarity,
    /// The marker is seen mirrored (from its back side): `pose.gamma = −π`.
    pub mirrored: bool,
    /// ID confidence in `[0, 1]`: the smallest margin of an ID (or left column) dot
    /// ([`HpCodeParams::min_id_confidence`] says how each dot's margin is measured).
    pub id_confidence: f64,
    /// The three finders, `right`/`bottom` as in the pattern (after mirror resolution).
    pub finders: FinderTriple,
    /// Image pixel `(col, row)` at the analysis window's centre index and the window side.
    pub window: ((i64, i64), usize),
    /// Phase-engine output on the window (planes in the window frame).
    pub analysis: PhaseAnalysis,
    /// The whole-field fit that gave the pose (docs/design.md#field-fit); `None` when the
    /// window's planes gave it ([`HpCodeParams::field_fit`] off, or a field too small to fit).
    pub field: Option<FieldFit>,
    /// Standard deviation of the pattern-x and pattern-y phases at the marker centre, radians
    /// (white noise and model error of the fit that gave the pose).
    pub phase_std: [f64; 2],
    /// Standard deviation of `pose.alpha` from the whole-field fit, radians; `None` without it.
    pub yaw_std: Option<f64>,
    /// The out-of-plane pose ([`HpCodeParams::pose_3d`]); `None` when not asked for, or when
    /// the marker's planes have no 3-D solution (logged).
    pub out_of_plane: Option<MarkerTilt>,
}

/// Detects HP code markers. Keeps the phase engine's FFT plans and the finder scanner's buffers
/// between frames.
///
/// # Example
///
/// ```
/// use vernier::hpcode::{HpCodeDetector, HpCodeParams};
/// use vernier::layout::HpCodeLayout;
/// use vernier::phase::wrap_to_pi;
/// use vernier::render::{render, RenderOptions};
/// use vernier::Pose;
///
/// # fn main() -> vernier::Result<()> {
/// // A 33-cell HP code (17 × 17 dots, 9 ID bits) of 10 µm period carrying ID 361, seen at
/// // 1.25 µm per pixel (a 132-px marker) turned by 2.5 rad.
/// let layout = HpCodeLayout::from_code_size(10.0, 33)?.with_id(361)?;
/// let truth = Pose::planar(6.0, -4.0, 2.5, 1.25);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(256, 256) };
/// let image = render(&layout, &truth, &options)?;
///
/// let mut detector = HpCodeDetector::new(HpCodeParams::new(10.0, 33))?;
/// let markers = detector.detect(&image)?;
/// assert_eq!(markers.len(), 1);
/// let (marker, tolerance) = (&markers[0], 0.01 * truth.pixel_size);
/// assert_eq!(marker.id, 361);
/// assert!((marker.pose.x - truth.x).abs() < tolerance);
/// assert!((marker.pose.y - truth.y).abs() < tolerance);
/// assert!(wrap_to_pi(marker.pose.alpha - truth.alpha).abs() < 1e-4);
/// # Ok(())
/// # }
/// ```
pub struct HpCodeDetector {
    params: HpCodeParams,
    scanner: FinderScanner,
    /// One per measuring thread (the first serves the sequential passes).
    workers: Vec<MarkerWorker>,
}

/// What one thread needs to measure markers: its phase engine (plans and buffers) and the
/// last radial Hann window.
#[derive(Default)]
struct MarkerWorker {
    engine: PhaseEngine,
    hann: (usize, f64, Vec<f32>),
}

/// One marker measurement: the settings and a worker's engine.
struct Measure<'a> {
    params: &'a HpCodeParams,
    engine: &'a mut PhaseEngine,
    hann: &'a mut (usize, f64, Vec<f32>),
}

impl<'a> Measure<'a> {
    fn new(params: &'a HpCodeParams, worker: &'a mut MarkerWorker) -> Self {
        Measure {
            params,
            engine: &mut worker.engine,
            hann: &mut worker.hann,
        }
    }
}

impl HpCodeDetector {
    /// A detector with `params` (validated).
    pub fn new(params: HpCodeParams) -> Result<Self> {
        // The shared physical ranges (vernier::limits) first, then the detector's own rules.
        crate::limits::check_period(params.period)?;
        crate::limits::check_code_size(params.code_size)?;
        if let Some(size) = params.window_size {
            crate::limits::check_window_size(size)?;
        }
        params.validate()?;
        Ok(HpCodeDetector {
            params,
            scanner: FinderScanner::default(),
            workers: vec![MarkerWorker::default()],
        })
    }

    /// Current settings.
    pub fn params(&self) -> &HpCodeParams {
        &self.params
    }

    /// Finder squares of `image` (step 1 only), filtered by the polarity setting.
    pub fn find_finders(&mut self, image: &GreyImage) -> Vec<Finder> {
        let mut finders = self.scanner.find(image, self.params.min_contrast);
        if let Some(p) = self.params.polarity {
            finders.retain(|f| f.polarity == p);
        }
        log::trace!("finders: {finders:?}");
        finders
    }

    /// Every marker of `image`, in order of decreasing geometric fit of their finders. An image
    /// without markers gives an empty list. Markers sharing an ID are all returned.
    pub fn detect(&mut self, image: &GreyImage) -> Result<Vec<HpCodeMarker>> {
        let finders = self.find_finders(image);
        let candidates = candidate_triples(&finders, self.params.code_size);
        let mut tried = vec![false; candidates.len()];
        let mut markers: Vec<HpCodeMarker> = Vec::new();
        // Rounds of disjoint triples, best fit first, until every candidate has been tried: a
        // triple that gives no marker frees its finders for the next round's. Across two
        // markers, finders can fit a right angle with equal legs better than a marker's own,
        // which a tilt shears and perspective makes unequal (two markers side by side, tilted
        // by 25°, gave four better-fitting triples across them).
        let mut measured = 0;
        while measured < MAX_TRIPLES {
            let taken = taken_finders(&finders, &markers);
            let round = disjoint_triples(&candidates, &taken, &mut tried);
            if round.is_empty() {
                break;
            }
            let mut triples: Vec<FinderTriple> = round
                .into_iter()
                .map(|k| candidates[k].0)
                // Another triple of a marker found (a finder read twice).
                .filter(|t| !near_a_marker(&markers, t))
                .collect();
            triples.truncate(MAX_TRIPLES - measured);
            measured += triples.len();
            let jobs: Vec<_> = triples.into_iter().map(|t| (t, None)).collect();
            markers.extend(self.measure_all(image, &jobs)?);
        }
        // Markers with a finder missing (dust, damage): hypotheses from the finders left over,
        // each kept only when its grid and ID confirm it.
        let used = taken_finders(&finders, &markers);
        for triple in pair_hypotheses(&finders, self.params.code_size, &used, MAX_HYPOTHESES) {
            if near_a_marker(&markers, &triple) {
                continue;
            }
            // Sequential: each accepted hypothesis hides the ones near it.
            let worker = &mut self.workers[0];
            if let Some(m) = Measure::new(&self.params, worker).measure(image, &triple, None)? {
                markers.push(m);
            }
        }
        Ok(markers)
    }

    /// Tracking (docs/design.md#tracking): the markers of `previous` (the last frame's) found
    /// again in `image` without the finder search, each from its last finder triple moved to
    /// `predicted[i]` (its predicted centre, image pixels). The fine step then runs exactly as
    /// in [`HpCodeDetector::detect`], whose final window depends only on the fine geometry, so
    /// the poses are those of full detection while each marker moves less than half a period
    /// from its prediction. `None` when any marker is not found again with the same ID: the
    /// caller then runs the full detection.
    pub fn track(
        &mut self,
        image: &GreyImage,
        previous: &[HpCodeMarker],
        predicted: &[Vector2<f64>],
    ) -> Result<Option<Vec<HpCodeMarker>>> {
        if previous.is_empty() || previous.len() != predicted.len() {
            return Ok(None);
        }
        let jobs: Vec<(FinderTriple, Option<&HpCodeMarker>)> = previous
            .iter()
            .zip(predicted)
            .map(|(m, &to)| {
                // `finders` is after mirror resolution; measure() resolves it again.
                let t = if m.mirrored {
                    m.finders.mirrored()
                } else {
                    m.finders
                };
                let shift = to - t.center();
                let moved = FinderTriple {
                    corner: t.corner + shift,
                    right: t.right + shift,
                    bottom: t.bottom + shift,
                    ..t
                };
                (moved, Some(m))
            })
            .collect();
        let found = self.measure_all(image, &jobs)?;
        let same = found.len() == previous.len()
            && found
                .iter()
                .zip(previous)
                .all(|(a, b)| a.id == b.id && a.mirrored == b.mirrored);
        Ok(same.then_some(found))
    }

    /// The markers of `jobs` (a finder triple, and the marker it was found as in the last
    /// frame when tracking), in their order. Each thread (with its own engine) takes the
    /// next job not yet taken, so that the costly ones (real markers, each with its field
    /// fit) spread over the cores wherever they sit in the list; the results are put back in
    /// the jobs' order, the sequential result whatever the thread count.
    fn measure_all(
        &mut self,
        image: &GreyImage,
        jobs: &[(FinderTriple, Option<&HpCodeMarker>)],
    ) -> Result<Vec<HpCodeMarker>> {
        let threads = crate::parallel::thread_count(self.params.threads, jobs.len());
        while self.workers.len() < threads {
            self.workers.push(MarkerWorker::default());
        }
        let params = &self.params;
        let results = crate::parallel::map_in_order(
            &mut self.workers[..threads],
            jobs,
            |worker, (triple, previous)| {
                Measure::new(params, worker).measure(image, triple, *previous)
            },
        )
        .ok_or_else(|| {
            Error::PatternNotFound("internal: a marker-measuring thread panicked".into())
        })?;
        let mut markers = Vec::with_capacity(jobs.len());
        for result in results {
            markers.extend(result?);
        }
        Ok(markers)
    }
}

/// Per finder, whether one of `markers` uses it.
fn taken_finders(finders: &[Finder], markers: &[HpCodeMarker]) -> Vec<bool> {
    finders
        .iter()
        .map(|f| markers.iter().any(|m| m.finders.uses(f)))
        .collect()
}

/// Whether the centre of `triple` lies within four modules of a marker of `markers`.
fn near_a_marker(markers: &[HpCodeMarker], triple: &FinderTriple) -> bool {
    let (center, module) = (triple.center(), triple.module_px);
    markers
        .iter()
        .any(|m| (m.origin_px - center).norm() < 4.0 * module)
}

impl Measure<'_> {
    /// Whether a window of `size` around the marker of `triple` gets the radial Hann
    /// apodisation: only when it reaches beyond the marker (the setting wins).
    fn apodize(&self, triple: &FinderTriple, size: usize) -> bool {
        self.params
            .apodize
            .unwrap_or_else(|| self.params.window_size.is_some() && size > auto_window_for(triple))
    }

    /// Window side for the marker of `triple` (finders' estimate).
    fn window_size(&self, triple: &FinderTriple) -> usize {
        self.params
            .window_size
            .unwrap_or_else(|| auto_window_for(triple))
    }

    /// Window (centre pixel at index S/2, side `size`) around `center` (image pixels), its
    /// phase planes and the marker grid they give; `None` when the grid does not fit `triple`.
    fn analyze_window(
        &mut self,
        image: &GreyImage,
        triple: &FinderTriple,
        center: Vector2<f64>,
        size: usize,
        hann: bool,
    ) -> Result<Option<WindowResult>> {
        let (index_center, hann_center) = match self.params.pose_formula {
            PoseFormula::Symmetric => (window_center(center), (size as f64 - 1.0) / 2.0),
            // The original: index S/2 on the truncated coarse centre.
            PoseFormula::Original => (
                (center.x.floor() as i64, center.y.floor() as i64),
                (size / 2) as f64,
            ),
        };
        let hann_center = hann.then_some(hann_center);
        let window = self.window_image(image, index_center, size, triple.polarity, hann_center)?;
        let prior = lobe_prior(triple);
        let analysis =
            match self
                .engine
                .analyze_with_prior(&window, &self.params.phase, Some(&prior))
            {
                Ok(a) => a,
                Err(Error::PatternNotFound(why)) => {
                    log::trace!("window {size} px at {index_center:?}: {why}");
                    return Ok(None);
                }
                Err(e) => return Err(e),
            };
        let origin = Vector2::new(index_center.0 as f64, index_center.1 as f64);
        Ok(fine::locate(&analysis.planes, triple, origin)
            .map(|grid| (index_center, analysis, grid)))
    }

    /// Fine measurement of one finder triple; `None` when the window's grid does not confirm
    /// the marker or its ID cannot be read. `previous`: the marker as the last frame found
    /// it (tracking), whose field fit this one starts from when the ID and handedness agree.
    fn measure(
        &mut self,
        image: &GreyImage,
        triple: &FinderTriple,
        previous: Option<&HpCodeMarker>,
    ) -> Result<Option<HpCodeMarker>> {
        let coarse = triple.center();
        if !(coarse.x.is_finite() && coarse.y.is_finite()) {
            return Ok(None);
        }
        let reject = |why: &str| {
            log::debug!(
                "HP code candidate at ({:.1}, {:.1}) px, module {:.2} px: {why}",
                coarse.x,
                coarse.y,
                triple.module_px
            );
            Ok(None)
        };
        let (center, analysis, read) = match self.locate_and_read(image, triple)? {
            Ok(found) => found,
            Err(why) => return reject(&why),
        };
        let size = analysis.size.1;
        let window_center = Vector2::new(center.0 as f64, center.1 as f64);
        let MarkerRead {
            reading,
            finders,
            grid,
            dots,
            dots_std,
        } = read;
        let (icx, icy) = image.center();
        let image_center = Vector2::new(icx as f64, icy as f64);
        let previous = previous.filter(|m| m.id == reading.id && m.mirrored == reading.mirrored);
        let (grid, field) = self.field_fit(image, grid, &analysis, reading.id, previous);
        let (phase_std, yaw_std) = match &field {
            Some(fit) => {
                let c = grid.dots.center - image_center;
                (fit.phase_std_at(c.x, c.y), Some(fit.mean_direction_std()))
            }
            None => (analysis.phase_std, None),
        };
        // Planes over dust can move the pose while every check on the dots passes.
        if let Some(dots_std) = dots_std {
            if let Err(why) = planes_agree_with_dots(&grid, &dots, dots_std, phase_std) {
                return reject(&why);
            }
        }
        let pose = self.pose(
            &grid,
            &analysis,
            window_center,
            image_center,
            reading.mirrored,
        );
        let out_of_plane =
            self.out_of_plane(&grid, field.as_ref(), &analysis, image_center, &reading);
        Ok(Some(HpCodeMarker {
            id: reading.id,
            code_size: grid.code_size,
            pose,
            origin_px: grid.dots.center,
            polarity: triple.polarity,
            mirrored: reading.mirrored,
            id_confidence: reading.confidence,
            finders,
            window: (center, size),
            analysis,
            field,
            phase_std,
            yaw_std,
            out_of_plane,
        }))
    }

    /// The out-of-plane pose of the marker read as `reading` ([`HpCodeParams::pose_3d`]):
    /// `None` when not asked for, or (logged) when its planes have no 3-D solution.
    fn out_of_plane(
        &self,
        grid: &fine::MarkerGrid,
        field: Option<&FieldFit>,
        analysis: &PhaseAnalysis,
        image_center: Vector2<f64>,
        reading: &marker_id::IdReading,
    ) -> Option<MarkerTilt> {
        if !self.params.pose_3d {
            return None;
        }
        let input = tilt_input(grid, field, analysis, image_center, reading.mirrored);
        marker_tilt(&input, self.params.period, self.params.focal_length_px)
            .map_err(|e| log::warn!("HP code {}: no out-of-plane pose: {e}", reading.id))
            .ok()
    }

    /// The marker of `triple` up to its field fit: its window's centre (image pixels) and
    /// planes, and its dots located and ID read. The inner `Err` says why there is no marker.
    fn locate_and_read(
        &mut self,
        image: &GreyImage,
        triple: &FinderTriple,
    ) -> Result<std::result::Result<ReadResult, String>> {
        let (center, analysis, grid) = match self.marker_window(image, triple)? {
            Ok(found) => found,
            Err(why) => return Ok(Err(why)),
        };
        let (grid, dots, dots_std) = match on_its_dots(image, grid, triple) {
            Ok(found) => found,
            Err(why) => return Ok(Err(why.to_string())),
        };
        let input = ReadInput {
            triple,
            analysis: &analysis,
            window_center: Vector2::new(center.0 as f64, center.1 as f64),
            grid,
            dots,
            dots_std,
        };
        Ok(self
            .read_marker_or_sharpened(image, &input)
            .map(|read| (center, analysis, read)))
    }

    /// The window of the marker of `triple` and its planes and grid: on the finders' window
    /// (the whole marker, apodised, when that one has too few periods), then on the window the
    /// measured centre and width call for. The inner `Err` says why there is no marker.
    fn marker_window(
        &mut self,
        image: &GreyImage,
        triple: &FinderTriple,
    ) -> Result<std::result::Result<WindowResult, String>> {
        let coarse = triple.center();
        // Period steps along the marker axes as the finders see them.
        let steps = |leg: Vector2<f64>| leg.normalize() * 2.0 * triple.module_px;
        let precheck = marker_id::grid_precheck(
            image,
            triple.polarity,
            coarse,
            steps(triple.right - triple.corner),
            steps(triple.bottom - triple.corner),
            MIN_PRECHECK,
        );
        if precheck < MIN_PRECHECK {
            return Ok(Err(format!(
                "no dot grid around the centre ({precheck:.2})"
            )));
        }
        let size = self.window_size(triple);
        let mut first =
            self.analyze_window(image, triple, coarse, size, self.apodize(triple, size))?;
        if first.is_none() && self.params.window_size.is_none() {
            // Too few periods inside the marker's dot field (small markers, dust over it):
            // the whole marker, apodised, has about twice as many.
            let width = auto_window_width(triple);
            let wide = 2 * crate::phase::fft_size::at_most((width / 2.0).ceil() as usize)
                .max(MIN_WINDOW / 2);
            let hann = self.params.apodize.unwrap_or(true);
            first = self.analyze_window(image, triple, coarse, wide, hann)?;
        }
        let Some(mut found) = first else {
            return Ok(Err("no grid matching the finders in the window".into()));
        };
        if self.params.pose_formula == PoseFormula::Symmetric {
            // Second pass on the window the measured centre and width call for, when the
            // finders' estimate chose another: the result then depends on the fine geometry
            // only, not on the coarse one (stable from frame to frame, exactly covariant under
            // image rotations and flips).
            let fine = found.2.dots;
            let module = (fine.step_x.norm() + fine.step_y.norm()) / 4.0;
            let size2 = self.params.window_size.unwrap_or_else(|| {
                let width = found.2.code_size as f64 * module;
                auto_window_size(width, module, found.2.alpha(false))
            });
            if window_center(fine.center) != found.0 || size2 != size {
                let hann = self.apodize(triple, size2);
                if let Some(second) =
                    self.analyze_window(image, triple, fine.center, size2, hann)?
                {
                    found = second;
                }
            }
        }
        Ok(Ok(found))
    }

    /// [`Measure::read_marker`] on the raw image, and again on the image sharpened at the
    /// module's scale when the marker is blurred and the first reading failed. `Err` says why
    /// the first reading failed.
    fn read_marker_or_sharpened(
        &self,
        image: &GreyImage,
        input: &ReadInput,
    ) -> std::result::Result<MarkerRead, String> {
        let view = ReadingView::raw(image);
        match self.read_marker(image, &view, input) {
            Ok(read) => Ok(read),
            // Blur beyond a quarter period merges a dot's level with its neighbours' spill:
            // read again with the detail at the module's scale restored. Only there: on a
            // sharp marker an undecided dot is an occluder's or a defect's, which sharpening
            // would decide.
            Err(why) => {
                let sharp =
                    ReadingView::sharpened_if_blurred(image, input.triple.polarity, &input.dots);
                match sharp.and_then(|view| self.read_marker(image, &view, input).ok()) {
                    Some(read) => {
                        log::debug!("HP code ID {} read sharpened", read.reading.id);
                        Ok(read)
                    }
                    None => Err(why),
                }
            }
        }
    }

    /// The whole-field fit of marker `id` located by `grid` (window planes `analysis`), when
    /// enabled and more precise than the window: the refined grid and the fit, else `grid` as
    /// it is. `previous`: the marker in the last frame (tracking), whose fit this one starts
    /// from.
    fn field_fit(
        &self,
        image: &GreyImage,
        grid: fine::MarkerGrid,
        analysis: &PhaseAnalysis,
        id: u64,
        previous: Option<&HpCodeMarker>,
    ) -> (fine::MarkerGrid, Option<FieldFit>) {
        let (icx, icy) = image.center();
        let at = grid.dots.center - Vector2::new(icx as f64, icy as f64);
        let refined = if self.params.field_fit {
            let rival = Rival {
                phase_std: analysis.phase_std,
                at: (at.x, at.y),
            };
            let previous = previous.and_then(|m| m.field.as_ref());
            fine::refine_on_field(image, &grid, id, rival, previous)
                .filter(|(_, fit)| fit.beats(&rival))
        } else {
            None
        };
        match refined {
            Some((refined, fit)) => {
                let tilt = fit.perspective.unwrap_or_default();
                log::debug!(
                    "marker {}: field fit over {} px, {} harmonics, {} iterations, {:.1} % inliers, \
                         residual σ {:.2e} ({:.2} × the white noise's), orientation σ {:.2e} rad, \
                         perspective ({:.2e}, {:.2e}) per period taken at {:.3}",
                    id,
                    fit.pixels,
                    fit.harmonics,
                    fit.iterations,
                    100.0 * fit.inlier_fraction,
                    fit.residual_std,
                    fit.model_error_ratio(),
                    fit.mean_direction_std(),
                    tilt.x,
                    tilt.y,
                    fit.tilt_weight
                );
                (refined, Some(fit))
            }
            None => {
                if self.params.field_fit {
                    log::debug!(
                        "marker {}: no whole-field fit or a less precise one, window planes kept",
                        id
                    );
                }
                (grid, None)
            }
        }
    }

    /// Reads the ID of the marker whose dots `input` locates, and checks that it is one: its
    /// ID confidence, its handedness (a mirrored marker's grid located again from the
    /// swapped finders), the ends of its field, its corners and the grid's support. Levels
    /// are read on `view`; the grid is located on `image`. `Err` says why it is no marker.
    fn read_marker(
        &self,
        image: &GreyImage,
        view: &ReadingView,
        input: &ReadInput,
    ) -> std::result::Result<MarkerRead, String> {
        let polarity = input.triple.polarity;
        let reading = marker_id::read_id(&view.image, polarity, &view.local(&input.dots))
            .ok_or("ID dots outside the image or without contrast")?;
        // An uncertain ID is never reported as a marker.
        if reading.confidence < self.params.min_id_confidence {
            return Err(format!(
                "ID {} read with confidence {:.3} < {} (ID margin {:.3}, other edge {:.3})",
                reading.id,
                reading.confidence,
                self.params.min_id_confidence,
                reading.parts.0,
                reading.parts.1
            ));
        }
        let (finders, grid, dots, dots_std) = if reading.mirrored {
            let mirrored = input.triple.mirrored();
            let g = fine::locate(&input.analysis.planes, &mirrored, input.window_center)
                .ok_or("mirrored grid does not fit")?;
            let (g, dots, std) =
                on_its_dots(image, g, &mirrored).map_err(|why| format!("mirrored: {why}"))?;
            (mirrored, g, dots, std)
        } else {
            (*input.triple, input.grid, input.dots, input.dots_std)
        };
        let local = view.local(&dots);
        // A grid a whole period off the marker: every check inside the field passes.
        if !marker_id::field_ends_at_its_edges(&view.image, polarity, &local) {
            return Err("dot field does not end at its bottom and right edges".into());
        }
        // Three finder-like shapes around something that is not this marker's dot grid.
        let light = marker_id::FieldLight::measure(&view.image, polarity, &local)
            .ok_or("dot field outside the image")?;
        if !marker_id::corners_consistent(&view.image, polarity, &local, &light) {
            return Err("corners do not show three finders and a block of dots".into());
        }
        let support = marker_id::grid_support(&light);
        if support < MIN_GRID_SUPPORT {
            return Err(format!("grid support {support:.3} < {MIN_GRID_SUPPORT}"));
        }
        Ok(MarkerRead {
            reading,
            finders,
            grid,
            dots,
            dots_std,
        })
    }

    /// Pose of the marker from its grid (window and image centres in image pixels).
    fn pose(
        &self,
        grid: &fine::MarkerGrid,
        analysis: &PhaseAnalysis,
        window_center: Vector2<f64>,
        image_center: Vector2<f64>,
        mirrored: bool,
    ) -> Pose {
        let period = self.params.period;
        // ±1: pattern y is 90° clockwise on screen from pattern x (front) or anticlockwise.
        let hand = if mirrored { -1.0 } else { 1.0 };
        let (alpha, pixel_size, position) = match self.params.pose_formula {
            PoseFormula::Symmetric => {
                let ps =
                    period * (grid.plane_x.frequency() + grid.plane_y.frequency()) / (2.0 * TAU);
                let camera_px = grid.dots.center - image_center;
                let alpha = grid.alpha(mirrored);
                (alpha, ps, rotate2(camera_px * ps, -alpha))
            }
            PoseFormula::Original => {
                let plane1 = analysis.planes[0];
                let ps = period * plane1.frequency() / TAU;
                let alpha = if grid.x_from_plane == 0 {
                    grid.plane_x.angle()
                } else {
                    grid.plane_y.angle() - hand * FRAC_PI_2
                };
                // Marker centre from the window centre along the pattern axes, pattern units
                // (the original's `−pos`, with the whole-period shift).
                let (kx, ky) = grid.period_shift;
                let dx = -period * (grid.plane_x.c - TAU * kx - grid.center_phase) / TAU;
                let dy = -period * (grid.plane_y.c - TAU * ky - grid.center_phase) / TAU;
                let w = rotate2((window_center - image_center) * ps, -alpha);
                (alpha, ps, Vector2::new(w.x + dx, w.y + hand * dy))
            }
        };
        if mirrored {
            // cTp = Rz(α)·Rx(π)·Trans(x, y, 0): (x, −y) = Rz(−α)·t.
            Pose {
                x: position.x,
                y: -position.y,
                z: 0.0,
                alpha: wrap_angle(alpha),
                beta: 0.0,
                gamma: wrap_angle(PI),
                pixel_size,
            }
        } else {
            Pose::planar(position.x, position.y, alpha, pixel_size)
        }
    }

    /// The `size × size` window whose index `size/2` is the image pixel `center`, zero outside
    /// the image, made bright-dot (inverted for dark dots) and, with `hann_center`, multiplied
    /// by the radial Hann window centred at that index (both axes).
    fn window_image(
        &mut self,
        image: &GreyImage,
        center: (i64, i64),
        size: usize,
        polarity: Polarity,
        hann_center: Option<f64>,
    ) -> Result<GreyImage> {
        let half = (size / 2) as i64;
        let fill = match polarity {
            Polarity::BrightDots => 0.0,
            Polarity::DarkDots => 1.0,
        };
        let mut window = image.window(center.0 - half, center.1 - half, size, size, fill)?;
        let pixels = window.pixels_mut();
        if polarity == Polarity::DarkDots {
            for v in pixels.iter_mut() {
                *v = 1.0 - *v;
            }
        }
        if let Some(hann_center) = hann_center {
            if self.hann.0 != size || self.hann.1 != hann_center {
                *self.hann = (size, hann_center, hann_window(size, hann_center));
            }
            for (v, w) in pixels.iter_mut().zip(&self.hann.2) {
                *v *= w;
            }
        }
        Ok(window)
    }
}

/// Where the marker's dots are, for reading the ID and checking the marker
/// (docs/design.md#hp-dot-homography): `grid` fitted to its own dots (under a tilt the planes'
/// grid drifts off the far edges; with too few dots measurable, `grid`'s own), both numbered
/// from the finders that sit on the dots, and the standard deviation of the fitted centre
/// (periods; `None` without a fit). `Err` says why not.
fn on_its_dots(
    image: &GreyImage,
    grid: fine::MarkerGrid,
    finders: &FinderTriple,
) -> std::result::Result<(fine::MarkerGrid, marker_id::DotGrid, Option<f64>), &'static str> {
    let fit = dot_homography::fit_dot_homography(image, finders.polarity, &grid.dots);
    let dots = fit.map_or(grid.dots, |f| f.grid);
    let shift = dot_homography::finder_renumbering(&dots, finders)
        .ok_or("no two finders on the dot lattice")?;
    if shift != Vector2::zeros() {
        log::debug!("HP code centre renumbered by {shift:?} periods");
    }
    let center_std = fit.map(|f| f.center_std);
    Ok((grid.renumbered(shift), dots.renumbered(shift), center_std))
}

/// What [`Measure::read_marker`] reads from: the finders, the window's analysis and the
/// grid located on the marker's dots ([`on_its_dots`]).
struct ReadInput<'a> {
    triple: &'a FinderTriple,
    analysis: &'a PhaseAnalysis,
    /// Centre of the analysis window, image pixels.
    window_center: Vector2<f64>,
    grid: fine::MarkerGrid,
    dots: marker_id::DotGrid,
    /// Standard deviation of the dots' fitted centre, periods (`None` without a fit).
    dots_std: Option<f64>,
}

/// What a marker's out-of-plane pose is measured from: its whole-field fit, else its
/// window's planes.
fn tilt_input(
    grid: &fine::MarkerGrid,
    field: Option<&FieldFit>,
    analysis: &PhaseAnalysis,
    image_center: Vector2<f64>,
    mirrored: bool,
) -> TiltInput {
    let origin = grid.dots.center - image_center;
    match field {
        Some(fit) => TiltInput::from_field(fit, [[1, 0], [0, 1]], origin, mirrored),
        None => {
            let gradient = |p: &crate::phase::PhasePlane| Vector2::new(p.a, p.b);
            let phase_std = match grid.x_from_plane {
                0 => analysis.phase_std,
                _ => [analysis.phase_std[1], analysis.phase_std[0]],
            };
            let window = analysis.size.0.min(analysis.size.1) as f64;
            TiltInput::from_window(
                [gradient(&grid.plane_x), gradient(&grid.plane_y)],
                phase_std,
                window,
                origin,
                mirrored,
            )
        }
    }
}

/// A marker read and checked: its ID reading, and its finders, grid and dots, mirrored where
/// the reading says so.
struct MarkerRead {
    reading: marker_id::IdReading,
    finders: FinderTriple,
    grid: fine::MarkerGrid,
    dots: marker_id::DotGrid,
    dots_std: Option<f64>,
}

/// Whether the centre the pose is computed from (`grid`'s, its planes' phase σ `phase_std`,
/// radians) is where the marker's dots are (`dots`, fitted with centre σ `dots_std`, periods):
/// within [`MAX_CENTRE_DISAGREEMENT`] period, plus the bias of linear planes under a tilt and
/// [`CENTRE_SIGMAS`] standard deviations of the two. `Err` says how far off.
fn planes_agree_with_dots(
    grid: &fine::MarkerGrid,
    dots: &marker_id::DotGrid,
    dots_std: f64,
    phase_std: [f64; 2],
) -> std::result::Result<(), String> {
    let apart = (grid.dots.center - dots.center).norm() / grid.dots.step_x.norm();
    // Planes left unrefined (`PhaseParams::refine_iterations` 0) carry no σ: none allowed.
    let planes_std = (phase_std[0].max(phase_std[1]) / TAU).max(0.0);
    // A plane fitted to the phase of a tilted grid takes in the mean of its quadratic term,
    // |p|·⟨u²⟩ over its pixels: at most |p|₁·h²/3 for pixels inside the marker (0.03–0.05
    // ·|p|₁·h² seen for the windows on keystoned real images).
    let h = dots.half_width();
    let tilt_bias = dots.perspective.abs().sum() * h * h / 3.0;
    let allowed = MAX_CENTRE_DISAGREEMENT + tilt_bias + CENTRE_SIGMAS * dots_std.hypot(planes_std);
    match apart <= allowed {
        true => Ok(()),
        false => Err(format!(
            "the planes' centre is {apart:.4} period off the dots' (allowed {allowed:.4})"
        )),
    }
}

/// A window's centre pixel (index S/2), its phase analysis and the marker grid it gives.
type WindowResult = ((i64, i64), PhaseAnalysis, fine::MarkerGrid);

/// A window's centre pixel, its phase analysis and the marker read on its dots
/// ([`Measure::locate_and_read`]).
type ReadResult = ((i64, i64), PhaseAnalysis, MarkerRead);

/// Pixel at index S/2 of the window that covers the pixels symmetric about
/// `floor(center) + ½`, as the engine's separable window is: a rotated or flipped image then
/// gets exactly the rotated or flipped window.
fn window_center(center: Vector2<f64>) -> (i64, i64) {
    (center.x.floor() as i64 + 1, center.y.floor() as i64 + 1)
}

/// Automatic window side for the marker of `triple`, from its finders.
fn auto_window_for(triple: &FinderTriple) -> usize {
    let u = triple.right - triple.corner;
    auto_window_size(auto_window_width(triple), triple.module_px, u.y.atan2(u.x))
}

/// Marker width from its finders, pixels: the legs plus one finder (7 modules).
fn auto_window_width(triple: &FinderTriple) -> f64 {
    let (u, v) = (triple.right - triple.corner, triple.bottom - triple.corner);
    0.5 * (u.norm() + v.norm()) + 7.0 * triple.module_px
}

/// Automatic window side for a marker `width` pixels wide, `module` pixels per half period,
/// turned by `angle` in the image: the largest FFT-friendly square (image axes) that stays
/// inside the marker and clear of its finder squares, so the window holds the marker's dot
/// grid and nothing else (0.55 to 0.7 marker widths depending on the angle). The finders
/// are not periodic: letting them in costs ~1e-5 rad of orientation on noise-free renders.
fn auto_window_size(width: f64, module: f64, angle: f64) -> usize {
    // Half-side h of an axis-aligned square seen in the marker frame: its support along a
    // marker axis is h·(|cos| + |sin|).
    let spread = angle.cos().abs() + angle.sin().abs();
    // Finder inner corners at (±, ±)(width/2 − 7 modules); marker edge at width/2.
    let clear_of_finders = (width / 2.0 - (7.0 + WINDOW_CLEARANCE) * module) * spread;
    let inside = (width / 2.0 - WINDOW_CLEARANCE * module) / spread;
    let half = clear_of_finders.min(inside).floor().max(0.0) as usize;
    (2 * crate::phase::fft_size::at_most(half)).max(MIN_WINDOW)
}

/// Radial Hann window of a `size × size` image: `(1 + cos(π·d/ρ))/2` for `d < ρ = size/2`,
/// 0 beyond, `d` = distance to index `(c, c)` (with `c = size/2` the same as
/// [`crate::snapshot::Snapshot::apodize`] with exponent 1; computed once per size).
fn hann_window(size: usize, c: f64) -> Vec<f32> {
    let rho = size as f64 / 2.0;
    let mut w = vec![0.0f32; size * size];
    for r in 0..size {
        let dy = r as f64 - c;
        for col in 0..size {
            let d = (col as f64 - c).hypot(dy);
            if d < rho {
                w[r * size + col] = (0.5 * (1.0 + (PI * d / rho).cos())) as f32;
            }
        }
    }
    w
}

/// Where the finders of `triple` expect the grid's lobes: along the finder legs, at the
/// period twice their module.
fn lobe_prior(triple: &FinderTriple) -> LobePrior {
    let frequency = |leg: Vector2<f64>| {
        let f = leg.normalize() / (2.0 * triple.module_px);
        [f.x, f.y]
    };
    LobePrior {
        frequencies: [
            frequency(triple.right - triple.corner),
            frequency(triple.bottom - triple.corner),
        ],
        tolerance: LOBE_TOLERANCE,
        min_prominence: GUIDED_PROMINENCE,
    }
}
