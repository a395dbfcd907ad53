//! Gaussian band-pass around one lobe, inverse transform, unwrapped phase and plane fit
//! (docs/design.md#phase-bandpass), computed on a **demodulated, decimated** grid.
//!
//! The band-passed signal is the trigonometric polynomial
//! `z(x, y) = Σ_k W(k)·G(k)·exp(2πi(kx·x/C + ky·y/R))` whose weights `W` (a Gaussian of σ bins
//! around the lobe) vanish outside a small square of `mc × mr` bins. Writing `k = k_lobe + m`,
//! `z(x, y) = exp(2πi(kx_lobe·x/C + ky_lobe·y/R))·Σ_m W·G·exp(2πi(mx·x/C + my·y/R))`, and at the
//! points `x = i·C/mc`, `y = j·R/mr` the sum is exactly an `mr × mc` inverse DFT. So a small
//! inverse FFT yields exact samples of the same band-limited phase field as the full-size inverse
//! of the original; only the Gaussian tail beyond `mc/2` bins (< 1e-7 of the peak) is dropped.
//! With `mc = C` and `mr = R` this is the original computation, pixel for pixel.

use super::plane::{fit_plane, PhasePlane};
use super::spectrum::{HalfSpectrum, C32};
use rustfft::{Fft, FftPlanner};
use std::f64::consts::{PI, TAU};
use std::sync::Arc;

/// Inverse-transform plans and buffers for one `(mr, mc)` decimated size.
pub(crate) struct BandpassPlan {
    mr: usize,
    mc: usize,
    row_ifft: Arc<dyn Fft<f32>>,
    col_ifft: Arc<dyn Fft<f32>>,
    grid: Vec<C32>,
    column: Vec<C32>,
    scratch: Vec<C32>,
}

impl BandpassPlan {
    pub(crate) fn new(mr: usize, mc: usize, planner: &mut FftPlanner<f32>) -> Self {
        let row_ifft = planner.plan_fft_inverse(mc);
        let col_ifft = planner.plan_fft_inverse(mr);
        let scratch_len = row_ifft
            .get_inplace_scratch_len()
            .max(col_ifft.get_inplace_scratch_len());
        BandpassPlan {
            mr,
            mc,
            row_ifft,
            col_ifft,
            grid: vec![C32::default(); mr * mc],
            column: vec![C32::default(); mr],
            scratch: vec![C32::default(); scratch_len],
        }
    }
}

/// Decimated unwrapped phase of one lobe: samples at pixel positions
/// `(offset.0 + i·step_x, offset.1 + j·step_y)`, row-major `rows × cols`, radians.
#[derive(Clone, Debug, Default)]
pub struct PhaseMap {
    /// Number of sample rows.
    pub rows: usize,
    /// Number of sample columns.
    pub cols: usize,
    /// Pixel distance between sample columns.
    pub step_x: f64,
    /// Pixel distance between sample rows.
    pub step_y: f64,
    /// Pixel position `(x, y)` of sample (0, 0).
    pub offset: (f64, f64),
    /// Unwrapped phase, radians (wrap it with `rem_euclid(2π)` to display the wrapped phase).
    pub phase: Vec<f32>,
    /// Band-pass amplitude, arbitrary units.
    pub amplitude: Vec<f32>,
}

/// Band-passes one lobe and fits its phase plane over the central crop.
///
/// `center` is the image centre pixel `(C div 2, R div 2)`; `crop_factor` the fraction removed by
/// the plane-fit crop. Returns the plane (image frame, `c` wrapped into `(−π, π]`) and the map.
pub(crate) fn lobe_phase(
    spectrum: &HalfSpectrum<'_>,
    lobe: (i64, i64),
    sigma: f64,
    crop_factor: f64,
    plan: &mut BandpassPlan,
    keep_map: bool,
) -> Option<(PhasePlane, Option<PhaseMap>)> {
    let (rows, cols) = (spectrum.rows, spectrum.cols);
    let (mr, mc) = (plan.mr, plan.mc);
    let (kx0, ky0) = lobe;
    transform_lobe(spectrum, lobe, sigma, plan);
    let (step_x, step_y) = (cols as f64 / mc as f64, rows as f64 / mr as f64);
    let (cx, cy) = ((cols / 2) as f64, (rows / 2) as f64);
    // Baseband phase, unwrapped from the sample nearest to the centre pixel ("quarters" method:
    // along the anchor row, then up and down each column).
    let anchor_i = ((cx / step_x).round() as usize).min(mc - 1);
    let anchor_j = ((cy / step_y).round() as usize).min(mr - 1);
    let phase = unwrap_quarters(&plan.grid, (mr, mc), (anchor_j, anchor_i));
    // Plane fit on the samples inside the central crop, in image-frame coordinates.
    let col_offset = (cols as f64 * crop_factor / 2.0).floor();
    let row_offset = (rows as f64 * crop_factor / 2.0).floor();
    let inside = |pos: f64, offset: f64, n: usize| pos >= offset && pos < n as f64 - offset;
    let samples = (0..mr)
        .flat_map(|j| (0..mc).map(move |i| (j, i)))
        .filter_map(|(j, i)| {
            let (x, y) = (i as f64 * step_x, j as f64 * step_y);
            (inside(x, col_offset, cols) && inside(y, row_offset, rows))
                .then(|| (x - cx, y - cy, phase[j * mc + i]))
        });
    let base = fit_plane(samples)?;
    // Add the carrier exp(2πi(kx0·x/C + ky0·y/R)) back, referred to the centre pixel.
    let (fx, fy) = (
        TAU * kx0 as f64 / cols as f64,
        TAU * ky0 as f64 / rows as f64,
    );
    let plane = PhasePlane {
        a: base.a + fx,
        b: base.b + fy,
        c: base.c + fx * cx + fy * cy,
    }
    .with_wrapped_offset();
    let map = keep_map.then(|| PhaseMap {
        rows: mr,
        cols: mc,
        step_x,
        step_y,
        offset: (0.0, 0.0),
        phase: (0..mr * mc)
            .map(|k| {
                (phase[k] + fx * (k % mc) as f64 * step_x + fy * (k / mc) as f64 * step_y) as f32
            })
            .collect(),
        amplitude: plan.grid.iter().map(|z| z.norm()).collect(),
    });
    Some((plane, map))
}

/// Band-passes `lobe` (Gaussian of `sigma` bins) into `plan.grid`: the decimated complex
/// baseband of the lobe, by a 2-D inverse DFT of the weighted bins around it.
fn transform_lobe(
    spectrum: &HalfSpectrum<'_>,
    lobe: (i64, i64),
    sigma: f64,
    plan: &mut BandpassPlan,
) {
    let (mr, mc) = (plan.mr, plan.mc);
    let (kx0, ky0) = lobe;
    // Gather the weighted bins around the lobe; offset m sits at index m mod M.
    let inv_two_sigma2 = 1.0 / (2.0 * sigma * sigma);
    let (hr, hc) = ((mr / 2) as i64, (mc / 2) as i64);
    for n in -hr..(mr as i64 - hr) {
        let wy = (-(n * n) as f64 * inv_two_sigma2).exp();
        let row = n.rem_euclid(mr as i64) as usize * mc;
        for m in -hc..(mc as i64 - hc) {
            let w = (wy * (-(m * m) as f64 * inv_two_sigma2).exp()) as f32;
            plan.grid[row + m.rem_euclid(mc as i64) as usize] = spectrum.at(kx0 + m, ky0 + n) * w;
        }
    }
    // 2-D inverse DFT: rows, then columns through a small gather buffer.
    plan.row_ifft
        .process_with_scratch(&mut plan.grid, &mut plan.scratch);
    for i in 0..mc {
        for j in 0..mr {
            plan.column[j] = plan.grid[j * mc + i];
        }
        plan.col_ifft
            .process_with_scratch(&mut plan.column, &mut plan.scratch);
        for j in 0..mr {
            plan.grid[j * mc + i] = plan.column[j];
        }
    }
}

/// The unwrapped phase of the `mr × mc` `grid`, from the sample `anchor = (j, i)` nearest
/// to the centre pixel ("quarters" method: along the anchor row, then up and down each
/// column).
fn unwrap_quarters(
    grid: &[C32],
    (mr, mc): (usize, usize),
    (anchor_j, anchor_i): (usize, usize),
) -> Vec<f64> {
    let mut phase = vec![0.0f64; mr * mc];
    let raw = |j: usize, i: usize| grid[j * mc + i].arg() as f64;
    let step = |prev_raw: f64, cur_raw: f64, offset: &mut f64| {
        let d = cur_raw - prev_raw;
        if d > PI {
            *offset -= TAU;
        } else if d <= -PI {
            *offset += TAU;
        }
    };
    let unwrap_line = |phase: &mut Vec<f64>,
                       idx: &dyn Fn(usize) -> usize,
                       len: usize,
                       start: usize,
                       base: f64,
                       raw_at: &dyn Fn(usize) -> f64| {
        for dir in [-1i64, 1] {
            let mut offset = base - raw_at(start);
            let mut prev = raw_at(start);
            let mut k = start as i64 + dir;
            while k >= 0 && (k as usize) < len {
                let cur = raw_at(k as usize);
                step(prev, cur, &mut offset);
                phase[idx(k as usize)] = cur + offset;
                prev = cur;
                k += dir;
            }
        }
    };
    let anchor_value = raw(anchor_j, anchor_i);
    phase[anchor_j * mc + anchor_i] = anchor_value;
    unwrap_line(
        &mut phase,
        &|i| anchor_j * mc + i,
        mc,
        anchor_i,
        anchor_value,
        &|i| raw(anchor_j, i),
    );
    for i in 0..mc {
        let base = phase[anchor_j * mc + i];
        unwrap_line(&mut phase, &|j| j * mc + i, mr, anchor_j, base, &|j| {
            raw(j, i)
        });
    }
    phase
}
