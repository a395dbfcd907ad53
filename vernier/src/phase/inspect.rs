//! Display products of the phase engine: the centred log-magnitude spectrum with the chosen
//! lobes, and the wrapped phase of each lobe at full resolution.
//!
//! These are for looking at (rerun viewer, debugging a failed detection), not for measuring:
//! [`PhaseEngine::inspect`] runs the band-pass at full image size so that every pixel has a
//! phase, which costs two extra full-size inverse transforms per image.

use super::{PhaseAnalysis, PhaseEngine, PhaseParams};
use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use std::f64::consts::TAU;

/// Centred log-magnitude spectrum of an image: `ln(1 + |G(kx, ky)|)`, row-major, `height × width`
/// (the image's own size), DC at pixel `(width div 2, height div 2)`; `kx` grows to the right
/// and `ky` downwards, in bins (cycles per image).
#[derive(Clone, Debug)]
pub struct SpectrumView {
    /// Columns (equals the image width).
    pub width: usize,
    /// Rows (equals the image height).
    pub height: usize,
    /// `ln(1 + |G|)`, row-major.
    pub log_magnitude: Vec<f32>,
}

impl SpectrumView {
    /// Pixel `(col, row)` of the view where bin `(kx, ky)` is drawn.
    pub fn bin_position(&self, kx: i64, ky: i64) -> (f64, f64) {
        (
            (self.width / 2) as f64 + kx as f64,
            (self.height / 2) as f64 + ky as f64,
        )
    }
}

/// What [`PhaseEngine::inspect`] returns.
#[derive(Clone, Debug)]
pub struct PhaseInspection {
    /// The analysis itself (planes in the image frame, lobes in bins of the full image).
    pub analysis: PhaseAnalysis,
    /// Centred log-magnitude spectrum of the image.
    pub spectrum: SpectrumView,
    /// Wrapped band-pass phase of each lobe, radians in `[0, 2π)`, row-major at the image's size
    /// (pixel `(col, row)` at index `row·width + col`).
    pub wrapped_phase: [Vec<f32>; 2],
}

impl PhaseEngine {
    /// Analyses `image` like [`PhaseEngine::analyze`] and also returns its spectrum and the
    /// full-resolution wrapped phase of both lobes, for display. The spectral stage runs at full
    /// size (no binning, full-size band-pass), which [`PhaseParams::full_resolution_bandpass`]
    /// documents as giving the same refined planes.
    ///
    /// Errors: those of [`PhaseEngine::analyze`].
    pub fn inspect(&mut self, image: &GreyImage, params: &PhaseParams) -> Result<PhaseInspection> {
        let full = PhaseParams {
            full_resolution_bandpass: true,
            keep_phase_maps: true,
            ..params.clone()
        };
        let analysis = self.analyze(image, &full)?;
        let (rows, cols) = (image.height(), image.width());
        let maps = analysis.maps.as_ref().ok_or_else(|| {
            Error::PatternNotFound("internal: the analysis kept no phase maps".into())
        })?;
        let wrapped_phase = [0, 1].map(|i| {
            maps[i]
                .phase
                .iter()
                .map(|&p| (p as f64).rem_euclid(TAU) as f32)
                .collect::<Vec<f32>>()
        });
        if wrapped_phase.iter().any(|w| w.len() != rows * cols) {
            return Err(Error::PatternNotFound(
                "internal: the phase maps are not at full resolution".into(),
            ));
        }

        let (cache, planners) = self.cache_for(rows, cols, full.sigma, true);
        let spectrum = cache.spectrum(planners).forward(image.pixels());
        let (half_rows, half_cols) = ((rows / 2) as i64, (cols / 2) as i64);
        let mut log_magnitude = Vec::with_capacity(rows * cols);
        for row in 0..rows as i64 {
            for col in 0..cols as i64 {
                let bin = spectrum.at(col - half_cols, row - half_rows);
                log_magnitude.push(bin.norm().ln_1p());
            }
        }
        Ok(PhaseInspection {
            analysis,
            spectrum: SpectrumView {
                width: cols,
                height: rows,
                log_magnitude,
            },
            wrapped_phase,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::PeriodicLayout;
    use crate::phase::wrap_to_pi;
    use crate::render::{render, RenderOptions};
    use crate::Pose;

    #[test]
    fn spectrum_peaks_at_the_lobes_and_phase_follows_the_planes() {
        let layout = PeriodicLayout::new(10.0, 41, 41).unwrap();
        let mut options = RenderOptions::new(160, 128);
        options.blur_sigma = 0.6;
        let image = render(&layout, &Pose::planar(1.3, -2.1, 0.2, 1.1), &options).unwrap();
        let mut engine = PhaseEngine::new();
        let params = PhaseParams::default();
        let inspection = engine.inspect(&image, &params).unwrap();
        let plain = engine.analyze(&image, &params).unwrap();
        // Same refined planes as the normal (binned, decimated) path.
        for (a, b) in inspection.analysis.planes.iter().zip(&plain.planes) {
            assert!((a.a - b.a).abs() < 1e-9 && (a.b - b.b).abs() < 1e-9);
            assert!(wrap_to_pi(a.c - b.c).abs() < 1e-7);
        }

        let view = &inspection.spectrum;
        assert_eq!((view.width, view.height), (160, 128));
        // Each lobe is the brightest bin of its 5×5 neighbourhood, and so is its mirror image.
        for lobe in &inspection.analysis.lobes {
            for sign in [1, -1] {
                let (x, y) = view.bin_position(sign * lobe.kx, sign * lobe.ky);
                let (x, y) = (x as usize, y as usize);
                let at = |c: usize, r: usize| view.log_magnitude[r * view.width + c];
                for r in y - 2..=y + 2 {
                    for c in x - 2..=x + 2 {
                        assert!(at(c, r) <= at(x, y), "lobe ({x}, {y}) not a maximum");
                    }
                }
            }
        }

        // Inside the central half the wrapped phase is the fitted plane, wrapped.
        let (cx, cy) = (80.0, 64.0);
        for (phase, plane) in inspection
            .wrapped_phase
            .iter()
            .zip(&inspection.analysis.planes)
        {
            assert!(phase.iter().all(|p| (0.0..TAU as f32).contains(p)));
            let mut worst = 0.0f64;
            for row in 32..96 {
                for col in 40..120 {
                    let expected = plane.at(col as f64 - cx, row as f64 - cy);
                    let got = phase[row * 160 + col] as f64;
                    worst = worst.max(wrap_to_pi(got - expected).abs());
                }
            }
            // Measured 2e-5 rad: the band-pass keeps the fundamental only.
            assert!(worst < 1e-3, "wrapped phase off the plane by {worst} rad");
        }
    }

    #[test]
    fn blank_image_is_an_error_not_a_panic() {
        let image = GreyImage::new(64, 64, vec![0.5; 64 * 64]).unwrap();
        let err = PhaseEngine::new()
            .inspect(&image, &PhaseParams::default())
            .unwrap_err();
        assert!(matches!(err, Error::PatternNotFound(_)), "{err}");
    }
}
