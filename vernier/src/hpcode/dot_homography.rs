//! The dot grid of an HP code fitted to its own dots (docs/design.md#hp-dot-homography).
//!
//! The window's phase planes give a linear grid at the marker centre, and the three finders add
//! two projective terms ([`super::fine`]). Under a tilt of 20° and more that grid is still a
//! few tenths of a period off the dots at the marker's far edges, where the ID is read: the
//! planes are a window average, and three finders leave no equation to spare for a leg whose
//! finder is blurred or bitten by the tilt. Here the lattice itself says where its dots are:
//! the local phase of blocks of 3 × 3 dots that every HP code has (all of the field but the
//! finders and the two edges that may carry the ID), and a homography (8 parameters) fitted to
//! the block centres by least squares, with blocks that disagree (dust, hair, a scratch)
//! removed. The pose keeps the window's planes; this grid only says where to read the ID and
//! run the marker checks.

use super::grouping::FinderTriple;
use super::marker_id::{in_finder_corner, DotGrid};
use crate::grey_image::{GreyImage, Polarity};
use crate::order_stats::robust_sigma;
use nalgebra::{Matrix2, SMatrix, SVector, Vector2};
use num_complex::Complex64;
use std::f64::consts::TAU;

/// Radius of a block's weight `(1 − ρ²)²` (`ρ` the distance from its centre over the radius),
/// periods: the block's 3 × 3 dots, nothing of the dots beyond (at 2 periods and more).
const BLOCK_RADIUS: f64 = 1.5;
/// Samples per period along each axis at least; larger periods are sampled with a stride
/// (aliasing needs harmonics of order 7 and up, which blur removes).
const SAMPLES_PER_PERIOD: f64 = 8.0;
/// Spacing of the blocks, dots: every other dot along both axes (16–64 blocks for markers of
/// 13–21 dots per side), which over-determines the 8 parameters several times.
const BLOCK_STRIDE: usize = 2;
/// A block is used when its modulation is at least this fraction of the median block's: dust
/// or glare over a block flattens its dots.
const MIN_RELATIVE_STRENGTH: f64 = 0.5;
/// Outlier cut: blocks whose distance from the first fit exceeds this many robust standard
/// deviations ([`robust_sigma`] of the distances) are removed, but never below
/// [`MIN_OUTLIER_CUT`]. Each fit after the first is on the blocks within the cut of the one
/// before; a few blocks under dust do not move the least-squares first fit enough to hide.
const OUTLIER_SIGMAS: f64 = 3.0;
/// Smallest outlier cut, periods: agreement to 0.05 period is what reading the ID needs.
const MIN_OUTLIER_CUT: f64 = 0.05;
/// Refits without the outliers of the previous fit.
const OUTLIER_ROUNDS: usize = 2;
/// Fewest blocks the fit keeps (the homography has 8 parameters).
const MIN_BLOCKS: usize = 12;
/// Measure-and-fit rounds: the first on the inner part of the field, the second on the whole
/// field measured on the first round's grid (a third moved the far dots by under 0.01 px on
/// keystoned real images).
const ROUNDS: usize = 2;
/// Reach of the first round's blocks from the centre, fraction of the half-width: a tilt
/// moves the start grid's dots off by the square of the distance from the centre, so the
/// inner half sees a quarter of the edges' drift.
const INNER_REACH: f64 = 0.5;
/// Largest relative change of depth across the fitted marker accepted (as
/// `fine::MAX_DEPTH_CHANGE`, with room for the fit's own noise).
const MAX_DEPTH_CHANGE: f64 = 0.3;

/// Largest distance of a finder from its place on the fitted grid, periods (as far as the
/// finders' own view of the marker may leave them, `fine::MAX_LEG_ERROR`).
const MAX_FINDER_ERROR: f64 = 0.35;

/// A grid fitted to the marker's dots.
#[derive(Clone, Copy, Debug)]
pub(crate) struct DotFit {
    /// The fitted grid (its numbering still the start grid's).
    pub grid: DotGrid,
    /// Standard deviation of its centre, periods: the robust scale of the kept blocks'
    /// distances from the fit over the square root of their count (of distances, not of one
    /// coordinate: on the safe side by a factor of about 1.7).
    pub center_std: f64,
}

/// A block's measurement: the dot coordinates `u = (c − h, r − h)` of its centre dot from the
/// marker centre, and the image position where the lattice puts that dot, pixels.
#[derive(Clone, Copy, Debug)]
struct BlockFix {
    u: Vector2<f64>,
    seen: Vector2<f64>,
}

/// `grid` refitted as a homography to the marker's own dots (module docs), or `None` when too
/// few blocks can be measured (marker at the image edge, covered) or the fit is implausible;
/// the caller then keeps `grid`.
pub(crate) fn fit_dot_homography(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
) -> Option<DotFit> {
    let mut fitted = DotFit {
        grid: *grid,
        center_std: f64::NAN,
    };
    let h = grid.half_width();
    for round in 0..ROUNDS {
        // The first round measures the inner half of the field only, where the start grid is
        // close enough that no block's phase wraps; the later ones, on the grid it gives, all.
        let reach = if round == 0 { INNER_REACH * h } else { h };
        let blocks = measure_blocks(image, polarity, &fitted.grid, reach);
        let next = fit_robust(&blocks, &fitted.grid);
        log::trace!(
            "dot homography round {round}: {} blocks, corner dot moved {:?}, centre σ {:?} period",
            blocks.len(),
            next.map(|f| f.grid.at(0.0, 0.0) - fitted.grid.at(0.0, 0.0)),
            next.map(|f| f.center_std)
        );
        fitted = next?;
    }
    Some(fitted)
}

/// The renumbering of `dots` (whole periods along the marker axes, for
/// [`DotGrid::renumbered`]) that puts the finders of `triple` where they belong: the corner,
/// right and bottom finders at marker coordinates `(−L/2, −L/2)`, `(L/2, −L/2)` and
/// `(−L/2, L/2)`, `L = n − 4` periods apart. Two finders at least must agree on it, each within
/// [`MAX_FINDER_ERROR`] of its place: under a steep tilt one finder may merge with its
/// neighbouring dots and be found a period off, which the finders' own view of the marker
/// then spreads over the centre. `None` when no two finders agree.
pub(crate) fn finder_renumbering(dots: &DotGrid, triple: &FinderTriple) -> Option<Vector2<f64>> {
    let half = (dots.size as f64 - 4.0) / 2.0;
    let places = [(-half, -half), (half, -half), (-half, half)].map(|(x, y)| Vector2::new(x, y));
    let shifts: Vec<Vector2<f64>> = [triple.corner, triple.right, triple.bottom]
        .iter()
        .zip(places)
        .filter_map(|(&finder, place)| {
            let off = dots.marker_coordinates(finder)? - place;
            let shift = off.map(f64::round);
            ((off - shift).amax() <= MAX_FINDER_ERROR).then_some(shift)
        })
        .collect();
    let agreeing = |s: &Vector2<f64>| shifts.iter().filter(|t| *t == s).count();
    let best = shifts.iter().max_by_key(|s| agreeing(s))?;
    (agreeing(best) >= 2).then_some(*best)
}

/// Dot coordinates `(r, c)` of the block centres: every [`BLOCK_STRIDE`]-th dot whose 3 × 3
/// block lies in the field, clear of row 0 and column 0 (either may carry the ID) and of the
/// three finders (dots 0–3 in their corners).
fn block_centers(n: usize) -> impl Iterator<Item = (usize, usize)> {
    let range = move || (2..n.saturating_sub(1)).step_by(BLOCK_STRIDE);
    range()
        .flat_map(move |r| range().map(move |c| (r, c)))
        .filter(move |&(r, c)| {
            (r - 1..=r + 1).all(|rr| (c - 1..=c + 1).all(|cc| !in_finder_corner(n, rr, cc)))
        })
}

/// The blocks within `reach` dots of the centre (along both axes) that can be measured, strong
/// enough ([`MIN_RELATIVE_STRENGTH`]).
fn measure_blocks(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
    reach: f64,
) -> Vec<BlockFix> {
    let h = grid.half_width();
    let measured: Vec<(BlockFix, f64)> = block_centers(grid.size)
        .map(|(r, c)| (r as f64, c as f64))
        .filter(|&(r, c)| (r - h).abs().max((c - h).abs()) <= reach)
        .filter_map(|(r, c)| {
            let (seen, strength) = block_phase(image, polarity, grid, r, c)?;
            let u = Vector2::new(c - h, r - h);
            Some((BlockFix { u, seen }, strength))
        })
        .collect();
    let mut strengths: Vec<f64> = measured.iter().map(|m| m.1).collect();
    let Some(median) = crate::order_stats::median(&mut strengths) else {
        return Vec::new();
    };
    measured
        .into_iter()
        .filter(|m| m.1 >= MIN_RELATIVE_STRENGTH * median)
        .map(|m| m.0)
        .collect()
}

/// Where the dots of the block centred on grid dot `(r, c)` are: the grid's position moved by
/// the block's local phase along the grid's local axes (within half a period of it), and the
/// block's modulation (mean of both axes, material units). `None` when the block leaves the
/// image or its steps are singular.
fn block_phase(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
    r: f64,
    c: f64,
) -> Option<(Vector2<f64>, f64)> {
    let at = grid.at(r, c);
    let step_x = grid.at(r, c + 0.5) - grid.at(r, c - 0.5);
    let step_y = grid.at(r + 0.5, c) - grid.at(r - 0.5, c);
    let steps = Matrix2::from_columns(&[step_x, step_y]);
    let to_lattice = steps.try_inverse()?;
    let reach = (step_x.abs() + step_y.abs()) * BLOCK_RADIUS;
    let period = 0.5 * (step_x.norm() + step_y.norm());
    let stride = ((period / SAMPLES_PER_PERIOD).floor() as usize).max(1);
    let (x0, x1) = ((at.x - reach.x).floor(), (at.x + reach.x).ceil());
    let (y0, y1) = ((at.y - reach.y).floor(), (at.y + reach.y).ceil());
    let inside = |lo: f64, hi: f64, size: usize| lo >= 0.0 && hi < size as f64;
    if !(inside(x0, x1, image.width()) && inside(y0, y1, image.height())) {
        return None;
    }
    let sign = f64::from(polarity.sign());
    // Σw, Σw·v, and per axis Σw·v·e and Σw·e with e = exp(−2πi·l): the weighted mean is taken
    // out of the first sum with the second, so the background's level does not leak in. Along
    // a row, l and e change by the same step at every sample: no trigonometry per sample.
    let (mut sw, mut swv) = (0.0, 0.0);
    let (mut zv, mut z1) = ([Complex64::default(); 2], [Complex64::default(); 2]);
    let dl = to_lattice.column(0) * stride as f64;
    let turn = [0, 1].map(|axis| Complex64::from_polar(1.0, -TAU * dl[axis]));
    let (width, pixels) = (image.width(), image.pixels());
    let last_step = (x1 - x0) as usize / stride;
    for y in (y0 as usize..=y1 as usize).step_by(stride) {
        let row = pixels.get(y * width..(y + 1) * width)?;
        let start = to_lattice * (Vector2::new(x0, y as f64) - at);
        let Some((first, last)) = steps_within(start, dl, BLOCK_RADIUS, last_step) else {
            continue;
        };
        let mut l = start + dl * first as f64;
        let mut e = [0, 1].map(|axis| Complex64::from_polar(1.0, -TAU * l[axis]));
        let x = |step: usize| x0 as usize + step * stride;
        for x in (x(first)..=x(last)).step_by(stride) {
            let rho2 = l.norm_squared() / (BLOCK_RADIUS * BLOCK_RADIUS);
            if rho2 < 1.0 {
                let w = (1.0 - rho2) * (1.0 - rho2);
                let v = sign * f64::from(*row.get(x)?);
                sw += w;
                swv += w * v;
                for axis in 0..2 {
                    zv[axis] += e[axis] * (w * v);
                    z1[axis] += e[axis] * w;
                }
            }
            l += dl;
            e = [e[0] * turn[0], e[1] * turn[1]];
        }
    }
    if sw <= 0.0 {
        return None;
    }
    let mean = swv / sw;
    let z = [zv[0] - z1[0] * mean, zv[1] - z1[1] * mean];
    // A dot at lattice offset δ gives cos 2π(l − δ), whose sum with e is ∝ exp(−2πi·δ).
    let offset = Vector2::new(-z[0].arg() / TAU, -z[1].arg() / TAU);
    let strength = 0.5 * (z[0].norm() + z[1].norm()) / sw;
    Some((at + steps * offset, strength))
}

/// The first and last steps `k` (of `0..=last`) of the row `l + k·dl` (lattice offsets from
/// a block's centre) that may lie within `radius` of the centre: the roots of
/// `|l + k·dl|² = r²`, one step wider on each side for rounding (the caller still weighs each
/// sample). `None` when the row misses the disc.
fn steps_within(
    l: Vector2<f64>,
    dl: Vector2<f64>,
    radius: f64,
    last: usize,
) -> Option<(usize, usize)> {
    let (a, b, c) = (dl.dot(&dl), l.dot(&dl), l.dot(&l) - radius * radius);
    if a <= 0.0 {
        return Some((0, last));
    }
    let discriminant = b * b - a * c;
    if discriminant < 0.0 {
        return None;
    }
    let root = discriminant.sqrt();
    let (low, high) = (
        ((-b - root) / a).floor() - 1.0,
        ((-b + root) / a).ceil() + 1.0,
    );
    if high < 0.0 || low > last as f64 {
        return None;
    }
    Some((low.max(0.0) as usize, (high as usize).min(last)))
}

/// The homography through `blocks`, refitted [`OUTLIER_ROUNDS`] times without the blocks beyond
/// the outlier cut of the previous fit, as a [`DotGrid`] of `like`'s size; `None` with fewer
/// than [`MIN_BLOCKS`] blocks, a singular fit or one beyond [`MAX_DEPTH_CHANGE`].
fn fit_robust(blocks: &[BlockFix], like: &DotGrid) -> Option<DotFit> {
    if blocks.len() < MIN_BLOCKS {
        return None;
    }
    let mut fitted = fit_homography(blocks, like)?;
    let mut center_std = f64::NAN;
    for _ in 0..OUTLIER_ROUNDS {
        let period = 0.5 * (fitted.step_x.norm() + fitted.step_y.norm());
        let residuals: Vec<f64> = blocks.iter().map(residual_of(&fitted, period)).collect();
        let cut = (OUTLIER_SIGMAS * robust_sigma(&mut residuals.clone())).max(MIN_OUTLIER_CUT);
        let kept: Vec<BlockFix> = (blocks.iter().zip(&residuals))
            .filter(|(_, &r)| r <= cut)
            .map(|(b, _)| *b)
            .collect();
        if kept.len() < MIN_BLOCKS {
            return None;
        }
        fitted = fit_homography(&kept, like)?;
        // The centre is fitted from all kept blocks: their scatter over √count.
        let mut distances: Vec<f64> = kept.iter().map(residual_of(&fitted, period)).collect();
        center_std = robust_sigma(&mut distances) / (kept.len() as f64).sqrt();
    }
    let h = like.half_width();
    let depth_change = fitted.perspective.abs().sum() * h;
    (depth_change <= MAX_DEPTH_CHANGE).then_some(DotFit {
        grid: fitted,
        center_std,
    })
}

/// A block's distance from where `grid` puts it, in periods of `period` pixels.
fn residual_of(grid: &DotGrid, period: f64) -> impl Fn(&BlockFix) -> f64 + '_ {
    move |b| (grid.at_marker(b.u) - b.seen).norm() / period
}

/// Least-squares homography `x = (A·u + t)/(1 + p·u)` through the blocks, in its linear form
/// `A·u + t − x·(p·u) = x` (each equation weighted by `1/(1 + p·u)` of `like`, which makes it
/// the image-distance error to first order), as the [`DotGrid`] `centre = t`,
/// `steps = A − t·pᵀ`, `perspective = p`.
fn fit_homography(blocks: &[BlockFix], like: &DotGrid) -> Option<DotGrid> {
    // Unknowns: a11 a12 a21 a22 t1 t2 p1 p2.
    let mut normal = SMatrix::<f64, 8, 8>::zeros();
    let mut rhs = SVector::<f64, 8>::zeros();
    for b in blocks {
        let (u, x) = (b.u, b.seen);
        let weight = 1.0 / (1.0 + like.perspective.dot(&u)).max(0.5);
        let rows = [
            ([u.x, u.y, 0.0, 0.0, 1.0, 0.0, -x.x * u.x, -x.x * u.y], x.x),
            ([0.0, 0.0, u.x, u.y, 0.0, 1.0, -x.y * u.x, -x.y * u.y], x.y),
        ];
        for (row, value) in rows {
            let row = SVector::<f64, 8>::from(row) * weight;
            normal += row * row.transpose();
            rhs += row * (value * weight);
        }
    }
    let s = normal.lu().solve(&rhs)?;
    let center = Vector2::new(s[4], s[5]);
    let perspective = Vector2::new(s[6], s[7]);
    let a = Matrix2::new(s[0], s[1], s[2], s[3]);
    let steps = a - center * perspective.transpose();
    let fitted = DotGrid {
        perspective,
        fitted_to_dots: true,
        ..DotGrid::new(
            center,
            steps.column(0).into(),
            steps.column(1).into(),
            like.size,
        )
    };
    (fitted.center.iter().all(|v| v.is_finite()) && steps.determinant().abs() > 1e-9)
        .then_some(fitted)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An image of Gaussian dots (σ = 0.2 period, dark on bright when `dark`) at every dot of
    /// `truth`, and the blobs `(centre, radius)` at the background's level over them.
    fn dots(truth: &DotGrid, dark: bool, blobs: &[(Vector2<f64>, f64)]) -> GreyImage {
        let (w, h) = (400, 400);
        let period = truth.step_x.norm();
        let sigma = 0.2 * period;
        let n = truth.size;
        let centres: Vec<Vector2<f64>> = (0..n * n)
            .map(|i| truth.at((i / n) as f64, (i % n) as f64))
            .collect();
        let mut pixels = vec![0.0f32; w * h];
        for (i, v) in pixels.iter_mut().enumerate() {
            let p = Vector2::new((i % w) as f64, (i / w) as f64);
            let mut dot: f64 = centres
                .iter()
                .filter(|c| (*c - p).amax() < 4.0 * sigma)
                .map(|c| (-(c - p).norm_squared() / (2.0 * sigma * sigma)).exp())
                .sum();
            if blobs.iter().any(|(c, r)| (c - p).norm() < *r) {
                dot = 0.0;
            }
            let dot = 0.2 + 0.6 * dot.min(1.0);
            *v = if dark { 1.0 - dot } else { dot } as f32;
        }
        GreyImage::new(w, h, pixels).unwrap()
    }

    /// Largest distance, periods, between two grids' dots along row 0 and column 0.
    fn edge_error(a: &DotGrid, b: &DotGrid) -> f64 {
        let period = b.step_x.norm();
        (0..a.size)
            .flat_map(|k| [(0.0, k as f64), (k as f64, 0.0)])
            .map(|(r, c)| (a.at(r, c) - b.at(r, c)).norm() / period)
            .fold(0.0, f64::max)
    }

    /// A tilted grid of 17 dots per side at about 18 px.
    fn tilted() -> DotGrid {
        DotGrid {
            perspective: Vector2::new(0.012, -0.008),
            ..DotGrid::new(
                Vector2::new(201.3, 198.6),
                Vector2::new(17.6, 3.7),
                Vector2::new(-3.7, 17.6),
                17,
            )
        }
    }

    #[test]
    fn renumbering_moves_the_labels_not_the_dots() {
        let grid = tilted();
        let shift = Vector2::new(2.0, -1.0);
        let moved = grid.renumbered(shift);
        for (r, c) in [(0.0, 0.0), (3.0, 16.0), (8.0, 8.0), (16.0, 5.0)] {
            let same = grid.at(r + shift.y, c + shift.x) - moved.at(r, c);
            assert!(same.norm() < 1e-9, "dot ({r}, {c}) moved by {same:?}");
        }
        let u = grid.marker_coordinates(grid.at(2.5, 13.0)).unwrap();
        assert!((u - Vector2::new(5.0, -5.5)).norm() < 1e-9, "{u:?}");
    }

    #[test]
    fn two_finders_on_the_lattice_renumber_a_grid_a_period_off() {
        // Finders at their places on the true grid (L = 13 periods), but the corner one found
        // a period off diagonally (merged with its neighbouring dots); the grid to renumber is
        // the true one numbered a period off along both axes.
        let truth = tilted();
        let place = |x: f64, y: f64| truth.at(8.0 + y, 8.0 + x);
        let mut triple = FinderTriple {
            corner: place(-5.5, -7.5),
            right: place(6.5, -6.5),
            bottom: place(-6.5, 6.5),
            module_px: 4.5,
            polarity: Polarity::BrightDots,
            misfit: 0.0,
        };
        let off = truth.renumbered(Vector2::new(1.0, -1.0));
        let shift = finder_renumbering(&off, &triple).unwrap();
        let renumbered = off.renumbered(shift);
        assert!(
            (renumbered.center - truth.center).norm() < 1e-9,
            "{shift:?}"
        );
        // With the right finder also off its place, no two finders agree.
        triple.right = place(6.5, -6.0);
        assert_eq!(finder_renumbering(&off, &triple), None);
    }

    #[test]
    fn a_tilted_marker_s_edge_dots_are_found_where_its_linear_grid_misses_them() {
        // Depth changing by 16 % across the marker, a blob over two blocks; the linear grid
        // with the centre's steps is 0.5 period off at the ID edges.
        let truth = tilted();
        let linear = DotGrid::new(truth.center, truth.step_x, truth.step_y, 17);
        assert!(edge_error(&linear, &truth) > 0.4);
        let blob = (truth.at(10.0, 10.0), 25.0);
        for dark in [false, true] {
            let image = dots(&truth, dark, &[blob]);
            let polarity = if dark {
                Polarity::DarkDots
            } else {
                Polarity::BrightDots
            };
            let fitted = fit_dot_homography(&image, polarity, &linear).unwrap().grid;
            let error = edge_error(&fitted, &truth);
            assert!(error < 0.02, "dark {dark}: edge dots {error:.3} period off");
        }
    }
}
