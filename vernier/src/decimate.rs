//! Anti-aliased 2 × 2 decimation (docs/design.md#anti-aliased-binning).
//!
//! A 2 × 2 box average folds every frequency above the binned Nyquist frequency (a quarter
//! cycle per input pixel) back into the binned band. The whole-field fit models such folded
//! harmonics where they land apart from the others, but along the pixel axes they land on (or
//! within a few cycles per field of) another harmonic and cannot be told apart; left in the
//! residual, they bias the fitted position by up to ~1e-3 px, locked to the pixel grid.
//!
//! Here each output pixel is the input low-passed by a separable, symmetric windowed-sinc
//! filter (Kaiser window; Oppenheim & Schafer, *Discrete-Time Signal Processing*, §7.5.3),
//! whose stop band starts at the binned Nyquist frequency: what is left above it is below
//! 3.5e-3 of its amplitude per axis (−49 dB), so nothing folds. The filter is symmetric about
//! the output pixel's centre, so it moves no phase; below the stop band it only scales each
//! frequency by a real gain, which the fit's free amplitudes absorb.
//!
//! Output pixels lie two input pixels apart, placed symmetrically about the image's centre
//! along each axis ([`centre_offset`]): between two input pixels (an even-length filter) on
//! an axis of even length, on an input pixel (an odd-length one) on an axis of odd length.
//! A flip or a quarter turn of the image then maps output pixels onto output pixels, and the
//! taps beyond the image repeat its edge pixels alike in every view.

use crate::grey_image::GreyImage;
use std::sync::OnceLock;

/// Taps on each side of the output pixel's centre, per axis (32 or 33 in all).
const HALF_TAPS: usize = 16;
/// Cut-off of the windowed sinc, cycles per input pixel: midway through the transition band
/// from ~0.16 (gain within 1 %) to 0.25 (the binned Nyquist frequency).
const CUTOFF: f64 = 0.205;
/// Kaiser window's β for ~50 dB of stop-band attenuation (β = 0.1102·(A − 8.7)).
const KAISER_BETA: f64 = 4.551;

/// One axis's filter: its taps, the first at `first` input pixels from the output pixel's
/// centre, one pixel apart, summing to 1.
struct Taps {
    values: Vec<f32>,
    first: f64,
}

impl Taps {
    /// The filter of an axis of `n` input pixels ([`centre_offset`]).
    fn for_axis(n: usize) -> &'static Taps {
        static EVEN: OnceLock<Taps> = OnceLock::new();
        static ODD: OnceLock<Taps> = OnceLock::new();
        let (cell, count) = if n % 2 == 0 {
            (&EVEN, 2 * HALF_TAPS)
        } else {
            (&ODD, 2 * HALF_TAPS + 1)
        };
        cell.get_or_init(|| Taps::new(count))
    }

    /// `count` taps of the windowed sinc (Kaiser window over `±(HALF_TAPS + ½)`), centred.
    fn new(count: usize) -> Taps {
        let first = -((count - 1) as f64) / 2.0;
        let half_width = HALF_TAPS as f64 + 0.5;
        let raw: Vec<f64> = (0..count)
            .map(|k| {
                let t = first + k as f64;
                let x = 2.0 * std::f64::consts::PI * CUTOFF * t;
                let sinc = if x == 0.0 { 1.0 } else { x.sin() / x };
                sinc * bessel_i0(KAISER_BETA * (1.0 - (t / half_width).powi(2)).sqrt())
            })
            .collect();
        let total: f64 = raw.iter().sum();
        Taps {
            values: raw.iter().map(|v| (v / total) as f32).collect(),
            first,
        }
    }

    /// Offset of the first tap's input pixel from `start + 2i`, the even pixel that output
    /// pixel `i` of an axis of `n` pixels starts from (a whole number: the taps lie on input
    /// pixels).
    fn first_source(&self, n: usize) -> i64 {
        (self.first + centre_offset(n)).round() as i64
    }

    /// The input indices that `outputs` output pixels from `start` on read along an axis of
    /// `n` pixels, in order and clamped to the axis (its edge pixels repeated): output pixel
    /// `i`'s taps are the `values.len()` indices from the `2i`-th on, contiguous.
    fn sources(&self, start: usize, outputs: usize, n: usize) -> impl Iterator<Item = usize> {
        let first = start as i64 + self.first_source(n);
        let count = (2 * (outputs - 1) + self.values.len()) as i64;
        (first..first + count).map(move |j| j.clamp(0, n as i64 - 1) as usize)
    }
}

/// Modified Bessel function of the first kind, order 0 (its power series; `x` ≤ ~10 here).
fn bessel_i0(x: f64) -> f64 {
    let (mut sum, mut term, mut k) = (1.0, 1.0, 1.0);
    while term > 1e-17 * sum {
        term *= (0.5 * x / k).powi(2);
        sum += term;
        k += 1.0;
    }
    sum
}

/// Where output pixel `i` of an axis of `n` input pixels sits: at input `start + 2i` plus
/// this, pixels (0.5 on an even axis, 0 on an odd one), `start` even. Both place the output
/// pixels symmetrically about the axis's centre `(n − 1)/2`.
pub(crate) fn centre_offset(n: usize) -> f64 {
    if n % 2 == 0 {
        0.5
    } else {
        0.0
    }
}

/// Variance of the output of white input noise of unit variance along an axis of `n` input
/// pixels (`Σ h²`, ~0.39; the 2-pixel box's is 0.5). Below the stop band the output noise
/// has the box's level (its spectrum there is the input's, halved per axis), above it none:
/// the output's total variance is the product of the axes' gains times the input's, while
/// the fit's information sits where the level is the box's.
pub(crate) fn noise_gain(n: usize) -> f64 {
    let taps = Taps::for_axis(n);
    taps.values.iter().map(|&h| (h as f64).powi(2)).sum()
}

/// The anti-aliased 2 × 2 decimation of `image`'s region `cols × rows`, both starting on an
/// even pixel: `cols.len() / 2 × rows.len() / 2` pixels, pixel `(c, r)` centred at input
/// `(cols.start + 2c, rows.start + 2r)` plus each axis's [`centre_offset`]. `None` if the
/// region is empty, does not start on even pixels or is not inside the image.
pub(crate) fn decimate_2x2(
    image: &GreyImage,
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
) -> Option<GreyImage> {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature the function is compiled for.
            return unsafe { decimate_2x2_avx2(image, cols, rows) };
        }
    }
    decimate_2x2_generic(image, cols, rows)
}

/// [`decimate_2x2`] compiled for AVX2: the same arithmetic, in the same order, on wider
/// vectors (the filter's multiply-adds were all of its time).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn decimate_2x2_avx2(
    image: &GreyImage,
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
) -> Option<GreyImage> {
    decimate_2x2_generic(image, cols, rows)
}

/// [`decimate_2x2`], for whatever the caller is compiled for.
#[inline(always)]
fn decimate_2x2_generic(
    image: &GreyImage,
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
) -> Option<GreyImage> {
    let (width, height) = (image.width(), image.height());
    let (cb, rb) = (cols.len() / 2, rows.len() / 2);
    if cb == 0 || rb == 0 || cols.end > width || rows.end > height {
        return None;
    }
    if cols.start % 2 != 0 || rows.start % 2 != 0 {
        return None;
    }
    let (along_x, along_y) = (Taps::for_axis(width), Taps::for_axis(height));
    let (taps_x, taps_y) = (&along_x.values, &along_y.values);
    let pixels = image.pixels();
    // The input rows the vertical pass reads, each filtered along its columns first.
    let rows_read: Vec<usize> = along_y.sources(rows.start, rb, height).collect();
    let mut horizontal = vec![0.0f32; rows_read.len() * cb];
    // Output `c` reads inputs `2c + k`: the even and odd inputs apart (polyphase), so that
    // each tap runs over contiguous inputs. The columns read are the same on every row.
    let columns: Vec<usize> = along_x.sources(cols.start, cb, width).collect();
    let even_columns: Vec<usize> = columns.iter().step_by(2).copied().collect();
    let odd_columns: Vec<usize> = columns.iter().skip(1).step_by(2).copied().collect();
    let (mut even, mut odd) = (
        vec![0.0f32; even_columns.len()],
        vec![0.0f32; odd_columns.len()],
    );
    for (line, &row) in horizontal.chunks_exact_mut(cb).zip(&rows_read) {
        let input = &pixels[row * width..(row + 1) * width];
        for (v, &c) in even.iter_mut().zip(&even_columns) {
            *v = input[c];
        }
        for (v, &c) in odd.iter_mut().zip(&odd_columns) {
            *v = input[c];
        }
        // Tap pairs: even input `c + j` then odd input `c + j`, for each `j`.
        filter_line(line, taps_x, |j| (&even[j..], &odd[j..]));
    }
    let mut out = vec![0.0f32; rb * cb];
    for (r, line) in out.chunks_exact_mut(cb).enumerate() {
        // Tap `k` reads row `2r + k`: each pair of taps two consecutive rows.
        filter_line(line, taps_y, |j| {
            let from = (2 * r + 2 * j) * cb;
            (
                &horizontal[from..],
                horizontal.get(from + cb..).unwrap_or(&[]),
            )
        });
    }
    GreyImage::new(cb, rb, out).ok()
}

/// Outputs filtered at once, kept in registers over all the taps.
const LANES: usize = 8;

/// `line[c] = Σ_j taps[2j]·a_j[c] + taps[2j+1]·b_j[c]` with `(a_j, b_j) = inputs(j)`, each
/// sum in the order of the taps (the same rounding whatever the blocking), [`LANES`] outputs
/// at a time so that their sums stay in registers rather than going through memory per tap.
#[inline(always)]
fn filter_line<'a>(
    line: &mut [f32],
    taps: &[f32],
    inputs: impl Fn(usize) -> (&'a [f32], &'a [f32]),
) {
    let n = line.len();
    let full = n / LANES * LANES;
    for c in (0..full).step_by(LANES) {
        let mut sum = [0.0f32; LANES];
        for (j, pair) in taps.chunks(2).enumerate() {
            let (a, b) = inputs(j);
            let a = &a[c..c + LANES];
            for l in 0..LANES {
                sum[l] += pair[0] * a[l];
            }
            if let Some(&tb) = pair.get(1) {
                let b = &b[c..c + LANES];
                for l in 0..LANES {
                    sum[l] += tb * b[l];
                }
            }
        }
        line[c..c + LANES].copy_from_slice(&sum);
    }
    for (c, out) in line.iter_mut().enumerate().skip(full) {
        let mut sum = 0.0f32;
        for (j, pair) in taps.chunks(2).enumerate() {
            let (a, b) = inputs(j);
            sum += pair[0] * a[c];
            if let Some(&tb) = pair.get(1) {
                sum += tb * b[c];
            }
        }
        *out = sum;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Largest gain of the filters from the binned Nyquist frequency up (3.0e-3 and 2.8e-3).
    const STOP_BAND_GAIN: f64 = 3.5e-3;

    /// Gain at `f` cycles per input pixel of the filter along an axis of `n` pixels.
    fn gain(n: usize, f: f64) -> f64 {
        let taps = Taps::for_axis(n);
        (taps.values.iter().enumerate())
            .map(|(k, &h)| {
                let t = taps.first + k as f64;
                h as f64 * (std::f64::consts::TAU * f * t).cos()
            })
            .sum()
    }

    #[test]
    fn the_filters_pass_low_frequencies_and_stop_from_the_binned_nyquist() {
        for n in [96, 97] {
            for f in (0..=160).map(|i| i as f64 * 1e-3) {
                assert!((gain(n, f) - 1.0).abs() < 0.01, "{n}, {f}: {}", gain(n, f));
            }
            for f in (250..=500).map(|i| i as f64 * 1e-3) {
                assert!(
                    gain(n, f).abs() < STOP_BAND_GAIN,
                    "{n}, {f}: {}",
                    gain(n, f)
                );
            }
            assert!((noise_gain(n) - 0.388).abs() < 0.01, "{}", noise_gain(n));
        }
    }

    #[test]
    fn decimation_keeps_a_low_wave_in_phase_and_removes_a_high_one() {
        // A wave at 0.1 cycle/px survives at the output pixels' centres (2c + 0.5 on the even
        // axis, 2r on the odd one); one at 0.3 cycle/px, which a box average would fold to
        // 0.2, is gone.
        let (w, h) = (96usize, 81usize);
        let wave = |f: f64, x: f64, y: f64| (std::f64::consts::TAU * f * (x + 0.5 * y)).cos();
        let pixels = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f64, (i / w) as f64);
                (0.5 + 0.2 * wave(0.1, x, y) + 0.2 * wave(0.3, x, y)) as f32
            })
            .collect();
        let image = GreyImage::new(w, h, pixels).unwrap();
        let out = decimate_2x2(&image, 8..88, 10..70).unwrap();
        assert_eq!((out.width(), out.height()), (40, 30));
        // Away from the image's edges, where every tap sees a real pixel; the filter is
        // separable, so the wave's gain is the product of its axes' gains.
        for r in 3..28 {
            for c in 4..36 {
                let (x, y) = (8.0 + 2.0 * c as f64 + 0.5, 10.0 + 2.0 * r as f64);
                let expected = 0.5 + 0.2 * gain(w, 0.1) * gain(h, 0.05) * wave(0.1, x, y);
                let got = out.pixels()[r * 40 + c] as f64;
                assert!(
                    (got - expected).abs() < 2e-3,
                    "({c}, {r}): {got} vs {expected}"
                );
            }
        }
    }

    #[test]
    fn a_flipped_image_decimates_to_the_flipped_output() {
        // Odd width and even height: the output pixels of a region symmetric about the
        // image's centre map onto each other under either flip.
        let (w, h) = (97usize, 64usize);
        let value = |x: usize, y: usize| ((x * 7 + y * 13) % 23) as f32 / 23.0;
        let image = GreyImage::new(w, h, (0..w * h).map(|i| value(i % w, i / w)).collect());
        let image = image.unwrap();
        let flipped = (0..w * h)
            .map(|i| value(w - 1 - i % w, h - 1 - i / w))
            .collect();
        let flipped = GreyImage::new(w, h, flipped).unwrap();
        let (cols, rows) = (20..78, 6..58);
        let out = decimate_2x2(&image, cols.clone(), rows.clone()).unwrap();
        let back = decimate_2x2(&flipped, cols, rows).unwrap();
        let (cb, rb) = (out.width(), out.height());
        for r in 0..rb {
            for c in 0..cb {
                let (a, b) = (
                    out.pixels()[r * cb + c],
                    back.pixels()[(rb - 1 - r) * cb + cb - 1 - c],
                );
                assert!((a - b).abs() < 1e-6, "({c}, {r}): {a} vs {b}");
            }
        }
    }

    /// The vectorised build gives the portable one's output to the last bit.
    #[test]
    fn every_build_decimates_alike() {
        let (w, h) = (97, 64);
        let pixels: Vec<f32> = (0..w * h)
            .map(|i| ((i * 7919 % 1013) as f32 / 1013.0).sin())
            .collect();
        let image = GreyImage::new(w, h, pixels).unwrap();
        let (cols, rows) = (4..90, 0..64);
        let portable = decimate_2x2_generic(&image, cols.clone(), rows.clone()).unwrap();
        assert_eq!(decimate_2x2(&image, cols, rows).unwrap(), portable);
    }

    #[test]
    fn decimation_refuses_empty_or_outside_regions() {
        let image = GreyImage::new(8, 8, vec![0.5; 64]).unwrap();
        assert!(decimate_2x2(&image, 0..1, 0..8).is_none());
        assert!(decimate_2x2(&image, 0..10, 0..8).is_none());
        assert!(decimate_2x2(&image, 1..7, 0..8).is_none());
        let flat = decimate_2x2(&image, 0..8, 0..8).unwrap();
        assert!(flat.pixels().iter().all(|&v| (v - 0.5).abs() < 1e-6));
    }
}
