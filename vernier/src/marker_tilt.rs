//! Out-of-plane pose of a marker that sits anywhere in the image (HP codes, stamps) from its
//! whole-field fit (docs/design.md#pose-3d-markers).
//!
//! **Geometry.** A pinhole camera of focal length `f` pixels (principal point at the image
//! centre) sees the marker's pattern point `u` (pattern units, from the marker origin) at
//! `q = q₀ + A·u/(1 + e·u)`: `q₀` is the origin's image point, `A` the tangent map there
//! (pixels per pattern unit, the gradients of the fit's planes inverted) and `e = r₃/T_z`,
//! `r₃ = (−sin β, cos β·sin γ)` the depth row of `R = Rz(α)·Ry(β)·Rx(γ)` over the pattern
//! axes and `T_z` the origin's depth. The fit's lattice `u = v/(1 − p·v)` measures
//! `p = P·e` per period. The tangent map is `A = (f/T_z)·(R₂ − q₀·r₃ᵀ/f)`: off the optical
//! axis, perspective shears it by `q₀/f`.
//!
//! * **Orthographic** (no focal length, the microscope default): `A = R₂/s`, solved by
//!   [`orthographic_candidates`] into `(β, ±γ)` and its mirror `(−β, ∓γ)`.
//! * **Perspective** (`f` given): `A + q₀·eᵀ = (f/T_z)·R₂` with `e` predicted by each mirror
//!   branch's own angles and depth, solved by fixed-point iteration (the correction is
//!   `|q₀|/f`, a few hundredths); then `T_z = s·f` and the origin's camera position
//!   `T = (q₀·s, T_z)`.
//!
//! **Which mirror.** Each branch predicts the sign of `p` along `r₃`; the fit measured `p`
//! with its covariance `C` (model error counted). `t = p·r̂₃/√(r̂₃ᵀ·C·r̂₃)` is the cue in
//! standard deviations; the branch it points to is chosen, and
//! [`MarkerTilt::cue_strength`] is `erf(|t|/√2)`, the probability that noise alone would give
//! a smaller `|t|`: near 0 when the image shows no perspective (orthographic optics, where
//! the mirror cannot be told), above [`CLEAR_CUE`] for a clear one.
//!
//! **Covariance.** The gradients' covariance (white noise of the fit) is propagated through
//! the whole solve numerically along its principal axes, first order plus the second-order
//! term that keeps the variance finite at the fronto-parallel fold (as
//! [`crate::megarena::pose3d::angle_covariance`] does).

use crate::error::{Error, Result};
use crate::megarena::pose3d::{orthographic_candidates, pixel_from_pattern};
use crate::megarena::PatternPlanes;
use crate::phase::{wrap_to_pi, FieldFit, PhasePlane};
use crate::pose::Pose;
use nalgebra::{Matrix2, Matrix4, SymmetricEigen, Vector2, Vector3, Vector4};
use std::f64::consts::{PI, TAU};

/// Cue strength above which the mirror choice is documented as clear: the measured
/// perspective lies 1.64 standard deviations or more on the chosen side.
pub const CLEAR_CUE: f64 = 0.9;

/// Fixed-point iterations of the perspective solve (its contraction is about `|q₀|/f`).
const PERSPECTIVE_ITERATIONS: usize = 8;

/// What the out-of-plane pose of one marker is measured from, in the marker's pattern axes.
#[derive(Clone, Copy, Debug)]
pub struct TiltInput {
    /// Phase gradients of the pattern x and y planes (`2π` per period), rad/pixel, image
    /// frame (y down).
    pub gradients: [Vector2<f64>; 2],
    /// Covariance of `(gx_col, gx_row, gy_col, gy_row)`, (rad/pixel)².
    pub gradient_covariance: Matrix4<f64>,
    /// The marker origin's image point relative to the image centre pixel, pixels.
    pub origin_from_centre: Vector2<f64>,
    /// The measured perspective `p` per period along the pattern x and y axes and its
    /// covariance; `None` when the fit did not measure it.
    pub perspective: Option<(Vector2<f64>, Matrix2<f64>)>,
    /// The marker is seen from its back (its planes are left-handed).
    pub mirrored: bool,
}

/// Out-of-plane pose of one marker.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MarkerTilt {
    /// The chosen solution: `beta`, `gamma`, `alpha` the 3-D angles (`gamma` near `±π` for
    /// a mirrored marker), `x, y` as for every pose (the pattern point `(−x, −y)` lies on the
    /// optical axis), `z` its depth and `pixel_size = z/f` with a focal length, `z = 0` and
    /// the scale at the marker origin without one.
    pub pose: Pose,
    /// The other mirror solution.
    pub mirror: Pose,
    /// How clear the mirror choice is, `[0, 1)` (see the module doc; [`CLEAR_CUE`]).
    pub cue_strength: f64,
    /// Its uncertainty (white noise of the fit; the mirror ambiguity not included).
    pub covariance: TiltCovariance,
}

/// Uncertainty of an out-of-plane pose from the marker's own fit.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct TiltCovariance {
    /// Covariance of `(β, γ, α)`, rad².
    pub angles: [[f64; 3]; 3],
    /// Standard deviation of the marker origin's depth (the camera-frame translation's z),
    /// pattern units; `None` without a focal length (the depth is unobserved).
    pub depth_std: Option<f64>,
}

impl TiltInput {
    /// The input of a marker whose whole-field fit `fit` measured its planes: pattern axis `k`
    /// is `Σ_l axes[k][l]·(fit plane l)` (a signed permutation: the identity for HP codes, a
    /// stamp's matched orientation), its origin `origin_from_centre` pixels from the image
    /// centre.
    pub fn from_field(
        fit: &FieldFit,
        axes: [[i64; 2]; 2],
        origin_from_centre: Vector2<f64>,
        mirrored: bool,
    ) -> TiltInput {
        let r = Matrix2::from_fn(|k, l| axes[k][l] as f64);
        let planes = fit.planes.map(|p| Vector2::new(p.a, p.b));
        let gradients = [0, 1].map(|k| planes[0] * r[(k, 0)] + planes[1] * r[(k, 1)]);
        // The 4-vector (g_x, g_y) is (R ⊗ I₂)·(g₁, g₂).
        let map = Matrix4::from_fn(|i, j| {
            if i % 2 == j % 2 {
                r[(i / 2, j / 2)]
            } else {
                0.0
            }
        });
        let perspective = fit
            .perspective
            .zip(fit.perspective_covariance)
            .map(|(p, c)| (r * p, r * c * r.transpose()));
        TiltInput {
            gradients,
            gradient_covariance: map * fit.gradient_covariance() * map.transpose(),
            origin_from_centre,
            perspective,
            mirrored,
        }
    }

    /// The input of a marker measured on its window's planes alone (gradients `gradients` of
    /// pattern x and y, offsets' σ `phase_std`, radians, over a `window_px`-pixel window):
    /// each gradient component of a flat fit carries `σ_c·√12/window_px` (the yaw's model,
    /// [`crate::MarkerPose::covariance`]), and no perspective is measured.
    pub fn from_window(
        gradients: [Vector2<f64>; 2],
        phase_std: [f64; 2],
        window_px: f64,
        origin_from_centre: Vector2<f64>,
        mirrored: bool,
    ) -> TiltInput {
        let slope = phase_std.map(|s| (s * 12f64.sqrt() / window_px).powi(2));
        TiltInput {
            gradients,
            gradient_covariance: Matrix4::from_diagonal(&Vector4::new(
                slope[0], slope[0], slope[1], slope[1],
            )),
            origin_from_centre,
            perspective: None,
            mirrored,
        }
    }
}

/// Checks a focal length setting: `None`, or finite and > 0 pixels.
pub fn check_focal_length(focal_px: Option<f64>) -> Result<()> {
    match focal_px {
        Some(f) if !(f.is_finite() && f > 0.0) => Err(Error::parameter(
            "focal_length_px",
            format!("must be > 0 pixels, got {f}"),
        )),
        _ => Ok(()),
    }
}

impl TiltCovariance {
    /// The same covariance with lengths multiplied by `factor` (pattern units → metres).
    pub fn scaled(&self, factor: f64) -> TiltCovariance {
        TiltCovariance {
            depth_std: self.depth_std.map(|s| s * factor),
            ..*self
        }
    }
}

/// One mirror branch's solution: its angles and the marker origin's depth (or, without a
/// focal length, the scale at the origin), with the pose.
#[derive(Clone, Copy, Debug)]
struct Branch {
    values: Vector4<f64>,
    pose: Pose,
}

/// The out-of-plane pose of the marker described by `input`, for a pattern of physical period
/// `period`; `focal_px`, the focal length in pixels, for the perspective solution and depth.
pub fn marker_tilt(input: &TiltInput, period: f64, focal_px: Option<f64>) -> Result<MarkerTilt> {
    check_focal_length(focal_px)?;
    // A mirrored marker is the proper one turned by π about its x axis: y flips.
    let hand = if input.mirrored { -1.0 } else { 1.0 };
    let gradients = [input.gradients[0], input.gradients[1] * hand];
    let flip = Matrix4::from_diagonal(&Vector4::new(1.0, 1.0, hand, hand));
    let covariance = flip * input.gradient_covariance * flip;
    let q0 = input.origin_from_centre;
    let branches = solve(&gradients, q0, period, focal_px, None)?;
    let (chosen, cue_strength) = choose(&branches, input.perspective, hand);
    let best = branches[chosen];
    let other = branches[1 - chosen];
    let spread = propagate(&gradients, &covariance, |g| {
        solve(g, q0, period, focal_px, Some(best.values)).ok()
    })
    .ok_or_else(|| Error::Decode("the out-of-plane solution is degenerate".into()))?;
    let angle_covariance = std::array::from_fn(|i| std::array::from_fn(|j| spread[(i, j)]));
    let depth_std = focal_px.map(|_| spread[(3, 3)].max(0.0).sqrt());
    let unflip = |p: Pose| {
        if input.mirrored {
            Pose {
                y: -p.y,
                gamma: crate::phase::wrap_angle(p.gamma + PI),
                ..p
            }
        } else {
            p
        }
    };
    Ok(MarkerTilt {
        pose: unflip(best.pose),
        mirror: unflip(other.pose),
        cue_strength,
        covariance: TiltCovariance {
            angles: angle_covariance,
            depth_std,
        },
    })
}

/// The two mirror branches for right-handed `gradients`; with `near`, the one branch nearest
/// those values (twice).
fn solve(
    gradients: &[Vector2<f64>; 2],
    q0: Vector2<f64>,
    period: f64,
    focal_px: Option<f64>,
    near: Option<Vector4<f64>>,
) -> Result<[Branch; 2]> {
    let planes: PatternPlanes = gradients.map(|g| PhasePlane {
        a: g.x,
        b: g.y,
        c: -g.dot(&q0),
    });
    let start = orthographic_candidates(&planes, period, 0.0)?;
    let Some(f) = focal_px else {
        let branch = |p: Pose| Branch {
            values: Vector4::new(p.beta, p.gamma, p.alpha, p.pixel_size),
            pose: p,
        };
        return Ok(pick([branch(start[0]), branch(start[1])], near));
    };
    let tangent = pixel_from_pattern(&planes, period)?;
    let perspective = |seed: Pose| -> Result<Branch> {
        let mut pose = seed;
        for _ in 0..PERSPECTIVE_ITERATIONS {
            let depth = pose.pixel_size * f;
            let e = depth_row(&pose) / depth;
            let centred = tangent + q0 * e.transpose();
            let g = centred
                .try_inverse()
                .ok_or_else(|| Error::Decode("the phase planes are degenerate".into()))?
                * (TAU / period);
            let planes: PatternPlanes = [0, 1].map(|l| PhasePlane {
                a: g[(l, 0)],
                b: g[(l, 1)],
                c: 0.0,
            });
            let [c0, c1] = orthographic_candidates(&planes, period, 0.0)?;
            let d = |c: &Pose| (c.beta - pose.beta).hypot(c.gamma - pose.gamma);
            pose = if d(&c0) <= d(&c1) { c0 } else { c1 };
        }
        let depth = pose.pixel_size * f;
        Ok(Branch {
            values: Vector4::new(pose.beta, pose.gamma, pose.alpha, depth),
            pose: placed(&pose, q0, depth, f),
        })
    };
    Ok(pick([perspective(start[0])?, perspective(start[1])?], near))
}

/// Both branches, or with `near` the nearer one twice (the same branch under a small change of
/// the gradients, continuous where `β` or `γ` crosses 0).
fn pick(branches: [Branch; 2], near: Option<Vector4<f64>>) -> [Branch; 2] {
    let Some(target) = near else {
        return branches;
    };
    let d = |b: &Branch| (b.values[0] - target[0]).hypot(b.values[1] - target[1]);
    let best = if d(&branches[0]) <= d(&branches[1]) {
        branches[0]
    } else {
        branches[1]
    };
    [best, best]
}

/// `r₃ = (−sin β, cos β·sin γ)`: the depth change per pattern unit along the pattern axes.
fn depth_row(pose: &Pose) -> Vector2<f64> {
    Vector2::new(-pose.beta.sin(), pose.beta.cos() * pose.gamma.sin())
}

/// The pose whose rotation is `angles`' and whose origin sits at camera point
/// `T = (q₀·T_z/f, T_z)`, in the pose's convention `T = R·(x, y, 0) + (0, 0, z)`:
/// `z = (Rᵀ·T)_z / r₃₃`, `(x, y) = (Rᵀ·(T − z·e_z))_{x,y}`, `pixel_size = z/f`.
fn placed(angles: &Pose, q0: Vector2<f64>, depth: f64, f: f64) -> Pose {
    let r = angles.rotation();
    let t = Vector3::new(q0.x * depth / f, q0.y * depth / f, depth);
    let local = r.transpose() * t;
    let r33 = r[(2, 2)];
    let z = local.z / r33;
    let xy = r.transpose() * (t - Vector3::new(0.0, 0.0, z));
    Pose {
        x: xy.x,
        y: xy.y,
        z,
        pixel_size: z / f,
        ..*angles
    }
}

/// The branch that the measured perspective points to, and the cue's strength. `hand` flips
/// the measured y component with the gradients (a mirrored marker).
fn choose(
    branches: &[Branch; 2],
    perspective: Option<(Vector2<f64>, Matrix2<f64>)>,
    hand: f64,
) -> (usize, f64) {
    let Some((p, c)) = perspective else {
        return (0, 0.0);
    };
    let flip = Matrix2::new(1.0, 0.0, 0.0, hand);
    let (p, c) = (flip * p, flip * c * flip);
    let r3 = depth_row(&branches[0].pose);
    let along = r3.norm();
    let variance = (r3.transpose() * c * r3)[(0, 0)];
    if !(along > 0.0 && variance > 0.0 && p.iter().all(|v| v.is_finite())) {
        return (0, 0.0);
    }
    let t = p.dot(&r3) / variance.sqrt();
    let chosen = usize::from(t < 0.0);
    (chosen, libm::erf(t.abs() / std::f64::consts::SQRT_2))
}

/// Covariance of `solve(g)`'s four values when the gradients `g` carry the covariance
/// `covariance`: along each principal axis `u_i` (variance `λ_i`) the gradients move by
/// `±√λ_i·u_i`, `d_i = (f₊ − f₋)/2`, `e_i = f₊ + f₋ − 2f₀`, `Σ = Σ_i d_i·d_iᵀ + ½·e_i·e_iᵀ`.
/// `None` when a solve fails.
fn propagate(
    gradients: &[Vector2<f64>; 2],
    covariance: &Matrix4<f64>,
    solve: impl Fn(&[Vector2<f64>; 2]) -> Option<[Branch; 2]>,
) -> Option<Matrix4<f64>> {
    let value = |g: &[Vector2<f64>; 2]| solve(g).map(|b| b[0].values);
    let f0 = value(gradients)?;
    let eigen = SymmetricEigen::new(*covariance);
    let mut sum = Matrix4::zeros();
    for (i, &lambda) in eigen.eigenvalues.iter().enumerate() {
        if lambda.is_nan() || lambda <= 0.0 {
            continue;
        }
        let step = eigen.eigenvectors.column(i) * lambda.sqrt();
        let moved = |sign: f64| {
            let g = [
                gradients[0] + Vector2::new(step[0], step[1]) * sign,
                gradients[1] + Vector2::new(step[2], step[3]) * sign,
            ];
            value(&g)
        };
        let (plus, minus) = (moved(1.0)?, moved(-1.0)?);
        let mut d = (plus - minus) / 2.0;
        let mut e = plus + minus - 2.0 * f0;
        // α wraps.
        d[2] = wrap_to_pi(plus[2] - minus[2]) / 2.0;
        e[2] = wrap_to_pi(plus[2] - f0[2]) + wrap_to_pi(minus[2] - f0[2]);
        sum += d * d.transpose() + 0.5 * e * e.transpose();
    }
    Some(sum)
}
