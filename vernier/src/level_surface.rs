//! Smooth surfaces of grey levels: how the light (an illumination gradient, a vignette, a
//! colour cast's offset) varies across a marker, fitted to samples that the layout says look
//! alike everywhere (dots, gaps between dots), so that each reading can be taken relative to
//! the light where it is instead of against one threshold for the whole marker
//! (docs/design.md#level-surfaces).
//!
//! The surface is a quadratic in the position, fitted by least squares and refitted without
//! the samples beyond [`OUTLIER_SIGMAS`] robust standard deviations of the residuals (dust,
//! hair, a finder read where the samples were meant to be dots), [`REFITS`] times. With fewer
//! than [`MIN_QUADRATIC_SAMPLES`] samples, or samples bunched so that a quadratic is not
//! determined, it is their (trimmed) mean.

use crate::order_stats::robust_sigma;
use nalgebra::{Matrix6, Vector6};

/// Fewest samples for a quadratic surface; with fewer, a constant.
const MIN_QUADRATIC_SAMPLES: usize = 24;
/// Residuals beyond this many robust standard deviations are left out of the refit.
const OUTLIER_SIGMAS: f64 = 3.0;
/// Refits without outliers after the first least-squares fit.
const REFITS: usize = 2;

/// A level sample: position `x`, `y` (any frame, the caller's units) and its level.
pub(crate) type LevelSample = [f64; 3];

/// A quadratic (or constant) surface of grey levels over a rectangle of positions.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LevelSurface {
    /// Centre of the rectangle the positions are scaled from.
    center: [f64; 2],
    /// Half-sides of that rectangle (positions at its edges scale to ±1, for conditioning).
    half: [f64; 2],
    /// Coefficients of `1, x, y, x², x·y, y²` in scaled positions.
    coefficients: [f64; 6],
}

impl LevelSurface {
    /// Fits `samples`, positions scaled from the rectangle `min`–`max`; `None` without samples.
    pub(crate) fn fit(samples: &[LevelSample], min: [f64; 2], max: [f64; 2]) -> Option<Self> {
        let mut surface = LevelSurface {
            center: [0.5 * (min[0] + max[0]), 0.5 * (min[1] + max[1])],
            half: [
                (0.5 * (max[0] - min[0])).max(f64::EPSILON),
                (0.5 * (max[1] - min[1])).max(f64::EPSILON),
            ],
            coefficients: [0.0; 6],
        };
        let mut inliers: Vec<LevelSample> = samples.to_vec();
        for round in 0..=REFITS {
            surface.coefficients = surface.least_squares(&inliers)?;
            if round == REFITS {
                break;
            }
            let residuals: Vec<f64> = inliers
                .iter()
                .map(|s| (s[2] - surface.at(s[0], s[1])).abs())
                .collect();
            let cut = OUTLIER_SIGMAS * robust_sigma(&mut residuals.clone());
            let kept: Vec<LevelSample> = inliers
                .iter()
                .zip(&residuals)
                .filter(|&(_, &r)| r <= cut)
                .map(|(s, _)| *s)
                .collect();
            if kept.len() == inliers.len() || kept.is_empty() {
                break;
            }
            inliers = kept;
        }
        Some(surface)
    }

    /// Level at position `(x, y)`.
    pub(crate) fn at(&self, x: f64, y: f64) -> f64 {
        let b = self.basis(x, y);
        (0..6).map(|k| b[k] * self.coefficients[k]).sum()
    }

    fn basis(&self, x: f64, y: f64) -> [f64; 6] {
        let x = (x - self.center[0]) / self.half[0];
        let y = (y - self.center[1]) / self.half[1];
        [1.0, x, y, x * x, x * y, y * y]
    }

    /// Least-squares coefficients for `samples`: a quadratic when there are enough and they
    /// determine it, their mean otherwise; `None` without samples.
    fn least_squares(&self, samples: &[LevelSample]) -> Option<[f64; 6]> {
        if samples.is_empty() {
            return None;
        }
        let mean = samples.iter().map(|s| s[2]).sum::<f64>() / samples.len() as f64;
        let constant = [mean, 0.0, 0.0, 0.0, 0.0, 0.0];
        if samples.len() < MIN_QUADRATIC_SAMPLES {
            return Some(constant);
        }
        let mut normal = Matrix6::<f64>::zeros();
        let mut rhs = Vector6::<f64>::zeros();
        for s in samples {
            let b = Vector6::from(self.basis(s[0], s[1]));
            normal += b * b.transpose();
            rhs += b * s[2];
        }
        // Samples bunched in part of the rectangle leave the quadratic undetermined.
        Some(match normal.cholesky() {
            Some(ch) => ch.solve(&rhs).into(),
            None => constant,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn light(x: f64, y: f64) -> f64 {
        0.3 + 0.02 * x - 0.01 * y + 1e-4 * x * y
    }

    #[test]
    fn a_quadratic_light_is_recovered_through_dust() {
        let mut samples = Vec::new();
        for r in 0..30 {
            for c in 0..30 {
                let (x, y) = (c as f64, r as f64);
                // A blob over 37 of the 900 samples, far off the light.
                let dust = (x - 8.0).powi(2) + (y - 20.0).powi(2) < 13.0;
                samples.push([x, y, light(x, y) + if dust { 0.5 } else { 0.0 }]);
            }
        }
        let surface = LevelSurface::fit(&samples, [0.0, 0.0], [29.0, 29.0]).unwrap();
        for (x, y) in [(0.0, 0.0), (8.0, 20.0), (29.0, 29.0), (-2.0, 31.0)] {
            assert!(
                (surface.at(x, y) - light(x, y)).abs() < 1e-9,
                "at ({x}, {y})"
            );
        }
        // A plain least-squares fit is pulled by the blob.
        let plain = LevelSurface {
            coefficients: surface.least_squares(&samples).unwrap(),
            ..surface
        };
        assert!((plain.at(8.0, 20.0) - light(8.0, 20.0)).abs() > 1e-2);
    }

    #[test]
    fn few_samples_give_their_mean_and_none_give_nothing() {
        let samples = [[0.0, 0.0, 1.0], [5.0, 1.0, 3.0]];
        let surface = LevelSurface::fit(&samples, [0.0, 0.0], [5.0, 1.0]).unwrap();
        assert_eq!(surface.at(100.0, -7.0), 2.0);
        assert!(LevelSurface::fit(&[], [0.0, 0.0], [1.0, 1.0]).is_none());
    }
}
