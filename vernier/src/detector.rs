//! One entry point for every marker type: configuration → detector → marker poses.
//!
//! Each marker type lives in its own module (periodic grid, HP code, stamp, Megarena); this
//! module only dispatches and converts their results into the common [`MarkerPose`].

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::hpcode::{HpCodeDetector, HpCodeMarker, HpCodeParams};
use crate::marker_tilt::{MarkerTilt, TiltCovariance};
use crate::megarena::{MegarenaDetection, MegarenaDetector, MegarenaParams};
use crate::megarena_sequence::LineSequence;
use crate::pattern_file::Pattern;
use crate::periodic::{PeriodicDetection, PeriodicDetector, PeriodicParams};
use crate::pose::Pose;
use crate::stamp::{StampDetection, StampDetector, StampParams};
use nalgebra::Vector2;

/// One detected marker, in the units of the pattern (µm by convention) and radians.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MarkerPose {
    /// Marker identity: decoded ID (HP code), bitmap index (stamp), 0 for periodic and Megarena.
    pub id: u64,
    /// Pose of the marker's pattern frame in the camera frame (see [`crate::pose`]).
    pub pose: Pose,
    /// Image position `(col, row)` of the marker origin, pixels.
    pub origin_px: Vector2<f64>,
    /// Fraction of the image variance explained by the two grid fundamentals, `[0, 1]`.
    pub quality: f64,
    /// Estimated standard deviation of the two phase offsets, radians (noise model of the fit).
    pub phase_std: [f64; 2],
    /// Another marker in the same image carries the same ID (all are reported).
    pub duplicate_id: bool,
    /// Confidence of the coarse decoding in `[0, 1]` where the marker type has one.
    pub decode_confidence: Option<f64>,
    /// `Some` when `pose` carries measured out-of-plane angles `beta`, `gamma`
    /// ([`DetectorSettings::pose_3d`], Megarena patterns and periodic grids): the strength of the perspective cue that
    /// chose between the two mirror solutions `(β, γ)` and `(−β, −γ)` (see
    /// [`crate::megarena::pose3d::OutOfPlanePose::cue_strength`]: ≈ 1 for a clear cue, near 0
    /// when the image shows no perspective and the sign of both angles is a guess). `None` for
    /// planar poses.
    pub pose_3d_cue_strength: Option<f64>,
    /// Shorter side of the image the phase planes were fitted on, pixels: the marker's
    /// analysis window (HP codes, stamps) or the whole image (periodic, Megarena). The
    /// `window_px` to give [`MarkerPose::covariance`].
    pub window_px: usize,
    /// Standard deviation of `pose.alpha` measured by the fit itself, radians (HP codes'
    /// whole-field fit, docs/design.md#field-fit); `None`: [`MarkerPose::covariance`] derives
    /// it from `phase_std` and the window.
    pub yaw_std: Option<f64>,
    /// Standard deviation of each component (`∂φ/∂col`, `∂φ/∂row`) of the phase gradients of
    /// the pattern x and y planes, rad/pixel, where the marker type's fit states it (periodic
    /// grids: [`PeriodicDetection::gradient_std`]); `None`: [`MarkerPose::covariance`] takes a
    /// flat fit over the window, `√12·phase_std/window_px` (Megarena). Sets the roll, pitch
    /// and 3-D yaw variances of out-of-plane poses only.
    pub slope_std: Option<[f64; 2]>,
    /// The marker's own scale, pattern units per pixel, measured from its phase planes. It is
    /// `pose.pixel_size` unless a calibrated pixel size was given
    /// ([`DetectorSettings::pixel_size`], docs/design.md#calibrated-scale).
    pub measured_pixel_size: f64,
    /// Standard deviation of `measured_pixel_size`, pattern units per pixel (set by
    /// [`Detector`]; 0 until then). Isotropic slope noise moves a phase gradient's length by
    /// the same relative amount as its direction, so `σ_s/s = σ_yaw` of
    /// [`MarkerPose::covariance`].
    pub pixel_size_std: f64,
    /// The out-of-plane pose's own covariance where the marker type measures it with the
    /// angles (HP codes and stamps, [`crate::marker_tilt`]): [`MarkerPose::covariance`] takes
    /// its roll, pitch, yaw and depth from here. `None` for planar poses, periodic grids and
    /// Megarena patterns (their slope model, [`MarkerPose::slope_std`]).
    pub tilt_covariance: Option<TiltCovariance>,
}

impl MarkerPose {
    /// 6×6 covariance of `(x, y, z, roll, pitch, yaw)` of the camera-frame pose `cTp` (the
    /// translation of [`Pose::camera_from_pattern`], as published by the node), in **pattern
    /// units and radians**, estimated from the white-noise level of the phase fit
    /// (docs/design.md#uncertainty). Along the pattern axes the position errors are
    /// `σ_x = P·σ_c1/2π` and `σ_y = P·σ_c2/2π`; the pattern axes are turned by `alpha` in the
    /// camera frame, so the position block is `Rz(α)·diag(σ_x², σ_y²)·Rz(α)ᵀ`, plus
    /// `ε²·t·tᵀ` for the marker's own measured scale (relative σ `ε` =
    /// `pixel_size_std/measured_pixel_size`): the translation `t` is pixels times that scale, so
    /// its error stretches `t` radially (6e-3 µm for a marker 620 µm from the image centre at
    /// `ε` = 1e-5, four times its offsets' σ on `Image96`–`Image125`). A calibrated pixel size
    /// (`pose.pixel_size` other than the measured one) counts as exact.
    /// Yaw from the plane slopes over the analysed `window_px` pixels:
    /// `σ_α = κ·σ_c1/(k·window_px)`, `k` the grid frequency in rad/px, `κ` the slope factor of
    /// the fit (docs/design.md#uncertainty): √12 (periodic grids, HP codes and stamps average
    /// both planes' directions under the engine's sine-cubed window, 4.85/√2 = 3.43; Megarena
    /// fits its planes uniformly over the dots and takes one, √12 = 3.46). When the fit
    /// measured it ([`MarkerPose::yaw_std`], the whole-field fit), that σ is used instead.
    /// Unobserved axes (z, roll, pitch for planar poses) get a variance of `1e6` (large, per
    /// ROS convention for "unknown").
    ///
    /// With out-of-plane angles ([`MarkerPose::pose_3d_cue_strength`] set), `cTp`'s rotation
    /// `Rz(α)·Ry(β)·Rx(γ)` is roll `γ`, pitch `β`, yaw `α`, and the roll/pitch block is the
    /// covariance of `(γ, β)` from
    /// [`angle_covariance`](crate::megarena::pose3d::angle_covariance): a slope error `σ_g` on
    /// each of the four phase-gradient components ([`MarkerPose::slope_std`], else
    /// `σ_g = σ_c·√12/window_px`, the flat fit of the yaw's model), propagated numerically
    /// through the orthographic solution. The 3-D `alpha` is the image direction of the
    /// pattern x axis, normal to the y plane's gradient: its σ is that plane's direction σ,
    /// `σ_α = σ_g,y/k`. It does not include the mirror ambiguity (a wrong cue flips both
    /// signs). `z` stays unobserved (`1e6`).
    pub fn covariance(&self, period: f64, window_px: f64) -> [[f64; 6]; 6] {
        let mut cov = [[0.0; 6]; 6];
        let sx = period * self.phase_std[0] / std::f64::consts::TAU;
        let sy = period * self.phase_std[1] / std::f64::consts::TAU;
        let (vx, vy) = (sx * sx, sy * sy);
        let (s, c) = self.pose.alpha.sin_cos();
        cov[0][0] = c * c * vx + s * s * vy;
        cov[1][1] = s * s * vx + c * c * vy;
        cov[0][1] = c * s * (vx - vy);
        let own_scale = self.pose.pixel_size == self.measured_pixel_size;
        if own_scale && self.measured_pixel_size > 0.0 {
            let e = self.pixel_size_std / self.measured_pixel_size;
            let t = [
                c * self.pose.x - s * self.pose.y,
                s * self.pose.x + c * self.pose.y,
            ];
            for (i, ti) in t.iter().enumerate() {
                for (j, tj) in t.iter().enumerate() {
                    cov[i][j] += e * e * ti * tj;
                }
            }
        }
        cov[1][0] = cov[0][1];
        cov[2][2] = 1e6;
        cov[3][3] = 1e6;
        cov[4][4] = 1e6;
        // Slope error ≈ phase error spread over the window: σ_α ≈ κ·σ_c / (k·window), κ =
        // √(L²·Σw²x²·(Σw)²/((Σwx²)²·Σw²)) per axis: √12 for a flat fit, 4.83–4.88 for the
        // sine-cubed window over 64–1024 px, /√2 for the mean of both planes' directions
        // (checked on renders: tests/efficiency.rs).
        let kappa = 12f64.sqrt();
        let k = std::f64::consts::TAU * self.pose.pixel_size / period;
        let s_alpha = if let Some(measured) = self.yaw_std {
            measured
        } else if k > 0.0 && window_px > 0.0 {
            self.phase_std[0] * kappa / (k * window_px)
        } else {
            f64::INFINITY
        };
        cov[5][5] = s_alpha * s_alpha;
        if let Some(tilt) = &self.tilt_covariance {
            // (β, γ, α) → (pitch, roll, yaw) = indices (4, 3, 5).
            let index = [4, 3, 5];
            for (i, &a) in index.iter().enumerate() {
                for (j, &b) in index.iter().enumerate() {
                    cov[a][b] = tilt.angles[i][j];
                }
            }
            if let Some(depth) = tilt.depth_std {
                cov[2][2] = depth * depth;
            }
        } else if self.pose_3d_cue_strength.is_some() {
            // Slope of a plane fitted over an L-pixel window from offset noise σ_c:
            // σ_slope = σ_c·√12/L (the yaw's model), for ∂φ/∂col and ∂φ/∂row of each plane,
            // unless the fit states its own.
            let flat = |k: usize| {
                if window_px > 0.0 {
                    self.phase_std[k] * 12f64.sqrt() / window_px
                } else {
                    f64::INFINITY
                }
            };
            let slopes = self.slope_std.unwrap_or_else(|| [flat(0), flat(1)]);
            let angles = crate::megarena::pose3d::angle_covariance(&self.pose, period, slopes);
            // (β, γ) → (pitch, roll) = indices (4, 3).
            cov[4][4] = angles[0][0];
            cov[3][3] = angles[1][1];
            cov[3][4] = angles[0][1];
            cov[4][3] = angles[0][1];
            // The 3-D alpha is normal to the y plane's gradient: that plane's direction σ.
            let s_alpha = if k > 0.0 {
                slopes[1] / k
            } else {
                f64::INFINITY
            };
            cov[5][5] = s_alpha * s_alpha;
            // With a focal length, z = pixel_size·f of the point on the optical axis: the
            // measured scale's relative error.
            if self.pose.z > 0.0 && own_scale && self.measured_pixel_size > 0.0 {
                let e = self.pixel_size_std / self.measured_pixel_size;
                cov[2][2] = (self.pose.z * e).powi(2);
            }
        }
        cov
    }
}

/// The marker families the library detects.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MarkerKind {
    /// Plain periodic grid (pose modulo one period).
    #[default]
    Periodic,
    /// HP code markers (QR-like finders + ID).
    HpCode,
    /// Stamp / bitmap markers (square frame + bitmap).
    Stamp,
    /// Megarena absolute encoded grid.
    Megarena,
}

impl std::str::FromStr for MarkerKind {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s.to_ascii_lowercase().as_str() {
            "periodic" => Ok(MarkerKind::Periodic),
            "hpcode" | "hp_code" | "hp" => Ok(MarkerKind::HpCode),
            "stamp" | "bitmap" => Ok(MarkerKind::Stamp),
            "megarena" => Ok(MarkerKind::Megarena),
            other => Err(Error::parameter(
                "pattern_type",
                format!("expected periodic, hpcode, stamp or megarena, got `{other}`"),
            )),
        }
    }
}

/// Flat, user-facing detector settings shared by the CLI flags and the ROS node parameters.
///
/// Fields left `None` take the pattern file's value, then the marker type's default.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DetectorSettings {
    /// Marker family. Ignored when `pattern_file` names a class that implies it.
    pub pattern_type: MarkerKind,
    /// JSON pattern file (optional).
    pub pattern_file: Option<std::path::PathBuf>,
    /// Physical period `P`, pattern units (µm by convention).
    pub period: Option<f64>,
    /// HP code width in half-period cells `W` (33, 37, ...).
    pub code_size: Option<usize>,
    /// Megarena LFSR bit depth (4..=12).
    pub code_depth: Option<u32>,
    /// Side of the square window analysed around each marker, pixels (HP code, stamp).
    pub window_size: Option<usize>,
    /// Dot polarity; `None` (default): found per marker (HP code, stamp), bright dots for
    /// the full-image types (periodic, Megarena).
    pub polarity: Option<crate::grey_image::Polarity>,
    /// Stamp bitmaps (PNG files, 1 = dot), in ID order.
    pub bitmaps: Vec<std::path::PathBuf>,
    /// Measure the out-of-plane angles too (6-DoF pose, docs/design.md#pose-3d). Default
    /// `false`: planar poses, `beta = gamma = 0`.
    ///
    /// Measured for every marker type from its two phase planes, which fix the affine map
    /// pattern → image: Megarena patterns and periodic grids over the whole image (a periodic
    /// grid's axes labelled by its planar `alpha`), HP codes and stamps from their whole-field
    /// fit at the marker's origin (their window's planes without one,
    /// docs/design.md#pose-3d-markers). When set, each [`MarkerPose::pose`] is the
    /// out-of-plane solution: `beta` (about the pattern's intrinsic y axis) and `gamma` (about
    /// its intrinsic x axis), radians, in the frames of [`crate::pose`]
    /// (`cTp = Rz(α)·Ry(β)·Rx(γ)·Trans(x, y, 0)`, camera x right, y down, z into the scene);
    /// `alpha` and `pixel_size` are then those of the same 3-D solution (they differ from the
    /// planar ones by terms of order `β·γ`), `x`, `y` those of the pattern point on the optical
    /// axis, and `z` its depth with [`DetectorSettings::focal_length_px`] (0 without: the depth
    /// is unobserved). Of the two mirror solutions `(β, γ)` and `(−β, −γ)`, which no
    /// orthographic image tells apart, the one the perspective cue favours is reported, its
    /// strength in [`MarkerPose::pose_3d_cue_strength`]; [`MarkerPose::covariance`] then gives
    /// roll and pitch real variances. A marker whose planes have no 3-D solution is reported
    /// planar with `pose_3d_cue_strength` `None`, and the reason logged.
    pub pose_3d: bool,
    /// Refine each marker on its whole dot field (a periodic grid: the whole image), robustly
    /// (docs/design.md#field-fit). `None` (default): on for HP codes and stamps, off for
    /// periodic grids, whose whole-image fit costs ~100× the phase engine (155 ms against
    /// 1.5 ms on a 512² image) for 2.7× less position noise and 4.3× less orientation noise.
    /// `Some(b)`: `b` for every type; `Some(false)` keeps the analysis window's planes
    /// (faster, less precise).
    pub field_fit: Option<bool>,
    /// Calibrated pixel size, pattern units per pixel (docs/design.md#calibrated-scale; measure
    /// it with `vernier calibrate`). A microscope's pixel size is fixed by its optics, so when
    /// it is known, positions use it instead of each marker's own measured scale, whose error
    /// (σ_s/s ≈ 1e-5) would otherwise move a marker 500 px from the image centre by 5e-3 px.
    /// `None` (default): each marker's measured scale. The measured scale is reported either
    /// way ([`MarkerPose::measured_pixel_size`]).
    pub pixel_size: Option<f64>,
    /// Focal length of a perspective camera, pixels (`f_x` of its calibration; principal
    /// point taken at the image centre), for [`DetectorSettings::pose_3d`]: each marker's
    /// depth `z` (pattern units) and, for HP codes and stamps off the optical axis, the
    /// perspective solution of its angles. `None` (default): orthographic optics (a
    /// microscope), `z` unobserved. Needs `pose_3d`.
    pub focal_length_px: Option<f64>,
}

impl DetectorSettings {
    /// Checks every value given against its range in [`crate::limits`], naming the first
    /// invalid setting (values taken from a pattern file are checked when it is read).
    pub fn validate(&self) -> Result<()> {
        use crate::limits;
        if let Some(period) = self.period {
            limits::check_period(period)?;
        }
        if let Some(w) = self.code_size {
            limits::check_code_size(w)?;
        }
        if let Some(depth) = self.code_depth {
            limits::check_code_depth(depth)?;
        }
        if let Some(size) = self.window_size {
            limits::check_window_size(size)?;
        }
        if let Some(pixel_size) = self.pixel_size {
            limits::check_pixel_size(pixel_size)?;
        }
        crate::marker_tilt::check_focal_length(self.focal_length_px)?;
        if self.focal_length_px.is_some() && !self.pose_3d {
            return Err(Error::parameter(
                "focal_length_px",
                "sets the depth of the out-of-plane pose only: turn pose_3d on too",
            ));
        }
        Ok(())
    }

    /// Builds the detector these settings describe ([`DetectorSettings::to_config`], then
    /// [`Detector::new`] with the calibrated [`DetectorSettings::pixel_size`]).
    pub fn build(&self) -> Result<Detector> {
        Ok(Detector::new(self.to_config()?)?.with_pixel_size(self.pixel_size))
    }

    /// Builds the detector configuration, naming the first missing or invalid setting.
    ///
    /// Every value is checked against its physical range in [`crate::limits`] (the same
    /// checks as the CLI, pattern files and the ROS node), whichever marker type uses it.
    pub fn to_config(&self) -> Result<DetectorConfig> {
        self.validate()?;
        let pattern = match &self.pattern_file {
            Some(path) => Some(Pattern::from_file(path)?),
            None => None,
        };
        let kind = match &pattern {
            Some(Pattern::Periodic(_)) => MarkerKind::Periodic,
            Some(Pattern::HpCode(_)) => MarkerKind::HpCode,
            Some(Pattern::Megarena(_)) => MarkerKind::Megarena,
            Some(Pattern::Bitmap(_)) => MarkerKind::Stamp,
            Some(other) => {
                return Err(Error::pattern(
                    other.class_name(),
                    "no detector for this pattern class",
                ))
            }
            None => self.pattern_type,
        };
        let period = self.period.or_else(|| {
            pattern
                .as_ref()
                .map(|p| crate::layout::Layout::period(p.layout()))
        });
        let pattern = pattern.as_ref();
        match kind {
            MarkerKind::Periodic => {
                let mut p = PeriodicParams::new(required_period(period)?);
                p.polarity = self.polarity.unwrap_or_default();
                p.field_fit = self.field_fit.unwrap_or(false);
                p.pose_3d = self.pose_3d;
                p.focal_length_px = self.focal_length_px;
                Ok(DetectorConfig::Periodic(p))
            }
            MarkerKind::Megarena => self.megarena_config(pattern, period),
            MarkerKind::HpCode => self.hpcode_config(pattern, period),
            MarkerKind::Stamp => self.stamp_config(pattern, period),
        }
    }

    /// [`Self::to_config`] for a Megarena, `pattern` the pattern file read if any.
    fn megarena_config(
        &self,
        pattern: Option<&Pattern>,
        period: Option<f64>,
    ) -> Result<DetectorConfig> {
        // An explicit code depth wins over the pattern file's sequence.
        let sequence = match (self.code_depth, pattern) {
            (Some(depth), _) => LineSequence::generated(depth)
                .map_err(|e| Error::parameter("code_depth", e.to_string()))?,
            (None, Some(Pattern::Megarena(layout))) => layout.sequence().clone(),
            (None, _) => {
                return Err(Error::parameter(
                    "code_depth",
                    "required for Megarena patterns (give it or a pattern file)",
                ))
            }
        };
        let mut p = MegarenaParams::with_sequence(required_period(period)?, sequence);
        p.polarity = self.polarity.unwrap_or_default();
        p.pose_3d = self.pose_3d;
        p.focal_length_px = self.focal_length_px;
        Ok(DetectorConfig::Megarena(p))
    }

    /// [`Self::to_config`] for an HP code, `pattern` the pattern file read if any.
    fn hpcode_config(
        &self,
        pattern: Option<&Pattern>,
        period: Option<f64>,
    ) -> Result<DetectorConfig> {
        // W from the flag, else from an HPCodePattern file (`size` dots → 2·size − 1).
        let code_size = match (self.code_size, pattern) {
            (Some(w), _) => w,
            (None, Some(Pattern::HpCode(layout))) => layout.code_size(),
            (None, _) => {
                return Err(Error::parameter(
                    "code_size",
                    "required for HP codes: width in half periods, e.g. 33 or 37",
                ))
            }
        };
        let mut p = HpCodeParams::new(required_period(period)?, code_size);
        p.window_size = self.window_size;
        p.polarity = self.polarity;
        p.field_fit = self.field_fit.unwrap_or(true);
        p.pose_3d = self.pose_3d;
        p.focal_length_px = self.focal_length_px;
        p.validate()?;
        Ok(DetectorConfig::HpCode(p))
    }

    /// [`Self::to_config`] for stamps, `pattern` the pattern file read if any.
    fn stamp_config(
        &self,
        pattern: Option<&Pattern>,
        period: Option<f64>,
    ) -> Result<DetectorConfig> {
        // ID order: the pattern file's bitmap first, then the bitmap files.
        let period = required_period(period)?;
        let mut bitmaps = Vec::new();
        if let Some(Pattern::Bitmap(layout)) = pattern {
            bitmaps.push(layout.clone());
        }
        for path in &self.bitmaps {
            bitmaps.push(crate::layout::BitmapLayout::from_image_file(period, path)?);
        }
        if bitmaps.is_empty() {
            return Err(Error::parameter(
                "bitmaps",
                "stamp detection needs a bitmap (PNG file) or a BitmapPattern file",
            ));
        }
        let mut p = StampParams::new(period, bitmaps);
        p.window_size = self.window_size;
        p.polarity = self.polarity;
        p.field_fit = self.field_fit.unwrap_or(true);
        p.pose_3d = self.pose_3d;
        p.focal_length_px = self.focal_length_px;
        Ok(DetectorConfig::Stamp(p))
    }
}

/// The period given or read from the pattern file, or the error that asks for it.
fn required_period(period: Option<f64>) -> Result<f64> {
    period.ok_or_else(|| Error::parameter("period", "required (give it or a pattern file)"))
}

/// Which detector to build, with its settings.
#[derive(Clone, Debug)]
pub enum DetectorConfig {
    /// Plain periodic grid: pose modulo one period and 90°.
    Periodic(PeriodicParams),
    /// Megarena absolute encoded grid: absolute pose over the whole pattern.
    Megarena(MegarenaParams),
    /// Stamp / bitmap markers: identity (bitmap index) and absolute pose of each.
    Stamp(StampParams),
    /// HP code markers: decoded ID and absolute pose of each.
    HpCode(HpCodeParams),
}

impl DetectorConfig {
    /// The same configuration with each frame's markers measured on `threads` threads (HP
    /// codes and stamps; 0 = every core): 1 where images are themselves detected in parallel.
    pub fn with_marker_threads(mut self, threads: usize) -> Self {
        match &mut self {
            DetectorConfig::Stamp(p) => p.threads = threads,
            DetectorConfig::HpCode(p) => p.threads = threads,
            DetectorConfig::Periodic(_) | DetectorConfig::Megarena(_) => {}
        }
        self
    }

    /// Physical period of the pattern, pattern units.
    pub fn period(&self) -> f64 {
        match self {
            DetectorConfig::Periodic(p) => p.period,
            DetectorConfig::Megarena(p) => p.period,
            DetectorConfig::Stamp(p) => p.period,
            DetectorConfig::HpCode(p) => p.period,
        }
    }
}

/// A detector of any marker type. Keeps FFT plans and buffers between frames.
pub struct Detector {
    inner: Inner,
    /// Frame-to-frame state of [`Detector::detect_next`].
    track: TrackState,
    /// Physical period, pattern units (for the scale's σ).
    period: f64,
    /// Calibrated pixel size, pattern units per pixel ([`DetectorSettings::pixel_size`]).
    pixel_size: Option<f64>,
}

/// What tracking keeps between frames: the last two frames' markers (HP codes or stamps).
#[derive(Default)]
struct TrackState {
    hp_codes: History<HpCodeMarker>,
    stamps: History<StampDetection>,
    /// Frames tracked since the last full detection.
    since_full: usize,
    /// Frames of the stream found by tracking / by full detection (for diagnostics).
    tracked_frames: u64,
    full_frames: u64,
}

/// The last two frames' markers of one type.
struct History<T> {
    last: Vec<T>,
    before: Vec<T>,
}

impl<T> Default for History<T> {
    fn default() -> Self {
        History {
            last: Vec::new(),
            before: Vec::new(),
        }
    }
}

/// A marker that tracking follows: where it is, and what must not change.
trait Tracked {
    /// Image position `(col, row)` of the marker's origin, pixels.
    fn at(&self) -> Vector2<f64>;
    /// Its ID.
    fn identity(&self) -> u64;
}

impl Tracked for HpCodeMarker {
    fn at(&self) -> Vector2<f64> {
        self.origin_px
    }
    fn identity(&self) -> u64 {
        self.id
    }
}

impl Tracked for StampDetection {
    fn at(&self) -> Vector2<f64> {
        self.origin_px
    }
    fn identity(&self) -> u64 {
        self.id as u64
    }
}

impl<T: Tracked> History<T> {
    /// Each last marker's predicted position in the next frame: constant velocity from the
    /// last two frames when it was in both, else where it was.
    fn predicted(&self) -> Vec<Vector2<f64>> {
        self.last
            .iter()
            .enumerate()
            .map(|(i, m)| match self.before.get(i) {
                Some(b) if b.identity() == m.identity() => 2.0 * m.at() - b.at(),
                _ => m.at(),
            })
            .collect()
    }
}

/// A detector whose markers can be tracked: found again from their last detections and
/// predicted positions, or searched for afresh.
trait Tracker {
    /// One marker as the detector reports it.
    type Marker: Tracked;
    /// The markers of `last` found again at `predicted`; `None` when one is lost.
    fn track(
        &mut self,
        image: &GreyImage,
        last: &[Self::Marker],
        predicted: &[Vector2<f64>],
    ) -> Result<Option<Vec<Self::Marker>>>;
    /// Every marker of `image`, searched for.
    fn search(&mut self, image: &GreyImage) -> Result<Vec<Self::Marker>>;
}

impl Tracker for HpCodeDetector {
    type Marker = HpCodeMarker;
    fn track(
        &mut self,
        image: &GreyImage,
        last: &[HpCodeMarker],
        predicted: &[Vector2<f64>],
    ) -> Result<Option<Vec<HpCodeMarker>>> {
        HpCodeDetector::track(self, image, last, predicted)
    }
    fn search(&mut self, image: &GreyImage) -> Result<Vec<HpCodeMarker>> {
        self.detect(image)
    }
}

impl Tracker for StampDetector {
    type Marker = StampDetection;
    fn track(
        &mut self,
        image: &GreyImage,
        last: &[StampDetection],
        predicted: &[Vector2<f64>],
    ) -> Result<Option<Vec<StampDetection>>> {
        StampDetector::track(self, image, last, predicted)
    }
    fn search(&mut self, image: &GreyImage) -> Result<Vec<StampDetection>> {
        self.detect(image)
    }
}

/// Counts of [`TrackState`]: frames since the last full search, tracked and full frames.
type TrackCounts<'a> = (&'a mut usize, &'a mut u64, &'a mut u64);

/// The next frame's markers in `history`, by `detector`: tracked from the last ones and
/// their predicted positions, unless a full search is `due` or tracking loses one.
fn next_frame<D: Tracker>(
    detector: &mut D,
    image: &GreyImage,
    history: &mut History<D::Marker>,
    (since_full, tracked_frames, full_frames): TrackCounts,
    due: bool,
) -> Result<Vec<MarkerPose>>
where
    for<'m> MarkerPose: From<&'m D::Marker>,
{
    let mut tracked = None;
    if !history.last.is_empty() && !due {
        tracked = detector.track(image, &history.last, &history.predicted())?;
    }
    let found = match tracked {
        Some(found) => {
            *since_full += 1;
            *tracked_frames += 1;
            found
        }
        None => {
            *since_full = 0;
            *full_frames += 1;
            detector.search(image)?
        }
    };
    history.before = std::mem::replace(&mut history.last, found);
    Ok(history.last.iter().map(MarkerPose::from).collect())
}

/// How a stream's frames were processed by [`Detector::detect_next`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TrackingCounts {
    /// Frames whose markers were found again from their last positions.
    pub tracked: u64,
    /// Frames that ran the full search (first frame, loss, reacquisition, other types).
    pub full: u64,
}

enum Inner {
    Periodic(Box<PeriodicDetector>),
    Megarena(Box<MegarenaDetector>),
    Stamp(Box<StampDetector>),
    HpCode(Box<HpCodeDetector>),
}

impl Detector {
    /// Builds the detector (validates the settings).
    pub fn new(config: DetectorConfig) -> Result<Self> {
        let period = config.period();
        let inner = match config {
            DetectorConfig::Periodic(p) => Inner::Periodic(Box::new(PeriodicDetector::new(p)?)),
            DetectorConfig::Megarena(p) => Inner::Megarena(Box::new(MegarenaDetector::new(p)?)),
            DetectorConfig::Stamp(p) => Inner::Stamp(Box::new(StampDetector::new(p)?)),
            DetectorConfig::HpCode(p) => Inner::HpCode(Box::new(HpCodeDetector::new(p)?)),
        };
        Ok(Detector {
            inner,
            track: TrackState::default(),
            period,
            pixel_size: None,
        })
    }

    /// The same detector reporting positions with a calibrated pixel size (pattern units per
    /// pixel; `None`: each marker's measured scale). See [`DetectorSettings::pixel_size`];
    /// the value is checked by [`DetectorSettings::validate`].
    pub fn with_pixel_size(mut self, pixel_size: Option<f64>) -> Self {
        self.pixel_size = pixel_size;
        self
    }

    /// Physical period of the pattern, pattern units: with [`MarkerPose::covariance`], the
    /// σ of each marker's position.
    pub fn period(&self) -> f64 {
        self.period
    }

    /// What every frame's markers go through last: duplicate IDs flagged, the measured
    /// scale's σ, and the calibrated scale applied.
    fn finish(&self, mut markers: Vec<MarkerPose>) -> Vec<MarkerPose> {
        flag_duplicate_ids(&mut markers);
        for m in &mut markers {
            let yaw_variance = m.covariance(self.period, m.window_px as f64)[5][5];
            m.pixel_size_std = m.measured_pixel_size * yaw_variance.sqrt();
            if let Some(pixel_size) = self.pixel_size {
                m.pose = m.pose.with_pixel_size(pixel_size);
            }
        }
        markers
    }

    /// Detects the markers of the next frame of a stream (servo loops, recordings), tracking
    /// them from frame to frame (docs/design.md#tracking): for HP codes and framed stamps the
    /// search (finders, frames) runs only on the first frame, when a marker is lost or its ID
    /// changes, and every `reacquire_every` frames (new markers appear then; 0 = only on
    /// loss); in between each marker is measured again from its predicted position (constant
    /// velocity), its whole-field fit started from the last frame's
    /// (docs/design.md#tracked-field-fit). The poses are those of [`Detector::detect`] to
    /// within a small fraction of their σ on renders while markers move less than half a
    /// period per frame beyond the prediction. Other marker types run [`Detector::detect`] on
    /// every frame (periodic and Megarena have no search to skip).
    pub fn detect_next(
        &mut self,
        image: &GreyImage,
        reacquire_every: usize,
    ) -> Result<Vec<MarkerPose>> {
        let t = &mut self.track;
        let due = reacquire_every > 0 && t.since_full + 1 >= reacquire_every;
        let counts = (&mut t.since_full, &mut t.tracked_frames, &mut t.full_frames);
        let markers = match &mut self.inner {
            Inner::HpCode(d) => next_frame(d.as_mut(), image, &mut t.hp_codes, counts, due)?,
            Inner::Stamp(d) => next_frame(d.as_mut(), image, &mut t.stamps, counts, due)?,
            _ => {
                self.track.full_frames += 1;
                return self.detect(image);
            }
        };
        Ok(self.finish(markers))
    }

    /// How the frames given to [`Detector::detect_next`] were processed so far.
    pub fn tracking_counts(&self) -> TrackingCounts {
        TrackingCounts {
            tracked: self.track.tracked_frames,
            full: self.track.full_frames,
        }
    }

    /// Detects every marker in `image`. An image without any marker gives an empty list for
    /// marker types that search (HP code, stamp) and [`Error::PatternNotFound`] for the
    /// full-image types (periodic, Megarena). A `window_size` larger than the image is an
    /// [`Error::InvalidParameter`], never an empty list.
    pub fn detect(&mut self, image: &GreyImage) -> Result<Vec<MarkerPose>> {
        let markers = match &mut self.inner {
            Inner::Periodic(d) => vec![MarkerPose::from(&d.detect(image)?)],
            Inner::Megarena(d) => vec![MarkerPose::from(&d.detect(image)?)],
            Inner::Stamp(d) => {
                if let Some(size) = d.params().window_size {
                    crate::limits::check_window_fits(size, image.width(), image.height())?;
                }
                d.detect(image)?.iter().map(MarkerPose::from).collect()
            }
            Inner::HpCode(d) => {
                if let Some(size) = d.params().window_size {
                    crate::limits::check_window_fits(size, image.width(), image.height())?;
                }
                d.detect(image)?.iter().map(MarkerPose::from).collect()
            }
        };
        Ok(self.finish(markers))
    }
}

impl From<&PeriodicDetection> for MarkerPose {
    fn from(found: &PeriodicDetection) -> Self {
        // With pose_3d, the chosen orthographic 3-D solution replaces the planar pose (same
        // grid node; alpha and pixel size of the 3-D decomposition).
        let (pose, pose_3d_cue_strength) = match &found.out_of_plane {
            Some(o) => (o.pose(), Some(o.cue_strength)),
            None => (found.pose, None),
        };
        MarkerPose {
            id: 0,
            pose,
            origin_px: found.origin_px,
            quality: found.analysis.quality,
            phase_std: found.phase_std,
            duplicate_id: false,
            decode_confidence: None,
            pose_3d_cue_strength,
            window_px: found.analysis.size.0.min(found.analysis.size.1),
            yaw_std: found.yaw_std,
            slope_std: Some(found.gradient_std),
            measured_pixel_size: pose.pixel_size,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        }
    }
}

impl From<&MegarenaDetection> for MarkerPose {
    fn from(found: &MegarenaDetection) -> Self {
        // With pose_3d, the chosen orthographic 3-D solution replaces the planar pose (same
        // x, y; alpha and pixel size of the 3-D decomposition).
        let (pose, pose_3d_cue_strength) = match &found.out_of_plane {
            Some(o) => (o.pose(), Some(o.cue_strength)),
            None => (found.pose, None),
        };
        MarkerPose {
            id: 0,
            pose,
            origin_px: found.origin_px,
            quality: found.analysis.quality,
            phase_std: found.analysis.phase_std,
            duplicate_id: false,
            decode_confidence: Some(found.decode_confidence),
            pose_3d_cue_strength,
            window_px: found.analysis.size.0.min(found.analysis.size.1),
            yaw_std: None,
            slope_std: None,
            measured_pixel_size: pose.pixel_size,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        }
    }
}

impl From<&StampDetection> for MarkerPose {
    fn from(found: &StampDetection) -> Self {
        let planar = MarkerPose {
            id: found.id as u64,
            pose: found.pose,
            origin_px: found.origin_px,
            quality: found.analysis.quality,
            phase_std: found.phase_std,
            duplicate_id: false,
            decode_confidence: Some(found.decode_confidence),
            pose_3d_cue_strength: None,
            window_px: found.analysis.size.0.min(found.analysis.size.1),
            yaw_std: found.yaw_std,
            slope_std: None,
            measured_pixel_size: found.pose.pixel_size,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        };
        planar.with_tilt(found.out_of_plane.as_ref())
    }
}

impl From<&HpCodeMarker> for MarkerPose {
    fn from(found: &HpCodeMarker) -> Self {
        let planar = MarkerPose {
            id: found.id,
            pose: found.pose,
            origin_px: found.origin_px,
            quality: found.analysis.quality,
            phase_std: found.phase_std,
            duplicate_id: false,
            decode_confidence: Some(found.id_confidence),
            pose_3d_cue_strength: None,
            window_px: found.analysis.size.0.min(found.analysis.size.1),
            yaw_std: found.yaw_std,
            slope_std: None,
            measured_pixel_size: found.pose.pixel_size,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        };
        planar.with_tilt(found.out_of_plane.as_ref())
    }
}

impl MarkerPose {
    /// This planar marker with the out-of-plane pose `tilt` (HP codes and stamps), if any: its
    /// pose, cue and covariance; the measured scale is the 3-D solution's.
    fn with_tilt(self, tilt: Option<&MarkerTilt>) -> MarkerPose {
        match tilt {
            Some(t) => MarkerPose {
                pose: t.pose,
                pose_3d_cue_strength: Some(t.cue_strength),
                measured_pixel_size: t.pose.pixel_size,
                tilt_covariance: Some(t.covariance),
                ..self
            },
            None => self,
        }
    }
}

/// Sets `duplicate_id` on every marker whose ID occurs more than once.
pub fn flag_duplicate_ids(markers: &mut [MarkerPose]) {
    for i in 0..markers.len() {
        let id = markers[i].id;
        let count = markers.iter().filter(|m| m.id == id).count();
        markers[i].duplicate_id = count > 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn marker(alpha: f64, phase_std: [f64; 2]) -> MarkerPose {
        MarkerPose {
            id: 0,
            pose: Pose::planar(1.0, 2.0, alpha, 0.5),
            origin_px: Vector2::zeros(),
            quality: 1.0,
            phase_std,
            duplicate_id: false,
            decode_confidence: None,
            pose_3d_cue_strength: None,
            window_px: 256,
            yaw_std: None,
            slope_std: None,
            measured_pixel_size: 0.5,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        }
    }

    /// The measured scale's σ stretches the camera-frame translation radially; a calibrated
    /// scale adds nothing.
    #[test]
    fn the_measured_scale_error_stretches_the_translation() {
        let mut m = marker(0.3, [1e-3, 1e-3]);
        m.pose.x = 600.0;
        m.pose.y = -200.0;
        let plain = m.covariance(10.0, 256.0);
        m.pixel_size_std = 0.5 * 1e-5;
        let with_scale = m.covariance(10.0, 256.0);
        let t = m.pose.camera_from_pattern().translation.vector;
        for (i, j) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
            let added = with_scale[i][j] - plain[i][j];
            assert!(
                (added - 1e-10 * t[i] * t[j]).abs() < 1e-15,
                "{i}{j}: {added}"
            );
        }
        assert_eq!(with_scale[5][5], plain[5][5]);
        m.pose.pixel_size = 0.49; // calibrated
        assert_eq!(m.covariance(10.0, 256.0)[0][0], plain[0][0]);
    }

    /// `pose_3d` reaches every marker type's parameters with the focal length; a focal length
    /// without `pose_3d`, or not above 0, is refused by name.
    #[test]
    fn pose_3d_and_the_focal_length_reach_every_marker_type() {
        let dir = std::env::temp_dir().join(format!("vernier_pose3d_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bitmap = dir.join("stamp.png");
        image::GrayImage::from_fn(9, 9, |x, y| {
            image::Luma([if (x + y) % 3 == 0 { 255 } else { 0 }])
        })
        .save(&bitmap)
        .unwrap();
        let settings = |pattern_type| DetectorSettings {
            pattern_type,
            period: Some(10.0),
            code_size: Some(33),
            code_depth: Some(8),
            bitmaps: vec![bitmap.clone()],
            pose_3d: true,
            focal_length_px: Some(8000.0),
            ..DetectorSettings::default()
        };
        let focal = Some(8000.0);
        match settings(MarkerKind::HpCode).to_config() {
            Ok(DetectorConfig::HpCode(p)) => assert!(p.pose_3d && p.focal_length_px == focal),
            other => panic!("HP code: {other:?}"),
        }
        match settings(MarkerKind::Stamp).to_config() {
            Ok(DetectorConfig::Stamp(p)) => assert!(p.pose_3d && p.focal_length_px == focal),
            other => panic!("stamp: {other:?}"),
        }
        match settings(MarkerKind::Megarena).to_config() {
            Ok(DetectorConfig::Megarena(p)) => assert!(p.pose_3d && p.focal_length_px == focal),
            other => panic!("Megarena: {other:?}"),
        }
        match settings(MarkerKind::Periodic).to_config() {
            Ok(DetectorConfig::Periodic(p)) => assert!(p.pose_3d && p.focal_length_px == focal),
            other => panic!("periodic: {other:?}"),
        }
        let planar = DetectorSettings {
            pose_3d: false,
            ..settings(MarkerKind::HpCode)
        };
        let negative = DetectorSettings {
            focal_length_px: Some(-1.0),
            ..settings(MarkerKind::HpCode)
        };
        for wrong in [planar, negative] {
            let e = wrong
                .to_config()
                .err()
                .map(|e| e.to_string())
                .unwrap_or_default();
            assert!(e.contains("focal_length_px"), "{e}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn covariance_is_in_the_camera_frame() {
        let tau = std::f64::consts::TAU;
        let (period, window) = (tau, 100.0);
        // σ_x = 1 along the pattern x axis, σ_y = 3 along y (P = 2π: σ = σ_c).
        let axis_aligned = marker(0.0, [1.0, 3.0]).covariance(period, window);
        assert_eq!((axis_aligned[0][0], axis_aligned[1][1]), (1.0, 9.0));
        assert_eq!(axis_aligned[0][1], 0.0);
        // Turned by a quarter turn, the pattern's x axis is the camera's y axis.
        let turned = marker(std::f64::consts::FRAC_PI_2, [1.0, 3.0]).covariance(period, window);
        assert!((turned[0][0] - 9.0).abs() < 1e-12 && (turned[1][1] - 1.0).abs() < 1e-12);
        // At 45°, the anisotropy shows as a correlation of camera x and y.
        let diagonal = marker(std::f64::consts::FRAC_PI_4, [1.0, 3.0]).covariance(period, window);
        assert!((diagonal[0][0] - 5.0).abs() < 1e-12 && (diagonal[1][1] - 5.0).abs() < 1e-12);
        assert!((diagonal[0][1] + 4.0).abs() < 1e-12 && diagonal[1][0] == diagonal[0][1]);
        // The trace does not depend on the angle.
        assert!((turned[0][0] + turned[1][1] - 10.0).abs() < 1e-12);
    }

    #[test]
    fn out_of_plane_angles_get_a_variance_only_when_measured() {
        let (period, window) = (10.0, 512.0);
        let mut m = marker(0.4, [1e-3, 1e-3]);
        let planar = m.covariance(period, window);
        assert_eq!((planar[2][2], planar[3][3], planar[4][4]), (1e6, 1e6, 1e6));
        m.pose.beta = 0.2;
        m.pose.gamma = -0.1;
        m.pose_3d_cue_strength = Some(0.9);
        let tilted = m.covariance(period, window);
        // Roll (γ) and pitch (β): small positive variances, symmetric correlation; z unknown.
        assert!(tilted[3][3] > 0.0 && tilted[3][3] < 1e-4, "{tilted:?}");
        assert!(tilted[4][4] > 0.0 && tilted[4][4] < 1e-4, "{tilted:?}");
        assert_eq!(tilted[3][4], tilted[4][3]);
        assert!(tilted[3][4].powi(2) <= tilted[3][3] * tilted[4][4]);
        assert_eq!(tilted[2][2], 1e6);
        // The position block is the planar model's; the yaw, one plane's direction under the
        // flat model, equals the planar one when both planes are equally noisy.
        for (i, j) in [(0, 0), (0, 1), (1, 1)] {
            assert_eq!(tilted[i][j], planar[i][j]);
        }
        assert!((tilted[5][5] / planar[5][5] - 1.0).abs() < 1e-12);
        // A fit's own slope σ replaces the flat model: the yaw is the y plane's direction σ.
        let mut stated = m.clone();
        stated.slope_std = Some([2e-5, 3e-5]);
        let k = std::f64::consts::TAU * m.pose.pixel_size / period;
        let own = stated.covariance(period, window);
        assert!((own[5][5].sqrt() * k / 3e-5 - 1.0).abs() < 1e-12, "{own:?}");
        assert!(own[3][3] > 0.0 && own[4][4] > 0.0 && own[3][3] != tilted[3][3]);
        // Linear regime: twice the phase noise, four times the variance.
        m.phase_std = [2e-3, 2e-3];
        let noisier = m.covariance(period, window);
        for k in [3, 4] {
            let ratio = noisier[k][k] / tilted[k][k];
            assert!((ratio - 4.0).abs() < 0.05, "{ratio}");
        }
    }
}
