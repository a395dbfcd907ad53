//! White-noise level of an image of a dot grid, for the reported uncertainty
//! (docs/design.md#uncertainty).
//!
//! The refinement's residual counts everything its two cosines do not model as noise: the dots'
//! harmonics (a dot is not a cosine), aliasing, missing dots, glyphs. That overestimates the
//! noise several times on clean-ish images. Here the white noise is measured apart from the
//! pattern, using the pattern's own periodicity: for an integer pixel displacement `d` that is
//! (nearly) a lattice vector of the grid, the second difference
//!
//! `D(p) = g(p + d) − 2·g(p) + g(p − d)`
//!
//! cancels the periodic image exactly, whatever the dots' profile, blur or pixel integration,
//! and keeps `6σ²` of white noise. `d` is the displacement of at most a quarter of the window
//! per axis whose nearest lattice vector is closest (0.02–0.3 px off); the residual
//! mismatch `D ≈ e²·∂²g` (`e` that distance) is second order and sits only where the image
//! bends sharply (dot edges). Pixels where the pattern is not periodic (missing dots, glyphs,
//! frames, dust) give large `D` too, so the statistic is robust: the mean of the smaller half of
//! the `D²` values, divided by its Gaussian expectation `6σ²·0.14265`. Pixels are drawn with
//! density ∝ `w²` (the refinement's window squared), the weight with which each pixel's noise
//! enters the phase estimate, from a low-discrepancy sequence: deterministic, fixed per image
//! size, no allocation after the first call, 0.05–0.2 ms (512² to 1024² images). Differences that
//! touch a pixel at the sample's lowest or highest level are left out: clipped pixels (black
//! crushed, saturated dots) are equal without being noise-free, and a noise-free render's flat
//! levels say nothing about noise.
//!
//! On a tilted lattice (the whole-field fit's, with the coarse step's perspective) a
//! displacement is a lattice vector only near the tilt's centre; [`tilted_white_noise_variance`]
//! then picks the displacement and the samples that the tilt keeps within the same budget.
//!
//! The caller takes the smaller of this estimate and the fit residual (both upper bounds of the
//! white noise, up to their own statistical error of ~1 %) and clamps it to
//! [`MIN_NOISE_STD`](super::MIN_NOISE_STD).

use super::plane::PhasePlane;
use super::refine::sine_cubed;

/// Number of second differences drawn (relative standard deviation of the variance ≈ 2 %).
const SAMPLES: usize = 16384;

/// Largest displacement searched along each axis, pixels (and at most a quarter of the side).
const MAX_SHIFT: i64 = 64;

/// A displacement whose nearest lattice vector is farther than this (pixels) is not used: the
/// second difference would not cancel the pattern well enough.
const MAX_LATTICE_ERROR: f64 = 0.5;

/// Fewest usable samples for an estimate.
const MIN_SAMPLES: usize = 64;

/// `E[z² | |z| below its median]` for a standard normal `z`: the mean of the smaller half of
/// `z²` values.
const LOWER_HALF_SECOND_MOMENT: f64 = 0.142_652;

/// Samples per side of a region looked at for its quantisation step
/// ([`quantisation_variance_in`]) …
const QUANTISATION_SIDE: usize = 64;
/// … and most samples looked at in all ([`quantisation_variance`]).
const QUANTISATION_SAMPLES: usize = QUANTISATION_SIDE * QUANTISATION_SIDE;

/// Variance of the rounding of `pixels` to their sample levels, intensity units²: `q²/12` for
/// the smallest gap `q` between distinct values among up to 4096 evenly spread samples (1/255
/// in 8-bit grey data, grey JPEG included; ~0 in renders, float images, colour converted to
/// grey and apodised windows, whose values are no longer on a grid: no floor, unless the
/// caller knows the source's, `PhaseParams::rounding_variance`). Rounding is white
/// noise of that variance wherever the pattern spans several levels, but second differences
/// of rounded values are mostly exactly 0 on a clean image, so [`white_noise_variance`] (the
/// lower half of their squares) misses it: a clean 8-bit image of low contrast would report a
/// precision hundreds of times finer than its rounding allows. The callers take the larger of
/// the two. Missing levels (a pattern spanning a few levels with gaps) only make `q` larger,
/// the floor more cautious.
pub(crate) fn quantisation_variance(pixels: &[f32]) -> f64 {
    let stride = pixels.len().div_ceil(QUANTISATION_SAMPLES).max(1);
    quantisation_variance_of(pixels.iter().step_by(stride).copied())
}

/// [`quantisation_variance`] of the region `rows × cols` of a row-major image `width` pixels
/// wide, from a grid of up to [`QUANTISATION_SIDE`] samples per side.
pub(crate) fn quantisation_variance_in(
    pixels: &[f32],
    width: usize,
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
) -> f64 {
    let row_step = rows.len().div_ceil(QUANTISATION_SIDE).max(1);
    let col_step = cols.len().div_ceil(QUANTISATION_SIDE).max(1);
    quantisation_variance_of(rows.step_by(row_step).flat_map(|r| {
        let line = pixels.get(r * width + cols.start..r * width + cols.end);
        line.unwrap_or_default().iter().step_by(col_step).copied()
    }))
}

/// [`quantisation_variance`] of the given samples (all of them).
fn quantisation_variance_of(samples: impl Iterator<Item = f32>) -> f64 {
    let mut values: Vec<f32> = samples.filter(|v| v.is_finite()).collect();
    values.sort_unstable_by(f32::total_cmp);
    values.dedup();
    let gap = values
        .windows(2)
        .map(|w| w[1] as f64 - w[0] as f64)
        .fold(f64::INFINITY, f64::min);
    if gap.is_finite() {
        gap * gap / 12.0
    } else {
        0.0
    }
}

/// Sample positions of the noise estimate for one image size.
pub(crate) struct NoisePlan {
    rows: usize,
    cols: usize,
    /// `(col, row)` of each sample, drawn with density ∝ w² from the R2 low-discrepancy
    /// sequence (generalised golden ratio), fixed per size.
    positions: Vec<(u32, u32)>,
    squares: Vec<f64>,
}

impl NoisePlan {
    pub(crate) fn new(rows: usize, cols: usize) -> Self {
        let cdf = |n: usize| {
            let mut acc = 0.0;
            sine_cubed(n)
                .into_iter()
                .map(|w| {
                    acc += w * w;
                    acc
                })
                .collect::<Vec<f64>>()
        };
        let (cdf_x, cdf_y) = (cdf(cols), cdf(rows));
        let (draw_x, draw_y) = (InverseCdf::new(&cdf_x), InverseCdf::new(&cdf_y));
        const G1: f64 = 0.754_877_666_246_692_7;
        const G2: f64 = 0.569_840_290_998_053_2;
        let drawn: Vec<(u32, u32)> = (0..SAMPLES)
            .map(|k| {
                let u = (0.5 + G1 * k as f64).fract();
                let v = (0.5 + G2 * k as f64).fract();
                (draw_x.draw(&cdf_x, u) as u32, draw_y.draw(&cdf_y, v) as u32)
            })
            .collect();
        NoisePlan {
            rows,
            cols,
            positions: by_row(drawn),
            squares: Vec::with_capacity(SAMPLES),
        }
    }
}

/// `positions` (`(col, row)`) grouped by row, in increasing row order (a counting sort): the
/// estimate does not depend on the order of its samples, and reads scattered over a large
/// image were most of its time. Plans are made often (a tracked field box changes size), so
/// in linear time.
fn by_row(positions: Vec<(u32, u32)>) -> Vec<(u32, u32)> {
    let rows = positions
        .iter()
        .map(|&(_, y)| y as usize + 1)
        .max()
        .unwrap_or(0);
    let mut starts = vec![0usize; rows + 1];
    for &(_, y) in &positions {
        starts[y as usize + 1] += 1;
    }
    for r in 0..rows {
        starts[r + 1] += starts[r];
    }
    let mut sorted = vec![(0, 0); positions.len()];
    for p in positions {
        let slot = &mut starts[p.1 as usize];
        sorted[*slot] = p;
        *slot += 1;
    }
    sorted
}

/// Noise plans kept per thread for the sizes seen last, 256 KiB each: each tracked marker's
/// field box changes by a pixel or two from frame to frame (two markers of the real sequence
/// `Image96`–`Image125` and their windows need ~10 sizes; 4 remade a plan twice a frame).
const CACHED_PLANS: usize = 12;

thread_local! {
    static PLANS: std::cell::RefCell<crate::lru::Lru<(usize, usize), NoisePlan>> =
        std::cell::RefCell::new(crate::lru::Lru::new(CACHED_PLANS));
}

/// `f` with this thread's plan for `rows × cols`, made once per size ([`CACHED_PLANS`] sizes
/// kept): the whole-field fit reads the noise of every marker in every frame.
pub(crate) fn with_plan<R>(rows: usize, cols: usize, f: impl FnOnce(&mut NoisePlan) -> R) -> R {
    PLANS.with(|plans| {
        let mut plans = plans.borrow_mut();
        f(plans.get_or_insert_with((rows, cols), || NoisePlan::new(rows, cols)))
    })
}

/// Index of the first entry of the increasing `cdf` reaching `u·total`.
fn draw(cdf: &[f64], u: f64) -> usize {
    let total = cdf.last().copied().unwrap_or(0.0);
    cdf.partition_point(|&c| c < u * total)
        .min(cdf.len().saturating_sub(1))
}

/// [`draw`] in constant time: the draws at `u = j/B` for `B` [`INVERSE_BINS`] bins are
/// tabled once per plan, and a draw walks up from its bin's lower end (a step or two: the
/// bins are finer than the CDF's entries). The same index as [`draw`], whose binary search
/// per sample was 4 % of a tracked 5 MP frame (a tracked field box changes size from frame
/// to frame, so its plan is made afresh).
struct InverseCdf {
    starts: Vec<usize>,
}

/// Bins of [`InverseCdf`].
const INVERSE_BINS: usize = 1024;

impl InverseCdf {
    fn new(cdf: &[f64]) -> Self {
        let starts = (0..=INVERSE_BINS)
            .map(|j| draw(cdf, j as f64 / INVERSE_BINS as f64))
            .collect();
        InverseCdf { starts }
    }

    /// [`draw`]`(cdf, u)` for `u` in `[0, 1)`; `cdf` is the one this was made from.
    fn draw(&self, cdf: &[f64], u: f64) -> usize {
        let total = cdf.last().copied().unwrap_or(0.0);
        let mut bin = ((u * INVERSE_BINS as f64) as usize).min(INVERSE_BINS);
        if bin > 0 && bin as f64 / INVERSE_BINS as f64 > u {
            bin -= 1; // `u·B` rounded up to the next bin
        }
        // `draw` is monotone in `u`, so the bin's lower end is a lower bound of the answer.
        let mut i = self.starts.get(bin).copied().unwrap_or(0);
        let last = cdf.len().saturating_sub(1);
        while i < last && cdf[i] < u * total {
            i += 1;
        }
        i
    }
}

/// The integer displacement `(dx, dy)` (pixels; `dx > 0`, or `dx = 0` and `dy > 0`) closest to a
/// lattice vector of the grid given by `planes`, each component at most `max_shift` in
/// magnitude, with its distance (pixels) to that lattice vector. `None` for degenerate planes
/// or when no lattice vector fits the range.
pub(crate) fn lattice_shift(planes: &[PhasePlane; 2], max_shift: i64) -> Option<((i64, i64), f64)> {
    // Among (nearly) equally good displacements, the shortest.
    lattice_shift_by(planes, max_shift, |error, length| error + 1e-4 * length)
}

/// [`lattice_shift`] minimising `cost(distance to the lattice vector, length)`, pixels.
fn lattice_shift_by(
    planes: &[PhasePlane; 2],
    max_shift: i64,
    cost: impl Fn(f64, f64) -> f64,
) -> Option<((i64, i64), f64)> {
    let [p, q] = planes;
    let det = p.a * q.b - p.b * q.a;
    if !(det.abs() > 1e-12 && det.is_finite() && max_shift > 0) {
        return None;
    }
    // Lattice basis in pixels (the displacements advancing one plane by a whole turn and not
    // the other): the columns of 2π·J⁻¹, J = [[a₁, b₁], [a₂, b₂]].
    let tau = std::f64::consts::TAU;
    let t1 = (tau * q.b / det, -tau * q.a / det);
    let t2 = (-tau * p.b / det, tau * p.a / det);
    // Lattice indices of the displacements in range: m_l = (a_l·dx + b_l·dy)/2π.
    let reach = |a: f64, b: f64| (max_shift as f64 * (a.abs() + b.abs()) / tau).ceil() as i64;
    let (m1_max, m2_max) = (reach(p.a, p.b), reach(q.a, q.b));
    if m1_max > 4 * max_shift || m2_max > 4 * max_shift {
        return None; // finer than 2 px per period: not a grid the engine measures
    }
    let mut best: Option<((i64, i64), f64, f64)> = None;
    for m1 in -m1_max..=m1_max {
        for m2 in -m2_max..=m2_max {
            let (vx, vy) = (
                m1 as f64 * t1.0 + m2 as f64 * t2.0,
                m1 as f64 * t1.1 + m2 as f64 * t2.1,
            );
            let (dx, dy) = (vx.round() as i64, vy.round() as i64);
            if dx < 0 || (dx == 0 && dy <= 0) || dx > max_shift || dy.abs() > max_shift {
                continue;
            }
            let error = (dx as f64 - vx).hypot(dy as f64 - vy);
            let cost = cost(error, (dx as f64).hypot(dy as f64));
            if best.is_none_or(|b| cost < b.2) {
                best = Some(((dx, dy), error, cost));
            }
        }
    }
    best.map(|(d, error, _)| (d, error))
}

/// [`white_noise_variance`], at least the rounding's [`quantisation_variance`] of `pixels` and
/// `known_rounding` (the source's, when `pixels` are a scaled copy that hides its levels; 0
/// otherwise).
pub(crate) fn noise_variance(
    pixels: &[f32],
    weights: Option<&[f32]>,
    planes: &[PhasePlane; 2],
    plan: &mut NoisePlan,
    known_rounding: f64,
) -> Option<f64> {
    white_noise_variance(pixels, weights, planes, plan)
        .map(|v| v.max(quantisation_variance(pixels)).max(known_rounding))
}

/// A lattice's tilt about a centre ([`tilted_white_noise_variance`]): lattice coordinates
/// `u = v/(1 − p·v)` about `centre`, `v` linear in the image (docs/design.md#tilt-centre).
#[derive(Clone, Copy, Debug)]
pub(crate) struct LatticeTilt {
    /// Lattice coordinates of the centre, periods, in the numbering of the planes.
    pub centre: [f64; 2],
    /// The perspective `p`, per period.
    pub perspective: [f64; 2],
}

/// [`white_noise_variance`] of a lattice tilted by `tilt`. The displacement `d` is a lattice
/// vector only near the tilt's centre: at lattice offset `v` (periods) from it, the local
/// lattice moves `d` (`δ` in periods) by `(p·v)·δ + (p·δ)·v` to first order. On a steep tilt's
/// field a long `d`, chosen for its small rounding, is moved by up to a period there and keeps
/// the dots' edges in the second differences (a noise-free 16-bit stamp read 0.056 of noise,
/// which hid the tilt's misfit and left the marker 0.29 px off). Where the tilt keeps the
/// untilted choice of `d` within `MAX_LATTICE_ERROR` everywhere, that estimate stands. Else
/// `d` is the displacement whose usable region reaches farthest (the budget its rounding
/// leaves, over its length), and only the samples where the tilt's move stays within that
/// budget count.
pub(crate) fn tilted_white_noise_variance(
    pixels: &[f32],
    planes: &[PhasePlane; 2],
    plan: &mut NoisePlan,
    tilt: Option<LatticeTilt>,
) -> Option<f64> {
    let Some(tilt) = tilt else {
        return white_noise_variance(pixels, None, planes, plan);
    };
    let (rows, cols) = (plan.rows, plan.cols);
    let max_shift = MAX_SHIFT.min((rows.min(cols) / 4) as i64);
    // The untilted choice (`white_noise_variance`'s), where the tilt keeps it within the
    // budget everywhere.
    let (d, error) = lattice_shift(planes, max_shift).filter(|&(_, e)| e <= MAX_LATTICE_ERROR)?;
    let move_at = lattice_move(planes, rows, cols, d, &tilt);
    if moves_within(&move_at, rows, cols, MAX_LATTICE_ERROR - error) {
        return second_difference_variance(pixels, None, d, plan);
    }
    // Else the displacement whose usable region reaches farthest: its extent goes as the
    // budget the rounding leaves over the displacement's length.
    let (d, error) = lattice_shift_by(planes, max_shift, |error, length| {
        if error < MAX_LATTICE_ERROR {
            length / (MAX_LATTICE_ERROR - error)
        } else {
            f64::INFINITY
        }
    })
    .filter(|&(_, e)| e < MAX_LATTICE_ERROR)?;
    let (move_at, budget) = (
        lattice_move(planes, rows, cols, d, &tilt),
        MAX_LATTICE_ERROR - error,
    );
    // Weight 1 where the tilt keeps the displacement within the budget, 0 elsewhere.
    let weights = (!moves_within(&move_at, rows, cols, budget)).then(|| {
        (0..rows * cols)
            .map(|k| f32::from(u8::from(move_at(k % cols, k / cols) <= budget)))
            .collect::<Vec<f32>>()
    });
    second_difference_variance(pixels, weights.as_deref(), d, plan)
}

/// How far (pixels) the lattice tilted by `tilt` moves the displacement `(dx, dy)` at pixel
/// `(i, j)`: `(p·v)·δ + (p·δ)·v` to first order ([`tilted_white_noise_variance`]).
fn lattice_move<'a>(
    planes: &'a [PhasePlane; 2],
    rows: usize,
    cols: usize,
    (dx, dy): (i64, i64),
    tilt: &LatticeTilt,
) -> impl Fn(usize, usize) -> f64 + 'a {
    let [p, q] = planes;
    let det = p.a * q.b - p.b * q.a;
    let tau = std::f64::consts::TAU;
    let delta = [
        (p.a * dx as f64 + p.b * dy as f64) / tau,
        (q.a * dx as f64 + q.b * dy as f64) / tau,
    ];
    let (pr, centre) = (tilt.perspective, tilt.centre);
    let p_delta = pr[0] * delta[0] + pr[1] * delta[1];
    move |i, j| {
        // Pixel (i, j) sits at x = i − cols div 2, y = j − rows div 2 in the planes' frame.
        let (x, y) = (i as f64 - (cols / 2) as f64, j as f64 - (rows / 2) as f64);
        let v = [
            (p.a * x + p.b * y + p.c) / tau - centre[0],
            (q.a * x + q.b * y + q.c) / tau - centre[1],
        ];
        let p_v = pr[0] * v[0] + pr[1] * v[1];
        let e = [
            p_v * delta[0] + p_delta * v[0],
            p_v * delta[1] + p_delta * v[1],
        ];
        // Lattice (periods) → pixels: 2π·J⁻¹, J = [[a₁, b₁], [a₂, b₂]].
        let ex = tau * (q.b * e[0] - p.b * e[1]) / det;
        let ey = tau * (-q.a * e[0] + p.a * e[1]) / det;
        ex.hypot(ey)
    }
}

/// True when `move_at` stays within `budget` over the whole `rows × cols` image: the move is
/// linear in the pixel position, so its largest size is at a corner.
fn moves_within(
    move_at: &impl Fn(usize, usize) -> f64,
    rows: usize,
    cols: usize,
    budget: f64,
) -> bool {
    [(0, 0), (cols, 0), (0, rows), (cols, rows)]
        .iter()
        .all(|&(i, j)| move_at(i, j) <= budget)
}

/// Robust estimate of the white-noise variance of `pixels` (row-major, the plan's size), in
/// intensity units², from second differences along a lattice vector of `planes` (module
/// documentation). `weights` (same size, ≥ 0), when given, exclude the pixels of weight 0 as in
/// the weighted refinement. `None` when no displacement fits the lattice or too few pixels are
/// usable; the caller then keeps the fit residual.
pub(crate) fn white_noise_variance(
    pixels: &[f32],
    weights: Option<&[f32]>,
    planes: &[PhasePlane; 2],
    plan: &mut NoisePlan,
) -> Option<f64> {
    let (rows, cols) = (plan.rows, plan.cols);
    if pixels.len() != rows * cols || weights.is_some_and(|w| w.len() != rows * cols) {
        return None;
    }
    let max_shift = MAX_SHIFT.min((rows.min(cols) / 4) as i64);
    let (d, error) = lattice_shift(planes, max_shift)?;
    if error > MAX_LATTICE_ERROR {
        return None;
    }
    second_difference_variance(pixels, weights, d, plan)
}

/// The white-noise variance from the second differences along the integer displacement
/// `(dx, dy)` ([`white_noise_variance`]).
fn second_difference_variance(
    pixels: &[f32],
    weights: Option<&[f32]>,
    (dx, dy): (i64, i64),
    plan: &mut NoisePlan,
) -> Option<f64> {
    let (rows, cols) = (plan.rows, plan.cols);
    if pixels.len() != rows * cols || weights.is_some_and(|w| w.len() != rows * cols) {
        return None;
    }
    let usable = |i: usize| weights.is_none_or(|w| w[i].is_finite() && w[i] > 0.0);
    // Sample (x, y) is usable when x ± dx and y ± dy stay inside the image.
    let down = dy >= 0;
    let (dx, dy) = (dx as usize, dy.unsigned_abs() as usize);
    let step = dy * cols;
    // Clipped pixels (at the image's extreme levels: black crushed, saturated dots) carry no
    // noise; second differences touching them would read the noise as smaller than it is.
    let (mut low, mut high) = (f32::INFINITY, f32::NEG_INFINITY);
    for &(x, y) in &plan.positions {
        let v = pixels[y as usize * cols + x as usize];
        low = low.min(v);
        high = high.max(v);
    }
    let unclipped = |v: f32| v > low && v < high;
    plan.squares.clear();
    for &(x, y) in &plan.positions {
        let (x, y) = (x as usize, y as usize);
        if x < dx || x + dx >= cols || y < dy || y + dy >= rows {
            continue;
        }
        let i = y * cols + x;
        let (i0, i1) = if down {
            (i - step - dx, i + step + dx)
        } else {
            (i + step - dx, i - step + dx)
        };
        if !(usable(i0) && usable(i) && usable(i1)) {
            continue;
        }
        let (g0, g, g1) = (pixels[i0], pixels[i], pixels[i1]);
        if !(unclipped(g0) && unclipped(g) && unclipped(g1)) {
            continue;
        }
        let d = g0 as f64 - 2.0 * g as f64 + g1 as f64;
        if d.is_finite() {
            plan.squares.push(d * d);
        }
    }
    let n = plan.squares.len();
    if n < MIN_SAMPLES {
        return None;
    }
    let half = n / 2;
    plan.squares.select_nth_unstable_by(half, f64::total_cmp);
    let lower: f64 = plan.squares[..half].iter().sum::<f64>() / half as f64;
    Some(lower / (6.0 * LOWER_HALF_SECOND_MOMENT))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tabled_inverse_cdf_draws_what_the_binary_search_draws() {
        for n in [1, 2, 3, 17, 255, 256, 1031, 4000] {
            let mut acc = 0.0;
            let cdf: Vec<f64> = sine_cubed(n)
                .into_iter()
                .map(|w| {
                    acc += w * w;
                    acc
                })
                .collect();
            let table = InverseCdf::new(&cdf);
            let edges = (0..=INVERSE_BINS).flat_map(|j| {
                let u = j as f64 / INVERSE_BINS as f64;
                [u, f64::from_bits(u.to_bits().saturating_sub(1)), u + 1e-12]
            });
            let spread = (0..20_000).map(|k| (0.5 + 0.754_877_666 * k as f64).fract());
            for u in edges.chain(spread).filter(|u| (0.0..1.0).contains(u)) {
                assert_eq!(table.draw(&cdf, u), draw(&cdf, u), "n {n}, u {u}");
            }
        }
    }
    use crate::phase::wrap_to_pi;

    fn grid(period: f64, angle: f64) -> [PhasePlane; 2] {
        let k = std::f64::consts::TAU / period;
        let (s, c) = angle.sin_cos();
        [
            PhasePlane {
                a: k * c,
                b: k * s,
                c: 0.3,
            },
            PhasePlane {
                a: -k * s,
                b: k * c,
                c: -1.0,
            },
        ]
    }

    #[test]
    fn quantisation_variance_is_the_rounding_of_the_sample_levels() {
        // A smooth ramp of values rounded to 8 and 12 bits, and the same unrounded.
        let ramp: Vec<f64> = (0..200_000)
            .map(|i| 0.3 + 0.2 * (i as f64 * 1e-4).sin())
            .collect();
        for bits in [8u32, 12] {
            let levels = ((1u32 << bits) - 1) as f64;
            let rounded: Vec<f32> = ramp
                .iter()
                .map(|v| ((v * levels).round() / levels) as f32)
                .collect();
            let expected = 1.0 / (12.0 * levels * levels);
            let got = quantisation_variance(&rounded);
            assert!((got / expected - 1.0).abs() < 1e-4, "{bits} bits: {got:e}");
        }
        let unrounded: Vec<f32> = ramp.iter().map(|&v| v as f32).collect();
        assert!(quantisation_variance(&unrounded) < 1e-12);
        assert_eq!(quantisation_variance(&[0.5; 10]), 0.0);
        assert_eq!(quantisation_variance(&[]), 0.0);
    }

    #[test]
    fn lattice_shift_lands_near_a_lattice_vector() {
        for (period, angle) in [(4.0, 0.0), (7.3, 0.4), (12.5, -1.1), (40.0, 0.77)] {
            let planes = grid(period, angle);
            let ((dx, dy), error) = lattice_shift(&planes, 64).unwrap();
            // The phases change by whole turns, to within the reported error.
            for p in &planes {
                let left = wrap_to_pi(p.a * dx as f64 + p.b * dy as f64);
                assert!(
                    left.abs() <= p.frequency() * error + 1e-9,
                    "{period} {angle}"
                );
            }
            // Few lattice vectors fit in the search range at long periods.
            let limit = if period < 20.0 {
                0.2
            } else {
                MAX_LATTICE_ERROR
            };
            assert!(error < limit, "period {period}, angle {angle}: {error} px");
        }
    }

    /// Sharp, aliased square dots (far from a cosine) at `low`/`high` plus Gaussian noise of σ
    /// `sigma`, clamped to [0, 1].
    fn sharp_grid(
        rows: usize,
        cols: usize,
        planes: &[PhasePlane; 2],
        levels: (f64, f64),
        sigma: f64,
    ) -> Vec<f32> {
        let on = |x: f64, y: f64| planes.iter().all(|p| p.at(x, y).cos() > 0.0);
        dots_image(rows, cols, on, levels, sigma)
    }

    /// `levels.1` where `on(x, y)` (centred pixel coordinates), `levels.0` elsewhere, plus
    /// Gaussian noise of σ `sigma`, clamped to [0, 1].
    fn dots_image(
        rows: usize,
        cols: usize,
        on: impl Fn(f64, f64) -> bool,
        levels: (f64, f64),
        sigma: f64,
    ) -> Vec<f32> {
        let (cx, cy) = ((cols / 2) as f64, (rows / 2) as f64);
        let mut state = 12345u64;
        let mut gauss = || {
            // Sum of 12 uniforms − 6: unit variance, near Gaussian.
            (0..12)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    (state >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0
        };
        (0..rows * cols)
            .map(|k| {
                let (x, y) = ((k % cols) as f64 - cx, (k / cols) as f64 - cy);
                let level = if on(x, y) { levels.1 } else { levels.0 };
                (level + sigma * gauss()).clamp(0.0, 1.0) as f32
            })
            .collect()
    }

    /// A steep tilt (stress scene 54440's stamp lattice, 25° off before a short lens: the
    /// lattice ~5 % finer at one edge than at the other) moves the long displacement that
    /// fits the flat lattice best by most of a period at the field's edges: read without the
    /// tilt, the noise comes out 1.35× too large (more dot edges in the lower half of the
    /// second differences); with it, 1.11×.
    #[test]
    fn measures_white_noise_under_a_tilted_sharp_grid() {
        let (rows, cols) = (320usize, 320usize);
        let planes = grid(9.007, 2.407);
        let tilt = LatticeTilt {
            centre: [0.0, 0.0],
            perspective: [-1.6e-3, 1.7e-4],
        };
        let tau = std::f64::consts::TAU;
        let on = |x: f64, y: f64| {
            let v = planes.map(|p| p.at(x, y) / tau);
            let p = tilt.perspective;
            let scale = 1.0 / (1.0 - p[0] * v[0] - p[1] * v[1]);
            v.iter().all(|&vl| (tau * vl * scale).cos() > 0.0)
        };
        let mut plan = NoisePlan::new(rows, cols);
        for sigma in [0.001, 0.003, 0.01] {
            let image = dots_image(rows, cols, on, (0.2, 0.8), sigma);
            let flat = white_noise_variance(&image, None, &planes, &mut plan).map(f64::sqrt);
            let tilted = tilted_white_noise_variance(&image, &planes, &mut plan, Some(tilt))
                .map(f64::sqrt)
                .unwrap();
            assert!(
                (tilted / sigma - 1.0).abs() < 0.2,
                "σ {sigma}: {tilted:.2e} with the tilt, {flat:?} without"
            );
        }
    }

    #[test]
    fn measures_white_noise_under_a_sharp_grid() {
        let (rows, cols) = (128usize, 144usize);
        let planes = grid(9.3, 0.35);
        let mut plan = NoisePlan::new(rows, cols);
        // Noise-free: nothing but the exactly repeated levels, nothing to measure (or nearly 0).
        let clean = sharp_grid(rows, cols, &planes, (0.2, 0.8), 0.0);
        let v = white_noise_variance(&clean, None, &planes, &mut plan);
        assert!(v.is_none_or(|v| v.sqrt() < 0.01), "clean: {v:?}");
        for sigma in [0.003, 0.02] {
            let pixels = sharp_grid(rows, cols, &planes, (0.2, 0.8), sigma);
            let measured = white_noise_variance(&pixels, None, &planes, &mut plan)
                .unwrap()
                .sqrt();
            assert!(
                (measured / sigma - 1.0).abs() < 0.1,
                "σ {sigma}: measured {measured}"
            );
        }
    }

    #[test]
    fn clipped_levels_are_left_out() {
        // Black crushed to 0 and dots saturated at 1: a third of the background and of the dots
        // sit at the clipping levels, the rest keeps the noise above the cut (a truncated normal:
        // 0.68σ), the clipped pixels' own noise is 0.71σ: the estimate follows the noise the
        // pixels really carry instead of the zero differences between clipped ones.
        let (rows, cols) = (128usize, 128usize);
        let planes = grid(7.7, -0.6);
        let sigma = 0.05;
        let pixels = sharp_grid(rows, cols, &planes, (0.02, 0.98), sigma);
        let mut plan = NoisePlan::new(rows, cols);
        let measured = white_noise_variance(&pixels, None, &planes, &mut plan)
            .unwrap()
            .sqrt();
        assert!(
            (0.6..1.05).contains(&(measured / sigma)),
            "measured {measured}"
        );
    }
}
