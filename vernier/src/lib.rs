//! # vernier
//!
//! Sub-pixel pose measurement of micro-fabricated periodic dot markers in microscope images
//! (a Rust successor of the VERNIER method, FEMTO-ST).
pub mod binarize;
pub mod error;
pub mod layout;
pub mod limits;
pub use error::{Error, Result};
pub mod grey_image;
pub mod megarena_sequence;
pub mod output;
pub mod pattern_file;
pub mod phase;
pub use grey_image::{parse_polarity_setting, DecodeLimits, GreyImage, PixelFormat, Polarity};
pub use phase::{PhaseAnalysis, PhaseEngine, PhaseParams, PhasePlane, Refinement};
pub mod pose;
pub mod render;
pub use pose::Pose;
pub mod periodic;
pub use periodic::{PeriodicDetector, PeriodicParams};
pub mod detector;
pub use detector::{Detector, DetectorConfig, MarkerPose};
pub mod export;
pub mod hpcode;
pub mod megarena;
pub mod snapshot;
pub mod stamp;
