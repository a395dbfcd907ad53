//! Matching detections to the ground truth of one scene.
//!
//! A detection matches a truth marker of the scene's family when its origin is within
//! `max(3 px, 0.5 period)` of the truth origin (nearest pairs first, one detection per
//! marker). Then: matched with the right ID = found (position and angle errors recorded),
//! another ID = wrong ID, matched to a marker cut by the border = ignored, unmatched = false
//! marker; expected markers left unmatched = missed.

use crate::bound::{BoundKind, KnownShapeErrors};
use crate::markers::{Expectation, TruthMarker};
use crate::scene::Scene;
use std::f64::consts::FRAC_PI_2;
use vernier::phase::wrap_to_pi;
use vernier::MarkerPose;

/// Outcome of one detection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Verdict {
    /// Matched truth `index` with its ID.
    Found {
        /// Index into the scene's truth.
        truth: usize,
        /// Origin distance, pixels.
        position_error: f64,
        /// |angle difference|, radians.
        angle_error: f64,
        /// The detector's own predicted σ of the origin, pixels: `P·√(σ_c1² + σ_c2²)/2π` from
        /// [`MarkerPose::phase_std`] (`P` the true period in pixels), so that
        /// `position_error / predicted_std_px` is Rayleigh-like (median 0.83, p99 2.15) when
        /// the error is the noise the detector accounts for.
        predicted_std_px: f64,
    },
    /// Matched truth `index`, another ID.
    WrongId {
        /// Index into the scene's truth.
        truth: usize,
    },
    /// Matched a marker cut by the border.
    Ignored {
        /// Index into the scene's truth.
        truth: usize,
    },
    /// Matched nothing.
    False,
}

/// Result of one scene.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneResult {
    /// Expected markers.
    pub markers: usize,
    /// Found with the right ID.
    pub found: usize,
    /// Matched with another ID.
    pub wrong_id: usize,
    /// Detections matching nothing.
    pub false_markers: usize,
    /// Expected markers not matched.
    pub missed: usize,
    /// Position errors of the found markers, pixels.
    pub position_errors: Vec<f64>,
    /// Angle errors of the found markers, radians.
    pub angle_errors: Vec<f64>,
    /// Position errors of the found markers over their predicted σ (see
    /// [`Verdict::Found::predicted_std_px`]), where that σ is positive and finite.
    pub normalised_errors: Vec<f64>,
    /// `(position error, its Cramér–Rao bound)` of the found markers that have a bound
    /// ([`TruthMarker::position_bound`], [`BoundKind::CramerRao`]), pixels.
    pub bounded_errors: Vec<(f64, f64)>,
    /// `(position error, its JPEG model's figure)` of the found markers in grey JPEG files
    /// ([`BoundKind::JpegModel`]), pixels.
    pub jpeg_modelled_errors: Vec<(f64, f64)>,
    /// `(the reference estimators' errors, the JPEG model's figure)` of the same markers
    /// ([`crate::bound::PositionBound::known_shape`]), pixels.
    pub known_shape_errors: Vec<(KnownShapeErrors, f64)>,
    /// One verdict per detection.
    pub verdicts: Vec<Verdict>,
    /// Detector error or panic message, if detection failed.
    pub error: Option<String>,
    /// Detection time, milliseconds.
    pub detect_ms: f64,
}

impl SceneResult {
    /// True when something was missed, wrong or false, or the detector failed.
    pub fn failed(&self) -> bool {
        self.error.is_some() || self.missed > 0 || self.wrong_id > 0 || self.false_markers > 0
    }
}

/// Largest angle error of a marker counted as found, rad: beyond it the pose is wrong (a
/// quarter-turn reading), counted with the wrong IDs. Perspective biases stay far below it.
pub const MAX_ANGLE_ERROR: f64 = 0.05;

/// Match radius around a truth origin, pixels.
pub fn match_radius(truth: &TruthMarker) -> f64 {
    (0.5 * truth.period_px).max(3.0)
}

/// Scores `detections` (or a detector failure) against `scene`'s truth.
pub fn evaluate(
    scene: &Scene,
    detections: std::result::Result<&[MarkerPose], String>,
    detect_ms: f64,
) -> SceneResult {
    let truth = &scene.truth;
    let markers = truth
        .iter()
        .filter(|t| t.expectation == Expectation::Expected && t.family == scene.spec.family)
        .count();
    let detections = match detections {
        Ok(d) => d,
        Err(e) => {
            let mut r = empty_result(markers, Vec::new(), detect_ms);
            r.missed = markers;
            r.error = Some(e);
            return r;
        }
    };
    let mut r = empty_result(markers, match_verdicts(scene, detections), detect_ms);
    for v in &r.verdicts {
        match *v {
            Verdict::Found {
                truth: ti,
                position_error,
                angle_error,
                predicted_std_px,
            } => {
                if let Some(b) = truth.get(ti).and_then(|t| t.position_bound) {
                    match b.kind {
                        BoundKind::CramerRao => &mut r.bounded_errors,
                        BoundKind::JpegModel => &mut r.jpeg_modelled_errors,
                    }
                    .push((position_error, b.px));
                    if let Some(k) = b.known_shape {
                        r.known_shape_errors.push((k, b.px));
                    }
                }
                r.found += 1;
                r.position_errors.push(position_error);
                r.angle_errors.push(angle_error);
                if predicted_std_px.is_finite() && predicted_std_px > 0.0 {
                    r.normalised_errors.push(position_error / predicted_std_px);
                }
            }
            Verdict::WrongId { .. } => r.wrong_id += 1,
            Verdict::Ignored { .. } => {}
            Verdict::False => r.false_markers += 1,
        }
    }
    r.missed = markers - r.found - r.wrong_id;
    r
}

/// A result of `markers` expected markers with `verdicts` and nothing counted yet.
fn empty_result(markers: usize, verdicts: Vec<Verdict>, detect_ms: f64) -> SceneResult {
    SceneResult {
        markers,
        found: 0,
        wrong_id: 0,
        false_markers: 0,
        missed: 0,
        position_errors: Vec::new(),
        angle_errors: Vec::new(),
        normalised_errors: Vec::new(),
        bounded_errors: Vec::new(),
        jpeg_modelled_errors: Vec::new(),
        known_shape_errors: Vec::new(),
        verdicts,
        error: None,
        detect_ms,
    }
}

/// The verdict on each detection: matched one to one with the scene's truth markers of its
/// family within [`match_radius`], nearest pairs first.
fn match_verdicts(scene: &Scene, detections: &[MarkerPose]) -> Vec<Verdict> {
    let truth = &scene.truth;
    // Candidate pairs within the match radius, nearest first.
    let mut pairs: Vec<(f64, usize, usize)> = Vec::new();
    for (di, d) in detections.iter().enumerate() {
        for (ti, t) in truth.iter().enumerate() {
            if t.family != scene.spec.family || t.expectation == Expectation::Foreign {
                continue;
            }
            let dist = (d.origin_px.x - t.origin_px[0]).hypot(d.origin_px.y - t.origin_px[1]);
            if dist < match_radius(t) {
                pairs.push((dist, di, ti));
            }
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut verdicts = vec![Verdict::False; detections.len()];
    let mut det_used = vec![false; detections.len()];
    let mut truth_used = vec![false; truth.len()];
    for (dist, di, ti) in pairs {
        if det_used[di] || truth_used[ti] {
            continue;
        }
        det_used[di] = true;
        truth_used[ti] = true;
        let t = &truth[ti];
        let d = &detections[di];
        verdicts[di] = if t.expectation == Expectation::Ignored {
            Verdict::Ignored { truth: ti }
        } else if d.id == t.id
            && wrap_to_pi(d.pose.alpha - t.angle).abs() < MAX_ANGLE_ERROR
            && (wrap_to_pi(d.pose.gamma).abs() > FRAC_PI_2) == t.mirrored
        {
            Verdict::Found {
                truth: ti,
                position_error: dist,
                angle_error: wrap_to_pi(d.pose.alpha - t.angle).abs(),
                predicted_std_px: t.period_px * d.phase_std[0].hypot(d.phase_std[1])
                    / std::f64::consts::TAU,
            }
        } else {
            // A wrong ID, or the right ID with the marker turned (a quarter-turn reading of
            // a symmetric ID) or seen from the wrong side: a wrong answer either way.
            Verdict::WrongId { truth: ti }
        };
    }
    verdicts
}
