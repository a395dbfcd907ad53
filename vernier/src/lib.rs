//! # vernier
//!
//! Sub-pixel pose measurement of micro-fabricated periodic dot markers in microscope images
//! (a Rust successor of the VERNIER method, FEMTO-ST), usable without ROS.
//!
//! A marker is a square grid of dots. Its image is essentially two plane waves whose phases are
//! linear in the pixel position; fitting these *phase planes* over the whole grid gives the
//! position to about 1/1000 of a pixel, modulo one period. A *coarse step* specific to each
//! marker type (Megarena code, HP code finders and ID, stamp frame and bitmap) then removes the
//! `2kπ` ambiguity and the grid's quarter-turn symmetry.
//!
//! The full design — the method, every coarse step, frames and units, the pattern file format,
//! the defects of the original fixed here, and the accuracy and speed figures with the commands
//! that reproduce them — is `docs/design.md` in the repository; doc comments cite its sections
//! as `docs/design.md#<anchor>`.
//!
//! ## Quick start
//!
//! [`Detector`] is the one entry point for every marker type: build a [`DetectorConfig`]
//! (directly, or from the flat [`detector::DetectorSettings`] the CLI and the ROS node use),
//! then call [`Detector::detect`] on each frame; it keeps FFT plans and buffers between frames.
//!
//! ```
//! use vernier::hpcode::HpCodeParams;
//! use vernier::layout::HpCodeLayout;
//! use vernier::render::{render, RenderOptions};
//! use vernier::{Detector, DetectorConfig, GreyImage, Pose};
//!
//! # fn main() -> vernier::Result<()> {
//! // A synthetic frame: an HP code (33 half-period cells, 10 µm period, ID 5) at a known pose.
//! // A real one would come from `GreyImage::open("frame.png")?`.
//! let marker = HpCodeLayout::from_code_size(10.0, 33)?.with_id(5)?;
//! let truth = Pose::planar(12.0, 7.5, -0.4, 1.25); // µm, µm, rad, µm per pixel
//! let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(240, 200) };
//! let frame: GreyImage = render(&marker, &truth, &options)?;
//!
//! let mut detector = Detector::new(DetectorConfig::HpCode(HpCodeParams::new(10.0, 33)))?;
//! for found in detector.detect(&frame)? {
//!     assert_eq!(found.id, 5);
//!     assert!((found.pose.x - truth.x).abs() < 0.0125); // 1/100 px
//!     assert!((found.pose.y - truth.y).abs() < 0.0125);
//!     let in_metres = found.pose.scaled(1e-6); // what the ROS node publishes
//!     assert!((in_metres.x - 12.0e-6).abs() < 1e-7);
//! }
//! # Ok(())
//! # }
//! ```
//!
//! ## Marker types
//!
//! | marker | detector (runnable example on each) | what comes out |
//! |---|---|---|
//! | plain periodic grid | [`PeriodicDetector`] | pose modulo one period and a quarter turn |
//! | Megarena (LFSR-coded absolute grid) | [`megarena::MegarenaDetector`] | absolute position over the whole pattern, full turn, decode confidence; out-of-plane angles on request |
//! | HP code (QR-like finders, ID in missing dots) | [`hpcode::HpCodeDetector`] | every marker with its ID, ID confidence and full-turn pose |
//! | stamp / bitmap | [`stamp::StampDetector`] | every stamp with its bitmap index and pose |
//!
//! All of them run the [`PhaseEngine`] (also with an example): spectrum (`phase/spectrum.rs`),
//! lobe search (`phase/lobes.rs`), band-pass planes (`phase/bandpass.rs`) and the windowed
//! refinement on the pixels (`phase/refine.rs`).
//!
//! ## Frames and units
//!
//! - Image frame of phase planes: `x = col − C div 2`, `y = row − R div 2`, pixels, y down.
//! - Camera frame: origin at the centre pixel, `x` right, `y` down, `z` into the scene
//!   (orthographic microscope, `pixel_size` pattern units per pixel).
//! - Pattern frame: `x_p` along increasing layout column, `y_p` along increasing layout row,
//!   origin at the central dot (periodic, HP code, stamp/bitmap) or at dot (0, 0) (Megarena).
//! - [`Pose`] `(x, y, z, alpha, beta, gamma, pixel_size)`:
//!   `cTp = Trans(0,0,z)·Rz(α)·Ry(β)·Rx(γ)·Trans(x,y,0)`; the image centre sees the pattern point
//!   `(−x, −y)`, `alpha` is positive clockwise on screen.
//! - Lengths are in the pattern unit (that of the period, µm by convention), angles in radians;
//!   [`Pose::scaled`] converts (`1e-6`: µm → m).
//!
//! ## Modules
//!
//! - Input: [`grey_image`] ([`GreyImage`]: `[0, 1]` pixels, any size, 8/16-bit, colour → luma;
//!   [`Polarity`]).
//! - Measuring: [`phase`], [`periodic`], [`megarena`] (+ [`megarena_sequence`]), [`hpcode`]
//!   (+ [`binarize`]), [`stamp`] (+ [`snapshot`]), [`detector`] (dispatch and [`MarkerPose`]),
//!   [`pose`], [`calibration`] (pixel size and its variation across the field).
//! - Patterns: [`layout`] (periodic, Megarena, HP code, bitmap, fingerprint, custom),
//!   [`pattern_file`] (JSON pattern files), [`render`] (synthetic images at a known pose),
//!   [`export`] (PNG, SVG, GDSII, OASIS).
//! - Errors: [`Error`], [`Result`]; bad input is always an error, never a panic.
#![deny(missing_docs)]
pub mod binarize;
pub mod error;
pub mod layout;
pub mod limits;
pub use error::{Error, Result};
mod decimate;
mod frame_buffer;
pub mod grey_image;
pub mod image_file;
mod level_surface;
mod lru;
pub mod megarena_sequence;
mod order_stats;
pub mod output;
mod parallel;
pub mod pattern_file;
pub mod phase;
mod sharpen;
pub use grey_image::{parse_polarity_setting, GreyImage, PixelFormat, Polarity};
pub use image_file::{DecodeLimits, FrameReader};
pub use phase::{LobePrior, PhaseAnalysis, PhaseEngine, PhaseParams, PhasePlane, Refinement};
pub mod pose;
pub mod render;
pub use pose::Pose;
pub mod periodic;
pub use periodic::{PeriodicDetector, PeriodicParams};
pub mod calibration;
pub mod detector;
pub use detector::{Detector, DetectorConfig, DetectorSettings, MarkerKind, MarkerPose};
pub mod export;
pub mod hpcode;
pub mod marker_tilt;
pub mod megarena;
pub mod snapshot;
pub mod stamp;
pub use hpcode::{HpCodeDetector, HpCodeMarker, HpCodeParams};
pub use megarena::{MegarenaDetection, MegarenaDetector, MegarenaParams};
pub use periodic::PeriodicDetection;
pub use stamp::{StampDetection, StampDetector, StampParams};
