//! 2-D real-to-complex spectrum with plans and buffers cached per image size.
//!
//! Layout of the stored half spectrum: **kx-major** (`bins[kx * rows + ky_index]`),
//! `kx ∈ [0, cols/2]`, `ky_index ∈ [0, rows)` with `ky = ky_index` for `ky_index < rows − rows/2`
//! (non-negative frequencies) and `ky = ky_index − rows` otherwise, the usual FFT order. The
//! transform is the unnormalised forward DFT `G[k] = Σ g[n]·exp(−2πi k·n/N)`
//! (docs/design.md#phase-spectrum). Bins with `kx < 0` follow from Hermitian symmetry:
//! `G(−kx, −ky) = conj G(kx, ky)`.

use num_complex::Complex;
use realfft::{RealFftPlanner, RealToComplex};
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

/// Single-precision complex number used for spectra.
pub type C32 = Complex<f32>;

/// Forward 2-D FFT plans and work buffers for one image size.
pub struct SpectrumPlan {
    rows: usize,
    cols: usize,
    row_fft: Arc<dyn RealToComplex<f32>>,
    col_fft: Arc<dyn Fft<f32>>,
    row_in: Vec<f32>,
    row_out: Vec<C32>,
    row_scratch: Vec<C32>,
    /// Rows of half spectra before the column transforms, row-major `rows × (cols/2+1)`.
    staging: Vec<C32>,
    col_scratch: Vec<C32>,
    /// The spectrum, kx-major (see module docs).
    bins: Vec<C32>,
}

impl SpectrumPlan {
    /// Plans the transforms of a `rows × cols` image (both ≥ 1) with the engine's planners.
    pub fn new(
        rows: usize,
        cols: usize,
        real_planner: &mut RealFftPlanner<f32>,
        planner: &mut FftPlanner<f32>,
    ) -> Self {
        let row_fft = real_planner.plan_fft_forward(cols);
        let col_fft = planner.plan_fft_forward(rows);
        let half = cols / 2 + 1;
        SpectrumPlan {
            rows,
            cols,
            row_in: row_fft.make_input_vec(),
            row_out: row_fft.make_output_vec(),
            row_scratch: row_fft.make_scratch_vec(),
            row_fft,
            staging: vec![C32::default(); rows * half],
            col_scratch: vec![C32::default(); col_fft.get_inplace_scratch_len()],
            col_fft,
            bins: vec![C32::default(); rows * half],
        }
    }

    /// Computes the half spectrum of `pixels` (row-major, `rows × cols`).
    pub fn forward(&mut self, pixels: &[f32]) -> HalfSpectrum<'_> {
        let (rows, cols) = (self.rows, self.cols);
        let half = cols / 2 + 1;
        debug_assert_eq!(pixels.len(), rows * cols);
        for (row, staged) in pixels
            .chunks_exact(cols)
            .zip(self.staging.chunks_exact_mut(half))
        {
            self.row_in.copy_from_slice(row);
            // Sizes come from the plan itself, so the transform cannot fail.
            let _ = self.row_fft.process_with_scratch(
                &mut self.row_in,
                &mut self.row_out,
                &mut self.row_scratch,
            );
            staged.copy_from_slice(&self.row_out);
        }
        transpose(&self.staging, &mut self.bins, rows, half);
        self.col_fft
            .process_with_scratch(&mut self.bins, &mut self.col_scratch);
        HalfSpectrum {
            rows,
            cols,
            bins: &self.bins,
        }
    }
}

/// Cache-blocked transpose of a row-major `rows × cols` matrix into `out` (`cols × rows`).
fn transpose(input: &[C32], out: &mut [C32], rows: usize, cols: usize) {
    const BLOCK: usize = 16;
    for r0 in (0..rows).step_by(BLOCK) {
        for c0 in (0..cols).step_by(BLOCK) {
            for r in r0..(r0 + BLOCK).min(rows) {
                for c in c0..(c0 + BLOCK).min(cols) {
                    out[c * rows + r] = input[r * cols + c];
                }
            }
        }
    }
}

/// Borrowed view of a computed half spectrum (see module docs for the layout).
#[derive(Clone, Copy)]
pub struct HalfSpectrum<'a> {
    /// Image rows `R`.
    pub rows: usize,
    /// Image columns `C`.
    pub cols: usize,
    /// Bins, kx-major, `(cols/2 + 1) × rows`.
    pub bins: &'a [C32],
}

impl HalfSpectrum<'_> {
    /// Largest representable |ky| is `rows/2`; `ky` in `[−(rows/2), rows − rows/2 − 1]`... this maps
    /// a signed `ky` to its storage index.
    #[inline]
    fn ky_index(&self, ky: i64) -> usize {
        ky.rem_euclid(self.rows as i64) as usize
    }

    /// Bin at signed integer frequency `(kx, ky)` (cycles per image along columns and rows),
    /// using Hermitian symmetry for `kx < 0`. Frequencies are taken modulo the image size.
    #[inline]
    pub fn at(&self, kx: i64, ky: i64) -> C32 {
        let c = self.cols as i64;
        let kx = kx.rem_euclid(c);
        // Fold kx into [0, cols/2] using G(kx) = conj G(−kx).
        if kx <= c / 2 {
            self.bins[kx as usize * self.rows + self.ky_index(ky)]
        } else {
            self.bins[(c - kx) as usize * self.rows + self.ky_index(-ky)].conj()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Direct DFT of one bin, double precision.
    fn direct_dft(pixels: &[f32], rows: usize, cols: usize, kx: i64, ky: i64) -> Complex<f64> {
        let mut sum = Complex::new(0.0, 0.0);
        for r in 0..rows {
            for c in 0..cols {
                let angle = -std::f64::consts::TAU
                    * (kx as f64 * c as f64 / cols as f64 + ky as f64 * r as f64 / rows as f64);
                sum += Complex::from_polar(pixels[r * cols + c] as f64, angle);
            }
        }
        sum
    }

    #[test]
    fn matches_direct_dft_even_and_odd_sizes() {
        for &(rows, cols) in &[(8usize, 10usize), (7, 9), (6, 5), (1, 4)] {
            let pixels: Vec<f32> = (0..rows * cols)
                .map(|i| ((i * 7919) % 101) as f32 / 101.0)
                .collect();
            let mut plan = SpectrumPlan::new(
                rows,
                cols,
                &mut RealFftPlanner::new(),
                &mut FftPlanner::new(),
            );
            let spectrum = plan.forward(&pixels);
            for ky in -(rows as i64) / 2..=(rows as i64 - 1) / 2 {
                for kx in -(cols as i64) / 2..=(cols as i64 - 1) / 2 {
                    let expected = direct_dft(&pixels, rows, cols, kx, ky);
                    let got = spectrum.at(kx, ky);
                    let err = ((got.re as f64 - expected.re).powi(2)
                        + (got.im as f64 - expected.im).powi(2))
                    .sqrt();
                    assert!(
                        err < 1e-4,
                        "{rows}x{cols} bin ({kx},{ky}): {got} vs {expected}"
                    );
                }
            }
        }
    }
}
