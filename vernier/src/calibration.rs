//! Pixel-size calibration (docs/design.md#calibrated-scale): the object-side size of a pixel,
//! with its uncertainty, and how it varies across the field of view, from the scales that
//! markers measure.
//!
//! A microscope's pixel size is fixed by its optics, while each marker measures it with an
//! error of ~1e-5 (its σ is [`MarkerPose::pixel_size_std`]). Pooling many measurements — the
//! markers of several images, or tiles of a periodic or Megarena pattern that fills the field —
//! gives the pixel size to the precision a servo loop needs, and a plane fitted through them
//! shows whether it varies across the field (field distortion, a tilted part):
//!
//! `s(x, y) = s₀·(1 + g_x·x + g_y·y)`, `(x, y)` image-frame pixels relative to the image centre
//! pixel (docs/design.md#frames), by weighted least squares with weights `1/σᵢ²`. The reported
//! σ of each coefficient is the least-squares σ, multiplied by `√(χ²/dof)` when the samples
//! scatter more than their own σ predict (vibration between images, focus drift): honest
//! either way.

use crate::detector::{Detector, MarkerPose};
use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use nalgebra::{Matrix3, Vector2, Vector3};

/// One measurement of the pixel size at a point of the field.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ScaleSample {
    /// Where it was measured: image-frame pixels `(x right, y down)` relative to the image's
    /// centre pixel `(C div 2, R div 2)`.
    pub position_px: Vector2<f64>,
    /// Measured pixel size, pattern units per pixel.
    pub pixel_size: f64,
    /// Its standard deviation, pattern units per pixel (> 0).
    pub std: f64,
}

impl ScaleSample {
    /// The sample a detected marker gives: its measured scale, placed where it was measured
    /// — its origin for the marker types that search (HP codes, stamps), the image centre for
    /// those measured over the whole image (periodic, Megarena: an analysis window as large as
    /// the image). `image_size` `(width, height)`, pixels. `None` when the scale or its σ is
    /// not a positive number.
    pub fn from_marker(marker: &MarkerPose, image_size: (usize, usize)) -> Option<Self> {
        let (w, h) = image_size;
        let whole_image = marker.window_px >= w.min(h);
        let center = Vector2::new((w / 2) as f64, (h / 2) as f64);
        let sample = ScaleSample {
            position_px: if whole_image {
                Vector2::zeros()
            } else {
                marker.origin_px - center
            },
            pixel_size: marker.measured_pixel_size,
            std: marker.pixel_size_std,
        };
        sample.is_usable().then_some(sample)
    }

    fn is_usable(&self) -> bool {
        self.pixel_size.is_finite()
            && self.pixel_size > 0.0
            && self.std.is_finite()
            && self.std > 0.0
    }
}

/// Result of [`calibrate`].
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Calibration {
    /// Pixel size at the image centre `s₀`, pattern units per pixel.
    pub pixel_size: f64,
    /// Standard deviation of `pixel_size`, pattern units per pixel.
    pub pixel_size_std: f64,
    /// Relative scale gradient `(g_x, g_y)`, per pixel (`None` with fewer than 4 samples or
    /// when they do not span the field in two directions: then `s₀` is their weighted mean).
    pub gradient: Option<Vector2<f64>>,
    /// Standard deviations of `gradient`, per pixel.
    pub gradient_std: Option<Vector2<f64>>,
    /// `χ²` per degree of freedom of the fit: ≈ 1 when the samples scatter as their σ say,
    /// larger when something else moves them (then every σ above includes `√(χ²/dof)`).
    /// `None` with a single sample.
    pub chi2_per_dof: Option<f64>,
    /// Samples used.
    pub samples: usize,
}

/// Fits `s(x, y) = s₀·(1 + g·(x, y))` through `samples` (see the module doc). Errors when no
/// sample is usable (finite, positive, with a positive σ).
pub fn calibrate(samples: &[ScaleSample]) -> Result<Calibration> {
    let usable: Vec<&ScaleSample> = samples.iter().filter(|s| s.is_usable()).collect();
    if usable.is_empty() {
        return Err(Error::parameter(
            "images",
            "no marker with a measured scale: nothing to calibrate",
        ));
    }
    // A plane needs the samples to span two directions; otherwise the mean.
    let plane = usable.len() >= 4 && spans_two_directions(&usable);
    let basis = |s: &ScaleSample| {
        if plane {
            Vector3::new(1.0, s.position_px.x, s.position_px.y)
        } else {
            Vector3::new(1.0, 0.0, 0.0)
        }
    };
    let (mut normal, mut rhs) = (Matrix3::zeros(), Vector3::zeros());
    for s in &usable {
        let (b, w) = (basis(s), 1.0 / (s.std * s.std));
        normal += w * b * b.transpose();
        rhs += w * s.pixel_size * b;
    }
    if !plane {
        normal[(1, 1)] = 1.0;
        normal[(2, 2)] = 1.0;
    }
    let inverse = normal
        .try_inverse()
        .ok_or_else(|| Error::parameter("images", "the samples do not determine the scale"))?;
    let c = inverse * rhs;
    let unknowns = if plane { 3 } else { 1 };
    let dof = usable.len().saturating_sub(unknowns);
    let chi2: f64 = usable
        .iter()
        .map(|s| ((s.pixel_size - basis(s).dot(&c)) / s.std).powi(2))
        .sum();
    let chi2_per_dof = (dof > 0).then(|| chi2 / dof as f64);
    let inflation = chi2_per_dof.map_or(1.0, |r| r.max(1.0).sqrt());
    let std = |k: usize| inverse[(k, k)].max(0.0).sqrt() * inflation;
    let s0 = c[0];
    // g = (c₁, c₂)/s₀; σ_g from c₁, c₂ (s₀'s relative error is far smaller).
    let gradient = plane.then(|| Vector2::new(c[1], c[2]) / s0);
    let gradient_std = plane.then(|| Vector2::new(std(1), std(2)) / s0);
    Ok(Calibration {
        pixel_size: s0,
        pixel_size_std: std(0),
        gradient,
        gradient_std,
        chi2_per_dof,
        samples: usable.len(),
    })
}

/// Whether the samples' positions span two directions (their scatter matrix is not close to
/// rank one: the smaller spread is at least 1 % of the larger, and at least one pixel).
fn spans_two_directions(samples: &[&ScaleSample]) -> bool {
    let n = samples.len() as f64;
    let mean = samples.iter().map(|s| s.position_px).sum::<Vector2<f64>>() / n;
    let scatter = samples.iter().fold(nalgebra::Matrix2::zeros(), |m, s| {
        let d = s.position_px - mean;
        m + d * d.transpose() / n
    });
    let eigen = scatter.symmetric_eigenvalues();
    let (small, large) = (eigen.min(), eigen.max());
    small >= 1.0 && small >= 1e-4 * large
}

/// Scale samples from `tiles × tiles` tiles of an image filled by one pattern (a periodic or
/// Megarena pattern under the whole field of view), each measured on its own by `detector`
/// (the pattern's own detector: a Megarena's missing lines would bias a plain grid fit by
/// ~1e-4 in a tile); tiles where nothing is found are skipped. `tiles` in `1..=16`, each tile
/// at least 32 px.
pub fn tile_samples(
    image: &GreyImage,
    detector: &mut Detector,
    tiles: usize,
) -> Result<Vec<ScaleSample>> {
    if !(1..=16).contains(&tiles) {
        return Err(Error::parameter(
            "tiles",
            format!("must be in 1..=16, got {tiles}"),
        ));
    }
    let (tw, th) = (image.width() / tiles, image.height() / tiles);
    if tw.min(th) < 32 {
        return Err(Error::parameter(
            "tiles",
            format!(
                "{tiles} × {tiles} tiles of a {}x{} image are smaller than 32 px",
                image.width(),
                image.height()
            ),
        ));
    }
    let center = image.center();
    let mut samples = Vec::new();
    let mut skipped = None;
    for row in 0..tiles {
        for col in 0..tiles {
            let tile = image.crop(col * tw, row * th, tw, th)?;
            let found = match detector.detect(&tile) {
                Ok(found) => found,
                Err(e) => {
                    skipped.get_or_insert(e);
                    continue;
                }
            };
            // Measured over the whole tile: placed at the tile's centre pixel.
            let (tc, tr) = tile.center();
            let position = Vector2::new(
                (col * tw + tc) as f64 - center.0 as f64,
                (row * th + tr) as f64 - center.1 as f64,
            );
            for m in &found {
                if let Some(s) = ScaleSample::from_marker(m, (tw, th)) {
                    samples.push(ScaleSample {
                        position_px: position + s.position_px,
                        ..s
                    });
                }
            }
        }
    }
    match (samples.is_empty(), skipped) {
        (true, Some(e)) => Err(Error::parameter(
            "tiles",
            format!("no tile of {tiles} × {tiles} could be measured ({e}); use fewer tiles"),
        )),
        _ => Ok(samples),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(x: f64, y: f64, pixel_size: f64, std: f64) -> ScaleSample {
        ScaleSample {
            position_px: Vector2::new(x, y),
            pixel_size,
            std,
        }
    }

    #[test]
    fn recovers_a_scale_gradient_and_inflates_sigma_for_extra_scatter() {
        // s = 0.5·(1 + 2e-6·x − 1e-6·y) on a 5 × 5 grid of samples, σ 1e-6.
        let truth = |x: f64, y: f64| 0.5 * (1.0 + 2e-6 * x - 1e-6 * y);
        let mut samples = Vec::new();
        for i in -2..=2 {
            for j in -2..=2 {
                let (x, y) = (200.0 * i as f64, 150.0 * j as f64);
                samples.push(sample(x, y, truth(x, y), 1e-6));
            }
        }
        let fit = calibrate(&samples).unwrap();
        assert!((fit.pixel_size - 0.5).abs() < 1e-12);
        let g = fit.gradient.unwrap();
        assert!((g - Vector2::new(2e-6, -1e-6)).norm() < 1e-12, "{g}");
        assert!(fit.chi2_per_dof.unwrap() < 1e-12);
        // σ of the mean of 25 samples of σ 1e-6.
        assert!((fit.pixel_size_std - 2e-7).abs() < 1e-12);
        // Alternate ±3σ offsets: χ²/dof ≈ 9·25/22, σ inflated by its root.
        let spread: Vec<ScaleSample> = samples
            .iter()
            .enumerate()
            .map(|(k, s)| ScaleSample {
                pixel_size: s.pixel_size + if k % 2 == 0 { 3e-6 } else { -3e-6 },
                ..*s
            })
            .collect();
        let noisy = calibrate(&spread).unwrap();
        let r = noisy.chi2_per_dof.unwrap();
        assert!(r > 5.0, "{r}");
        assert!(noisy.pixel_size_std > 2e-7 * r.sqrt() * 0.99);
    }

    #[test]
    fn collinear_or_few_samples_give_the_weighted_mean() {
        let fit = calibrate(&[
            sample(0.0, 0.0, 1.0, 1e-3),
            sample(100.0, 0.0, 1.003, 2e-3),
            sample(200.0, 0.0, 1.0, 1e-3),
            sample(300.0, 0.0, 1.0, 1e-3),
        ])
        .unwrap();
        assert!(fit.gradient.is_none());
        let mean = (3.0 * 1e6 + 1.003 * 0.25e6) / 3.25e6;
        assert!((fit.pixel_size - mean).abs() < 1e-12);
        let single = calibrate(&[sample(5.0, 5.0, 2.0, 1e-4)]).unwrap();
        assert_eq!((single.pixel_size, single.pixel_size_std), (2.0, 1e-4));
        assert_eq!(single.chi2_per_dof, None);
        assert!(calibrate(&[sample(0.0, 0.0, f64::NAN, 1.0)]).is_err());
        assert!(calibrate(&[]).is_err());
    }
}
