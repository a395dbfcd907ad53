//! # vernier-stress
//!
//! A generalisation stress suite for the HP code and stamp detectors of [`vernier`]: scenes
//! generated deterministically from a `u64` seed (markers at random poses, scales, IDs and
//! polarities, one degradation category each), detected through [`vernier::Detector`] with
//! the settings a CLI user would give, and scored against their ground truth.
//!
//! * [`scene`]: seeds → scenes (image + truth); [`markers`]: families and truth convention;
//! * [`degrade`], [`clutter`], [`raster`], [`geometry`]: how the images are made;
//! * [`bound`]: the Cramér–Rao bound of a marker's position on noisy scenes, and its JPEG
//!   model on JPEG scenes with two reference estimators that test it on the files;
//! * [`evaluate`]: matching detections to the truth; [`suite`]: running and tallying many
//!   scenes; [`dump`]: writing a scene for inspection; [`data`]: the shared data folder.
//!
//! Run `cargo bench -p vernier-stress --bench stress -- --help` for the full suite and
//! `cargo test -p vernier-stress` for the small fixed-seed version with the targets.
//!
//! ## Scenes
//!
//! * Families: HP codes W = 33 or 37 (random IDs over all `(W − 15)/2` bits, image period
//!   4–40 px log-uniform) and stamps (`stamp69x69`, `stampD`, `stampG`, `stamp+` = IDs 0–3,
//!   4–12 px); 1–3 markers of one scale per scene, full-turn angles, anywhere inside the
//!   frame, at least 2 periods apart; image sides adapted to the markers (≤ 1600 px, odd and
//!   even); random polarity, left to the detector (its default finds it per marker); a
//!   quarter of the HP codes with a non-zero ID seen from the back (mirrored: the detector
//!   must read the same ID and say so, `gamma = −π`; drawn from a stream of their own, so
//!   that every other draw of a seed is what it was before).
//! * Categories: `clean` (optics σ 0.4–0.7 px, 16 bits) and one category per degradation
//!   ([`degrade::Degradation`]), plus `combined` (2–4 of them).
//! * Clutter markers: an HP code of the other W in an HP scene is *expected* (the detector's
//!   code size is a prior that accepts W ± 8 and reads the ID for the W measured); a marker of
//!   the other family is *foreign* (a detection on it is a false marker); a marker of the
//!   scene's family cut by the image border is *ignored* (a detection on it is neither found
//!   nor false).
//! * Detector settings: exactly what a CLI user gives (`--hpcode --period 10 --code-size W`
//!   or `--stamp --period 10 --bitmap …` ×4), nothing tuned per scene.

pub mod bound;
pub mod clutter;
pub mod data;
pub mod degrade;
pub mod dump;
pub mod error;
pub mod evaluate;
pub mod geometry;
pub mod markers;
pub mod raster;
pub mod real;
pub mod scene;
pub mod suite;

pub use error::{Result, StressError};
pub use markers::{Family, TruthMarker};
pub use scene::{Category, Generator, Scene, SceneSpec};
pub use suite::{run, select_seeds, Outcome, Report};
