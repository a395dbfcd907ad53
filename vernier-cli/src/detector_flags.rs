//! The detector's command-line flags, shared by `vernier detect` and `vernier live`
//! (`#[command(flatten)]`): one definition, so both commands read the same pattern files and
//! settings the same way.

use std::path::PathBuf;

use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::{Detector, Polarity};

/// Which marker to look for and how (pattern file or type and sizes, window, polarity,
/// tracking).
#[derive(clap::Args)]
pub struct DetectorFlags {
    /// JSON pattern file describing the marker (PeriodicPattern, HPCodePattern, ...).
    #[arg(long)]
    pub pattern: Option<PathBuf>,
    /// Marker type when no pattern file is given: periodic, hpcode, stamp or megarena.
    #[arg(long = "type", default_value = "periodic")]
    pub marker_type: MarkerKind,
    /// Shorthand for `--type hpcode`.
    #[arg(long)]
    pub hpcode: bool,
    /// Shorthand for `--type megarena`.
    #[arg(long)]
    pub megarena: bool,
    /// Shorthand for `--type stamp`.
    #[arg(long)]
    pub stamp: bool,
    /// Physical period of the dot grid, pattern units (µm by convention).
    #[arg(long, allow_hyphen_values = true)]
    pub period: Option<f64>,
    /// HP code width in half-period cells (33, 37, ...).
    #[arg(long)]
    pub code_size: Option<usize>,
    /// Megarena LFSR bit depth (4–12).
    #[arg(long)]
    pub code_depth: Option<u32>,
    /// Side of the window analysed around each marker, pixels (8–32768, at most the
    /// image's larger side).
    #[arg(long)]
    pub window_size: Option<usize>,
    /// Stamp bitmap PNG files (1 = dot), in ID order; repeat the flag for several.
    #[arg(long)]
    pub bitmap: Vec<PathBuf>,
    /// Also measure the out-of-plane angles `beta` (about the pattern's y axis) and `gamma`
    /// (about its x axis), radians: 6-DoF pose, every marker type (HP codes and stamps from
    /// their whole-field fit). Orthographic model (`z` stays 0) unless --focal-length-px is
    /// given. Of the two mirror solutions `(beta, gamma)` and `(-beta, -gamma)` the
    /// perspective cue's choice is printed, its strength (0-1) in the JSON as
    /// `pose_3d_cue_strength`.
    #[arg(long = "pose-3d")]
    pub pose_3d: bool,
    /// With --pose-3d: the camera's focal length in pixels (fx of its calibration, principal
    /// point at the image centre). Each marker's depth `z` is then measured (pattern units),
    /// and the angles of markers off the optical axis are solved in perspective.
    #[arg(long = "focal-length-px", requires = "pose_3d")]
    pub focal_length_px: Option<f64>,
    /// HP codes and stamps: keep the analysis window's planes instead of refining each marker
    /// on its whole dot field (docs/design.md#field-fit): faster, less precise.
    #[arg(long = "no-field-fit", conflicts_with = "field_fit")]
    pub no_field_fit: bool,
    /// Periodic grids: refine the engine's planes on every pixel of the image
    /// (docs/design.md#field-fit): 2.5× less position noise, 4× less orientation noise, ~100×
    /// the cost (155 ms against 1.5 ms on a 512² image). HP codes and stamps do it by default.
    #[arg(long = "field-fit")]
    pub field_fit: bool,
    /// Treat the images as one sequence, in order, and track the markers from frame to frame
    /// (HP codes and framed stamps: the search runs on the first frame, on loss and every
    /// `--reacquire-every` frames, and each whole-field fit starts from the last frame's; the
    /// poses of full detection to a small fraction of their σ while markers move less than
    /// half a period per frame).
    #[arg(long)]
    pub track: bool,
    /// With `--track`, run the full search every this many frames (new markers are found
    /// then); 0 = only when a marker is lost.
    #[arg(long, value_name = "FRAMES", default_value_t = 30)]
    pub reacquire_every: usize,
    /// Dot polarity: `auto` (default: found per marker for HP codes and stamps, bright for
    /// periodic and Megarena), `bright` dots on a dark background or `dark` dots on a bright one.
    #[arg(long, default_value = "auto")]
    pub polarity: PolarityArg,
    /// Calibrated pixel size, pattern units per pixel (measure it with `vernier calibrate`):
    /// positions use it instead of each marker's own measured scale, whose ~1e-5 error moves
    /// a marker 500 px from the image centre by 5e-3 px. The measured scale is still printed
    /// (`measured_pixel_size`, `pixel_size_std`). Default: each marker's measured scale.
    #[arg(long, value_name = "UNITS_PER_PX", allow_hyphen_values = true)]
    pub pixel_size: Option<f64>,
}

impl DetectorFlags {
    /// The marker type: a shorthand flag (`--hpcode`, `--megarena`, `--stamp`) wins over
    /// `--type`.
    fn marker_kind(&self) -> MarkerKind {
        if self.hpcode {
            MarkerKind::HpCode
        } else if self.megarena {
            MarkerKind::Megarena
        } else if self.stamp {
            MarkerKind::Stamp
        } else {
            self.marker_type
        }
    }

    /// The detector settings these flags describe (checked later, by
    /// [`DetectorSettings::to_config`]).
    pub fn settings(&self) -> DetectorSettings {
        DetectorSettings {
            pattern_type: self.marker_kind(),
            pattern_file: self.pattern.clone(),
            period: self.period,
            code_size: self.code_size,
            code_depth: self.code_depth,
            window_size: self.window_size,
            polarity: self.polarity.0,
            bitmaps: self.bitmap.clone(),
            pose_3d: self.pose_3d,
            field_fit: match (self.field_fit, self.no_field_fit) {
                (true, _) => Some(true),
                (_, true) => Some(false),
                _ => None,
            },
            pixel_size: self.pixel_size,
            focal_length_px: self.focal_length_px,
        }
    }

    /// A detector built from the flags; the error says which setting is wrong.
    pub fn detector(&self) -> Result<Detector, String> {
        self.settings().build().map_err(|e| e.to_string())
    }

    /// `Some(reacquire_every)` with `--track`, else `None`.
    pub fn tracking(&self) -> Option<usize> {
        self.track.then_some(self.reacquire_every)
    }

    /// The polarity the images are shown with (rerun's spectrum view): `auto` is bright dots.
    pub fn display_polarity(&self) -> Polarity {
        self.polarity.0.unwrap_or_default()
    }
}

/// `--polarity auto|bright|dark` (`auto` = `None`).
#[derive(Clone, Copy, Debug)]
pub struct PolarityArg(pub Option<Polarity>);

impl std::str::FromStr for PolarityArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        vernier::parse_polarity_setting(s)
            .map(PolarityArg)
            .map_err(|e| e.to_string())
    }
}
