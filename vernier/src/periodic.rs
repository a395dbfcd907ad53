//! Detector of plain periodic dot grids (docs/design.md#periodic): the pose modulo one period and
//! the grid's 90° symmetry.

use crate::error::Result;
use crate::grey_image::{GreyImage, Polarity};
use crate::megarena::{pose3d, PatternPlanes};
use crate::phase::{
    fit_dot_field_against, wrap_to_pi, FieldFit, NodeMask, PhaseAnalysis, PhaseEngine, PhaseParams,
    PhasePlane, Rival,
};
use crate::pose::Pose;
use nalgebra::{Matrix2, Vector2};
use std::f64::consts::{FRAC_PI_2, SQRT_2, TAU};

/// Slope factor `κ` of a plane fitted by the phase engine under its sine-cubed window: the
/// standard deviation of each gradient component is `κ·σ_c/L`, `σ_c` the phase offset's and
/// `L` the window side, pixels (4.83–4.88 over 64–1024 px, docs/design.md#uncertainty).
const ENGINE_SLOPE_FACTOR: f64 = 4.85;

/// Settings of [`PeriodicDetector`].
#[derive(Clone, Debug, PartialEq)]
pub struct PeriodicParams {
    /// Physical period `P` of the grid, pattern units (µm by convention). Must be > 0.
    pub period: f64,
    /// Dot polarity of the images.
    pub polarity: Polarity,
    /// Phase-engine settings.
    pub phase: PhaseParams,
    /// Refine the engine's planes on every pixel of the image, robustly
    /// (docs/design.md#field-fit): 2.5× less position noise and 4× less orientation noise,
    /// dust and scratches ignored, but one sweep of the whole image per iteration (4–8):
    /// ~100× the engine's cost (155 ms against 1.5 ms at 512²). Default `false`.
    pub field_fit: bool,
    /// Also measure the out-of-plane angles (docs/design.md#pose-3d): every detection then
    /// carries [`PeriodicDetection::out_of_plane`], the orthographic solutions with the
    /// perspective cue's choice (`z = 0` without [`Self::focal_length_px`]), from the final planes (the field
    /// fit's when there is one). Costs one demodulation pass over the image. Default `false`.
    pub pose_3d: bool,
    /// Focal length of a perspective camera, pixels: with `pose_3d`, the depth
    /// `z = pixel_size·focal` of the pattern point on the optical axis (the image centre).
    /// `None` (default): `z` unknown (0).
    pub focal_length_px: Option<f64>,
}

impl PeriodicParams {
    /// Defaults for a grid of physical period `period` (pattern units).
    pub fn new(period: f64) -> Self {
        PeriodicParams {
            period,
            polarity: Polarity::BrightDots,
            phase: PhaseParams::default(),
            field_fit: false,
            pose_3d: false,
            focal_length_px: None,
        }
    }
}

/// One periodic-grid measurement.
#[derive(Clone, Debug)]
pub struct PeriodicDetection {
    /// Pose with `x, y ∈ [−P/2, P/2)` (pattern units) and `alpha ∈ [0, π/2)`: the grid is only
    /// known modulo one period and a quarter turn.
    pub pose: Pose,
    /// Image position `(col, row)` of the grid node the pose refers to, pixels.
    pub origin_px: Vector2<f64>,
    /// Phase-engine output (the pose comes from the field fit when there is one).
    pub analysis: PhaseAnalysis,
    /// The whole-image fit the pose was computed from; `None` when
    /// [`PeriodicParams::field_fit`] is off, the fit failed or the engine's planes are more
    /// precise.
    pub field: Option<FieldFit>,
    /// Standard deviation of each plane's phase at the image centre, radians (the field fit's
    /// when there is one, else the engine's).
    pub phase_std: [f64; 2],
    /// Standard deviation of `pose.alpha`, radians, when the field fit measured it.
    pub yaw_std: Option<f64>,
    /// Standard deviation of each component (`∂φ/∂col`, `∂φ/∂row`) of the phase gradient of the
    /// grid's x plane and of its y plane as labelled by `pose.alpha` ([`pattern_planes`]),
    /// rad/pixel: `√2·yaw_std·|∇φ|` with the field fit (the two planes' direction errors,
    /// independent, make the mean direction's), else the engine's slope of a plane under its
    /// sine-cubed window, `4.85·σ_c/L` (`L` the analysed window's shorter side, pixels;
    /// docs/design.md#uncertainty). What the out-of-plane angles' covariance is propagated from.
    pub gradient_std: [f64; 2],
    /// Out-of-plane pose (docs/design.md#pose-3d, `z = 0`) when [`PeriodicParams::pose_3d`] is
    /// set; `None` otherwise. The grid's axes are labelled by the planar `pose.alpha` (see
    /// [`pattern_planes`]); each candidate's `x, y` (pattern units, in `[−P/2, P/2)`) refer to
    /// the same grid node as `pose` and `origin_px`, its `alpha` is the image direction of that
    /// labelling's pattern x axis.
    pub out_of_plane: Option<pose3d::OutOfPlanePose>,
}

/// Measures the pose of a periodic grid filling the image. Keeps FFT plans between calls.
///
/// # Example
///
/// ```
/// use vernier::layout::PeriodicLayout;
/// use vernier::render::{render, RenderOptions};
/// use vernier::{PeriodicDetector, PeriodicParams, Pose};
///
/// # fn main() -> vernier::Result<()> {
/// // 10 µm period, 1.25 µm per pixel; the truth lies inside the reported range
/// // (x, y in [−P/2, P/2), alpha in [0, π/2)), so it comes back as is.
/// let layout = PeriodicLayout::new(10.0, 41, 41)?;
/// let truth = Pose::planar(2.5, -1.0, 0.3, 1.25);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(128, 128) };
/// let image = render(&layout, &truth, &options)?;
///
/// let mut detector = PeriodicDetector::new(PeriodicParams::new(10.0))?;
/// let pose = detector.detect(&image)?.pose;
/// let tolerance = 0.01 * truth.pixel_size; // 1/100 px, in µm
/// assert!((pose.x - truth.x).abs() < tolerance && (pose.y - truth.y).abs() < tolerance);
/// assert!((pose.alpha - truth.alpha).abs() < 1e-4);
/// assert!((pose.pixel_size / truth.pixel_size - 1.0).abs() < 1e-4);
/// # Ok(())
/// # }
/// ```
pub struct PeriodicDetector {
    params: PeriodicParams,
    engine: PhaseEngine,
}

impl PeriodicDetector {
    /// A detector with `params` (validated).
    pub fn new(params: PeriodicParams) -> Result<Self> {
        crate::limits::check_period(params.period)?;
        params.phase.validate()?;
        Ok(PeriodicDetector {
            params,
            engine: PhaseEngine::new(),
        })
    }

    /// Current settings.
    pub fn params(&self) -> &PeriodicParams {
        &self.params
    }

    /// Measures `image`.
    pub fn detect(&mut self, image: &GreyImage) -> Result<PeriodicDetection> {
        let image = &*image.as_bright_dots(self.params.polarity);
        let analysis = self.engine.analyze(image, &self.params.phase)?;
        let field = if self.params.field_fit {
            let rival = Rival {
                phase_std: analysis.phase_std,
                at: (0.0, 0.0),
            };
            fit_whole_image(image, &analysis.planes, rival).filter(|fit| fit.beats(&rival))
        } else {
            None
        };
        let planes = field.as_ref().map_or(analysis.planes, |f| f.planes);
        let pose = periodic_pose(&planes, self.params.period);
        let (cx, cy) = image.center();
        let origin_px = Vector2::new(cx as f64, cy as f64) + pose.origin_in_image();
        let (phase_std, yaw_std) = match &field {
            Some(fit) => (fit.phase_std_at(0.0, 0.0), Some(fit.mean_direction_std())),
            None => (analysis.phase_std, None),
        };
        let order = axis_order(&planes, pose.alpha);
        let gradient_std = match (&field, yaw_std) {
            (Some(fit), Some(yaw)) => order.map(|l| SQRT_2 * yaw * fit.planes[l].frequency()),
            _ => {
                let window = analysis.size.0.min(analysis.size.1).max(1) as f64;
                order.map(|l| ENGINE_SLOPE_FACTOR * phase_std[l] / window)
            }
        };
        let out_of_plane = if self.params.pose_3d {
            let axes = pattern_planes(&planes, pose.alpha);
            Some(pose3d::out_of_plane(
                image,
                &axes,
                self.params.period,
                self.params.focal_length_px,
            )?)
        } else {
            None
        };
        Ok(PeriodicDetection {
            pose,
            origin_px,
            analysis,
            field,
            phase_std,
            yaw_std,
            gradient_std,
            out_of_plane,
        })
    }
}

/// The grid's planes refined on every pixel of `image` (docs/design.md#field-fit): every node
/// within one period of the image is a dot, and no cell is discrepant inside that span. `None`
/// where the fit fails or cannot beat `rival`, the window's fit.
fn fit_whole_image(image: &GreyImage, planes: &[PhasePlane; 2], rival: Rival) -> Option<FieldFit> {
    let corners = image.corners_from_center();
    let span = |p: &PhasePlane| {
        let u = corners.map(|(x, y)| p.at(x, y) / TAU);
        let lo = u.iter().copied().fold(f64::INFINITY, f64::min).floor() as i64 - 1;
        let hi = u.iter().copied().fold(f64::NEG_INFINITY, f64::max).ceil() as i64 + 1;
        lo..=hi
    };
    let (k1, k2) = (span(&planes[0]), span(&planes[1]));
    let inside = |v: i64, k: &std::ops::RangeInclusive<i64>| k.contains(&v.div_euclid(2));
    let mask = NodeMask::from_cells(k1.clone(), k2.clone(), |v1, v2| {
        v1.rem_euclid(2) == 0 && v2.rem_euclid(2) == 0 && inside(v1, &k1) && inside(v2, &k2)
    });
    fit_dot_field_against(image, *planes, &mask, Some(rival), None)
}

/// Pose of the grid from its two planes (image frame; docs/design.md#periodic): the grid
/// node nearest the image centre is the pattern origin, the orientation is the bisector of the
/// two lattice directions (as for HP codes: both planes inform it, and a slight shear moves
/// neither axis alone), reduced to `[0, π/2)`, and the pixel size is the mean of the two
/// periods'.
pub fn periodic_pose(planes: &[PhasePlane; 2], period: f64) -> Pose {
    let [p1, p2] = planes;
    let a1 = p1.angle();
    // Plane 2 runs a quarter turn from plane 1, either way round (the engine orders them by
    // direction, not by handedness).
    let quarter = if wrap_to_pi(p2.angle() - a1) >= 0.0 {
        FRAC_PI_2
    } else {
        -FRAC_PI_2
    };
    let bisector = a1 + wrap_to_pi(p2.angle() - a1 - quarter) / 2.0;
    let alpha = bisector.rem_euclid(FRAC_PI_2);
    let pixel_size = period * (p1.frequency() + p2.frequency()) / (2.0 * TAU);
    // The node (φ₁, φ₂) = 2π·(k₁, k₂) nearest the image centre, where φ = c.
    let gradients = Matrix2::new(p1.a, p1.b, p2.a, p2.b);
    let node = gradients
        .try_inverse()
        .map(|inverse| inverse * Vector2::new(-wrap_to_pi(p1.c), -wrap_to_pi(p2.c)))
        .unwrap_or_else(Vector2::zeros);
    Pose::from_origin_in_image(node, alpha, pixel_size)
}

/// The grid's planes as the absolute planes of a pattern frame (pattern x plane, then y plane,
/// right-handed in the image frame: x right, y down), the axes labelled by the planar
/// orientation `alpha` (radians, image frame, e.g. [`periodic_pose`]'s, in `[0, π/2)`): the x
/// plane is the one whose gradient points nearest `alpha`, the y plane the other, each negated
/// where its gradient points the opposite way (the y plane's nearest `alpha + π/2`). Offsets
/// are wrapped to `[−π, π)`: both phases 0 at the grid node nearest the image centre in phase,
/// the node of [`periodic_pose`]. The input to [`pose3d::out_of_plane`].
pub fn pattern_planes(planes: &[PhasePlane; 2], alpha: f64) -> PatternPlanes {
    let along = |p: &PhasePlane, direction: f64| (p.angle() - direction).cos();
    let [x, y] = axis_order(planes, alpha).map(|l| &planes[l]);
    let oriented = |p: &PhasePlane, direction: f64| {
        let p = if along(p, direction) < 0.0 {
            p.flipped()
        } else {
            *p
        };
        PhasePlane {
            c: wrap_to_pi(p.c),
            ..p
        }
    };
    [oriented(x, alpha), oriented(y, alpha + FRAC_PI_2)]
}

/// Indices of the planes of the grid's x and y axes as labelled by `alpha` (radians, image
/// frame): the x plane's gradient is the one more nearly parallel to `alpha`.
fn axis_order(planes: &[PhasePlane; 2], alpha: f64) -> [usize; 2] {
    let along = |p: &PhasePlane| (p.angle() - alpha).cos().abs();
    if along(&planes[0]) >= along(&planes[1]) {
        [0, 1]
    } else {
        [1, 0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes of a grid of period `period` px whose lattice directions are `a1` and `a2`
    /// (image frame), with a node at `node` (pixels from the image centre).
    fn planes(a1: f64, a2: f64, period: f64, node: Vector2<f64>) -> [PhasePlane; 2] {
        [a1, a2].map(|a| {
            let k = TAU / period;
            let (s, c) = a.sin_cos();
            PhasePlane {
                a: k * c,
                b: k * s,
                c: -k * (c * node.x + s * node.y),
            }
        })
    }

    #[test]
    fn pose_takes_the_bisector_and_a_node_near_the_centre() {
        let node = Vector2::new(2.3, -4.1);
        // A slight shear: plane 2 runs 2 mrad short of a quarter turn from plane 1.
        for a1 in [0.4, 0.0005] {
            let p = planes(a1, a1 + FRAC_PI_2 - 0.002, 10.0, node);
            let pose = periodic_pose(&p, 5.0);
            let expected = (a1 - 0.001).rem_euclid(FRAC_PI_2);
            assert!(
                (pose.alpha - expected).abs() < 1e-12,
                "{a1}: {}",
                pose.alpha
            );
            assert!((0.0..FRAC_PI_2).contains(&pose.alpha));
            assert!((pose.pixel_size - 0.5).abs() < 1e-12);
            // The pose's origin is a grid node (the one at `node`, the nearest to the centre).
            let origin = pose.origin_in_image();
            assert!((origin - node).norm() < 1e-9, "{a1}: {origin:?}");
        }
    }

    /// The planes of a pose through [`pattern_planes`] give back that pose whatever the
    /// engine's order and signs, tilted or not: the labelling is right-handed.
    #[test]
    fn pattern_planes_give_back_the_pose_in_any_engine_order() {
        let period = 10.0;
        for (beta, gamma) in [(0.0, 0.0), (0.3, -0.2), (-0.1, 0.25)] {
            let truth = Pose {
                x: 2.0,
                y: -3.0,
                z: 0.0,
                alpha: 0.6,
                beta,
                gamma,
                pixel_size: 1.2,
            };
            let [px, py] = pose3d::planes_of_pose(&truth, period).unwrap();
            // On the fronto-parallel fold the angles grow like the square root of the planes'
            // rounding errors (≈ 1e-4 rad from 1e-16).
            let tolerance = if beta == 0.0 && gamma == 0.0 {
                1e-3
            } else {
                1e-9
            };
            for swap in [false, true] {
                for (s1, s2) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                    let signed = |p: PhasePlane, s: f64| if s > 0.0 { p } else { p.flipped() };
                    let (p1, p2) = (signed(px, s1), signed(py, s2));
                    let engine = if swap { [p2, p1] } else { [p1, p2] };
                    let alpha = periodic_pose(&engine, period).alpha;
                    let axes = pattern_planes(&engine, alpha);
                    let candidates = pose3d::orthographic_candidates(&axes, period, 0.0).unwrap();
                    let found = candidates.iter().any(|c| {
                        (c.alpha - truth.alpha).abs() < 1e-12
                            && (c.beta - beta).abs() < tolerance
                            && (c.gamma - gamma).abs() < tolerance
                            && (c.pixel_size - truth.pixel_size).abs() < 1e-8
                            && (c.x - truth.x).abs() < 1e-9
                            && (c.y - truth.y).abs() < 1e-9
                    });
                    assert!(found, "({beta}, {gamma}) {swap} {s1} {s2}: {candidates:?}");
                }
            }
        }
    }
}
