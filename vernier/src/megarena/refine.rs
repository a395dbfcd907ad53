//! Lattice refinement from the individual dots.
//!
//! The phase engine fits one phase plane per grid direction to the whole (windowed) image. On a
//! Megarena the coding lines and the missing dots of the 3×3 cells leave holes in the grid; each
//! missing dot removes a term `∇w·m` (window slope × dot moment) from the fit, so an uneven
//! distribution of the holes biases the planes by a few 1e-3 px. Here the present dots are
//! measured one by one: a small symmetric window centred on the node the planes predict gives
//! the local complex amplitude `z = Σ w(u)·(g − g_bg)·e^{−i k·u}` of each grid direction; a
//! symmetric dot centred on the node gives a real `z`, a dot displaced along `k` gives
//! `arg z = G·Δφ` (`Δφ` = plane error at the node, `G < 1` the window gain, measured from the
//! same data with the window's derivative). Fitting `Δφ` by a weighted plane over the dots and
//! adding it to the planes removes the bias: absent dots simply do not contribute.
//!
//! The window is a separable Hann window of radius `0.4·p` (p = smaller pixel period), which
//! stays clear of the neighbouring dots in any orientation, so a missing neighbour changes
//! nothing. Its taps come from a per-frame table indexed by the node's sub-pixel position
//! quantised to 1/64 px (the quantisation offset is compensated exactly in the phase), so a dot
//! costs a few hundred multiply-adds: column sums with the row kernel (element-wise,
//! vectorised), then short dot products with the column kernel.

use super::thumbnail::{Lattice, Thumbnail};
use crate::grey_image::GreyImage;
use crate::phase::PhasePlane;
use nalgebra::{Matrix3, Vector3};
use std::f64::consts::PI;

/// Window radius, fraction of the smaller pixel period.
const WINDOW_RADIUS: f64 = 0.4;
/// Sub-pixel quantisation of the window centre: 1/QUANTA px.
const QUANTA: usize = 64;
/// Most dots measured (a pseudo-random subset beyond): bounds the cost to ~0.5 ms whatever the
/// image size; 2048 dots average the per-dot pixel-sampling and noise errors to ~1e-4 px.
const MAX_DOTS: usize = 2048;
/// The window gain is measured on one dot in this many.
const GAIN_STRIDE: usize = 8;
/// Register width of the column sums (windows up to this many pixels wide, i.e. pixel periods
/// up to ~17 px, take the fast path).
const WIDE: usize = 16;
/// A node counts as a present dot when its contrast exceeds this fraction of the dot contrast.
const PRESENT_FRACTION: f32 = 0.5;

/// Per-dot local phase of one lobe, for the weighted plane fit.
#[derive(Clone, Copy, Default)]
struct DotPhase {
    x: f64,
    y: f64,
    /// `arg z`, radians (to be divided by the gain).
    phase: f64,
    /// `k·ε`: phase of the node relative to the quantised window centre, radians.
    offset: f64,
    weight: f64,
}

/// Corrected planes and fit statistics.
#[derive(Clone, Copy, Debug)]
pub(super) struct DotwiseFit {
    pub planes: [PhasePlane; 2],
    /// Number of dots used.
    pub dots: usize,
}

/// Refines `planes` (image frame) on the present dots of `thumb` (sampled with the same planes,
/// contrasts computed). `white` is the dot contrast. `None` when fewer than 16 dots can be
/// measured or the gain is implausible (then the caller keeps the engine's planes).
pub(super) fn refine_on_dots(
    image: &GreyImage,
    planes: &[PhasePlane; 2],
    thumb: &Thumbnail,
    white: f64,
) -> Option<DotwiseFit> {
    let lattice = Lattice::new(image, planes).ok()?;
    let (w, h) = (image.width(), image.height());
    let period = planes[0].pixel_period().min(planes[1].pixel_period());
    let radius = WINDOW_RADIUS * period;
    if !(1.0..256.0).contains(&radius) {
        return None;
    }
    let threshold = PRESENT_FRACTION * white as f32;
    // Centre-weighted fit, as the phase engine's (sin³ apodisation over the image): on a
    // distorted image the planes then describe the neighbourhood of the centre pixel the pose
    // refers to. Beyond MAX_DOTS dots, node n is kept with probability min(1, s·√W(n)) and
    // weighted by W/probability (importance sampling of the same weighted fit, favouring the
    // centre; pseudo-random, as a regular stride could alias with the 3×3 cells).
    let image_window = |qc: f64, qr: f64| {
        sine_cubed(qc / (w - 1).max(1) as f64) * sine_cubed(qr / (h - 1).max(1) as f64)
    };
    let (present, scale) = sampling_scale(thumb, &lattice, threshold, &image_window);
    let mut sums = DotSums::new(image, planes, radius, present);
    for (i, n1) in thumb.orders(0).enumerate() {
        for (j, n2) in thumb.orders(1).enumerate() {
            let idx = i * thumb.dims[1] + j;
            let (Some(&contrast), Some(&background)) =
                (thumb.contrast.get(idx), thumb.background_level.get(idx))
            else {
                continue;
            };
            if contrast.is_nan() || contrast <= threshold {
                continue;
            }
            let (qc, qr) = lattice.position(n1 as f64, n2 as f64);
            let window = image_window(qc, qr);
            let probability = (scale * window.sqrt()).min(1.0);
            if !(probability > 0.0 && kept(n1, n2, probability)) {
                continue;
            }
            sums.add_dot(qc, qr, background, window, probability);
        }
    }
    sums.corrected_planes()
}

/// The number of present dots and the sampling scale `s` (keep probability `min(1, s·√W)`):
/// infinite, i.e. every dot kept, up to MAX_DOTS dots.
fn sampling_scale(
    thumb: &Thumbnail,
    lattice: &Lattice,
    threshold: f32,
    image_window: &impl Fn(f64, f64) -> f64,
) -> (usize, f64) {
    let mut present = 0usize;
    let mut root_sum = 0.0;
    for (i, n1) in thumb.orders(0).enumerate() {
        for (j, n2) in thumb.orders(1).enumerate() {
            if thumb
                .contrast
                .get(i * thumb.dims[1] + j)
                .is_some_and(|&v| v > threshold)
            {
                let (qc, qr) = lattice.position(n1 as f64, n2 as f64);
                present += 1;
                root_sum += image_window(qc, qr).sqrt();
            }
        }
    }
    let scale = if present > MAX_DOTS && root_sum > 0.0 {
        MAX_DOTS as f64 / root_sum
    } else {
        f64::INFINITY
    };
    (present, scale)
}

/// Entry `(a, b)` of [`dot_products`]' result: kernel row `a` (re/im × lobe, then the
/// slope kernels from 4) against column-sum row `b`.
fn product(products: &[f32], a: usize, b: usize) -> f64 {
    let slot = match (a / 4, b / 4) {
        (0, 0) => 0,
        (1, 0) => 8,
        _ => 16,
    };
    // Within a block: lobe l = (a % 4) / 2, then (re,re), (im,im), (re,im), (im,re).
    let l = (a % 4) / 2;
    let (ar, br) = (a % 2, b % 2);
    let k = match (ar, br) {
        (0, 0) => 0,
        (1, 1) => 1,
        (0, 1) => 2,
        _ => 3,
    };
    products.get(slot + 4 * l + k).copied().unwrap_or(0.0) as f64
}

/// The dot-wise measurement in progress: the kernel tables, and per lobe the dots' phases and
/// the window-gain sums.
struct DotSums<'a> {
    px: &'a [f32],
    size: (usize, usize),
    centre: (usize, usize),
    planes: &'a [PhasePlane; 2],
    norm: [f64; 2],
    columns: KernelTable,
    rows: KernelTable,
    samples: [Vec<DotPhase>; 2],
    /// Gain sums per direction: Σ Im(Y) and Σ |k|·Re(z).
    gain_num: [f64; 2],
    gain_den: [f64; 2],
    /// Column sums V_q(c) = Σ_r Y_q(r)·g(r, c), q = re/im × lobe (× window/slope).
    sums: Vec<f32>,
    dot_count: usize,
}

impl<'a> DotSums<'a> {
    fn new(image: &'a GreyImage, planes: &'a [PhasePlane; 2], radius: f64, present: usize) -> Self {
        let columns = KernelTable::new(radius, [planes[0].a, planes[1].a]);
        let rows = KernelTable::new(radius, [planes[0].b, planes[1].b]);
        let n = columns.taps;
        DotSums {
            px: image.pixels(),
            size: (image.width(), image.height()),
            centre: image.center(),
            planes,
            norm: planes.map(|p| p.frequency()),
            columns,
            rows,
            samples: [
                Vec::with_capacity(MAX_DOTS.min(present)),
                Vec::with_capacity(MAX_DOTS.min(present)),
            ],
            gain_num: [0.0f64; 2],
            gain_den: [0.0f64; 2],
            sums: vec![0.0f32; 8 * n],
            dot_count: 0,
        }
    }

    /// Measures the dot at node position `(qc, qr)` (skipped near the image border or where
    /// the window's real part is not positive) with its importance weight.
    fn add_dot(&mut self, qc: f64, qr: f64, background: f32, window: f64, probability: f64) {
        let (w, h) = self.size;
        let (cx, cy) = self.centre;
        let (columns, rows, planes, norm) = (&self.columns, &self.rows, self.planes, self.norm);
        let n = columns.taps;
        let reach = columns.reach as f64;
        let inside = qc - reach >= 0.0
            && qr - reach >= 0.0
            && qc + reach + 1.0 < w as f64
            && qr + reach + 1.0 < h as f64;
        if !inside {
            return;
        }
        let ((c0, fx, ex), (r0, fy, ey)) = (columns.locate(qc), rows.locate(qr));
        let (Some(kx), Some(ky)) = (columns.entry(fx), rows.entry(fy)) else {
            return;
        };
        let with_gain = self.dot_count % GAIN_STRIDE == 0;
        self.dot_count += 1;
        // z_l = Σ_c K_l(c)·V_l(c) (complex), minus the background's share.
        let products = dot_products(self.px, (w, c0, r0), kx, ky, n, with_gain, &mut self.sums);
        let dot = |a: usize, b: usize| product(&products, a, b);
        let bg = background as f64;
        let (x, y) = (qc - cx as f64, qr - cy as f64);
        for l in 0..2 {
            let (re, im) = (2 * l, 2 * l + 1);
            let complex = |ka: usize, vb: usize, ta: usize, tb: usize| -> (f64, f64) {
                // (K_re + iK_im)·(V_re + iV_im) − bg·(ΣK)(ΣY)
                let zr = dot(ka + re, vb + re) - dot(ka + im, vb + im);
                let zi = dot(ka + re, vb + im) + dot(ka + im, vb + re);
                let (kr, ki) = (columns.total(fx, ta + re), columns.total(fx, ta + im));
                let (yr, yi) = (rows.total(fy, tb + re), rows.total(fy, tb + im));
                (zr - bg * (kr * yr - ki * yi), zi - bg * (kr * yi + ki * yr))
            };
            let (zr, zi) = complex(0, 0, 0, 0);
            if zr.is_nan() || zr <= 0.0 {
                continue; // not a dot centred here (dust, edge): no phase
            }
            if with_gain {
                // ax: x-slope kernel with the y window; by: x window with the y slope.
                let ax = complex(4, 0, 4, 0);
                let by = complex(0, 4, 0, 4);
                let (kxh, kyh) = (planes[l].a / norm[l], planes[l].b / norm[l]);
                self.gain_num[l] += kxh * ax.1 + kyh * by.1;
                self.gain_den[l] += norm[l] * zr;
            }
            self.samples[l].push(DotPhase {
                x,
                y,
                phase: zi.atan2(zr),
                offset: planes[l].a * ex + planes[l].b * ey,
                weight: (zr * zr + zi * zi) * window / probability,
            });
        }
    }

    /// The planes corrected by the dots' phase errors (divided by the measured gain), or
    /// `None` with fewer than 16 dots or an implausible gain.
    fn corrected_planes(mut self) -> Option<DotwiseFit> {
        let planes = self.planes;
        let dots = self.samples[0].len().min(self.samples[1].len());
        if dots < 16 {
            return None;
        }
        let mut out = *planes;
        for l in 0..2 {
            let g = 1.0 - self.gain_num[l] / self.gain_den[l];
            if !(g.is_finite() && g > 0.1 && g <= 1.5) {
                return None;
            }
            for s in self.samples[l].iter_mut() {
                s.phase = s.phase / g + s.offset;
            }
            let delta = weighted_plane(&self.samples[l])?;
            out[l] = PhasePlane {
                a: planes[l].a + delta.a,
                b: planes[l].b + delta.b,
                c: planes[l].c + delta.c,
            };
        }
        Some(DotwiseFit { planes: out, dots })
    }
}

/// Column sums `V_q(c) = Σ_r Y_q(r)·g(r0 + r, c0 + c)` of the `n × n` window at `(c0, r0)`
/// (`at = (image width, c0, r0)`) into `sums`, then [`pair_products`]. Uses AVX2/FMA when the
/// CPU has them (same arithmetic, wider vectors).
fn dot_products(
    px: &[f32],
    at: (usize, usize, usize),
    kx: &[f32],
    ky: &[f32],
    n: usize,
    with_gain: bool,
    sums: &mut [f32],
) -> [f32; 24] {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { dot_products_avx2(px, at, kx, ky, n, with_gain, sums) };
        }
    }
    dot_products_generic(px, at, kx, ky, n, with_gain, sums)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dot_products_avx2(
    px: &[f32],
    at: (usize, usize, usize),
    kx: &[f32],
    ky: &[f32],
    n: usize,
    with_gain: bool,
    sums: &mut [f32],
) -> [f32; 24] {
    dot_products_generic(px, at, kx, ky, n, with_gain, sums)
}

#[inline(always)]
fn dot_products_generic(
    px: &[f32],
    (w, c0, r0): (usize, usize, usize),
    kx: &[f32],
    ky: &[f32],
    n: usize,
    with_gain: bool,
    sums: &mut [f32],
) -> [f32; 24] {
    let planes_q = if with_gain { 8 } else { 4 };
    // Each column sum is accumulated over the rows in registers (16 lanes, one q at a time);
    // the lanes beyond `n` read pixels further right with no use, so the padded read must
    // stay inside the buffer, else the plain loop below is used.
    let last = (r0 + n).saturating_sub(1) * w + c0 + WIDE;
    if n <= WIDE && last <= px.len() {
        for q in 0..planes_q {
            let mut acc = [0.0f32; WIDE];
            for r in 0..n {
                let start = (r0 + r) * w + c0;
                let (Some(line), Some(&weight)) = (px.get(start..start + WIDE), ky.get(q * n + r))
                else {
                    continue;
                };
                for (a, &g) in acc.iter_mut().zip(line) {
                    *a += weight * g;
                }
            }
            if let (Some(out), Some(src)) = (sums.get_mut(q * n..(q + 1) * n), acc.get(..n)) {
                out.copy_from_slice(src);
            }
        }
        return pair_products(kx, sums, n, with_gain);
    }
    if let Some(s) = sums.get_mut(..planes_q * n) {
        s.fill(0.0);
    }
    for r in 0..n {
        let start = (r0 + r) * w + c0;
        let Some(line) = px.get(start..start + n) else {
            continue;
        };
        for (q, out) in sums.chunks_exact_mut(n).take(planes_q).enumerate() {
            let Some(&weight) = ky.get(q * n + r) else {
                continue;
            };
            for (o, &g) in out.iter_mut().zip(line) {
                *o += weight * g;
            }
        }
    }
    pair_products(kx, sums, n, with_gain)
}

/// The products `Σ_c K_a(c)·V_b(c)` the phases need, in one pass with independent
/// accumulators: for each lobe `l` (blocks of 4: `(re,re), (im,im), (re,im), (im,re)`), first
/// window × window (slots 0..8), then, when `with_gain`, x-slope × y-window (8..16) and
/// x-window × y-slope (16..24). `kx` holds 8 kernels and `sums` 8 column sums, `n` apart.
#[inline(always)]
fn pair_products(kx: &[f32], sums: &[f32], n: usize, with_gain: bool) -> [f32; 24] {
    let mut p = [0.0f32; 24];
    let blocks: &[(usize, usize, usize)] = if with_gain {
        &[(0, 0, 0), (4, 0, 8), (0, 4, 16)]
    } else {
        &[(0, 0, 0)]
    };
    for &(ka, vb, slot) in blocks {
        for l in 0..2 {
            let (kr, ki) = (row(kx, n, ka + 2 * l), row(kx, n, ka + 2 * l + 1));
            let (vr, vi) = (row(sums, n, vb + 2 * l), row(sums, n, vb + 2 * l + 1));
            let mut acc = [0.0f32; 4];
            for (((&a, &b), &c), &d) in kr.iter().zip(ki).zip(vr).zip(vi) {
                acc[0] += a * c;
                acc[1] += b * d;
                acc[2] += a * d;
                acc[3] += b * c;
            }
            if let Some(out) = p.get_mut(slot + 4 * l..slot + 4 * l + 4) {
                out.copy_from_slice(&acc);
            }
        }
    }
    p
}

/// `sin³(π·t)` for `t ∈ [0, 1]`: the phase engine's apodisation profile.
fn sine_cubed(t: f64) -> f64 {
    (PI * t.clamp(0.0, 1.0)).sin().powi(3)
}

/// Row `q` of `n`-long rows stored back to back (empty when out of range).
fn row(v: &[f32], n: usize, q: usize) -> &[f32] {
    v.get(q * n..(q + 1) * n).unwrap_or(&[])
}

/// Deterministic pseudo-random selection of node `(n1, n2)` with probability `keep`.
fn kept(n1: i64, n2: i64, keep: f64) -> bool {
    if keep >= 1.0 {
        return true;
    }
    let mut z = (n1 as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15) ^ (n2 as u64);
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^= z >> 31;
    ((z >> 11) as f64 / (1u64 << 53) as f64) < keep
}

/// Window taps along one image axis for every quantised sub-pixel centre `f/QUANTA`: for the
/// pixels `u = j − f/QUANTA`, `j = −reach..=reach`, the 8 kernels `t(u)·e^{−i k_l u}`
/// (re₀, im₀, re₁, im₁) and `t'(u)·e^{−i k_l u}` (same order), with the Hann window
/// `t(u) = cos²(πu/2R)` (0 for `|u| ≥ R`) and its slope `t'`.
struct KernelTable {
    reach: usize,
    taps: usize,
    /// `QUANTA × 8 × taps` values.
    values: Vec<f32>,
    /// Sum of each kernel, `QUANTA × 8`.
    totals: Vec<f64>,
}

impl KernelTable {
    fn new(radius: f64, k: [f64; 2]) -> Self {
        let reach = radius.ceil() as usize;
        let taps = 2 * reach + 1;
        let mut values = vec![0.0f32; QUANTA * 8 * taps];
        let mut totals = vec![0.0f64; QUANTA * 8];
        let scale = PI / (2.0 * radius);
        for (f, (entry, total)) in values
            .chunks_exact_mut(8 * taps)
            .zip(totals.chunks_exact_mut(8))
            .enumerate()
        {
            for j in 0..taps {
                let u = j as f64 - reach as f64 - f as f64 / QUANTA as f64;
                let (t, dt) = if u.abs() < radius {
                    let (s, c) = (scale * u).sin_cos();
                    (c * c, -2.0 * scale * s * c)
                } else {
                    (0.0, 0.0)
                };
                for (l, &kl) in k.iter().enumerate() {
                    let (s, c) = (-kl * u).sin_cos();
                    for (q, v) in [
                        (2 * l, t * c),
                        (2 * l + 1, t * s),
                        (4 + 2 * l, dt * c),
                        (5 + 2 * l, dt * s),
                    ] {
                        if let Some(slot) = entry.get_mut(q * taps + j) {
                            *slot = v as f32;
                        }
                        if let Some(sum) = total.get_mut(q) {
                            *sum += v;
                        }
                    }
                }
            }
        }
        KernelTable {
            reach,
            taps,
            values,
            totals,
        }
    }

    /// First pixel of the window, table entry and residual offset `ε = position − centre` for
    /// a node at `position` (pixels, ≥ reach).
    fn locate(&self, position: f64) -> (usize, usize, f64) {
        let scaled = (position * QUANTA as f64).round();
        let centre = scaled / QUANTA as f64;
        let base = centre.floor();
        let f = (scaled - base * QUANTA as f64) as usize % QUANTA;
        (
            (base as usize).saturating_sub(self.reach),
            f,
            position - centre,
        )
    }

    /// The `8 × taps` kernels of entry `f`.
    fn entry(&self, f: usize) -> Option<&[f32]> {
        let size = 8 * self.taps;
        self.values.get(f * size..(f + 1) * size)
    }

    /// Sum of kernel `q` of entry `f`.
    fn total(&self, f: usize, q: usize) -> f64 {
        self.totals.get(f * 8 + q).copied().unwrap_or(0.0)
    }
}

/// Weighted least-squares plane through the dot phases, with one pass of outlier rejection
/// (dust, scratches: residuals beyond 5 robust σ); `None` when degenerate.
fn weighted_plane(samples: &[DotPhase]) -> Option<PhasePlane> {
    let fit = |keep: &dyn Fn(&DotPhase) -> bool| -> Option<PhasePlane> {
        let mut m = Matrix3::<f64>::zeros();
        let mut v = Vector3::<f64>::zeros();
        for s in samples.iter().filter(|s| keep(s)) {
            let basis = Vector3::new(s.x, s.y, 1.0);
            m += s.weight * basis * basis.transpose();
            v += s.weight * s.phase * basis;
        }
        let p = m.try_inverse()? * v;
        Some(PhasePlane {
            a: p[0],
            b: p[1],
            c: p[2],
        })
    };
    let first = fit(&|_| true)?;
    let mut residuals: Vec<f64> = samples
        .iter()
        .map(|s| (s.phase - first.at(s.x, s.y)).abs())
        .collect();
    let mid = residuals.len() / 2;
    let mad = if residuals.is_empty() {
        0.0
    } else {
        *residuals.select_nth_unstable_by(mid, f64::total_cmp).1
    };
    let limit = 5.0 * crate::order_stats::MAD_TO_SIGMA * mad;
    if limit > 0.0 {
        fit(&|s: &DotPhase| (s.phase - first.at(s.x, s.y)).abs() <= limit)
    } else {
        Some(first)
    }
}
