//! Out-of-plane pose from the two absolute phase planes (docs/design.md#pose-3d), orthographic
//! model, and a perspective cue choosing between the mirror solutions.
//!
//! **Orthographic solutions.** The planes give the affine map pixel ← pattern,
//! `M = (P/2π)⁻¹·[∇φ_x; ∇φ_y]⁻¹`, which must equal `R₂ₓ₂/s` (the top-left 2×2 of
//! `Rz(α)·Ry(β)·Rx(γ)` over the pixel size `s`). Its QR factorisation `M = Rot(α)·T` with
//! `T = [[cos β, sin β·sin γ], [0, cos γ]]/s` gives `α` directly, and `1/s² = k²` from the
//! orthonormality of the rotation: `k⁴ − (t₁₁² + t₁₂² + t₂₂²)·k² + t₁₁²·t₂₂² = 0` (larger root),
//! then `β₀ = acos(t₁₁/k)`, `γ₀ = acos(t₂₂/k)` (arguments clamped to `[0, 1]`: the original's
//! unguarded `acos` returned NaN, docs/design.md#defect-acos). The original lists four sign
//! combinations; the sign of the shear `t₁₂ = k·sin β·sin γ` rules out two of them, leaving
//! `(β₀, ±γ₀)` and its mirror `(−β₀, ∓γ₀)`, which no orthographic image can tell apart (Necker
//! ambiguity).
//!
//! **Perspective cue** (replaces the original's sign heuristic, whose defects are listed in
//! docs/design.md#defect-3d-heuristic). With a finite focal length the local grid frequency grows
//! with the depth: `|∇φ| ∝ depth`, so `∇log|∇φ| = ∇depth/depth`. The image is demodulated by each
//! plane over a grid of blocks; the residual phases are fitted by a quadratic whose Hessian `H`
//! gives `∇log|∇φ| = H·∇φ/|∇φ|²` for each plane. The candidate whose predicted depth gradient
//! (third row of `R`: `depth = z − sin β·x_p + cos β·sin γ·y_p`) points the same way is the most
//! likely one. On a truly orthographic image the cue is noise: see
//! [`OutOfPlanePose::cue_strength`].

use super::PatternPlanes;
use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::phase::{wrap_to_pi, PhasePlane};
use crate::pose::Pose;
use nalgebra::{Matrix2, Matrix6, Vector2, Vector6};
use std::f64::consts::TAU;

/// Blocks per image side used by the perspective cue.
const CUE_BLOCKS: usize = 8;

/// Out-of-plane pose of a pattern (docs/design.md#pose-3d), orthographic model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OutOfPlanePose {
    /// The two orthographic solutions `(β₀, ±γ₀)` and `(−β₀, ∓γ₀)` (same `x, y, alpha`,
    /// `pixel_size`; `z` as requested). Both explain the planes exactly.
    pub candidates: [Pose; 2],
    /// Index of the candidate chosen by the perspective cue (0 when there is no cue).
    pub most_likely: usize,
    /// Measured relative depth gradient `∇depth/depth` in the image frame, 1/pixel (zero
    /// vector when not measured).
    pub depth_gradient: Vector2<f64>,
    /// Cosine between the measured depth gradient and the chosen candidate's prediction times
    /// the measured gradient's size relative to the prediction's; near 0 when the image shows
    /// no perspective (then the choice is arbitrary), ≈ 1 for a clear cue.
    pub cue_strength: f64,
}

impl OutOfPlanePose {
    /// The chosen candidate.
    pub fn pose(&self) -> Pose {
        self.candidates[self.most_likely.min(1)]
    }
}

/// The two orthographic out-of-plane solutions of the absolute planes `planes` (pattern x and
/// y phases, image frame), for a grid of physical period `period`. `z` is set to `z`.
///
/// Errors when the planes are degenerate or mirror the pattern (left-handed).
pub fn orthographic_candidates(planes: &PatternPlanes, period: f64, z: f64) -> Result<[Pose; 2]> {
    let m = pixel_from_pattern(planes, period)?;
    let alpha = m[(1, 0)].atan2(m[(0, 0)]);
    let (s, c) = alpha.sin_cos();
    let t11 = m[(0, 0)].hypot(m[(1, 0)]);
    let t12 = c * m[(0, 1)] + s * m[(1, 1)];
    let t22 = -s * m[(0, 1)] + c * m[(1, 1)];
    if !(t22 > 0.0 && t11 > 0.0) {
        return Err(Error::Decode(
            "the phase planes describe a mirrored pattern: no rotation explains them".into(),
        ));
    }
    let sum = t11 * t11 + t12 * t12 + t22 * t22;
    let disc = (sum * sum - 4.0 * t11 * t11 * t22 * t22).max(0.0);
    let k = ((sum + disc.sqrt()) / 2.0).sqrt();
    let beta0 = (t11 / k).clamp(0.0, 1.0).acos();
    let gamma0 = (t22 / k).clamp(0.0, 1.0).acos();
    // sin β·sin γ has the sign of the shear t12.
    let gamma0 = if t12 < 0.0 { -gamma0 } else { gamma0 };
    let base = Pose {
        x: -period * planes[0].c / TAU,
        y: -period * planes[1].c / TAU,
        z,
        alpha: crate::phase::wrap_angle(alpha),
        beta: beta0,
        gamma: gamma0,
        pixel_size: 1.0 / k,
    };
    Ok([
        base,
        Pose {
            beta: -beta0,
            gamma: -gamma0,
            ..base
        },
    ])
}

/// The absolute planes that the orthographic pose `pose` produces for a grid of physical period
/// `period` (the inverse of [`orthographic_candidates`]): `[∇φ_x; ∇φ_y] = (2π/P)·M⁻¹` with
/// `M = R₂ₓ₂/s`, offsets `c_x = −2π·x/P`, `c_y = −2π·y/P`. `None` when the pattern is seen
/// edge-on (singular `M`).
pub fn planes_of_pose(pose: &Pose, period: f64) -> Option<PatternPlanes> {
    let r = pose.rotation();
    let m = Matrix2::new(r[(0, 0)], r[(0, 1)], r[(1, 0)], r[(1, 1)]) / pose.pixel_size;
    let g = m.try_inverse()? * (TAU / period);
    Some([
        PhasePlane {
            a: g[(0, 0)],
            b: g[(0, 1)],
            c: -TAU * pose.x / period,
        },
        PhasePlane {
            a: g[(1, 0)],
            b: g[(1, 1)],
            c: -TAU * pose.y / period,
        },
    ])
}

/// Covariance of the out-of-plane angles `(β, γ)` of `pose` (one of the orthographic solutions,
/// e.g. [`OutOfPlanePose::pose`]), rad², when each component of the two phase gradients
/// (`∂φ/∂col`, `∂φ/∂row` of the pattern x and y planes) carries an independent error of
/// standard deviation `gradient_std[k]` (rad/pixel, `k` = pattern x, y).
///
/// Propagated through [`orthographic_candidates`] numerically: each of the four gradient
/// components `g_i` is moved by `±σ_i`, and the solution nearest to `pose` (the same branch,
/// so that `β` or `γ` crossing 0 stays continuous) gives `f₊`, `f₋`. With `f₀` the unperturbed
/// solution, `d_i = (f₊ − f₋)/2 ≈ J_i·σ_i` and `e_i = f₊ + f₋ − 2f₀ ≈ H_i·σ_i²`, and
/// `Σ = Σ_i (d_i·d_iᵀ + ½·e_i·e_iᵀ)`: first-order propagation plus the second-order term of a
/// Gaussian error, which keeps the variance finite near the fronto-parallel fold (`β = γ = 0`)
/// where the first derivative is unbounded. Mixed second derivatives are neglected.
///
/// Infinite variances when a standard deviation is not finite or the perturbed planes have no
/// solution.
pub fn angle_covariance(pose: &Pose, period: f64, gradient_std: [f64; 2]) -> [[f64; 2]; 2] {
    let unknown = [[f64::INFINITY, 0.0], [0.0, f64::INFINITY]];
    if !gradient_std.iter().all(|s| s.is_finite() && *s >= 0.0) {
        return unknown;
    }
    let Some(planes) = planes_of_pose(pose, period) else {
        return unknown;
    };
    let target = Vector2::new(pose.beta, pose.gamma);
    let solve = |planes: &PatternPlanes| -> Option<Vector2<f64>> {
        let candidates = orthographic_candidates(planes, period, 0.0).ok()?;
        candidates
            .iter()
            .map(|c| Vector2::new(c.beta, c.gamma))
            .min_by(|u, v| (u - target).norm().total_cmp(&(v - target).norm()))
    };
    let Some(f0) = solve(&planes) else {
        return unknown;
    };
    let mut cov = Matrix2::<f64>::zeros();
    for (k, &sigma) in gradient_std.iter().enumerate() {
        for component in 0..2 {
            let moved = |sign: f64| {
                let mut p = planes;
                if component == 0 {
                    p[k].a += sign * sigma;
                } else {
                    p[k].b += sign * sigma;
                }
                solve(&p)
            };
            let (Some(plus), Some(minus)) = (moved(1.0), moved(-1.0)) else {
                return unknown;
            };
            let d = (plus - minus) / 2.0;
            let e = plus + minus - 2.0 * f0;
            cov += d * d.transpose() + 0.5 * e * e.transpose();
        }
    }
    [[cov[(0, 0)], cov[(0, 1)]], [cov[(1, 0)], cov[(1, 1)]]]
}

/// Out-of-plane pose with the perspective cue measured on `image` (bright dots, as analysed),
/// whose absolute planes are `planes`. `focal_px`: focal length in pixels for the perspective
/// variant (`z = pixel_size·focal`), `None` for the orthographic pose (`z = 0`).
pub fn out_of_plane(
    image: &GreyImage,
    planes: &PatternPlanes,
    period: f64,
    focal_px: Option<f64>,
) -> Result<OutOfPlanePose> {
    crate::marker_tilt::check_focal_length(focal_px)?;
    let mut candidates = orthographic_candidates(planes, period, 0.0)?;
    if let Some(f) = focal_px {
        for c in candidates.iter_mut() {
            c.z = c.pixel_size * f;
        }
    }
    let m = pixel_from_pattern(planes, period)?;
    let gradient = depth_gradient(image, planes).unwrap_or_else(Vector2::zeros);
    // Predicted ∇depth in the image for candidate 0 (candidate 1 predicts the opposite):
    // ∂depth/∂p = (−sin β, cos β·sin γ), ∇_q = M⁻ᵀ·∂/∂p.
    let c0 = candidates[0];
    let dp = Vector2::new(-c0.beta.sin(), c0.beta.cos() * c0.gamma.sin());
    let predicted = m
        .try_inverse()
        .map(|inv| inv.transpose() * dp)
        .unwrap_or_else(Vector2::zeros);
    let dot = gradient.dot(&predicted);
    let most_likely = usize::from(dot < 0.0);
    let cue_strength = if predicted.norm() > 0.0 && gradient.norm() > 0.0 {
        // Under a pinhole of focal f the relative depth gradient is ≈ ∇depth/(f·s): compare
        // directions only (f is unknown), scaled by how far the measurement is above zero.
        let cos = dot.abs() / (gradient.norm() * predicted.norm());
        cos * (1.0 - (-gradient.norm() / noise_floor(image)).exp())
    } else {
        0.0
    };
    Ok(OutOfPlanePose {
        candidates,
        most_likely,
        depth_gradient: gradient,
        cue_strength,
    })
}

/// Relative depth gradient below which the cue is considered noise, 1/pixel: a frequency change
/// of 1e-3 over the image side.
fn noise_floor(image: &GreyImage) -> f64 {
    1e-3 / image.width().max(image.height()).max(1) as f64
}

/// `M`: pattern units → pixels, from `[∇φ_x; ∇φ_y] = (2π/P)·M⁻¹`.
pub(crate) fn pixel_from_pattern(planes: &PatternPlanes, period: f64) -> Result<Matrix2<f64>> {
    let [px, py] = planes;
    let scale = period / TAU;
    Matrix2::new(px.a, px.b, py.a, py.b)
        .scale(scale)
        .try_inverse()
        .filter(|m| m.iter().all(|v| v.is_finite()))
        .ok_or_else(|| Error::Decode("the phase planes are degenerate".into()))
}

/// Measured `∇depth/depth` (1/pixel, image frame), mean over both planes; `None` when the image
/// is too small for a block grid or the fit is degenerate.
fn depth_gradient(image: &GreyImage, planes: &PatternPlanes) -> Option<Vector2<f64>> {
    let (w, h) = (image.width(), image.height());
    let n = CUE_BLOCKS;
    if w < 4 * n || h < 4 * n {
        return None;
    }
    let (cx, cy) = image.center();
    let mut sum = Vector2::zeros();
    for plane in planes {
        let phases = block_phases(image, plane, n)?;
        // Quadratic fit δ = q0 + q1 x + q2 y + q3 x² + q4 xy + q5 y² over block centres
        // (pixels from the image centre), weighted by the block amplitudes.
        let mut normal = Matrix6::<f64>::zeros();
        let mut rhs = Vector6::<f64>::zeros();
        for (bi, bj, delta, weight) in phases {
            let x = (bj as f64 + 0.5) * w as f64 / n as f64 - cx as f64;
            let y = (bi as f64 + 0.5) * h as f64 / n as f64 - cy as f64;
            let basis = Vector6::new(1.0, x, y, x * x, x * y, y * y);
            normal += weight * basis * basis.transpose();
            rhs += weight * delta * basis;
        }
        let q = normal.try_inverse()? * rhs;
        let hessian = Matrix2::new(2.0 * q[3], q[4], q[4], 2.0 * q[5]);
        let grad = Vector2::new(plane.a + q[1], plane.b + q[2]);
        let norm2 = grad.norm_squared();
        if norm2 <= 0.0 {
            return None;
        }
        sum += hessian * grad / norm2;
    }
    Some(sum / 2.0)
}

/// Residual phase of `plane` in each of `n × n` blocks: `(block row, block col, unwrapped
/// residual phase, weight)`. The residual is `arg Σ (g − ḡ)·e^{−iφ}` over the block.
fn block_phases(
    image: &GreyImage,
    plane: &PhasePlane,
    n: usize,
) -> Option<Vec<(usize, usize, f64, f64)>> {
    let sums = demodulated_block_sums(image, plane, n)?;
    // Remove the block mean's contribution: Σ ḡ·e^{−iφ} = ḡ·Σ e^{−iφ}, summed exactly per block.
    let kernel_sums = block_kernel_sums(image, plane, n)?;
    let mut out = Vec::with_capacity(n * n);
    let mut total = (0.0, 0.0);
    let mut values = vec![(0.0f64, 0.0f64); n * n];
    for (i, (s, k)) in sums.iter().zip(&kernel_sums).enumerate() {
        let mean = if s.3 > 0 { s.2 / s.3 as f64 } else { 0.0 };
        let v = (s.0 - mean * k.0, s.1 - mean * k.1);
        values[i] = v;
        total.0 += v.0;
        total.1 += v.1;
    }
    // Residual phases relative to the global one, unwrapped from the centre block.
    let reference = total.1.atan2(total.0);
    let raw: Vec<f64> = values
        .iter()
        .map(|v| wrap_to_pi(v.1.atan2(v.0) - reference))
        .collect();
    let unwrapped = unwrap_from_centre(&raw, n);
    for i in 0..n {
        for j in 0..n {
            let v = values[i * n + j];
            out.push((i, j, unwrapped[i * n + j], v.0.hypot(v.1)));
        }
    }
    Some(out)
}

/// Per block of `n × n`: `(Σ g·cos(−φ), Σ g·sin(−φ), Σ g, pixel count)`, `φ` the phase of
/// `plane`.
fn demodulated_block_sums(
    image: &GreyImage,
    plane: &PhasePlane,
    n: usize,
) -> Option<Vec<(f64, f64, f64, usize)>> {
    let (w, h) = (image.width(), image.height());
    let (cx, cy) = image.center();
    let px = image.pixels();
    let mut sums = vec![(0.0f64, 0.0f64, 0.0f64, 0usize); n * n]; // re, im, Σg, count
    let mut kernel = vec![(0.0f64, 0.0f64); w];
    let (step_s, step_c) = (-plane.a).sin_cos();
    for row in 0..h {
        // e^{−iφ} along the row by recurrence, re-anchored with an exact value every row.
        let y = row as f64 - cy as f64;
        let (s0, c0) = (-(plane.at(-(cx as f64), y))).sin_cos();
        let (mut re, mut im) = (c0, s0);
        for k in kernel.iter_mut() {
            *k = (re, im);
            let nre = re * step_c - im * step_s;
            im = re * step_s + im * step_c;
            re = nre;
        }
        let bi = row * n / h;
        let line = px.get(row * w..(row + 1) * w)?;
        for (col, (&g, &(kr, ki))) in line.iter().zip(&kernel).enumerate() {
            let cell = sums.get_mut(bi * n + col * n / w)?;
            let g = g as f64;
            cell.0 += g * kr;
            cell.1 += g * ki;
            cell.2 += g;
            cell.3 += 1;
        }
    }
    Some(sums)
}

/// `Σ e^{−iφ}` over each block of `n × n` of the image, `φ` the phase of `plane` (row by row,
/// each a geometric series).
fn block_kernel_sums(image: &GreyImage, plane: &PhasePlane, n: usize) -> Option<Vec<(f64, f64)>> {
    let (w, h) = (image.width(), image.height());
    let (cx, cy) = image.center();
    let mut kernel_sums = vec![(0.0f64, 0.0f64); n * n];
    for row in 0..h {
        let y = row as f64 - cy as f64;
        let bi = row * n / h;
        for bj in 0..n {
            let (c0, c1) = (bj * w / n, (bj + 1) * w / n);
            // Geometric series of e^{−iφ} over columns c0..c1 of this row.
            let phi0 = plane.at(c0 as f64 - cx as f64, y);
            let count = (c1 - c0) as f64;
            let (re, im) = geometric_sum(-phi0, -plane.a, count);
            let cell = kernel_sums.get_mut(bi * n + bj)?;
            cell.0 += re;
            cell.1 += im;
        }
    }
    Some(kernel_sums)
}

/// The `n × n` wrapped phases `raw` unwrapped from the centre block: rows first along the
/// centre column, then along each row.
fn unwrap_from_centre(raw: &[f64], n: usize) -> Vec<f64> {
    let mut unwrapped = vec![0.0f64; n * n];
    let mid = n / 2;
    unwrapped[mid * n + mid] = raw[mid * n + mid];
    let follow = |prev: f64, value: f64| prev + wrap_to_pi(value - prev);
    for i in (0..mid).rev() {
        unwrapped[i * n + mid] = follow(unwrapped[(i + 1) * n + mid], raw[i * n + mid]);
    }
    for i in mid + 1..n {
        unwrapped[i * n + mid] = follow(unwrapped[(i - 1) * n + mid], raw[i * n + mid]);
    }
    for i in 0..n {
        for j in (0..mid).rev() {
            unwrapped[i * n + j] = follow(unwrapped[i * n + j + 1], raw[i * n + j]);
        }
        for j in mid + 1..n {
            unwrapped[i * n + j] = follow(unwrapped[i * n + j - 1], raw[i * n + j]);
        }
    }
    unwrapped
}

/// `Σ_{m=0}^{count−1} e^{i(θ₀ + m·δ)}` as `(re, im)`.
fn geometric_sum(theta0: f64, delta: f64, count: f64) -> (f64, f64) {
    let half = delta / 2.0;
    let denom = half.sin();
    if denom.abs() < 1e-12 {
        let (s, c) = theta0.sin_cos();
        return (count * c, count * s);
    }
    let magnitude = (count * half).sin() / denom;
    let (s, c) = (theta0 + (count - 1.0) * half).sin_cos();
    (magnitude * c, magnitude * s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn geometric_sum_matches_direct_sum() {
        let (t0, d, n) = (0.3, 0.71, 13.0);
        let (mut re, mut im) = (0.0, 0.0);
        for m in 0..13 {
            let t = t0 + m as f64 * d;
            re += f64::cos(t);
            im += f64::sin(t);
        }
        let (gr, gi) = geometric_sum(t0, d, n);
        assert!((gr - re).abs() < 1e-12 && (gi - im).abs() < 1e-12);
    }

    #[test]
    fn candidates_reproduce_the_affine_map() {
        let truth = Pose {
            x: -100.0,
            y: -50.0,
            z: 0.0,
            alpha: 0.7,
            beta: 0.3,
            gamma: -0.2,
            pixel_size: 1.5,
        };
        let period = 10.0;
        let planes = planes_of_pose(&truth, period).unwrap();
        let [c0, c1] = orthographic_candidates(&planes, period, 0.0).unwrap();
        for c in [c0, c1] {
            assert!((c.alpha - truth.alpha).abs() < 1e-12);
            assert!((c.pixel_size - truth.pixel_size).abs() < 1e-12);
            assert!((c.x - truth.x).abs() < 1e-9 && (c.y - truth.y).abs() < 1e-9);
        }
        assert!(
            (c0.beta - 0.3).abs() < 1e-9 && (c0.gamma + 0.2).abs() < 1e-9,
            "{c0:?}"
        );
        assert!(
            (c1.beta + 0.3).abs() < 1e-9 && (c1.gamma - 0.2).abs() < 1e-9,
            "{c1:?}"
        );
    }

    #[test]
    fn angle_covariance_matches_monte_carlo() {
        use rand::{rngs::SmallRng, SeedableRng};
        use rand_distr::{Distribution, Normal};
        let period = 10.0;
        let sigma = 2e-5; // rad/pixel on each gradient component
                          // Away from the fronto-parallel fold the propagation is the Monte-Carlo spread to 1 %
                          // (measured); on the fold (β = γ = 0, where the angles grow like the square root of the
                          // gradient error) it is conservative (measured ×1.6–2.1).
        let cases = [
            ((0.3, -0.2), 0.95..1.05),
            ((0.1, 0.25), 0.95..1.05),
            ((-0.05, 0.02), 0.95..1.05),
            ((0.2, 0.0), 0.95..1.05),
            ((0.0, 0.0), 1.0..3.0),
        ];
        for ((beta, gamma), bounds) in cases {
            let truth = Pose {
                x: -100.0,
                y: -50.0,
                z: 0.0,
                alpha: 0.7,
                beta,
                gamma,
                pixel_size: 1.5,
            };
            let planes = planes_of_pose(&truth, period).unwrap();
            let predicted = angle_covariance(&truth, period, [sigma, sigma]);
            let mut rng = SmallRng::seed_from_u64(7);
            let normal = Normal::new(0.0, sigma).unwrap();
            let n = 4000;
            let mut sum = Matrix2::<f64>::zeros();
            let target = Vector2::new(beta, gamma);
            for _ in 0..n {
                let mut p = planes;
                for plane in p.iter_mut() {
                    plane.a += normal.sample(&mut rng);
                    plane.b += normal.sample(&mut rng);
                }
                let c = orthographic_candidates(&p, period, 0.0).unwrap();
                let v = c
                    .iter()
                    .map(|c| Vector2::new(c.beta, c.gamma))
                    .min_by(|u, v| (u - target).norm().total_cmp(&(v - target).norm()))
                    .unwrap();
                let d = v - target;
                sum += d * d.transpose();
            }
            let empirical = sum / n as f64;
            for i in 0..2 {
                let ratio = (predicted[i][i] / empirical[(i, i)]).sqrt();
                eprintln!("({beta}, {gamma}) axis {i}: predicted/Monte-Carlo std {ratio:.3}");
                assert!(
                    bounds.contains(&ratio),
                    "({beta}, {gamma}) axis {i}: predicted {predicted:?}, empirical {empirical}"
                );
            }
        }
        let unknown = angle_covariance(&Pose::planar(0.0, 0.0, 0.0, 1.0), 1.0, [f64::NAN, 1.0]);
        assert!(unknown[0][0].is_infinite() && unknown[1][1].is_infinite());
    }
}
