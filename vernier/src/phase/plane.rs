//! Phase planes `φ(x, y) = a·x + b·y + c` and their least-squares fit
//! (docs/design.md#phase-planes).

use std::f64::consts::{PI, TAU};

/// A phase plane `φ(x, y) = a·x + b·y + c` in the **image frame**: `x = col − C div 2`,
/// `y = row − R div 2` (pixels, y down), `φ` in radians.
///
/// The gradient `(a, b)` (rad/pixel) points along the grid direction of this lobe; `c` is the
/// phase at the image centre pixel. Phase 0 is a dot centre (bright-dot convention).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhasePlane {
    /// ∂φ/∂x, rad per pixel.
    pub a: f64,
    /// ∂φ/∂y, rad per pixel.
    pub b: f64,
    /// φ at the image centre pixel, rad.
    pub c: f64,
}

impl PhasePlane {
    /// Evaluates the plane at image-frame coordinates `(x, y)` (pixels from the centre pixel).
    pub fn at(&self, x: f64, y: f64) -> f64 {
        self.a * x + self.b * y + self.c
    }
    /// Spatial frequency `|∇φ|`, rad per pixel.
    pub fn frequency(&self) -> f64 {
        self.a.hypot(self.b)
    }
    /// Grid period along this direction, pixels: `2π/|∇φ|`.
    pub fn pixel_period(&self) -> f64 {
        TAU / self.frequency()
    }
    /// Direction of the gradient, `atan2(b, a)` in `(−π, π]`, image frame (positive = clockwise
    /// on screen, since y points down).
    pub fn angle(&self) -> f64 {
        self.b.atan2(self.a)
    }
    /// The same phase field seen with the opposite sign (`−a, −b, −c`).
    pub fn flipped(&self) -> PhasePlane {
        PhasePlane {
            a: -self.a,
            b: -self.b,
            c: -self.c,
        }
    }
    /// The plane with `c` reduced to `(−π, π]` (same wrapped phase everywhere).
    pub fn with_wrapped_offset(&self) -> PhasePlane {
        PhasePlane {
            c: wrap_to_pi(self.c),
            ..*self
        }
    }
}

/// Reduces an angle to `(−π, π]`.
pub fn wrap_to_pi(angle: f64) -> f64 {
    let w = angle.rem_euclid(TAU);
    if w > PI {
        w - TAU
    } else {
        w
    }
}

/// Reduces an angle to `[−π, π)` (the original's `wrap`, used for pose angles).
pub fn wrap_angle(angle: f64) -> f64 {
    // `rem_euclid` is exact, and so is `r − 2π` for r ∈ [π, 2π) (Sterbenz); adding π first
    // would round huge angles (1e15 rad + π loses 0.02 rad), so it is not done.
    let r = angle.rem_euclid(TAU);
    if r >= PI {
        r - TAU
    } else {
        r
    }
}

/// Unweighted least-squares plane through samples `(x, y, φ)`.
///
/// Returns `None` when the samples do not span a plane (fewer than 3, or collinear).
pub fn fit_plane(samples: impl Iterator<Item = (f64, f64, f64)>) -> Option<PhasePlane> {
    // Normal equations in centred form for conditioning.
    let mut n = 0.0;
    let (mut sx, mut sy, mut sp) = (0.0, 0.0, 0.0);
    let (mut sxx, mut sxy, mut syy, mut sxp, mut syp) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (x, y, p) in samples {
        n += 1.0;
        sx += x;
        sy += y;
        sp += p;
        sxx += x * x;
        sxy += x * y;
        syy += y * y;
        sxp += x * p;
        syp += y * p;
    }
    if n < 3.0 {
        return None;
    }
    let (mx, my, mp) = (sx / n, sy / n, sp / n);
    let cxx = sxx / n - mx * mx;
    let cxy = sxy / n - mx * my;
    let cyy = syy / n - my * my;
    let cxp = sxp / n - mx * mp;
    let cyp = syp / n - my * mp;
    let det = cxx * cyy - cxy * cxy;
    if det.abs() <= 1e-12 * (cxx * cyy).abs().max(f64::MIN_POSITIVE) || !det.is_finite() {
        return None;
    }
    let a = (cxp * cyy - cyp * cxy) / det;
    let b = (cyp * cxx - cxp * cxy) / det;
    Some(PhasePlane {
        a,
        b,
        c: mp - a * mx - b * my,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ramp_fit_matches_original_regression() {
        // The original's unit test: 8×10 ramp (value 2·col), crop 0.5 → a = 2, b = 0, c = 10.
        let (rows, cols) = (8usize, 10usize);
        let (r0, c0) = (rows / 4, cols * 5 / 20);
        let samples = (r0..rows - r0).flat_map(|r| {
            (c0..cols - c0).map(move |c| {
                (
                    c as f64 - (cols / 2) as f64,
                    r as f64 - (rows / 2) as f64,
                    2.0 * c as f64,
                )
            })
        });
        let p = fit_plane(samples).unwrap();
        assert!((p.a - 2.0).abs() < 1e-12 && p.b.abs() < 1e-12 && (p.c - 10.0).abs() < 1e-12);
    }

    #[test]
    fn degenerate_samples_give_none() {
        assert!(fit_plane([(0.0, 0.0, 1.0), (1.0, 1.0, 2.0)].into_iter()).is_none());
        assert!(fit_plane((0..10).map(|i| (i as f64, i as f64, 0.0))).is_none());
    }

    #[test]
    fn wraps() {
        assert!((wrap_to_pi(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_to_pi(-PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(PI) + PI).abs() < 1e-12);
        assert!((wrap_angle(0.5 + TAU) - 0.5).abs() < 1e-12);
    }
}
