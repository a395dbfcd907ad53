//! One entry point for every marker type: configuration → detector → marker poses.
//!
//! Each marker type lives in its own module (periodic grid, HP code, stamp, Megarena); this
//! module only dispatches and converts their results into the common [`MarkerPose`].

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::hpcode::{HpCodeDetector, HpCodeParams};
use crate::megarena::{MegarenaDetector, MegarenaParams};
use crate::megarena_sequence::LineSequence;
use crate::pattern_file::Pattern;
use crate::periodic::{PeriodicDetector, PeriodicParams};
use crate::pose::Pose;
use crate::stamp::{StampDetector, StampParams};
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
}

impl MarkerPose {
    /// 6×6 covariance of `(x, y, z, roll, pitch, yaw)` of the camera-frame pose `cTp` (the
    /// translation of [`Pose::camera_from_pattern`], as published by the node), in **pattern
    /// units and radians**, estimated from the phase-fit noise. Along the pattern axes the
    /// position errors are `σ_x = P·σ_c1/2π` and `σ_y = P·σ_c2/2π`; the pattern axes are turned
    /// by `alpha` in the camera frame, so the position block is `Rz(α)·diag(σ_x², σ_y²)·Rz(α)ᵀ`.
    /// Yaw from the plane slopes over `window_px` pixels. Unobserved axes (z, roll, pitch for
    /// planar poses) get a variance of `1e6` (large, per ROS convention for "unknown").
    pub fn covariance(&self, period: f64, window_px: f64) -> [[f64; 6]; 6] {
        let mut cov = [[0.0; 6]; 6];
        let sx = period * self.phase_std[0] / std::f64::consts::TAU;
        let sy = period * self.phase_std[1] / std::f64::consts::TAU;
        let (vx, vy) = (sx * sx, sy * sy);
        let (s, c) = self.pose.alpha.sin_cos();
        cov[0][0] = c * c * vx + s * s * vy;
        cov[1][1] = s * s * vx + c * c * vy;
        cov[0][1] = c * s * (vx - vy);
        cov[1][0] = cov[0][1];
        cov[2][2] = 1e6;
        cov[3][3] = 1e6;
        cov[4][4] = 1e6;
        // Slope error ≈ phase error spread over the window: σ_α ≈ σ_c·√12 / (k·window).
        let k = std::f64::consts::TAU * self.pose.pixel_size / period;
        let s_alpha = if k > 0.0 && window_px > 0.0 {
            self.phase_std[0] * 12f64.sqrt() / (k * window_px)
        } else {
            f64::INFINITY
        };
        cov[5][5] = s_alpha * s_alpha;
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
        Ok(())
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
        let require_period = || {
            period.ok_or_else(|| Error::parameter("period", "required (give it or a pattern file)"))
        };
        match kind {
            MarkerKind::Periodic => {
                let mut p = PeriodicParams::new(require_period()?);
                p.polarity = self.polarity.unwrap_or_default();
                Ok(DetectorConfig::Periodic(p))
            }
            MarkerKind::Megarena => {
                // An explicit code depth wins over the pattern file's sequence.
                let sequence = match (self.code_depth, &pattern) {
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
                let mut p = MegarenaParams::with_sequence(require_period()?, sequence);
                p.polarity = self.polarity.unwrap_or_default();
                Ok(DetectorConfig::Megarena(p))
            }
            MarkerKind::HpCode => {
                // W from the flag, else from an HPCodePattern file (`size` dots → 2·size − 1).
                let half_periods = match (self.code_size, &pattern) {
                    (Some(w), _) => w,
                    (None, Some(Pattern::HpCode(layout))) => layout.half_periods(),
                    (None, _) => {
                        return Err(Error::parameter(
                            "code_size",
                            "required for HP codes: width in half periods, e.g. 33 or 37",
                        ))
                    }
                };
                let mut p = HpCodeParams::new(require_period()?, half_periods);
                p.window_size = self.window_size;
                p.polarity = self.polarity;
                p.validate()?;
                Ok(DetectorConfig::HpCode(p))
            }
            MarkerKind::Stamp => {
                // ID order: the pattern file's bitmap first, then the bitmap files.
                let period = require_period()?;
                let mut bitmaps = Vec::new();
                if let Some(Pattern::Bitmap(layout)) = &pattern {
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
                Ok(DetectorConfig::Stamp(p))
            }
        }
    }
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
}

enum Inner {
    Periodic(PeriodicDetector),
    Megarena(Box<MegarenaDetector>),
    Stamp(Box<StampDetector>),
    HpCode(Box<HpCodeDetector>),
}

impl Detector {
    /// Builds the detector (validates the settings).
    pub fn new(config: DetectorConfig) -> Result<Self> {
        let inner = match config {
            DetectorConfig::Periodic(p) => Inner::Periodic(PeriodicDetector::new(p)?),
            DetectorConfig::Megarena(p) => Inner::Megarena(Box::new(MegarenaDetector::new(p)?)),
            DetectorConfig::Stamp(p) => Inner::Stamp(Box::new(StampDetector::new(p)?)),
            DetectorConfig::HpCode(p) => Inner::HpCode(Box::new(HpCodeDetector::new(p)?)),
        };
        Ok(Detector { inner })
    }

    /// Detects every marker in `image`. An image without any marker gives an empty list for
    /// marker types that search (HP code, stamp) and [`Error::PatternNotFound`] for the
    /// full-image types (periodic, Megarena). A `window_size` larger than the image is an
    /// [`Error::InvalidParameter`], never an empty list.
    pub fn detect(&mut self, image: &GreyImage) -> Result<Vec<MarkerPose>> {
        match &mut self.inner {
            Inner::Periodic(d) => {
                let found = d.detect(image)?;
                Ok(vec![MarkerPose {
                    id: 0,
                    pose: found.pose,
                    origin_px: found.origin_px,
                    quality: found.analysis.quality,
                    phase_std: found.analysis.phase_std,
                    duplicate_id: false,
                    decode_confidence: None,
                }])
            }
            Inner::Megarena(d) => {
                let found = d.detect(image)?;
                Ok(vec![MarkerPose {
                    id: 0,
                    pose: found.pose,
                    origin_px: found.origin_px,
                    quality: found.analysis.quality,
                    phase_std: found.analysis.phase_std,
                    duplicate_id: false,
                    decode_confidence: Some(found.decode_confidence),
                }])
            }
            Inner::Stamp(d) => {
                if let Some(size) = d.params().window_size {
                    crate::limits::check_window_fits(size, image.width(), image.height())?;
                }
                let mut markers: Vec<MarkerPose> = d
                    .detect(image)?
                    .into_iter()
                    .map(|found| MarkerPose {
                        id: found.id as u64,
                        pose: found.pose,
                        origin_px: found.origin_px,
                        quality: found.analysis.quality,
                        phase_std: found.analysis.phase_std,
                        duplicate_id: false,
                        decode_confidence: Some(found.decode_confidence),
                    })
                    .collect();
                flag_duplicate_ids(&mut markers);
                Ok(markers)
            }
            Inner::HpCode(d) => {
                if let Some(size) = d.params().window_size {
                    crate::limits::check_window_fits(size, image.width(), image.height())?;
                }
                let mut markers: Vec<MarkerPose> = d
                    .detect(image)?
                    .into_iter()
                    .map(|found| MarkerPose {
                        id: found.id,
                        pose: found.pose,
                        origin_px: found.origin_px,
                        quality: found.analysis.quality,
                        phase_std: found.analysis.phase_std,
                        duplicate_id: false,
                        decode_confidence: Some(found.id_confidence),
                    })
                    .collect();
                flag_duplicate_ids(&mut markers);
                Ok(markers)
            }
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
        }
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
}
