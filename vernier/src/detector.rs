//! One entry point for every marker type: configuration → detector → marker poses.
//!
//! Each marker type lives in its own module (periodic grid, HP code, stamp, Megarena); this
//! module only dispatches and converts their results into the common [`MarkerPose`].

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::pattern_file::Pattern;
use crate::periodic::{PeriodicDetector, PeriodicParams};
use crate::pose::Pose;
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
    /// 6×6 covariance of `(x, y, z, roll, pitch, yaw)` in **pattern units and radians**,
    /// estimated from the phase-fit noise: `σ_x = P·σ_c1/2π`, `σ_y = P·σ_c2/2π`, yaw from the
    /// plane slopes over `window_px` pixels. Unobserved axes (z, roll, pitch for planar poses)
    /// get a variance of `1e6` (large, per ROS convention for "unknown").
    pub fn covariance(&self, period: f64, window_px: f64) -> [[f64; 6]; 6] {
        let mut cov = [[0.0; 6]; 6];
        let sx = period * self.phase_std[0] / std::f64::consts::TAU;
        let sy = period * self.phase_std[1] / std::f64::consts::TAU;
        cov[0][0] = sx * sx;
        cov[1][1] = sy * sy;
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
    /// Dot polarity.
    pub polarity: crate::grey_image::Polarity,
    /// Stamp bitmaps (PNG files, 1 = dot), in ID order.
    pub bitmaps: Vec<std::path::PathBuf>,
}

impl DetectorSettings {
    /// Builds the detector configuration, naming the first missing or invalid setting.
    pub fn to_config(&self) -> Result<DetectorConfig> {
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
                p.polarity = self.polarity;
                Ok(DetectorConfig::Periodic(p))
            }
            other => Err(Error::parameter(
                "pattern_type",
                format!("{other:?} detection is not implemented yet"),
            )),
        }
    }
}

/// Which detector to build, with its settings.
#[derive(Clone, Debug)]
pub enum DetectorConfig {
    /// Plain periodic grid: pose modulo one period and 90°.
    Periodic(PeriodicParams),
}

impl DetectorConfig {
    /// Physical period of the pattern, pattern units.
    pub fn period(&self) -> f64 {
        match self {
            DetectorConfig::Periodic(p) => p.period,
        }
    }
}

/// A detector of any marker type. Keeps FFT plans and buffers between frames.
pub struct Detector {
    inner: Inner,
}

enum Inner {
    Periodic(PeriodicDetector),
}

impl Detector {
    /// Builds the detector (validates the settings).
    pub fn new(config: DetectorConfig) -> Result<Self> {
        let inner = match config {
            DetectorConfig::Periodic(p) => Inner::Periodic(PeriodicDetector::new(p)?),
        };
        Ok(Detector { inner })
    }

    /// Detects every marker in `image`. An image without any marker gives an empty list for
    /// marker types that search (HP code, stamp) and [`Error::PatternNotFound`] for the
    /// full-image types (periodic, Megarena).
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
