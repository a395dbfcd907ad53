//! Layout-aware, robust fit of a marker's whole dot field (docs/design.md#field-fit).
//!
//! The phase engine measures a window that must hold nothing but dots, so on a decoded marker
//! it sees a fraction of the dot field, under an apodising window. Once a coarse step knows the
//! layout, every pixel around every drawn dot can be used instead:
//!
//! * **Which pixels.** The caller gives the layout on the half-period cell grid
//!   ([`NodeMask::from_cells`]). Each pixel gets the weight `w_L = s(d)·Σ M(k)·b(u₁ − k₁)·
//!   b(u₂ − k₂)` over its four surrounding nodes, `u = φ/2π` its lattice coordinates,
//!   `M(k) ∈ {0, 1}` whether node `k`'s dot is drawn, `b(t) = cos²(πt/2)` on `|t| < 1` (a
//!   partition of unity: `Σ b = 1` wherever the dots go on, falling smoothly to 0 within one
//!   period of the field's edge), and `s(d) = sin²(πd/2c)` of the pixel's distance `d` to the
//!   nearest *discrepant* cell (where the layout differs from the periodic grid: a missing
//!   dot, ink of a finder, frame or glyph, the marker's edge), 1 beyond the clearance `c`: one
//!   period, longer on blurred images (six blur σ, σ measured from the (1, ±1) harmonics'
//!   amplitude). The image there is the periodic pattern up to the blurred edge of those
//!   features. The Fourier transform of `b` vanishes at every non-zero integer, so the dots'
//!   harmonics are orthogonal under the node kernels; `s` breaks that near the discrepant
//!   cells only, where the alternation below converges more slowly, to the same solution.
//! * **Which model.** `g = μ + μ_X·X + μ_Y·Y + Σ_l (B_l + E_l·X + F_l·Y)·cos φ_l +
//!   (1 + η_X·X + η_Y·Y)·Σ_h A_h·cos(h·φ)`: background, fundamental amplitudes and the
//!   harmonics' gain with linear trends (illumination), and every dot harmonic `h` up to order
//!   `MAX_ORDER` (8; 5 where the pixel grid folds them) per axis whose amplitude reaches
//!   `MIN_HARMONIC` (1e-3) of the fundamental. Each harmonic first has a free complex
//!   amplitude: its phase relative to the fundamentals' is the dots' shape, whatever it is,
//!   and the offsets follow the fundamentals alone. Point-symmetric dots (sharp, blurred or
//!   pixel-integrated dots of any round or square shape) have every harmonic in phase with
//!   the dot centres; where the free fit's phases are consistent with that (Hausman's test,
//!   `symmetric_shift`), the harmonics are then *tied* to the dot centres, real amplitudes,
//!   and every harmonic informs the offsets as well as the slopes — square dots carry ~80 %
//!   more position information in their harmonics than in the fundamentals. Where they are not
//!   (coma, oblique light, the two fabrication layers of a real stamp a little off centre), tying
//!   would move the offsets to where the harmonics' phases put them, away from the fundamentals'
//!   (0.016–0.019 px on marker 0 of `Image96`–`105`), and converges only linearly, so the phases
//!   stay free and the centre is the fundamentals', as the window's is (docs/design.md#field-fit).
//!   Modelling the harmonics removes their leakage into the planes without any window: every
//!   pixel counts fully (a flat aperture instead of the engine's sine-cubed one, κ = √12
//!   instead of 4.85).
//! * **How.** Gauss–Newton: each iteration is one sweep that solves the 17 unknowns
//!   `μ, μ_X, μ_Y, B_l, E_l, F_l, η_X, η_Y` and the plane corrections
//!   `δφ_l = α_l·X + β_l·Y + γ_l` in one weighted linear least-squares step, and corrects the
//!   harmonics by demodulating the weighted residual (exact while they stay orthogonal). It
//!   runs with free harmonic phases to convergence (or to the iteration limit), then, if the
//!   dots are point-symmetric, with tied ones from there (one to three more sweeps; a settled
//!   free fit stands if they do not settle).
//! * **Robust weights.** A pixel's weight is `w_L` with each node's term multiplied by the
//!   node's cell weight (still a sum of node kernels, so still orthogonal), times Tukey's
//!   biweight `(1 − (r/c)²)²` of its residual. A cell (one period around a node) whose RMS
//!   residual exceeds twice the median of the cells around it (7 × 7 nodes) loses weight, none
//!   is left beyond 4×: dust, hair and scratches spoil whole cells, while the dots' fine model
//!   error is in every cell alike and smooth model error (vignetting) in neighbouring ones.
//!   The biweight's cut-off is `c = max(4.685·σ, 2B)`, `σ` = 1.4826 × the median absolute
//!   residual (95 % efficiency on Gaussian noise), at least twice the fundamental's amplitude
//!   `B` (`MIN_CUTOFF`), so that only gross departures count as outliers on clean images.
//!   When the weights freeze, each rejected pixel's outlier is grown by hysteresis into the
//!   8-connected pixels whose residual exceeds 3 × the local scale (`OUTLIER_EDGE`): the soft,
//!   blurred edge of a hair or of dust, which the biweight keeps and which pulls the dots it
//!   crosses, goes with its core (`outlier_extents`).
//!   The first iteration is not weighted; the first two set the weights from their
//!   residuals, and later ones too while their steps stay large (a start spoiled by dust over
//!   the window, or an unweighted step pulled by a blob darker than the dots: weights judged on
//!   a model far from its solution count its own error as outliers). The next iteration
//!   freezes the weights, so the last iterations solve one fixed weighted least-squares
//!   problem at Gauss–Newton's quadratic rate (reweighting each time, as plain IRLS does,
//!   converges linearly).
//!
//! **Breakdown.** The scales are medians: up to half of the cells (or pixels) may be outliers.
//! Both weights redescend to 0, so a gross outlier has no influence at all. Like every
//! redescending M-estimator, the fit reaches the right solution when it starts in its basin:
//! the start (the window's planes) must be within a fraction of a period everywhere in the
//! field, which the coarse step guarantees; a fit that moves a plane by half a period anywhere
//! (dots renumbered there) is refused.
//!
//! `X, Y` are image-frame coordinates relative to the field's weighted centre, divided by its
//! half-size (conditioning, and `Σw·X = 0` decouples the harmonics' phases from their ramps).
//! Cost: one sweep for the start (which also centres `X, Y`) and one per iteration (~14
//! operations per harmonic, in single precision, and the normal equations' 170 products in
//! double precision per pixel, accumulated 64 pixels at a time), 4–8 iterations; AVX2 when the
//! CPU has it. A fit whose steps stop contracting once the weights are frozen is given up at
//! once rather than run to the iteration limit (it would be refused there).

use super::noise::{quantisation_variance_in, tilted_white_noise_variance, with_plan, LatticeTilt};
use super::normal_equations::NormalEquations;
use super::plane::{wrap_to_pi, PhasePlane};
use super::MIN_NOISE_STD;
use crate::grey_image::GreyImage;
use crate::order_stats::{median, robust_sigma, TUKEY_BIWEIGHT};
use nalgebra::{DMatrix, DVector, Matrix2, Matrix6, SMatrix, SVector, Vector2, Vector6};
use num_complex::Complex64;
use std::f64::consts::{PI, SQRT_2, TAU};

/// Highest harmonic order modelled along each lattice axis: the dots' harmonics
/// `e^{i(h₁φ₁ + h₂φ₂)}` with `|h₁|, |h₂| ≤ MAX_ORDER` (sharp, pixel-integrated dots have ~15 %
/// of the fundamental up to order 3, and sharp dots 30–40 px wide still a few percent at order
/// 8: left out, they biased such markers by 10–15× their Cramér–Rao bound). Orders above
/// [`MAX_FOLDED_ORDER`] are modelled only where the pixel grid sees them unfolded.
const MAX_ORDER: usize = 8;
/// Highest harmonic order modelled where the pixel grid folds the harmonic (its wave vector
/// beyond the Nyquist square: unbinned fields, 4–12 px per period): folded orders 6–8 land
/// among the modelled ones as fine dot detail the sampling has already scrambled, and moved
/// clean 5-px markers by up to 1.6e-3 px (stress suite).
const MAX_FOLDED_ORDER: i32 = 5;
/// Harmonics whose amplitude is below this fraction of the fundamental are left out of the
/// iterations (their leakage into the slopes is then below ~2e-5 rad of phase at the field's
/// edge): blurred images keep a few, sharp ones a few dozen.
const MIN_HARMONIC: f64 = 1e-3;
/// Smallest Tukey cut-off, in mean fundamental amplitudes `B`: a pixel is a gross outlier
/// only when it departs from the model by more than twice the fundamental's amplitude (about
/// half the dot contrast). Smaller departures are model detail (dot edges that vary from dot
/// to dot, harmonics beyond the modelled orders, illumination), which the cells' weights
/// judge as a whole. A pixel whose model error sits on the biweight's slope gets a weight
/// that moves with each noise draw, and frozen weights then scatter the result beyond the
/// white-noise prediction: at `c = B` sharp dots 40 px wide scattered 1.7× the predicted σ,
/// at `2B` as predicted (tests/efficiency.rs).
const MIN_CUTOFF: f64 = 2.0;
/// A cell (one lattice period around a node) whose RMS residual exceeds this many times the
/// median cell's starts losing weight (dust, hair, scratch over it) …
const CELL_FULL: f64 = 2.0;
/// … and has none beyond this many (cos² taper in between). For pure noise a cell of `p²`
/// pixels has an RMS within ~`1/√(2p²)` of the median: never rejected.
const CELL_ZERO: f64 = 4.0;
/// A pixel joined (8-connected) to one the biweight rejects, whose residual exceeds this many
/// times the residual's local scale, belongs to the same outlier: the soft or blurred edge of
/// dust, a hair or a scratch, below the cut-off yet far from the dots' model
/// ([`outlier_extents`], [`frozen_weights`]). Pure noise passes it once in 370 pixels, so a
/// rejection grows through noise by hardly a pixel.
const OUTLIER_EDGE: f64 = 3.0;
/// Half-width of the neighbourhood a cell's residual is compared with, nodes (a 7 × 7 block:
/// a dust spot or a hair covers a minority of it).
const CELL_NEIGHBOURHOOD: usize = 3;
/// Fewest iterations that update the robust weights (more while the steps are large, see
/// [`SETTLED_STEP`]); the next one freezes them and later ones keep them, so the fit converges
/// to the solution of one fixed weighted problem.
const ROBUST_ITERATIONS: usize = 2;
/// Most iterations per stage (free, then tied harmonics). Once the weights are frozen, a fit
/// runs on only while the contraction its steps show can bring it to [`CONVERGED`] within
/// the iterations left ([`sweeps_to_converge`]): a fit that contracts 10–100× per sweep, as
/// Gauss–Newton on a clean field does, stops after a few; one whose harmonics the robust
/// weights couple to the planes (hair or dust over many cells) contracts by a steady 0.6 and
/// takes 15–20.
const MAX_ITERATIONS: usize = 30;
/// Converged when no plane moves by more than this anywhere in the field, radians (1.6e-6 of
/// a period; the error left is at most the steps still to come, see [`CONVERGED_TAIL`]) …
const CONVERGED: f64 = 1e-5;
/// … or, once two steps of the frozen problem show its contraction `q`, when the steps still to
/// come sum to less than this fraction of [`CONVERGED`] (`s·q/(1 − q)` after a step `s`): the
/// same error left, without the sweep that would only confirm it.
const CONVERGED_TAIL: f64 = 0.1;
/// … or when they sum to less than this fraction of the planes' own σ at the field's edge (the
/// noise's; 1e-6 rad is ~1e-3 of it on a real 8-bit marker): stopping there moves the result
/// by a hundredth of its σ at most, and saves the sweep that a noisy field's slower
/// contraction would need to reach the fixed tolerance.
const CONVERGED_TAIL_OF_SIGMA: f64 = 0.01;
/// Once the weights are frozen, a fit whose step exceeds this many radians of phase at the
/// field's edge (1.6e-4 of a period) is given up as soon as its contraction cannot bring it
/// to [`CONVERGED`] within the iterations left ([`sweeps_to_converge`]); a smaller step may
/// stall for one iteration (a weakly determined harmonic settling) and still converge, so
/// it is given up when that happens twice running.
const GIVE_UP_STEP: f64 = 1e-3;
/// The robust weights are updated (beyond the [`ROBUST_ITERATIONS`]) until a step moves no plane
/// by more than this anywhere in the field, radians, and only then frozen: weights judged on
/// the residuals of a model still far from its solution (a start spoiled by dust over the
/// window, or an unweighted first step pulled by a blob darker than the dots) count its own
/// error as outliers. The Tukey cut-off is at least the fundamental's amplitude, so a plane
/// error below ~0.1 rad hardly moves a weight.
const SETTLED_STEP: f64 = 0.05;
/// The fit is refused when it moves a plane by half a period or more anywhere in the field,
/// radians: dots would be renumbered there, so the start was not in the basin (or the field is
/// not this grid).
const MAX_CORRECTION: f64 = PI;
/// Fewest regular nodes a field must have (a 4 × 4 block of dots).
const MIN_NODES: usize = 16;
/// The field is binned 2 × 2 (4× fewer pixels to sweep), through the anti-aliasing filter of
/// [`crate::decimate`], where its period is at least this many binned pixels: the fundamental
/// and the second harmonic stay in the filter's pass band (gain within 2 %), and every
/// harmonic of a quarter cycle per input pixel or more is removed rather than folded.
const MIN_BINNED_PERIOD: f64 = 6.0;
/// Two components of the model must differ by at least this many cycles per field side to be
/// told apart.
const MIN_SEPARATION_CYCLES: f64 = 2.0;
/// Linear unknowns: μ, μ_X, μ_Y, then (B, E, F) of each fundamental, then the harmonics'
/// illumination gradient (η_X, η_Y).
const LINEAR: usize = 11;
/// Most harmonics modelled: `((2·MAX_ORDER + 1)² − 1)/2 − 2`.
const MAX_HARMONICS: usize = ((2 * MAX_ORDER + 1) * (2 * MAX_ORDER + 1) - 1) / 2 - 2;
/// All unknowns: the linear ones and (α, β, γ) of each plane.
const UNKNOWNS: usize = LINEAR + 6;
/// The unknowns with those of a tilt ([`Tilt`]): the perspective `(p₁, p₂)`, and the free
/// harmonics' phase offsets of each plane.
const TILTED: usize = UNKNOWNS + 4;

/// The layout of a marker's dot field, on the half-period cell grid of the planes given to
/// [`fit_dot_field`]: cell `(v₁, v₂)` is centred where `φ_l = π·v_l`, so the lattice nodes
/// (dot centres, `φ_l = 2πk_l`) are the cells `(2k₁, 2k₂)`. A cell is *discrepant* where the
/// layout differs from the periodic dot grid: a missing dot, ink on an odd cell (finder, frame,
/// glyph) or the marker's edge. The fit weighs the pixels around every drawn dot, less within
/// one period (more on blurred images) of a discrepant cell and not at all on one.
#[derive(Clone, Debug)]
pub struct NodeMask {
    first: (i64, i64),
    dims: (usize, usize),
    /// Per node: its dot is drawn.
    present: Vec<bool>,
    /// Cell `(v₁, v₂)` of entry `(0, 0)` of the cell maps.
    first_cell: (i64, i64),
    /// Extent of the cell maps.
    cell_dims: (usize, usize),
    /// Per cell: the layout differs from the periodic grid there.
    discrepant: Vec<bool>,
    /// Taper length from discrepant cells, cells.
    clearance: f64,
    /// The discrepant cells within `ceil(clearance)` cells of each cell (pixels of a cell with
    /// none are at least `clearance` away from every discrepant one), as offsets from it,
    /// nearest first: cell `i`'s are `nearby[nearby_start[i]..nearby_start[i + 1]]`. Most
    /// cells have none or a few of the `(2·ceil(c) + 1)²` around them, so a pixel's distance
    /// search looks at those only.
    nearby: Vec<(i8, i8)>,
    nearby_start: Vec<usize>,
}

/// Shortest distance from a discrepant cell's square, in half-period cells, over which a
/// pixel's weight rises from 0 to 1 (`sin²`): one period. A blurred image gets
/// [`CLEARANCE_PER_BLUR`] cells per period of blur σ when that is longer
/// ([`NodeMask::with_clearance_for_blur`]).
const MIN_CLEARANCE: f64 = 2.0;
/// Clearance per unit of blur σ (both in cells): the edge of a finder, a frame or a missing
/// dot departs from the periodic model by ~`Φ(−d/σ)` of its contrast at distance `d`, so six
/// σ of taper keep that departure, weighted, below 1e-4 (a stress scene at σ = P/4: 4e-4 px
/// of bias with a one-period taper, 1e-5–2.4e-4 px with six σ).
const CLEARANCE_PER_BLUR: f64 = 6.0;
/// Longest clearance, cells (blur beyond σ = P/3 leaves the dots too faint to measure).
const MAX_CLEARANCE: f64 = 4.0;
/// Cells beyond the nodes that the cell maps cover: a weighted pixel is within one period (2
/// cells) of a drawn dot and looks at cells up to [`MAX_CLEARANCE`] from its own.
const CELL_MARGIN: i64 = 3 + MAX_CLEARANCE as i64;
/// `|A₁₁|/|B|`, the (1, ±1) harmonics' amplitude over the fundamental's, of sharp round dots
/// half a period wide (square ones: 0.64); blur σ (periods) lowers it by `e^{−2π²σ²}`.
const SHARP_DIAGONAL_RATIO: f64 = 0.70;

impl NodeMask {
    /// The nodes `k₁ ∈ k1`, `k₂ ∈ k2` of a layout whose half-period cell `(v₁, v₂)` holds ink
    /// where `ink(v₁, v₂)` (also asked for cells up to a few beyond the nodes; `false` outside
    /// the marker).
    pub fn from_cells(
        k1: std::ops::RangeInclusive<i64>,
        k2: std::ops::RangeInclusive<i64>,
        ink: impl Fn(i64, i64) -> bool,
    ) -> Self {
        let count = |r: &std::ops::RangeInclusive<i64>| (r.end() - r.start() + 1).max(0) as usize;
        let dims = (count(&k1), count(&k2));
        let mut present = Vec::with_capacity(dims.0 * dims.1);
        for a in k1.clone() {
            for b in k2.clone() {
                present.push(ink(2 * a, 2 * b));
            }
        }
        let first_cell = (2 * k1.start() - CELL_MARGIN, 2 * k2.start() - CELL_MARGIN);
        let cell_dims = (
            (2 * dims.0 as i64 - 1 + 2 * CELL_MARGIN).max(0) as usize,
            (2 * dims.1 as i64 - 1 + 2 * CELL_MARGIN).max(0) as usize,
        );
        let cell = |i: usize, j: usize| (first_cell.0 + i as i64, first_cell.1 + j as i64);
        let mut discrepant = Vec::with_capacity(cell_dims.0 * cell_dims.1);
        for i in 0..cell_dims.0 {
            for j in 0..cell_dims.1 {
                let (v1, v2) = cell(i, j);
                let periodic = v1.rem_euclid(2) == 0 && v2.rem_euclid(2) == 0;
                discrepant.push(ink(v1, v2) != periodic);
            }
        }
        let mut mask = NodeMask {
            first: (*k1.start(), *k2.start()),
            dims,
            present,
            first_cell,
            cell_dims,
            discrepant,
            clearance: MIN_CLEARANCE,
            nearby: Vec::new(),
            nearby_start: Vec::new(),
        };
        mask.list_nearby_discrepant();
        mask
    }

    /// The same mask with the taper lengthened for the blur measured on `model` (σ in
    /// periods from the (1, ±1) harmonics, [`SHARP_DIAGONAL_RATIO`]); `None` when the
    /// shortest one fits.
    fn with_clearance_for_blur(&self, model: &Model) -> Option<NodeMask> {
        let diagonal: Vec<f64> = model
            .harmonics
            .iter()
            .filter(|((h1, h2), _)| *h1 == 1 && h2.abs() == 1)
            .map(|(_, a)| a.norm())
            .collect();
        let contrast = model.contrast();
        if contrast <= 0.0 {
            return None;
        }
        // Harmonics too faint to be modelled: blur well beyond a quarter period.
        let ratio = (diagonal.iter().sum::<f64>() / diagonal.len().max(1) as f64 / contrast)
            .max(MIN_HARMONIC);
        let sigma = ((SHARP_DIAGONAL_RATIO / ratio).ln().max(0.0) / (2.0 * PI * PI)).sqrt();
        let clearance = (CLEARANCE_PER_BLUR * 2.0 * sigma).clamp(MIN_CLEARANCE, MAX_CLEARANCE);
        (clearance > MIN_CLEARANCE).then(|| {
            let mut wider = self.clone();
            wider.clearance = clearance;
            wider.list_nearby_discrepant();
            wider
        })
    }

    /// Fills `nearby` and `nearby_start` for the current clearance.
    fn list_nearby_discrepant(&mut self) {
        // At most MAX_CLEARANCE cells: offsets fit in a byte.
        let reach = self.clearance.ceil().min(MAX_CLEARANCE) as i8;
        let mut offsets: Vec<(i8, i8)> = (-reach..=reach)
            .flat_map(|da| (-reach..=reach).map(move |db| (da, db)))
            .collect();
        offsets.sort_by_key(|&(da, db)| i32::from(da).pow(2) + i32::from(db).pow(2));
        let ((v1, v2), (n1, n2)) = (self.first_cell, self.cell_dims);
        let (mut nearby, mut starts) = (Vec::new(), Vec::with_capacity(n1 * n2 + 1));
        for a in v1..v1 + n1 as i64 {
            for b in v2..v2 + n2 as i64 {
                starts.push(nearby.len());
                let discrepant = offsets
                    .iter()
                    .filter(|&&(da, db)| self.is_discrepant(a + i64::from(da), b + i64::from(db)));
                nearby.extend(discrepant);
            }
        }
        starts.push(nearby.len());
        self.nearby = nearby;
        self.nearby_start = starts;
    }

    /// The discrepant cells near cell index `i`, as offsets from it, nearest first.
    fn nearby_discrepant(&self, i: usize) -> &[(i8, i8)] {
        match (self.nearby_start.get(i), self.nearby_start.get(i + 1)) {
            (Some(&start), Some(&end)) => self.nearby.get(start..end).unwrap_or(&[]),
            _ => &[],
        }
    }

    /// Whether the dot of node `(k1, k2)` is drawn.
    pub fn get(&self, k1: i64, k2: i64) -> bool {
        self.index(k1, k2).is_some_and(|i| self.present[i])
    }

    /// Index of node `(k1, k2)` in per-node arrays of [`NodeMask::len`] entries.
    fn index(&self, k1: i64, k2: i64) -> Option<usize> {
        grid_index(self.first, self.dims, k1, k2)
    }

    /// Index of cell `(v1, v2)` in the cell maps.
    fn cell_index(&self, v1: i64, v2: i64) -> Option<usize> {
        grid_index(self.first_cell, self.cell_dims, v1, v2)
    }

    /// Whether cell `(v1, v2)` is discrepant (false outside the cell maps).
    fn is_discrepant(&self, v1: i64, v2: i64) -> bool {
        self.cell_index(v1, v2).is_some_and(|i| self.discrepant[i])
    }

    /// Weight factor in `[0, 1]` of a pixel at cell coordinates `v = 2u`: `sin²(π·d/2c)` of its
    /// distance `d` from the nearest discrepant cell's square, in cells, 1 from the clearance
    /// `c` on (the Euclidean distance: the blur is isotropic).
    #[inline(always)]
    fn clearance(&self, v: [f64; 2]) -> f64 {
        let (c1, c2) = (v[0].round() as i64, v[1].round() as i64);
        let Some(i) = self.cell_index(c1, c2) else {
            return 0.0;
        };
        let nearby = self.nearby_discrepant(i);
        if nearby.is_empty() {
            return 1.0;
        }
        // Squared distances in the search, one root at the end; a pixel on a discrepant cell
        // (offset (0, 0), listed first) is at distance 0, the least there is.
        let mut nearest2 = f64::INFINITY;
        for &(d1, d2) in nearby {
            let (w1, w2) = (c1 + i64::from(d1), c2 + i64::from(d2));
            let gap1 = ((v[0] - w1 as f64).abs() - 0.5).max(0.0);
            let gap2 = ((v[1] - w2 as f64).abs() - 0.5).max(0.0);
            nearest2 = nearest2.min(gap1 * gap1 + gap2 * gap2);
            if nearest2 == 0.0 {
                break;
            }
        }
        if nearest2 >= self.clearance * self.clearance {
            1.0
        } else {
            let s = (0.5 * PI * nearest2.sqrt() / self.clearance).sin();
            s * s
        }
    }

    /// Number of nodes (drawn or not) the mask spans.
    fn len(&self) -> usize {
        self.present.len()
    }

    /// Number of drawn dots.
    pub fn count(&self) -> usize {
        self.present.iter().filter(|&&r| r).count()
    }

    /// Image-frame point of the drawn nodes' mean `k̄` under `planes` (`φ_l = 2π·k̄_l`);
    /// `None` without drawn nodes or for singular planes.
    fn centroid_at(&self, planes: &[PhasePlane; 2]) -> Option<Vector2<f64>> {
        let (mut sum, mut n) = (Vector2::zeros(), 0.0);
        for (index, _) in self.present.iter().enumerate().filter(|(_, &p)| p) {
            let (i, j) = (index / self.dims.1.max(1), index % self.dims.1.max(1));
            sum += Vector2::new(
                (self.first.0 + i as i64) as f64,
                (self.first.1 + j as i64) as f64,
            );
            n += 1.0;
        }
        let k = (n > 0.0).then_some(sum / n)?;
        let m = Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
        Some(m.try_inverse()? * Vector2::new(TAU * k.x - planes[0].c, TAU * k.y - planes[1].c))
    }
}

/// Row-major index of `(a, b)` in a grid whose entry `(0, 0)` is `first` and whose extent is
/// `dims`; `None` outside.
fn grid_index(first: (i64, i64), dims: (usize, usize), a: i64, b: i64) -> Option<usize> {
    let (i, j) = (a - first.0, b - first.1);
    (i >= 0 && j >= 0 && (i as usize) < dims.0 && (j as usize) < dims.1)
        .then(|| i as usize * dims.1 + j as usize)
}

/// A mask's node weights for one sweep, padded by one node on every side so that a pixel's
/// four surrounding nodes are looked up without bounds checks per node: per node, `[1, w]` if
/// drawn (`w` its robust weight) and `[0, 0]` otherwise.
struct NodeWeights {
    /// Node `(k₁, k₂)` of entry `(0, 0)`.
    first: (i64, i64),
    /// Padded extent: nodes along `k₁` (rows of `entries`) and along `k₂`.
    dims: (usize, usize),
    entries: Vec<[f64; 2]>,
}

impl NodeWeights {
    /// The weights of `mask` with robust weights `nodes` (per mask node; empty: all 1).
    fn new(mask: &NodeMask, nodes: &[f64]) -> Self {
        let dims = (mask.dims.0 + 2, mask.dims.1 + 2);
        let mut entries = vec![[0.0; 2]; dims.0 * dims.1];
        for i in 0..mask.dims.0 {
            for j in 0..mask.dims.1 {
                let index = i * mask.dims.1 + j;
                if mask.present[index] {
                    let robust = nodes.get(index).copied().unwrap_or(1.0);
                    entries[(i + 1) * dims.1 + j + 1] = [1.0, robust];
                }
            }
        }
        NodeWeights {
            first: (mask.first.0 - 1, mask.first.1 - 1),
            dims,
            entries,
        }
    }

    /// Layout weight of lattice coordinates `u` (see the module doc), in `[0, 1]`, and the same
    /// with each node's term multiplied by its robust weight: still a sum of node kernels, so
    /// the harmonics stay orthogonal under it. `cos_pi_u` is `cos πu` per axis.
    #[inline(always)]
    fn weight(&self, u: [f64; 2], cos_pi_u: [f64; 2]) -> (f64, f64) {
        let (k1, k2) = (u[0].floor() as i64, u[1].floor() as i64);
        let (i, j) = (k1 - self.first.0, k2 - self.first.1);
        // Outside the padded table all four nodes are outside the mask.
        if i < 0 || j < 0 || i as usize + 1 >= self.dims.0 || j as usize + 1 >= self.dims.1 {
            return (0.0, 0.0);
        }
        let base = i as usize * self.dims.1 + j as usize;
        let node = |offset: usize| self.entries.get(base + offset).copied().unwrap_or([0.0; 2]);
        let (e00, e01) = (node(0), node(1));
        let (e10, e11) = (node(self.dims.1), node(self.dims.1 + 1));
        // b(t) = cos²(πt/2) = (1 + cos πt)/2 at t = u − k, cos πt = (−1)^k·cos πu.
        let partition = |k: i64, c: f64| {
            let b = 0.5 + 0.5 * if k % 2 == 0 { c } else { -c };
            [b, 1.0 - b]
        };
        let (b1, b2) = (partition(k1, cos_pi_u[0]), partition(k2, cos_pi_u[1]));
        let sum = |m: usize| {
            b1[0] * (b2[0] * e00[m] + b2[1] * e01[m]) + b1[1] * (b2[0] * e10[m] + b2[1] * e11[m])
        };
        (sum(0), sum(1))
    }
}

/// The window fit that a whole-field fit must beat to be kept ([`FieldFit::beats`]):
/// given to [`fit_dot_field_against`], it lets a fit that cannot beat it stop early.
#[derive(Clone, Copy, Debug)]
pub struct Rival {
    /// Standard deviation of each plane's phase of the window fit at `at`, radians.
    pub phase_std: [f64; 2],
    /// Image-frame point `(x, y)` where the two are compared (the marker's centre), pixels
    /// (docs/design.md#frames).
    pub at: (f64, f64),
}

impl Rival {
    /// The window's σ: both planes' phase σ in quadrature, radians.
    fn std(&self) -> f64 {
        self.phase_std[0].hypot(self.phase_std[1])
    }

    /// The same measure of a field fit with white-noise `covariance` in normalised `frame`,
    /// scaled by its residual over the white noise (`model_error_ratio`).
    fn field_std(&self, covariance: &Matrix6<f64>, frame: (f64, f64, f64), ratio: f64) -> f64 {
        let s = phase_std_at(covariance, frame, self.at);
        s[0].hypot(s[1]) * ratio
    }
}

/// Standard deviation of each plane's phase at the image-frame point `at`, radians, from the
/// covariance of `(α₁, β₁, γ₁, α₂, β₂, γ₂)` in the normalised coordinates of `frame`
/// (centre `x₀, y₀` and half-size `s`).
fn phase_std_at(covariance: &Matrix6<f64>, frame: (f64, f64, f64), at: (f64, f64)) -> [f64; 2] {
    let (x0, y0, s) = frame;
    let v = [(at.0 - x0) / s, (at.1 - y0) / s, 1.0];
    [0, 1].map(|l| {
        let mut var = 0.0;
        for (i, vi) in v.iter().enumerate() {
            for (j, vj) in v.iter().enumerate() {
                var += vi * vj * covariance[(3 * l + i, 3 * l + j)];
            }
        }
        var.max(0.0).sqrt()
    })
}

/// Result of [`fit_dot_field`].
#[derive(Clone, Debug)]
pub struct FieldFit {
    /// The refined planes (image frame, same node numbering as the start).
    pub planes: [PhasePlane; 2],
    /// Amplitude `|B_l|` of each fundamental at the field's centre, image intensity units.
    pub amplitudes: [f64; 2],
    /// Robust standard deviation of the residual (1.4826 × median |r|), intensity units: white
    /// noise and model error. The uncertainty counts the white noise alone (measured apart
    /// from the model when that is smaller, docs/design.md#uncertainty).
    pub residual_std: f64,
    /// Fraction of the field's layout weight that the robust weights kept, `[0, 1]`.
    pub inlier_fraction: f64,
    /// Whole cells (one period around a drawn dot, clear of the layout's other features) whose
    /// robust weight is below 1: dust, hair, scratches over the field. Noise alone never
    /// lowers a cell's weight (twice the median of the cells around it).
    pub spoiled_cells: usize,
    /// Pixels with a non-zero layout weight.
    pub pixels: usize,
    /// Gauss–Newton iterations run.
    pub iterations: usize,
    /// Dot harmonics modelled (besides the two fundamentals).
    pub harmonics: usize,
    /// Whether the harmonics were tied to the dot centres (their phases showed point-symmetric
    /// dots) and so informed the offsets; `false`: the offsets follow the fundamentals alone.
    pub harmonics_tied: bool,
    /// Covariance of the last correction `(α₁, β₁, γ₁, α₂, β₂, γ₂)` from white noise,
    /// radians².
    covariance: Matrix6<f64>,
    /// The residual's scale over the white noise's, ≥ 1: how far model error adds to the noise.
    model_error_ratio: f64,
    /// Field centre `(x₀, y₀)` (image frame) and half-size `s` of the normalised coordinates.
    frame: (f64, f64, f64),
    /// The field's perspective `p` per period, measured about the centre the caller gave
    /// ([`fit_dot_field_against`]'s `tilt`; `None` when not asked, or not measurable):
    /// lattice coordinates `u = v/(1 − p·v)`, `v` linear in the image
    /// (docs/design.md#tilt-centre).
    pub perspective: Option<Vector2<f64>>,
    /// The part of `perspective` that moved the planes, in `[0, 1]`: zero while it is not
    /// significant at the level 10⁻³ (an untilted field's measured `p` is noise), near 1 on a
    /// clear tilt, 1 where the fit carried the tilt in its phase model (a steep tilt whose
    /// curvature one linear step cannot take, docs/design.md#tilt-centre).
    pub tilt_weight: f64,
    /// The planes the fit started from (the window's, image frame): what stands when the fit
    /// does not beat the window ([`FieldFit::beats`]).
    start: [PhasePlane; 2],
    /// The converged model, for the next frame's fit of the same marker
    /// ([`fit_dot_field_tracked`]).
    warm: Box<WarmModel>,
}

/// What a converged fit hands on to the next frame's fit of the same marker (tracking,
/// docs/design.md#tracked-field-fit): everything but the planes changes little between two
/// frames of a servo loop (the dots' harmonics, the illumination terms, the robust scale and
/// the cells' weights, the tilt carried in the phase model).
#[derive(Clone, Debug)]
struct WarmModel {
    /// The model, its planes in the image frame (input pixels); no frozen weights (they are
    /// per pixel of a box that moves).
    model: Model,
    /// The field centre `(x₀, y₀)` from the drawn nodes' centroid
    /// ([`NodeMask::centroid_at`]; the same nodes in any numbering of them), and the
    /// half-size `s` of the normalised coordinates, input pixels.
    frame: (f64, f64, f64),
    /// The perspective carried in the final pass's phase model (zero: a flat pass).
    taken: Vector2<f64>,
    /// The fit's planes less the window's it started from (image frame): where the next
    /// frame's fit starts from its window's.
    correction: [PhasePlane; 2],
    /// Binning factor of the fit (1 or 2).
    factor: usize,
    /// The final sweep's robust residual σ and inlier fraction: the next frame's first sweep
    /// on these weights must look alike to keep them ([`WarmModel::still_fits`]).
    residual_std: f64,
    inlier_fraction: f64,
}

/// How much a tracked frame's first sweep may depart from the last fit before its weights are
/// judged afresh ([`WarmModel::still_fits`]): the residual's σ 25 % larger (dust arrived, the
/// focus or the light changed), or 2 % of the field's weight newly rejected.
const WARM_RESIDUAL_GROWTH: f64 = 1.25;
const WARM_INLIER_DROP: f64 = 0.02;

impl WarmModel {
    /// Whether `step`, the first sweep of a tracked frame on this model's robust weights, shows
    /// the same field: then its weights are frozen at once; otherwise they are set afresh
    /// from its residuals, as a cold fit does.
    fn still_fits(&self, step: &Step) -> bool {
        step.residual_std <= WARM_RESIDUAL_GROWTH * self.residual_std
            && step.inlier_fraction >= self.inlier_fraction - WARM_INLIER_DROP
    }

    /// This model in the frame of a (binned) sub-image whose pixel `(0, 0)` sits at
    /// image-frame `offset`, `f` input pixels per pixel; `None` at another binning.
    fn in_sub_frame(&self, f: usize, offset: [f64; 2]) -> Option<WarmModel> {
        if f != self.factor {
            return None;
        }
        let f = f as f64;
        let mut warm = self.clone();
        warm.model.planes = self.model.planes.map(|p| PhasePlane {
            a: f * p.a,
            b: f * p.b,
            c: p.c + p.a * offset[0] + p.b * offset[1],
        });
        let (dx, dy, s) = self.frame;
        warm.frame = (dx / f, dy / f, s / f);
        Some(warm)
    }

    /// This model for a fit from planes `start` of the nodes of `mask` over a field whose
    /// normalised coordinates have half-size `scale` (one frame for all): its centre where it
    /// was from the nodes' centroid, and the linear terms' slopes rescaled to `scale`. `None`
    /// when `start` is singular.
    fn moved_to(
        &self,
        start: &[PhasePlane; 2],
        scale: f64,
        mask: &NodeMask,
    ) -> Option<(Model, (f64, f64))> {
        let (dx, dy, s0) = self.frame;
        let at = mask.centroid_at(start)? + Vector2::new(dx, dy);
        let mut model = self.model.clone();
        model.planes = *start;
        let ratio = scale / s0;
        for k in [1, 2, 4, 5, 7, 8, 9, 10] {
            model.linear[k] *= ratio;
        }
        (at.x.is_finite() && at.y.is_finite() && ratio.is_finite()).then_some((model, (at.x, at.y)))
    }
}

impl FieldFit {
    /// The residual's scale over the white noise's, ≥ 1: how far model error (dot edges the
    /// model does not describe, clutter the weights kept) adds to the noise. The σs of the
    /// fit count the white noise alone; two fits of the same image that weigh its pixels
    /// differently (judged on other residuals) differ by up to about this many times them.
    pub fn model_error_ratio(&self) -> f64 {
        self.model_error_ratio
    }

    /// Standard deviation of each plane's phase at the image-frame point `(x, y)`, radians.
    pub fn phase_std_at(&self, x: f64, y: f64) -> [f64; 2] {
        phase_std_at(&self.covariance, self.frame, (x, y))
    }

    /// Whether this fit should replace `rival`, the window fit (its offsets' σ at its
    /// image-frame point):
    ///
    /// * when the field has spoiled cells, always: the window weighs every pixel alike, so the
    ///   same dust or hair may bias it while its σ, a noise figure, cannot show it;
    /// * otherwise the estimator with the smaller predicted position error is kept: the
    ///   window's σ, and the field's σ scaled by its residual over the white noise. The field
    ///   model stops at order-5 harmonics: on nearly noise-free images of sharp
    ///   dots many pixels wide its residual is model error, which the window's band-pass never
    ///   sees, and the window wins.
    /// * on a tilted field (a significant perspective, [`FieldFit::tilt_weight`] above 0),
    ///   also when the window's estimated error exceeds the fit's: see
    ///   `FieldFit::window_bias_shown`.
    pub fn beats(&self, rival: &Rival) -> bool {
        let field = rival.field_std(&self.covariance, self.frame, self.model_error_ratio);
        let window = rival.std();
        let beats =
            self.spoiled_cells > 0 || field < window || self.window_bias_shown(rival, field);
        if !beats {
            log::debug!("whole-field fit σ {field:.2e} rad not below the window's {window:.2e}");
        }
        beats
    }

    /// The tilt this fit measured but did not carry in its phase model, per period: its
    /// perspective times the weight it was taken at, zero without one.
    fn tilt_left(&self) -> Vector2<f64> {
        self.perspective.unwrap_or_default() * self.tilt_weight
    }

    /// Whether, on a tilted field, the window's planes are shown to be further off than this
    /// fit's σ `field` (radians) says it is. The window's flat planes cannot follow a tilt's
    /// curvature and take in its mean over the window, a bias `b` its σ (a noise figure) does
    /// not hold, while this fit measured the tilt and took it. The fit's move of the planes at
    /// the comparison point, `δ`, is the window's error less the fit's, so `E[δ²] = b² + σ_w² +
    /// σ_f²`, and `δ² − σ_f²` estimates the window's mean square error. The fit wins when its
    /// own, `σ_f²`, is smaller: `|δ| > √2·σ_f`. Untilted fields are judged on the σs alone.
    fn window_bias_shown(&self, rival: &Rival, field: f64) -> bool {
        if self.tilt_weight <= 0.0 {
            return false;
        }
        let (x, y) = rival.at;
        let moved = [0, 1].map(|l| self.planes[l].at(x, y) - self.start[l].at(x, y));
        let shown = moved[0].hypot(moved[1]) > SQRT_2 * field;
        if shown {
            log::debug!(
                "whole-field fit: tilted field, it moved the window's planes by ({:.2e}, {:.2e}) \
                 rad, beyond √2 × its σ {field:.2e}",
                moved[0],
                moved[1]
            );
        }
        shown
    }

    /// Standard deviation of the mean gradient direction `(θ₁ + θ₂)/2` of the two planes,
    /// `θ_l = atan2(b_l, a_l)`, radians (the orientation of a marker whose axes are the planes).
    pub fn mean_direction_std(&self) -> f64 {
        let s = self.frame.2;
        let mut g = Vector6::zeros();
        for (l, p) in self.planes.iter().enumerate() {
            let k2 = p.a * p.a + p.b * p.b;
            if k2 > 0.0 {
                // dθ = (a·db − b·da)/|k|², da = dα/s, db = dβ/s; halved for the mean.
                g[3 * l] = -0.5 * p.b / (s * k2);
                g[3 * l + 1] = 0.5 * p.a / (s * k2);
            }
        }
        (g.transpose() * self.covariance * g)[(0, 0)]
            .max(0.0)
            .sqrt()
    }
}

/// The harmonics `(h₁, h₂)` of order ≤ [`MAX_ORDER`] other than the fundamentals, one of each
/// `±h` pair (`h₁ > 0`, or `h₁ = 0 < h₂`).
fn all_harmonics() -> Vec<(i32, i32)> {
    let m = MAX_ORDER as i32;
    let mut list = Vec::new();
    for h1 in 0..=m {
        for h2 in -m..=m {
            if (h1 > 0 || h2 > 0) && (h1, h2) != (1, 0) && (h1, h2) != (0, 1) {
                list.push((h1, h2));
            }
        }
    }
    list
}

/// The harmonics that can be told apart on the pixel grid over a field of `side` pixels, lower
/// orders first: a harmonic above the Nyquist frequency appears at its wave vector folded
/// into the Nyquist square (aliased), and is kept only while that stays
/// [`MIN_SEPARATION_CYCLES`] per field from DC, both fundamentals and every harmonic kept
/// before it (and their opposites: the image is real). On a 4-px grid, say, the third
/// harmonic folds onto the fundamental and is left out; on a rotated grid most aliased
/// harmonics stay apart and are modelled.
///
/// On an `unaliased` grid (anti-aliased binning, [`crate::decimate`]) nothing folds: a
/// harmonic beyond the Nyquist square is gone from the image, and one is kept only while it
/// stays half the separation inside the square (that far from its own conjugate's fold).
/// On any grid, a harmonic of order above [`MAX_FOLDED_ORDER`] is kept only on those terms.
fn resolvable_harmonics(planes: &[PhasePlane; 2], side: f64, unaliased: bool) -> Vec<(i32, i32)> {
    let mut candidates = all_harmonics();
    candidates.sort_by_key(|&(a, b)| (a.abs().max(b.abs()), a.abs() + b.abs()));
    // The harmonic's wave vector (radians per pixel), and as the pixel grid sees it (folded
    // into the Nyquist square).
    let unfolded = |(h1, h2): (i32, i32)| {
        let (h1, h2) = (h1 as f64, h2 as f64);
        [
            h1 * planes[0].a + h2 * planes[1].a,
            h1 * planes[0].b + h2 * planes[1].b,
        ]
    };
    let wave = |h: (i32, i32)| unfolded(h).map(wrap_to_pi);
    let separation = MIN_SEPARATION_CYCLES * TAU / side.max(1.0);
    let inside = |h: (i32, i32)| (unfolded(h).iter()).all(|v| v.abs() <= PI - 0.5 * separation);
    let mut taken = vec![[0.0, 0.0], wave((1, 0)), wave((0, 1))];
    let mut kept = Vec::new();
    for h in candidates {
        let high_order = h.0.abs().max(h.1.abs()) > MAX_FOLDED_ORDER;
        if (unaliased || high_order) && !inside(h) {
            continue;
        }
        let k = wave(h);
        let near = |q: &[f64; 2]| {
            [1.0, -1.0].iter().any(|&sign| {
                wrap_to_pi(k[0] - sign * q[0]).hypot(wrap_to_pi(k[1] - sign * q[1])) < separation
            })
        };
        if !taken.iter().any(near) {
            taken.push(k);
            kept.push(h);
        }
    }
    kept
}

/// The fit's state between sweeps.
#[derive(Clone, Debug)]
struct Model {
    planes: [PhasePlane; 2],
    /// μ, μ_X, μ_Y, B₁, E₁, F₁, B₂, E₂, F₂, η_X, η_Y.
    linear: SVector<f64, LINEAR>,
    /// The modelled harmonics and their complex amplitudes.
    harmonics: Vec<((i32, i32), Complex64)>,
    /// Each harmonic's overlap with its own conjugate under the layout weight,
    /// `Σw·e^{2ih·φ}/Σw` ([`amplitude_step`]), in the order of `harmonics`.
    overlaps: Vec<Complex64>,
    /// Tukey cut-off `c·σ`, intensity units; `None` before the first residuals.
    cutoff: Option<f64>,
    /// Harmonics tied to the dot centres (real amplitudes).
    tied: bool,
    /// Robust weight of each cell (per node of the mask); empty before the first residuals.
    cells: Vec<f64>,
    /// Tukey weight of each pixel of the box (row-major), frozen after the robust iterations:
    /// the last iterations then solve one fixed weighted least-squares problem, at the
    /// quadratic rate of Gauss–Newton (reweighting every pixel each time, as IRLS does,
    /// converges only linearly). Empty while the weights still move.
    frozen: Vec<f32>,
}

/// One pixel of the field as the sweeps see it.
struct Pixel {
    /// Normalised coordinates.
    xn: f64,
    yn: f64,
    g: f64,
    /// Layout weight `w_L`.
    layout: f64,
    /// Layout weight with the nodes' robust weights.
    w: f64,
    /// `e^{iφ_l}`.
    z: [Complex64; 2],
    /// The planes' linear lattice coordinates `φ_lin,l/2π`, periods (their node numbering):
    /// the lattice coordinates themselves unless the field has a [`Warp`].
    linear: [f64; 2],
    /// `∂u_l/∂v_m`, the lattice coordinates' derivatives along the linear ones (identity
    /// without a [`Warp`]) …
    jacobian: [[f64; 2]; 2],
    /// … and `1/D²`, `D = 1 − p·v` (1 without one).
    inverse_square: f64,
    /// Index of the nearest node (the pixel's cell) in per-node arrays, if inside the mask.
    cell: Option<usize>,
    /// Columns since the previous pixel visited in this row; 0 for the first of the row,
    /// [`RESEED`] where the bank is to be seeded afresh within the row (a warped field).
    advance: usize,
    /// `e^{i(φ_l(x + 1) − φ_l(x))}`, the phase step to the next column …
    step: [Complex64; 2],
    /// … and how it turns per column, `e^{iΔ²φ_l}` (1 on a field without a [`Warp`]).
    chirp: [Complex64; 2],
    /// The field has a [`Warp`].
    warped: bool,
    /// Row-major index of the pixel in the field's box.
    index: usize,
}

/// Lanes of the harmonic bank's vectors: 16 single-precision numbers, two AVX2 registers, so
/// that the sums of [`HarmonicBank::evaluate`] run as two independent chains (one chain waits
/// on the FMA latency). Single precision halves the work of the sweep's costliest part; its
/// rounding (~1e-7 of the harmonics' amplitudes, ~1e-5 rad of phase drift over a row of
/// advances) is far below the noise, and the demodulation sums go to double precision at the
/// end of every row.
const LANES: usize = 16;
/// Longest gap, in columns, that the harmonic bank advances across; beyond it the bank is
/// seeded afresh (about the cost of this many advances).
const MAX_ADVANCE: usize = 8;
/// [`Pixel::advance`] of a pixel where the bank is seeded afresh within a row: a warped
/// field's steps are recomputed exactly every [`WARP_EXACT_COLUMNS`] columns.
const RESEED: usize = usize::MAX;
/// Columns over which a warped field's phases are advanced by their quadratic recurrence
/// (step and chirp, [`FieldPixels`]) before they are computed exactly again: the cubic term
/// of `u = v/(1 − p·v)` leaves ~3e-5 rad over them on the steepest tilts of the stress
/// suite (`p` 6e-3 per period at 30 px), far below the noise of such a fit.
const WARP_EXACT_COLUMNS: usize = 16;
/// Capacity of the harmonic bank: [`MAX_HARMONICS`] rounded up to whole [`LANES`].
const BANK: usize = MAX_HARMONICS.div_ceil(LANES) * LANES;

/// The modelled harmonics' exponentials `e^{ih·φ}` at the current pixel, advanced column by
/// column along a row (one complex product per harmonic instead of a power product), with
/// their amplitudes and demodulation sums; structure of arrays padded to whole SIMD lanes
/// (the padding has zero amplitude), so every loop runs over whole lanes and vectorises.
struct HarmonicBank {
    /// Harmonics modelled.
    n: usize,
    /// `n` rounded up to whole lanes: the loops' length.
    padded: usize,
    /// Highest order of the harmonics along either axis ([`top_order`]).
    top: usize,
    orders: [(i32, i32); BANK],
    re: Lanes,
    im: Lanes,
    step_re: [f32; BANK],
    step_im: [f32; BANK],
    amp_re: Lanes,
    amp_im: Lanes,
    /// `h_l·A_h` (re, im) for the slopes along `φ₁` and `φ₂`.
    slope1_re: Lanes,
    slope1_im: Lanes,
    slope2_re: Lanes,
    slope2_im: Lanes,
    /// A warped field's per-harmonic turn of the step per column, `e^{ih·Δ²φ}`
    /// ([`FieldPixels::chirp`]); `None` on a flat field, whose steps are constant.
    chirp: Option<[[f32; BANK]; 2]>,
    /// `Σ ψ·e^{−ih·φ}`: the demodulation sums.
    demodulated: RowSums,
    /// `Σ w·e^{2ih·φ}`: each harmonic's overlap with its own conjugate ([`amplitude_step`]),
    /// on the sweep that measures it ([`HarmonicBank::add_overlap`]) only.
    overlap: Option<RowSums>,
}

/// Complex sums per harmonic (re, im), kept in single precision over the current row (the
/// vectorised sweep) and in double precision over the rows before it.
struct RowSums {
    row: [[f32; BANK]; 2],
    total: [[f64; BANK]; 2],
}

impl Default for RowSums {
    fn default() -> Self {
        RowSums {
            row: [[0.0; BANK]; 2],
            total: [[0.0; BANK]; 2],
        }
    }
}

impl RowSums {
    /// Adds the current row's sums of the first `n` harmonics to the totals and clears them
    /// (the lanes up to `n` rounded up to whole [`LANES`]: all the sweep writes; a bank sized
    /// for the highest orders is cleared only as far as its harmonics reach).
    fn flush_row(&mut self, n: usize) {
        let written = (n.div_ceil(LANES) * LANES).min(BANK);
        for (total, row) in self.total.iter_mut().zip(&mut self.row) {
            for (t, r) in total[..n].iter_mut().zip(&row[..n]) {
                *t += *r as f64;
            }
            row[..written].fill(0.0);
        }
    }

    /// The totals of the first `n` harmonics as complex numbers (current row included).
    fn complex(&mut self, n: usize) -> Vec<Complex64> {
        self.flush_row(n);
        (0..n)
            .map(|k| Complex64::new(self.total[0][k], self.total[1][k]))
            .collect()
    }
}

/// Pairwise (tree) sum of the lanes: four short dependent steps, not sixteen. Each step adds
/// the upper half onto the lower one, written out at fixed widths so that each compiles to
/// vector additions (a loop over halving widths compiled to scalar code).
#[inline(always)]
fn tree_sum(v: [f32; LANES]) -> f64 {
    const _: () = assert!(LANES == 16, "tree_sum is written for 16 lanes");
    let eight: [f32; 8] = std::array::from_fn(|k| v[k] + v[k + 8]);
    let four: [f32; 4] = std::array::from_fn(|k| eight[k] + eight[k + 4]);
    let two = [four[0] + four[2], four[1] + four[3]];
    (two[0] + two[1]) as f64
}

/// A bank's values in whole lanes: indexing a chunk checks its bounds once for all its
/// lanes, and the lane loops compile to vector arithmetic with no iterator to build (zipped
/// chunk iterators were built out of line, per pixel, in the AVX2 sweep).
type Lanes = [[f32; LANES]; BANK / LANES];

/// The `k`-th value of `v`.
#[inline(always)]
fn lane_mut(v: &mut Lanes, k: usize) -> &mut f32 {
    &mut v[k / LANES][k % LANES]
}

impl HarmonicBank {
    /// The bank of `harmonics` (orders and amplitudes) for `planes`.
    fn new(harmonics: &[((i32, i32), Complex64)], planes: &[PhasePlane; 2]) -> Self {
        let zero = [0.0; BANK];
        let lanes = [[0.0; LANES]; BANK / LANES];
        let n = harmonics.len().min(MAX_HARMONICS);
        let mut bank = HarmonicBank {
            n,
            padded: n.div_ceil(LANES) * LANES,
            top: 1,
            orders: [(0, 0); BANK],
            re: lanes,
            im: lanes,
            step_re: zero,
            step_im: zero,
            amp_re: lanes,
            amp_im: lanes,
            slope1_re: lanes,
            slope1_im: lanes,
            slope2_re: lanes,
            slope2_im: lanes,
            chirp: None,
            demodulated: RowSums::default(),
            overlap: None,
        };
        for (k, &((h1, h2), a)) in harmonics.iter().take(n).enumerate() {
            let step =
                Complex64::from_polar(1.0, h1 as f64 * planes[0].a + h2 as f64 * planes[1].a);
            let (h1f, h2f) = (h1 as f64, h2 as f64);
            bank.orders[k] = (h1, h2);
            bank.step_re[k] = step.re as f32;
            bank.step_im[k] = step.im as f32;
            *lane_mut(&mut bank.amp_re, k) = a.re as f32;
            *lane_mut(&mut bank.amp_im, k) = a.im as f32;
            *lane_mut(&mut bank.slope1_re, k) = (h1f * a.re) as f32;
            *lane_mut(&mut bank.slope1_im, k) = (h1f * a.im) as f32;
            *lane_mut(&mut bank.slope2_re, k) = (h2f * a.re) as f32;
            *lane_mut(&mut bank.slope2_im, k) = (h2f * a.im) as f32;
        }
        bank.top = top_order(&bank.orders[..n]);
        bank
    }

    /// Exponentials at a pixel whose `e^{iφ_l}` is `z` (first pixel of a row, computed in
    /// double precision); the previous row's demodulation sums are added to the totals.
    #[inline(always)]
    fn seed(&mut self, z: &[Complex64; 2]) {
        self.flush_row();
        exponentials(
            &self.orders[..self.n],
            self.top,
            z,
            self.re.as_flattened_mut(),
            self.im.as_flattened_mut(),
        );
    }

    /// A warped field's bank at pixel `p`: its exponentials, their steps to the next column
    /// and the steps' turn per column, computed afresh.
    #[inline(always)]
    fn seed_warped(&mut self, p: &Pixel) {
        let orders = &self.orders[..self.n];
        let top = self.top;
        let (re, im) = (self.re.as_flattened_mut(), self.im.as_flattened_mut());
        exponentials(orders, top, &p.z, re, im);
        exponentials(orders, top, &p.step, &mut self.step_re, &mut self.step_im);
        let [cr, ci] = self.chirp.get_or_insert([[0.0; BANK]; 2]);
        exponentials(orders, top, &p.chirp, cr, ci);
    }

    /// Exponentials at pixel `p`: advanced from the previous pixel of its row when it is a
    /// few columns away, computed afresh at the start of a row and across a longer gap of
    /// unweighted pixels (a finder, missing dots), where advancing column by column would cost
    /// more than the powers.
    #[inline(always)]
    fn move_to(&mut self, p: &Pixel) {
        match (p.advance, p.warped) {
            (columns @ 1..=MAX_ADVANCE, false) => self.advance(columns),
            (columns @ 1..=MAX_ADVANCE, true) => self.advance_warped(columns),
            (0, true) => {
                self.flush_row();
                self.seed_warped(p);
            }
            (_, true) => self.seed_warped(p),
            (_, false) => self.seed(&p.z),
        }
    }

    /// Adds the current row's sums to the totals and clears them.
    fn flush_row(&mut self) {
        self.demodulated.flush_row(self.n);
        if let Some(overlap) = &mut self.overlap {
            overlap.flush_row(self.n);
        }
    }

    /// Exponentials `columns` pixels further along the row.
    #[inline(always)]
    fn advance(&mut self, columns: usize) {
        let m = self.padded;
        for _ in 0..columns {
            let re = &mut self.re.as_flattened_mut()[..m];
            let im = &mut self.im.as_flattened_mut()[..m];
            let (sr, si) = (&self.step_re[..m], &self.step_im[..m]);
            for k in 0..m {
                let (r, i) = (re[k], im[k]);
                re[k] = r * sr[k] - i * si[k];
                im[k] = r * si[k] + i * sr[k];
            }
        }
    }

    /// A warped field's exponentials `columns` pixels further along the row: each column
    /// multiplies them by their step and turns the step by its chirp.
    #[inline(always)]
    fn advance_warped(&mut self, columns: usize) {
        let m = self.padded;
        let Some([cr, ci]) = &self.chirp else {
            return;
        };
        for _ in 0..columns {
            let re = &mut self.re.as_flattened_mut()[..m];
            let im = &mut self.im.as_flattened_mut()[..m];
            let (sr, si) = (&mut self.step_re[..m], &mut self.step_im[..m]);
            let (cr, ci) = (&cr[..m], &ci[..m]);
            for k in 0..m {
                let (r, i) = (re[k], im[k]);
                re[k] = r * sr[k] - i * si[k];
                im[k] = r * si[k] + i * sr[k];
                let (a, b) = (sr[k], si[k]);
                sr[k] = a * cr[k] - b * ci[k];
                si[k] = a * ci[k] + b * cr[k];
            }
        }
    }

    /// `H = Σ_h Re(A_h e^{ih·φ})` and its derivatives along `φ₁`, `φ₂`
    /// (`d/dφ_l Re(A e^{ih·φ}) = −h_l·Im(A e^{ih·φ})`).
    #[inline(always)]
    fn evaluate(&self) -> (f64, [f64; 2]) {
        // One partial sum per lane (lane-wise arithmetic: whole vector registers).
        let (mut value, mut s1, mut s2) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        for c in 0..self.padded / LANES {
            let (er, ei) = (&self.re[c], &self.im[c]);
            let (ar, ai) = (&self.amp_re[c], &self.amp_im[c]);
            let (b1r, b1i) = (&self.slope1_re[c], &self.slope1_im[c]);
            let (b2r, b2i) = (&self.slope2_re[c], &self.slope2_im[c]);
            for lane in 0..LANES {
                value[lane] += ar[lane] * er[lane] - ai[lane] * ei[lane];
                s1[lane] -= b1r[lane] * ei[lane] + b1i[lane] * er[lane];
                s2[lane] -= b2r[lane] * ei[lane] + b2i[lane] * er[lane];
            }
        }
        (tree_sum(value), [tree_sum(s1), tree_sum(s2)])
    }

    /// Adds `ψ·e^{−ih·φ}` to the demodulation sums.
    #[inline(always)]
    fn demodulate(&mut self, psi: f64) {
        let m = self.padded;
        let psi = psi as f32;
        let [sr, si] = &mut self.demodulated.row;
        let (sr, si) = (&mut sr[..m], &mut si[..m]);
        let (re, im) = (&self.re.as_flattened()[..m], &self.im.as_flattened()[..m]);
        for k in 0..m {
            sr[k] += psi * re[k];
            si[k] -= psi * im[k];
        }
    }

    /// Adds `w·e^{2ih·φ}` to the overlap sums.
    #[inline(always)]
    fn add_overlap(&mut self, w: f64) {
        let m = self.padded;
        let w = w as f32;
        let [or, oi] = &mut self.overlap.get_or_insert_with(RowSums::default).row;
        let (or, oi) = (&mut or[..m], &mut oi[..m]);
        let (re, im) = (&self.re.as_flattened()[..m], &self.im.as_flattened()[..m]);
        for k in 0..m {
            or[k] += w * (re[k] * re[k] - im[k] * im[k]);
            oi[k] += w * (2.0 * re[k] * im[k]);
        }
    }

    /// The overlap sums as complex numbers, in the harmonics' order (zero where none was
    /// added).
    fn overlaps(&mut self) -> Vec<Complex64> {
        let n = self.n;
        self.overlap.get_or_insert_with(RowSums::default).complex(n)
    }

    /// The demodulation sums as complex numbers, in the harmonics' order.
    fn sums(&mut self) -> Vec<Complex64> {
        self.demodulated.complex(self.n)
    }
}

impl Model {
    /// Applies a step's harmonic corrections. Tied harmonics keep real amplitudes (the
    /// imaginary part of the correction is the offset error that the step's `γ` has taken
    /// already). Free ones take the whole correction, measured at the demodulation's centroid,
    /// and are turned back by the planes' move there, `A_h ← (A_h + d_h)·e^{−ih·δφ̄}`: the
    /// step does not move them, as the offsets' equations (fundamentals only) assume. The
    /// overlaps `Σw·e^{2ih·φ}/Σw` turn the other way, twice as fast.
    fn update_harmonics(&mut self, step: &Step) {
        let [cx, cy] = step.centroid;
        let moved = [0, 1]
            .map(|l| step.delta[3 * l] * cx + step.delta[3 * l + 1] * cy + step.delta[3 * l + 2]);
        let harmonics = self.harmonics.iter_mut().zip(&mut self.overlaps);
        for ((((h1, h2), a), overlap), d) in harmonics.zip(&step.harmonics) {
            let turn = *h1 as f64 * moved[0] + *h2 as f64 * moved[1];
            *a = if self.tied {
                Complex64::new((*a + d).re, 0.0)
            } else {
                (*a + d) * Complex64::from_polar(1.0, -turn)
            };
            // `e^{2ih·φ}` turns with the planes.
            *overlap *= Complex64::from_polar(1.0, 2.0 * turn);
        }
    }

    /// Ties the free harmonics to dot centres `shift` (radians per plane) from the planes'
    /// current ones: the offsets move there, and each harmonic keeps the real part of its
    /// amplitude seen from there, `Re(A_h·e^{−ih·δ})` (its overlap turns by `e^{2ih·δ}`).
    fn tie(&mut self, shift: [f64; 2]) {
        for (p, d) in self.planes.iter_mut().zip(shift) {
            p.c += d;
        }
        for (((h1, h2), a), overlap) in self.harmonics.iter_mut().zip(&mut self.overlaps) {
            let turn = *h1 as f64 * shift[0] + *h2 as f64 * shift[1];
            *a = Complex64::new((*a * Complex64::from_polar(1.0, -turn)).re, 0.0);
            *overlap *= Complex64::from_polar(1.0, 2.0 * turn);
        }
        self.tied = true;
    }

    /// The harmonics' illumination gain `1 + η_X·X + η_Y·Y` at a pixel.
    fn gain(&self, p: &Pixel) -> f64 {
        1.0 + self.linear[9] * p.xn + self.linear[10] * p.yn
    }

    /// Background plus fundamentals at a pixel (the linear part of the model).
    fn linear_at(&self, p: &Pixel) -> f64 {
        let m = &self.linear;
        let mut v = m[0] + m[1] * p.xn + m[2] * p.yn;
        for l in 0..2 {
            v += (m[3 + 3 * l] + m[4 + 3 * l] * p.xn + m[5 + 3 * l] * p.yn) * p.z[l].re;
        }
        v
    }

    /// Tukey weight `(1 − (r/c)²)²` of a pixel's residual `r` (1 before the first
    /// residuals).
    fn robust(&self, r: f64) -> f64 {
        match self.cutoff {
            None => 1.0,
            Some(c) => {
                let t = r / c;
                if t.abs() < 1.0 {
                    let q = 1.0 - t * t;
                    q * q
                } else {
                    0.0
                }
            }
        }
    }

    /// Mean fundamental amplitude.
    fn contrast(&self) -> f64 {
        0.5 * (self.linear[3].abs() + self.linear[6].abs())
    }
}

/// `e^{ikφ_l}` for `k = 0..=MAX_ORDER`, per lobe.
type Powers = [[Complex64; MAX_ORDER + 1]; 2];

/// The powers up to order `top` (those above it are left at 1: no harmonic asks for them).
fn powers(z: &[Complex64; 2], top: usize) -> Powers {
    let mut p = [[Complex64::new(1.0, 0.0); MAX_ORDER + 1]; 2];
    for (pl, zl) in p.iter_mut().zip(z) {
        for k in 1..=top.min(MAX_ORDER) {
            pl[k] = pl[k - 1] * zl;
        }
    }
    p
}

/// The highest order along either axis among `orders`.
fn top_order(orders: &[(i32, i32)]) -> usize {
    orders
        .iter()
        .map(|&(h1, h2)| h1.unsigned_abs().max(h2.unsigned_abs()) as usize)
        .max()
        .unwrap_or(1)
}

/// `e^{ih·φ}` of each harmonic of `orders`, `z` being `e^{iφ_l}`, into `(re, im)`; `top`:
/// at least [`top_order`] of `orders`.
#[inline(always)]
fn exponentials(
    orders: &[(i32, i32)],
    top: usize,
    z: &[Complex64; 2],
    re: &mut [f32],
    im: &mut [f32],
) {
    let powers = powers(z, top);
    for ((&(h1, h2), r), i) in orders.iter().zip(re.iter_mut()).zip(im.iter_mut()) {
        let e = harmonic(&powers, h1, h2);
        *r = e.re as f32;
        *i = e.im as f32;
    }
}

/// `e^{i(h₁φ₁ + h₂φ₂)}` from the powers (`|h_l| ≤ MAX_ORDER`).
fn harmonic(p: &Powers, h1: i32, h2: i32) -> Complex64 {
    let pick = |l: usize, h: i32| {
        let v = p[l][h.unsigned_abs() as usize];
        if h < 0 {
            v.conj()
        } else {
            v
        }
    };
    pick(0, h1) * pick(1, h2)
}

/// The field's pixel box: pixels within one period of the regular nodes, clipped to the image
/// ([`FieldBox::new`]: its bounds, coordinates normalised by its half-size; [`first_model`]
/// centres them on the field's layout weight).
struct FieldBox {
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
    /// Image-frame origin `(C div 2, R div 2)`.
    center: (f64, f64),
    /// Normalisation `(x₀, y₀, s)`.
    frame: (f64, f64, f64),
    /// Clearance factor of each pixel of the box (row-major; [`NodeMask::clearance`]), set
    /// once per fit on the start planes by [`FieldBox::set_clearance`]: the fit moves the
    /// planes by a small fraction of a cell, and the distance search is the costliest part of
    /// a pixel's weight.
    clearance: Vec<f32>,
    /// Per row of the box, the columns from the first to the last pixel of non-zero clearance
    /// (the sweeps skip the rest: the corners of a turned marker's box, the image beyond it).
    spans: Vec<std::ops::Range<usize>>,
    /// The perspective in the phase model, if any.
    warp: Option<Warp>,
}

/// A perspective built into the phase model: the second pass of a tilted field's fit
/// (docs/design.md#tilt-centre). Lattice coordinates `u = c + v/(1 − p·v)`, `v = u_lin − c`
/// the planes' linear coordinates about the tilt centre `c`: the planes are the tangent planes
/// of the lattice at `c`.
#[derive(Clone, Copy, Debug)]
struct Warp {
    /// `p`, per period.
    perspective: Vector2<f64>,
    /// `c`, periods, in the planes' numbering.
    centre: [f64; 2],
}

impl Warp {
    /// Lattice coordinates of the linear ones `lin`, with `∂u_l/∂v_m = δ_lm/D + v_l·p_m/D²`
    /// and `1/D²`; `None` beyond the horizon's neighbourhood (`D ≤ 1/2`, a perspective no
    /// microscope gives over a marker: `p·v` is a few 10⁻² at 25° before a short lens).
    #[inline(always)]
    fn apply(&self, lin: [f64; 2]) -> Option<([f64; 2], [[f64; 2]; 2], f64)> {
        let (p, c) = (self.perspective, self.centre);
        let v = [lin[0] - c[0], lin[1] - c[1]];
        let d = 1.0 - (p.x * v[0] + p.y * v[1]);
        // NaN fails too.
        if d.is_nan() || d <= 0.5 {
            return None;
        }
        let inverse = 1.0 / d;
        let square = inverse * inverse;
        let u = [c[0] + v[0] * inverse, c[1] + v[1] * inverse];
        let jacobian = [
            [inverse + v[0] * p.x * square, v[0] * p.y * square],
            [v[1] * p.x * square, inverse + v[1] * p.y * square],
        ];
        Some((u, jacobian, square))
    }
}

impl FieldBox {
    fn new(image: &GreyImage, planes: &[PhasePlane; 2], mask: &NodeMask) -> Option<Self> {
        let m = nalgebra::Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
        let inverse = m.try_inverse()?;
        let (mut lo, mut hi) = (
            Vector2::repeat(f64::INFINITY),
            Vector2::repeat(f64::NEG_INFINITY),
        );
        let (a0, b0) = mask.first;
        let (a1, b1) = (a0 + mask.dims.0 as i64, b0 + mask.dims.1 as i64);
        for (k1, k2) in [(a0 - 1, b0 - 1), (a0 - 1, b1), (a1, b0 - 1), (a1, b1)] {
            let phase = Vector2::new(TAU * k1 as f64 - planes[0].c, TAU * k2 as f64 - planes[1].c);
            let p = inverse * phase;
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let (cx, cy) = image.center();
        let (cx, cy) = (cx as f64, cy as f64);
        let clip = |v: f64, n: usize| (v.max(0.0).min(n as f64)) as usize;
        if !(lo.iter().chain(hi.iter()).all(|v| v.is_finite())) {
            return None;
        }
        let cols =
            clip((lo.x + cx).floor(), image.width())..clip((hi.x + cx).ceil() + 1.0, image.width());
        let rows = clip((lo.y + cy).floor(), image.height())
            ..clip((hi.y + cy).ceil() + 1.0, image.height());
        if cols.is_empty() || rows.is_empty() {
            return None;
        }
        let s = (cols.len().max(rows.len()) as f64 / 2.0).max(1.0);
        Some(FieldBox {
            cols,
            rows,
            center: (cx, cy),
            frame: (0.0, 0.0, s),
            clearance: Vec::new(),
            spans: Vec::new(),
            warp: None,
        })
    }

    /// Fills [`FieldBox::clearance`] for `mask` at the lattice coordinates of `planes`.
    fn set_clearance(&mut self, planes: &[PhasePlane; 2], mask: &NodeMask) {
        let mut clearance = Vec::with_capacity(self.rows.len() * self.cols.len());
        let mut spans = Vec::with_capacity(self.rows.len());
        for row in self.rows.clone() {
            let y = row as f64 - self.center.1;
            let start = clearance.len();
            for col in self.cols.clone() {
                let x = col as f64 - self.center.0;
                let lin = planes.map(|p| p.at(x, y) / TAU);
                let clear = match &self.warp {
                    None => mask.clearance(lin.map(|u| 2.0 * u)),
                    Some(warp) => warp
                        .apply(lin)
                        .map_or(0.0, |(u, _, _)| mask.clearance(u.map(|u| 2.0 * u))),
                };
                clearance.push(clear as f32);
            }
            let row_values = &clearance[start..];
            let first = row_values.iter().position(|&c| c > 0.0);
            let last = row_values.iter().rposition(|&c| c > 0.0);
            spans.push(match (first, last) {
                (Some(a), Some(b)) => self.cols.start + a..self.cols.start + b + 1,
                _ => self.cols.start..self.cols.start,
            });
        }
        self.clearance = clearance;
        self.spans = spans;
    }

    /// The columns of `row` that the sweeps visit (all before [`FieldBox::set_clearance`]).
    fn span(&self, row: usize) -> std::ops::Range<usize> {
        self.spans
            .get(row - self.rows.start)
            .cloned()
            .unwrap_or(self.cols.clone())
    }

    /// The pixels of the field with a non-zero layout weight, row by row; `nodes` holds the
    /// nodes' robust weights (empty: all 1).
    fn pixels<'a>(
        &'a self,
        image: &'a GreyImage,
        planes: &[PhasePlane; 2],
        mask: &'a NodeMask,
        nodes: &'a [f64],
    ) -> FieldPixels<'a> {
        FieldPixels {
            field: self,
            pixels: image.pixels(),
            width: image.width(),
            planes: *planes,
            mask,
            weights: NodeWeights::new(mask, nodes),
            step: planes.map(|p| Complex64::from_polar(1.0, p.a)),
            half_step: planes.map(|p| Complex64::from_polar(1.0, 0.5 * p.a)),
            chirp: [Complex64::new(1.0, 0.0); 2],
            half_chirp: [Complex64::new(1.0, 0.0); 2],
            exact_at: 0,
            reseeded: false,
            half: [Complex64::default(); 2],
            row: self.rows.start,
            col: self.cols.start,
            fresh_row: true,
            z: [Complex64::default(); 2],
            last: None,
            row_end: self.cols.start,
        }
    }
}

/// Iterator over the pixels of a [`FieldBox`] (a plain loop, so that it inlines into the
/// vectorised fit; closures would not inherit its target features).
struct FieldPixels<'a> {
    field: &'a FieldBox,
    pixels: &'a [f32],
    width: usize,
    planes: [PhasePlane; 2],
    mask: &'a NodeMask,
    weights: NodeWeights,
    /// `e^{ia_l}`: one column's phase step.
    step: [Complex64; 2],
    /// `e^{ia_l/2}`.
    half_step: [Complex64; 2],
    /// A warped field's phases advance by a step that changes along the row: `step` is the
    /// one from the current column to the next, and it turns by `chirp`, `e^{iΔ²φ_l}`, per
    /// column (the second difference of the phase; `half_chirp` for the half phases). Exact
    /// values are computed every [`WARP_EXACT_COLUMNS`] columns, at `exact_at`, …
    chirp: [Complex64; 2],
    half_chirp: [Complex64; 2],
    exact_at: usize,
    /// … and the bank is seeded afresh at the next pixel visited after that.
    reseeded: bool,
    /// `e^{iφ_l/2}` at `(col, row)`: `cos πu_l` for the layout weight.
    half: [Complex64; 2],
    row: usize,
    /// Next column.
    col: usize,
    /// `z` must be computed afresh (start of a row).
    fresh_row: bool,
    /// `e^{iφ_l}` at `(col, row)`.
    z: [Complex64; 2],
    /// Last column visited in this row.
    last: Option<usize>,
    /// End of this row's span ([`FieldBox::span`]).
    row_end: usize,
}

impl FieldPixels<'_> {
    /// Sets the phases of a warped field exactly at image-frame `(x, y)` (the current column),
    /// with their step to the next column and its turn per column, from the phases at the next
    /// two columns; leaves them as they are where the warp does not reach those columns.
    #[inline(always)]
    fn set_exact(&mut self, warp: &Warp, x: f64, y: f64) {
        let phase = |dx: f64| {
            let linear = self.planes.map(|p| p.at(x + dx, y) / TAU);
            warp.apply(linear)
                .map_or([f64::NAN; 2], |(u, _, _)| u.map(|u| TAU * u))
        };
        let (p0, p1, p2) = (phase(0.0), phase(1.0), phase(2.0));
        if [p0, p1, p2].iter().flatten().any(|v| !v.is_finite()) {
            // Beyond the warp's reach ([`Warp::apply`]): tried again at the next column.
            return;
        }
        let polar = |v: [f64; 2], k: f64| v.map(|v| Complex64::from_polar(1.0, k * v));
        let step = [p1[0] - p0[0], p1[1] - p0[1]];
        let chirp = [p2[0] - 2.0 * p1[0] + p0[0], p2[1] - 2.0 * p1[1] + p0[1]];
        self.z = polar(p0, 1.0);
        self.half = polar(p0, 0.5);
        self.step = polar(step, 1.0);
        self.half_step = polar(step, 0.5);
        self.chirp = polar(chirp, 1.0);
        self.half_chirp = polar(chirp, 0.5);
        self.exact_at = self.col;
    }
}

impl Iterator for FieldPixels<'_> {
    type Item = Pixel;

    #[inline(always)]
    fn next(&mut self) -> Option<Pixel> {
        let f = self.field;
        let (x0, y0, s) = f.frame;
        loop {
            if self.row >= f.rows.end {
                return None;
            }
            if self.fresh_row {
                let span = f.span(self.row);
                if span.is_empty() {
                    self.row += 1;
                    continue;
                }
                self.fresh_row = false;
                self.last = None;
                self.col = span.start;
                self.row_end = span.end;
                let y = self.row as f64 - f.center.1;
                let x = self.col as f64 - f.center.0;
                match &f.warp {
                    None => {
                        self.z = self.planes.map(|p| Complex64::from_polar(1.0, p.at(x, y)));
                        self.half = self
                            .planes
                            .map(|p| Complex64::from_polar(1.0, 0.5 * p.at(x, y)));
                    }
                    Some(warp) => self.set_exact(warp, x, y),
                }
            }
            if let Some(warp) = &f.warp {
                if self.col >= self.exact_at + WARP_EXACT_COLUMNS {
                    let y = self.row as f64 - f.center.1;
                    self.set_exact(warp, self.col as f64 - f.center.0, y);
                    self.reseeded = true;
                }
            }
            if self.col >= self.row_end {
                self.row += 1;
                self.fresh_row = true;
                continue;
            }
            let (row, col) = (self.row, self.col);
            let x = col as f64 - f.center.0;
            let y = row as f64 - f.center.1;
            let (z, half, step) = (self.z, self.half, self.step);
            self.col += 1;
            self.z = [z[0] * self.step[0], z[1] * self.step[1]];
            self.half = [half[0] * self.half_step[0], half[1] * self.half_step[1]];
            if f.warp.is_some() {
                self.step = [self.step[0] * self.chirp[0], self.step[1] * self.chirp[1]];
                self.half_step = [
                    self.half_step[0] * self.half_chirp[0],
                    self.half_step[1] * self.half_chirp[1],
                ];
            }
            let index = (row - f.rows.start) * f.cols.len() + (col - f.cols.start);
            let clear = f.clearance.get(index).copied().unwrap_or(0.0) as f64;
            if clear <= 0.0 {
                // On a discrepant cell (a finder, a missing dot) or outside the field: no
                // weight, whatever the nodes', so theirs are not computed.
                continue;
            }
            let linear = [self.planes[0].at(x, y) / TAU, self.planes[1].at(x, y) / TAU];
            let (u, jacobian, inverse_square) = match &f.warp {
                None => (linear, [[1.0, 0.0], [0.0, 1.0]], 1.0),
                Some(warp) => match warp.apply(linear) {
                    Some(applied) => applied,
                    None => continue,
                },
            };
            let (layout, w) = self.weights.weight(u, [half[0].re, half[1].re]);
            let (layout, w) = (layout * clear, w * clear);
            let g = self
                .pixels
                .get(row * self.width + col)
                .copied()
                .unwrap_or(f32::NAN) as f64;
            if layout > 0.0 && g.is_finite() {
                let advance = match self.last {
                    None => 0,
                    Some(_) if self.reseeded => RESEED,
                    Some(l) => col - l,
                };
                self.reseeded = false;
                self.last = Some(col);
                return Some(Pixel {
                    xn: (x - x0) / s,
                    yn: (y - y0) / s,
                    g,
                    layout,
                    w,
                    z,
                    step,
                    chirp: self.chirp,
                    warped: f.warp.is_some(),
                    linear,
                    jacobian,
                    inverse_square,
                    cell: self.mask.index(u[0].round() as i64, u[1].round() as i64),
                    advance,
                    index,
                });
            }
        }
    }
}

/// Refines `start` (image frame, docs/design.md#frames) on every pixel around the drawn dots
/// of `mask`, robustly (see the module doc). The covariance counts the white noise alone:
/// the smaller of the residual's scale and the noise measured apart from the model (lattice
/// second differences, `phase::noise`). `None` when the field has fewer than 16 drawn dots,
/// the normal equations are singular, the iterations do not converge, or the planes would
/// move by half a period somewhere in the field (the start was not this grid's).
pub fn fit_dot_field(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
) -> Option<FieldFit> {
    fit_dot_field_against(image, start, mask, None, None)
}

/// [`fit_dot_field`], given up (`None`) on its first sweep with settled robust weights when it
/// cannot beat `rival`: no spoiled cell, and a predicted σ ([`FieldFit::beats`]) already ten
/// times the window's. The fits it returns are those of [`fit_dot_field`] to the
/// last digit; where it gives up, the fit would have lost to the window anyway (or failed).
///
/// With `tilt` (the marker centre in lattice coordinates, periods, in the numbering of
/// `start`, and the coarse step's perspective), the fit also measures the field's tilt about
/// that centre and, where it is significant, moves the planes to where the tilt leaves them at
/// the centre; a steep tilt is fitted again with the tilt in the phase model, starting from
/// the coarse perspective when there is one ([`FieldFit::perspective`],
/// docs/design.md#tilt-centre).
pub fn fit_dot_field_against(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    rival: Option<Rival>,
    tilt: Option<TiltStart>,
) -> Option<FieldFit> {
    fit_field(image, start, mask, rival, tilt, None)
}

/// [`fit_dot_field_against`] for the next frame of a sequence, from `previous`, the last
/// frame's fit of the same marker and mask (docs/design.md#tracked-field-fit): the harmonics,
/// illumination terms, robust scale, cells' weights and carried tilt start where they
/// converged, so that the fit skips its start sweep and its first robust iterations and
/// settles in three sweeps instead of six. Where the first sweep shows a field that no
/// longer looks like the last one (the residual grown, weight newly rejected), the weights
/// are judged afresh as a cold fit judges them; where the warm fit fails, the cold fit runs.
/// The result is a fit of this frame alone: only the path to it is shorter.
pub fn fit_dot_field_tracked(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    rival: Option<Rival>,
    tilt: Option<TiltStart>,
    previous: &FieldFit,
) -> Option<FieldFit> {
    fit_field(image, start, mask, rival, tilt, Some(&previous.warm)).or_else(|| {
        log::debug!("whole-field fit: the warm start failed, fitted cold");
        fit_field(image, start, mask, rival, tilt, None)
    })
}

/// [`fit_dot_field_against`], warm-started from `warm` when given.
fn fit_field(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    rival: Option<Rival>,
    tilt: Option<TiltStart>,
    warm: Option<&WarmModel>,
) -> Option<FieldFit> {
    if mask.count() < MIN_NODES {
        return None;
    }
    let window = start;
    // A tracked fit starts where the last frame's fit put the planes, moved as the window's
    // moved: the window's own offset from the fit (the dots' asymmetry, model error seen
    // through its band-pass, 0.1 rad on a real stamp) cancels, its noise stays.
    let start = match warm {
        Some(w) => [0, 1].map(|l| {
            let d = &w.correction[l];
            PhasePlane {
                a: start[l].a + d.a,
                b: start[l].b + d.b,
                c: start[l].c + d.c,
            }
        }),
        None => start,
    };
    // The field's box, binned while the period allows (docs/design.md#field-fit).
    let field = FieldBox::new(image, &start, mask)?;
    let period = start
        .iter()
        .map(|p| p.pixel_period())
        .fold(f64::INFINITY, f64::min);
    let factor = if period / 2.0 >= MIN_BINNED_PERIOD {
        2
    } else {
        1
    };
    let f = factor as f64;
    // Bins start on even pixels of the image, not at the field's edge, and lie symmetrically
    // about the image's centre ([`crate::decimate::centre_offset`]): a half or quarter turn
    // or a flip maps bins onto bins, and the fit of the turned image sees the same binned
    // pixels (bins placed from the field's box would move the result within its noise).
    let aligned = |range: &std::ops::Range<usize>| {
        let start = range.start / factor * factor;
        start..start + (range.end - start) / factor * factor
    };
    let (cols, rows) = (aligned(&field.cols), aligned(&field.rows));
    let (left, top) = (cols.start, rows.start);
    // The rounding to the input's levels, per input pixel.
    let rounding =
        quantisation_variance_in(image.pixels(), image.width(), rows.clone(), cols.clone());
    // `centre`: where the sub-image's pixel (0, 0) sits from `(left, top)`, input pixels.
    let (sub, rounding, sampling, centre) = if factor == 2 {
        // A box average would fold the harmonics above its Nyquist frequency onto the
        // modelled ones, exactly so along the pixel axes: a bias locked to the pixel grid
        // (docs/design.md#anti-aliased-binning).
        use crate::decimate::{centre_offset, decimate_2x2, noise_gain};
        let gains = [noise_gain(image.width()), noise_gain(image.height())];
        let sampling = Sampling {
            unaliased: true,
            noise_colour: (0.5 / gains[0]) * (0.5 / gains[1]),
        };
        let centre = [centre_offset(image.width()), centre_offset(image.height())];
        let sub = decimate_2x2(image, cols, rows)?;
        (sub, rounding * gains[0] * gains[1], sampling, centre)
    } else {
        let sub = image.crop(left, top, cols.len(), rows.len()).ok()?;
        (sub, rounding, Sampling::DIRECT, [0.0; 2])
    };
    // Image-frame x of sub-image pixel i (frame x_s = i − w_s div 2): x = f·x_s + o.
    let (icx, icy) = image.center();
    let offset = [
        f * (sub.width() / 2) as f64 + left as f64 + centre[0] - icx as f64,
        f * (sub.height() / 2) as f64 + top as f64 + centre[1] - icy as f64,
    ];
    let to_sub = |p: &PhasePlane| PhasePlane {
        a: f * p.a,
        b: f * p.b,
        c: p.c + p.a * offset[0] + p.b * offset[1],
    };
    let start_sub = start.map(|p| to_sub(&p));
    // White noise measured apart from the model (lattice second differences): where the
    // model stops short of the dots' detail (sharp dots many pixels wide), the residual is
    // static model error, which does not scatter the result from frame to frame.
    // On a steeply tilted field, read only where the lattice still matches the planes (near
    // the tilt's centre): the dots' edges elsewhere would read as noise and hide the tilt.
    let lattice_tilt = tilt.map(|t| LatticeTilt {
        centre: t.centre,
        perspective: [t.perspective.x, t.perspective.y],
    });
    let white = with_plan(sub.height(), sub.width(), |plan| {
        tilted_white_noise_variance(sub.pixels(), &start_sub, plan, lattice_tilt)
    })
    .map(|v| v.max(rounding));
    // The rival's point in the (binned) sub-image frame.
    let rival = rival.map(|r| Rival {
        at: ((r.at.0 - offset[0]) / f, (r.at.1 - offset[1]) / f),
        ..r
    });
    let goal = Goal {
        white,
        rival,
        tilt_centre: tilt.map(|t| t.centre),
        prior: tilt.map_or(Vector2::zeros(), |t| t.perspective),
        sampling,
    };
    let warm = match warm {
        Some(w) => Some(w.in_sub_frame(factor, offset)?),
        None => None,
    };
    let mut fit = fit_dot_field_dispatch(&sub, start_sub, mask, goal, warm.as_ref())?;
    let to_image = |p: PhasePlane| {
        let (a, b) = (p.a / f, p.b / f);
        PhasePlane {
            a,
            b,
            c: p.c - a * offset[0] - b * offset[1],
        }
    };
    fit.planes = fit.planes.map(to_image);
    fit.start = window;
    let (x0, y0, s) = fit.frame;
    fit.frame = (f * x0 + offset[0], f * y0 + offset[1], f * s);
    let converged = fit.warm.model.planes.map(to_image);
    fit.warm.model.planes = converged;
    fit.warm.correction = [0, 1].map(|l| PhasePlane {
        a: converged[l].a - window[l].a,
        b: converged[l].b - window[l].b,
        c: converged[l].c - window[l].c,
    });
    let nodes = mask.centroid_at(&fit.planes)?;
    fit.warm.frame = (fit.frame.0 - nodes.x, fit.frame.1 - nodes.y, fit.frame.2);
    fit.warm.factor = factor;
    Some(fit)
}

/// [`fit_dot_field`] on an image (the field's box, maybe binned), vectorised where the CPU
/// allows.
fn fit_dot_field_dispatch(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: Goal,
    warm: Option<&WarmModel>,
) -> Option<FieldFit> {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { fit_dot_field_avx2(image, start, mask, goal, warm) };
        }
    }
    fit_dot_field_generic(image, start, mask, goal, warm)
}

/// [`fit_dot_field`] compiled for AVX2 and FMA (the same arithmetic on wider vectors).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn fit_dot_field_avx2(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: Goal,
    warm: Option<&WarmModel>,
) -> Option<FieldFit> {
    fit_dot_field_generic(image, start, mask, goal, warm)
}

#[inline(always)]
fn fit_dot_field_generic(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: Goal,
    warm: Option<&WarmModel>,
) -> Option<FieldFit> {
    if let Some(warm) = warm {
        return fit_warm(image, start, mask, &goal, warm);
    }
    let flat = fit_pass(image, start, mask, &goal, None, None);
    // A significant tilt whose curvature the flat phase model leaves in the residual above
    // the noise has also shaped the robust weights and the layout's clearance (both judged on
    // the flat lattice, up to a few tenths of a period off at the field's edge on steep
    // tilts), and the one linear step that takes it is short: the field is fitted again with
    // the tilt taken in its phase model, from the planes it left, and each further pass
    // measures what is left of the tilt (docs/design.md#tilt-centre).
    let Some(centre) = goal.tilt_centre else {
        return flat.map(|(fit, _)| fit);
    };
    let no_prior = goal.prior == Vector2::zeros();
    let (mut fit, mut misfit, mut taken) = match flat {
        Some((fit, misfit)) => (fit, misfit, Vector2::zeros()),
        // A flat fit that a steep tilt's curvature threw off may converge with the coarse
        // step's tilt in its phase.
        None if !no_prior => {
            let warp = Warp {
                perspective: goal.prior,
                centre,
            };
            let (fit, misfit) = fit_pass(image, start, mask, &goal, Some(warp), None)?;
            (fit, misfit, goal.prior)
        }
        None => return None,
    };
    log::trace!(
        "whole-field fit, first pass: tilt {:?} at weight {:.3}, its misfit {misfit:.2} of the \
         noise",
        fit.perspective,
        fit.tilt_weight
    );
    for pass in 2..=MAX_PASSES {
        let left = match fit.perspective {
            // The coarse step's whole tilt, where it measured one, rather than the flat
            // fit's one linear step, which a steep tilt's curvature cuts short.
            Some(_) if taken == Vector2::zeros() && !no_prior && misfit > 1.0 => goal.prior,
            Some(_) if fit.tilt_weight > 0.0 && misfit > 1.0 => fit.tilt_left(),
            _ => break,
        };
        let warp = Warp {
            perspective: taken + left,
            centre,
        };
        let Some((mut warped, m)) = fit_pass(image, fit.planes, mask, &goal, Some(warp), None)
        else {
            break;
        };
        log::debug!(
            "whole-field fit, pass {pass}, with the tilt ({:.2e}, {:.2e}) in its phase: \
             ({:.2e}, {:.2e}) left, misfit {m:.1}",
            warp.perspective.x,
            warp.perspective.y,
            warped.tilt_left().x,
            warped.tilt_left().y,
        );
        taken = warp.perspective;
        warped.iterations += fit.iterations;
        misfit = m;
        fit = warped;
    }
    if taken != Vector2::zeros() {
        let left = fit.tilt_left();
        fit.perspective = Some(taken + left);
        fit.tilt_weight = 1.0;
    }
    Some(fit)
}

/// Most passes of a tilted field's fit ([`fit_dot_field_generic`]).
const MAX_PASSES: usize = 8;

/// The tracked fit (docs/design.md#tracked-field-fit): one pass from `warm`, with the tilt
/// that the last frame's fit carried in its phase model; `None` (the caller fits cold) when
/// that pass fails, or leaves more tilt than the noise (the tilt changed: the cold passes
/// measure it afresh).
#[inline(always)]
fn fit_warm(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: &Goal,
    warm: &WarmModel,
) -> Option<FieldFit> {
    let warp = match goal.tilt_centre {
        Some(centre) if warm.taken != Vector2::zeros() => Some(Warp {
            perspective: warm.taken,
            centre,
        }),
        _ => None,
    };
    let (mut fit, misfit) = fit_pass(image, start, mask, goal, warp, Some(warm))?;
    if goal.tilt_centre.is_some() && fit.perspective.is_some() && misfit > 1.0 {
        log::debug!("whole-field fit: the tilt moved ({misfit:.1} of the noise left), fit cold");
        return None;
    }
    if let Some(warp) = warp {
        fit.perspective = Some(warp.perspective + fit.tilt_left());
        fit.tilt_weight = 1.0;
    }
    Some(fit)
}

/// One pass of the whole-field fit from `start`, with `warp` in its phase model if given and
/// from the last frame's model `warm` if given: the fit, and the mean square residual its
/// tilt explains over the white noise's variance.
#[inline(always)]
fn fit_pass(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: &Goal,
    warp: Option<Warp>,
    warm: Option<&WarmModel>,
) -> Option<(FieldFit, f64)> {
    let mut field = FieldBox::new(image, &start, mask)?;
    field.warp = warp;
    let mut model = match warm {
        // The start sweep measures the harmonics and centres the field: the warm model has
        // both (the centre moved with the lattice).
        Some(warm) => {
            let (model, (x0, y0)) = warm.moved_to(&start, field.frame.2, mask)?;
            field.frame = (x0, y0, field.frame.2);
            model
        }
        None => {
            field.set_clearance(&start, mask);
            first_model(image, &mut field, mask, start, goal.sampling.unaliased)?
        }
    };
    let wider = mask.with_clearance_for_blur(&model);
    if warm.is_some() || wider.is_some() {
        field.set_clearance(&start, wider.as_ref().unwrap_or(mask));
    }
    let mask = wider.as_ref().unwrap_or(mask);
    let mut run = Run {
        warm,
        ..Run::default()
    };
    // Free harmonic phases first: the offsets follow the fundamentals alone, whatever the
    // dots' shape. Then, where the harmonics' phases show point-symmetric dots, the harmonics
    // are tied to the dot centres and inform the offsets too (module doc). A free stage still
    // settling at the iteration limit (aliased harmonics on a 4-px grid, which their imaginary
    // parts couple more than real ones) is judged as it stands: tied, it may settle. A warm
    // model tied already goes on tied (the dots' shape does not change between frames).
    let (mut step, free_settled) = match converge(image, &field, mask, &mut model, goal, &mut run) {
        Ok(step) => (step, true),
        Err(Stall::AtLimit(step)) if !model.tied => (*step, false),
        Err(_) => return None,
    };
    let shift = if model.tied {
        None
    } else {
        symmetric_shift(&model, &step)
    };
    match shift {
        Some(shift) => {
            let mut tied = model.clone();
            tied.tie(shift);
            // Not a closure: it would be compiled apart from the AVX2 caller, without its
            // target features.
            let settled = match run.add_shift(shift.map(f64::abs)) {
                Some(()) => converge(image, &field, mask, &mut tied, goal, &mut run),
                None => Err(Stall::Failed),
            };
            match settled {
                Ok(tied_step) => (model, step) = (tied, tied_step),
                // A tied fit that does not settle leaves the free one standing, if it settled.
                Err(_) if free_settled => {}
                Err(_) => return None,
            }
        }
        None if free_settled => {}
        None => return None,
    }
    // The planes the sweeps converged to, where the next frame's sweeps will converge.
    let converged = model.planes;
    // The planes as the tilt leaves them at the centre.
    if let Some(tilt) = &step.tilt {
        let shift = tilt.planes_shift();
        for (l, plane) in model.planes.iter_mut().enumerate() {
            let d = [shift[3 * l], shift[3 * l + 1], shift[3 * l + 2]];
            correct_plane(plane, d, field.frame);
        }
    }
    let (perspective, tilt_weight) = step
        .tilt
        .map_or((None, 0.0), |t| (Some(t.perspective), t.weight));
    let fit = FieldFit {
        perspective,
        tilt_weight,
        start,
        planes: model.planes,
        amplitudes: [model.linear[3].abs(), model.linear[6].abs()],
        residual_std: step.residual_std,
        inlier_fraction: step.inlier_fraction,
        spoiled_cells: spoiled_cells(&model.cells, &step.cells),
        pixels: step.pixels,
        iterations: run.iterations,
        harmonics: model.harmonics.len(),
        harmonics_tied: model.tied,
        covariance: step.covariance,
        model_error_ratio: step.model_error_ratio,
        frame: field.frame,
        warm: Box::new(WarmModel {
            model: Model {
                frozen: Vec::new(),
                planes: converged,
                ..model
            },
            frame: field.frame,
            taken: field.warp.map_or(Vector2::zeros(), |w| w.perspective),
            correction: [PhasePlane {
                a: 0.0,
                b: 0.0,
                c: 0.0,
            }; 2],
            factor: 1,
            residual_std: step.residual_std,
            inlier_fraction: step.inlier_fraction,
        }),
    };
    Some((fit, step.tilt_misfit))
}

/// What a fit works against: the white noise measured apart from the model (intensity
/// variance, see [`iterate`]) and the window fit it must beat, if any.
struct Goal {
    white: Option<f64>,
    rival: Option<Rival>,
    /// Lattice coordinates of the marker centre, periods (the planes' numbering), when the fit
    /// is to measure the field's tilt about it ([`Tilt`]).
    tilt_centre: Option<[f64; 2]>,
    /// The perspective the coarse step measured ([`TiltStart::perspective`]).
    prior: Vector2<f64>,
    /// How the fitted image was sampled from the input.
    sampling: Sampling,
}

/// Where a marker's whole-field fit measures the field's tilt ([`fit_dot_field_against`]),
/// and the tilt the coarse step saw.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TiltStart {
    /// Lattice coordinates of the marker centre, periods, in the numbering of the start
    /// planes.
    pub centre: [f64; 2],
    /// The perspective `p` per period that the coarse step measured about `centre` (lattice
    /// coordinates `u = v/(1 − p·v)`, `v` linear in the image; docs/design.md#tilt-centre),
    /// zero when it has none. A fit whose flat first pass leaves a tilt it cannot follow
    /// starts its second pass from it rather than from its own one-step estimate.
    pub perspective: Vector2<f64>,
}

/// How the fitted image was sampled from the input (docs/design.md#anti-aliased-binning).
#[derive(Clone, Copy)]
struct Sampling {
    /// Binned through the anti-aliasing filter: nothing folds, and harmonics beyond the
    /// Nyquist square are not modelled ([`resolvable_harmonics`]).
    unaliased: bool,
    /// The noise variance at the planes' frequencies over the image's total noise variance,
    /// which the noise estimates measure: 1 for the input's own (white) noise, more where
    /// the filter took the noise's upper band away ([`crate::decimate::noise_gain`]).
    noise_colour: f64,
}

impl Sampling {
    /// The input's own pixels.
    const DIRECT: Sampling = Sampling {
        unaliased: false,
        noise_colour: 1.0,
    };
}

impl Goal {
    /// Whether the fit, `step` being its first sweep on settled weights, cannot beat the
    /// rival: no spoiled cell (which would make it win whatever its σ), no significant tilt
    /// and no warp (either biases the window) and a σ already [`HOPELESS`] times the
    /// window's. Where a fit loses by that much, the residual's scale,
    /// model error, separates them, and the remaining sweeps hardly change it (`stamp1.png`:
    /// residual 8.06e-2 at that sweep and 8.08e-2 at the end, σ 94 and 75 times the
    /// window's).
    fn hopeless(&self, model: &Model, step: &Step, field: &FieldBox) -> bool {
        let Some(rival) = &self.rival else {
            return false;
        };
        // A significant tilt biases the window's flat planes beyond its σ
        // ([`FieldFit::window_bias_shown`]): the σs do not rank the two there. A warped
        // field has one (the tilt in its phase, whatever is left of it).
        let tilted = field.warp.is_some() || step.tilt.is_some_and(|t| t.weight > 0.0);
        let field = rival.field_std(&step.covariance, field.frame, step.model_error_ratio);
        let hopeless = spoiled_cells(&model.cells, &step.cells) == 0
            && !tilted
            && field > HOPELESS * rival.std();
        log::trace!(
            "whole-field fit: σ {field:.2e} rad when its weights settle, the window's {:.2e}",
            rival.std()
        );
        if hopeless {
            log::debug!(
                "whole-field fit given up: σ {field:.2e} rad when its weights settle, the \
                 window's {:.2e}",
                rival.std()
            );
        }
        hopeless
    }
}

/// A fit whose predicted σ is this many times its rival's on its first sweep with settled
/// weights cannot beat it ([`Goal::hopeless`]). The residual's scale hardly moves after that
/// sweep, but tying the harmonics later may still lower σ: by 2× on sharp square dots
/// (`a_fit_that_cannot_beat_its_rival_stops_and_one_that_can_is_unchanged`).
const HOPELESS: f64 = 10.0;

/// Iteration state of one fit, across its free and tied stages.
#[derive(Default)]
struct Run<'a> {
    /// The last frame's model, when tracking: its robust weights are frozen on the first
    /// sweep if that sweep shows the same field ([`WarmModel::still_fits`]).
    warm: Option<&'a WarmModel>,
    /// Sweeps run (the start's not counted).
    iterations: usize,
    /// How far each plane moved in all, `Σ(|α| + |β| + |γ|)`, radians.
    total_shift: [f64; 2],
    /// The iteration that froze the weights; every iteration before it updated them.
    frozen_at: Option<usize>,
}

/// Why a stage of the fit stopped before converging.
enum Stall {
    /// Still contracting after [`MAX_ITERATIONS`]: the last sweep's output.
    AtLimit(Box<Step>),
    /// Not contracting, or refused (the planes moved too far, a singular step).
    Failed,
}

impl Run<'_> {
    /// Adds a move of each plane (radians); `None` (the fit refused) once a plane has moved by
    /// [`MAX_CORRECTION`] in all, or a move was not a number.
    fn add_shift(&mut self, moved: [f64; 2]) -> Option<()> {
        for (total, m) in self.total_shift.iter_mut().zip(moved) {
            *total += m;
        }
        let refused = self
            .total_shift
            .iter()
            .any(|t| t.is_nan() || *t >= MAX_CORRECTION);
        if refused {
            log::debug!(
                "whole-field fit refused: planes moved {:.2?} rad",
                self.total_shift
            );
            return None;
        }
        Some(())
    }
}

/// Gauss–Newton sweeps on `model` until its steps converge (the last sweep's output), or why
/// they did not (see the comments).
#[inline(always)]
fn converge(
    image: &GreyImage,
    field: &FieldBox,
    mask: &NodeMask,
    model: &mut Model,
    goal: &Goal,
    run: &mut Run,
) -> Result<Step, Stall> {
    let mut steps = StepHistory::default();
    // The previous iteration did not contract (see below).
    let mut slow_before = false;
    for stage_iteration in 1..=MAX_ITERATIONS {
        run.iterations += 1;
        let iteration = run.iterations;
        // A warm start's weights are the last frame's: its first sweep freezes them, if it
        // shows the same field (checked below).
        let warm_first = run.warm.is_some() && iteration == 1;
        let freeze = run.frozen_at.is_none()
            && (warm_first || (iteration > ROBUST_ITERATIONS && steps.previous <= SETTLED_STEP));
        let mut step = iterate(image, field, mask, model, freeze, goal).ok_or(Stall::Failed)?;
        let freeze = freeze && !(warm_first && run.warm.is_some_and(|w| !w.still_fits(&step)));
        let mut largest = 0.0f64;
        let mut moved = [0.0; 2];
        for (l, p) in model.planes.iter_mut().enumerate() {
            let d = [
                step.delta[3 * l],
                step.delta[3 * l + 1],
                step.delta[3 * l + 2],
            ];
            correct_plane(p, d, field.frame);
            moved[l] = d[0].abs() + d[1].abs() + d[2].abs();
            largest = largest.max(moved[l]);
        }
        run.add_shift(moved).ok_or(Stall::Failed)?;
        log::trace!(
            "whole-field fit iteration {iteration} ({} harmonics): step {largest:.1e} rad, \
             residual σ {:.2e}, {:.1} % inliers",
            if model.tied { "tied" } else { "free" },
            step.residual_std,
            100.0 * step.inlier_fraction
        );
        model.linear = step.linear;
        model.update_harmonics(&step);
        // The first sweep on frozen weights: its residual no longer holds the start's misfit.
        let first_frozen = run.frozen_at == Some(iteration - 1);
        if first_frozen && goal.hopeless(model, &step, field) {
            return Err(Stall::Failed);
        }
        if freeze {
            model.frozen = frozen_weights(&mut step, model.cutoff, mask, field.cols.len());
            run.frozen_at = Some(iteration);
        } else if run.frozen_at.is_none() {
            set_robust_weights(model, &step, mask);
        }
        // With the weights frozen, the iterations solve one fixed problem and contract
        // geometrically. One whose contraction (over the last sweep or the last two,
        // [`StepHistory::contraction`]) cannot reach convergence in the iterations left (a
        // field the model does not describe, harmonics that swap residual with the planes)
        // would use them all up and still be refused, so it is given up at once when its step
        // is large, or when it happens twice running (one slow iteration is a weakly
        // determined harmonic settling). A slow but steady one runs on.
        let contraction = steps.contraction(largest);
        let left = (MAX_ITERATIONS - stage_iteration) as f64;
        let slow = run.frozen_at.is_some_and(|f| iteration > f + 1)
            && contraction.is_some_and(|(_, fastest)| sweeps_to_converge(largest, fastest) > left)
            && largest >= CONVERGED;
        if slow && (largest > GIVE_UP_STEP || slow_before) {
            log::debug!(
                "whole-field fit not contracting: step {largest:.1e} rad after {:.1e}",
                steps.previous
            );
            return Err(Stall::Failed);
        }
        slow_before = slow;
        // The steps still to come: the geometric tail of the frozen problem's contraction over
        // the last sweep (which needs a previous step of this stage). Gauss–Newton speeds up
        // as it converges, so the last sweep's contraction is the one still to come; where a
        // pair of sweeps contracts and its second step grows, the next pair's first step is
        // large again and the test waits for it.
        let tail = match (run.frozen_at, contraction) {
            (Some(f), Some((last, _))) if iteration > f && last < 1.0 => {
                largest * last / (1.0 - last)
            }
            _ => f64::INFINITY,
        };
        steps.push(largest);
        let sigma = [0, 1]
            .map(|l| {
                (0..3)
                    .map(|k| step.covariance[(3 * l + k, 3 * l + k)])
                    .sum::<f64>()
            })
            .into_iter()
            .fold(f64::INFINITY, f64::min)
            .sqrt();
        let tail_tolerance = (CONVERGED_TAIL * CONVERGED).max(CONVERGED_TAIL_OF_SIGMA * sigma);
        let converged = largest < CONVERGED || tail < tail_tolerance;
        if run.frozen_at.is_some() && converged {
            return Ok(step);
        }
        if stage_iteration == MAX_ITERATIONS {
            // Still moving: the field does not follow the model well enough (perspective, a
            // deformed part) for one fixed answer, unless another model settles.
            log::debug!("whole-field fit not converged in {MAX_ITERATIONS} iterations");
            return Err(Stall::AtLimit(Box::new(step)));
        }
    }
    Err(Stall::Failed)
}

/// The largest plane steps of a stage's last two iterations, radians (infinite before there
/// are any).
struct StepHistory {
    previous: f64,
    before_previous: f64,
}

impl Default for StepHistory {
    fn default() -> Self {
        Self {
            previous: f64::INFINITY,
            before_previous: f64::INFINITY,
        }
    }
}

impl StepHistory {
    /// The contraction per iteration that a new step `largest` shows over the last iteration,
    /// and the faster of that and its mean over the last two (geometric); `None` on a stage's
    /// first step.
    ///
    /// Where dust or hair couples the harmonics' updates with the planes', the alternation
    /// overshoots and a mode of the error changes sign from one sweep to the next: the steps
    /// shrink by pairs (2.3e-3, 2.5e-3, 4.4e-4, 5.0e-4, 8.7e-5, ... rad on a hair-crossed
    /// marker), one sweep of each pair growing a little while the pair contracts 5×. Judged
    /// over one sweep, such a fit looks stalled; over two, it contracts.
    fn contraction(&self, largest: f64) -> Option<(f64, f64)> {
        if !self.previous.is_finite() {
            return None;
        }
        let last = largest / self.previous;
        let fastest = if self.before_previous.is_finite() {
            last.min((largest / self.before_previous).sqrt())
        } else {
            last
        };
        Some((last, fastest))
    }

    fn push(&mut self, largest: f64) {
        self.before_previous = self.previous;
        self.previous = largest;
    }
}

/// Sweeps a fit whose steps contract by `q` per sweep needs from a step `step` (radians)
/// until its step is below [`CONVERGED`]: `ln(CONVERGED/step)/ln q`, infinite when it does
/// not contract (`q ≥ 1`, or not a number).
fn sweeps_to_converge(step: f64, q: f64) -> f64 {
    if step <= CONVERGED {
        0.0
    } else if q < 1.0 && q > 0.0 {
        (CONVERGED / step).ln() / q.ln()
    } else if q == 0.0 {
        1.0
    } else {
        f64::INFINITY
    }
}

/// Adds the correction `δφ = α·X + β·Y + γ` (`d = (α, β, γ)`, in the normalised coordinates
/// of `frame` = `(x₀, y₀, s)`) to `plane` (image frame).
fn correct_plane(plane: &mut PhasePlane, d: [f64; 3], (x0, y0, s): (f64, f64, f64)) {
    plane.a += d[0] / s;
    plane.b += d[1] / s;
    plane.c += d[2] - d[0] * x0 / s - d[1] * y0 / s;
}

/// Level of the fit's tests (the two point-symmetry tests of [`symmetric_shift`], the tilt's
/// significance, [`Tilt::weight`]): 10⁻³. `−2·ln 10⁻³` is the upper quantile of χ² with two
/// degrees of freedom; [`SYMMETRY_TEST_Z`] the standard normal one, for other degrees of
/// freedom.
const TEST_LIMIT_TWO_DOF: f64 = 13.815_510_557_964_274;
/// Standard normal quantile at `1 − 10⁻³`.
const SYMMETRY_TEST_Z: f64 = 3.090_232_306_167_813;

/// The offset shift `δ` (radians, per plane) that puts the dot centres where the harmonics'
/// phases say they are, when tying the harmonics to them suits the dots; `None` when the dots
/// are not point-symmetric (or no harmonic informs both offsets).
///
/// With free phases, harmonic `h` has amplitude `A_h` relative to the fundamentals' phase; on
/// point-symmetric dots whose centres sit at `φ + δ` it is `A'_h·e^{ih·δ}` with `A'_h` real,
/// so `Im A_h ≈ Re A_h·(h·δ)` (to first order), while each fundamental, real by construction,
/// holds `B_l·δ_l ≈ 0`. The real and imaginary parts of each demodulated amplitude carry noise
/// of variance `σ_A² = 2σ²·Σw²/(Σw)²`, `σ²` the residual's (white noise and model error).
/// With `F = diag(B_l²)/σ_A²` (fundamentals) and `H = Σ_h Re(A_h)²·h·hᵀ/σ_A²` (harmonics),
/// `δ = (F + H)⁻¹·Σ_h Re(A_h)·Im(A_h)·h/σ_A²` is the tied offsets' move from the free ones.
/// The phases stay free when both tests find the dots asymmetric (coma, oblique light, the
/// two fabrication layers of a real stamp off centre), each at the level 10⁻³:
///
/// * **the move matters** (Hausman's test): on symmetric dots both estimates are right and
///   `δ` is noise of covariance `F⁻¹ − (F + H)⁻¹`, so `δᵀ·(F·H⁻¹·F + F)·δ` is χ² with two
///   degrees of freedom;
/// * **the harmonics disagree with one another**: the misfit of `Im A_h ≈ Re A_h·(h·δ_H)`,
///   `δ_H` from the harmonics alone, over `σ_A²` is χ² with two fewer degrees of freedom
///   than harmonics. Dust and hair, mostly low spatial frequencies, move the fundamentals
///   more than the harmonics: the first test then fires on symmetric dots, and the tied fit,
///   which the harmonics outvote the fundamentals in, is the more robust one.
fn symmetric_shift(model: &Model, step: &Step) -> Option<[f64; 2]> {
    let variance = step.amplitude_variance;
    if model.harmonics.is_empty() || variance <= 0.0 {
        return None;
    }
    let b = [model.linear[3], model.linear[6]];
    let fundamentals = nalgebra::Matrix2::from_diagonal(&Vector2::new(b[0] * b[0], b[1] * b[1]));
    let mut harmonics = nalgebra::Matrix2::zeros();
    let mut rhs = Vector2::zeros();
    let mut imaginary = 0.0;
    for &((h1, h2), a) in &model.harmonics {
        let g = Vector2::new(h1 as f64, h2 as f64) * a.re;
        harmonics += g * g.transpose();
        rhs += g * a.im;
        imaginary += a.im * a.im;
    }
    let shift = (fundamentals + harmonics).try_inverse()? * rhs;
    let harmonics_inverse = harmonics.try_inverse()?;
    let precision = fundamentals * harmonics_inverse * fundamentals + fundamentals;
    let moves = shift.dot(&(precision * shift)) / variance > TEST_LIMIT_TWO_DOF;
    let dof = model.harmonics.len().saturating_sub(2);
    let misfit = (imaginary - rhs.dot(&(harmonics_inverse * rhs))) / variance;
    let disagree = dof > 0 && misfit > chi_square_quantile(dof as f64, SYMMETRY_TEST_Z);
    let tied = !(moves && disagree);
    log::debug!(
        "whole-field fit: tying moves the offsets by {:.1e} rad ({}), harmonics' misfit χ² \
         {misfit:.1} over {dof} ({}): {}",
        shift.norm(),
        if moves { "significant" } else { "noise" },
        if disagree { "asymmetric" } else { "symmetric" },
        if tied { "tied" } else { "left free" }
    );
    tied.then_some([shift.x, shift.y])
}

/// Upper quantile of the χ² distribution with `dof` degrees of freedom at the level whose
/// standard normal quantile is `z` (Wilson–Hilferty: `(χ²/k)^{1/3}` is nearly normal; within
/// 1 % for `k ≥ 3`).
fn chi_square_quantile(dof: f64, z: f64) -> f64 {
    let v = 2.0 / (9.0 * dof);
    dof * (1.0 - v + z * v.sqrt()).powi(3)
}

/// Number of whole cells (at least half the largest cell's layout weight: clear of the
/// layout's other features) whose robust weight is below 1. `sums`: `(Σ w_L·r², Σ w_L)` per
/// node.
fn spoiled_cells(weights: &[f64], sums: &[[f64; 2]]) -> usize {
    let whole = whole_cells(sums);
    (0..weights.len())
        .filter(|&i| weights[i] < 1.0 && whole(i))
        .count()
}

/// Whether cell `i` is whole: at least half the largest cell's layout weight (`sums`:
/// `(Σ w_L·r², Σ w_L)` per node), i.e. clear of the layout's other features and of the field's
/// edge.
fn whole_cells(sums: &[[f64; 2]]) -> impl Fn(usize) -> bool + '_ {
    let largest = sums.iter().map(|s| s[1]).fold(0.0, f64::max);
    move |i| sums.get(i).is_some_and(|s| s[1] >= 0.5 * largest)
}

/// The pixels that an outlier covers, from a sweep's `residuals` (row-major, `width` per row,
/// NaN where the sweep did not go): each pixel whose residual reaches the biweight's `cutoff`
/// (weight 0 already), grown by hysteresis, as Canny grows edges (Canny 1986), into the
/// 8-connected pixels `j` whose residual exceeds `edge(j)` in magnitude. The biweight gives the
/// soft, blurred edge of a hair or of dust almost full weight; that edge is not point-symmetric
/// about the dots it crosses and pulls their centres.
fn outlier_extents(
    residuals: &[f32],
    width: usize,
    cutoff: f32,
    edge: impl Fn(usize) -> f32,
) -> Vec<bool> {
    let width = width.max(1);
    let last_row = (residuals.len() / width).saturating_sub(1);
    let mut grown: Vec<bool> = residuals.iter().map(|r| r.abs() >= cutoff).collect();
    let mut stack: Vec<usize> = (0..grown.len()).filter(|&i| grown[i]).collect();
    while let Some(i) = stack.pop() {
        let (row, col) = (i / width, i % width);
        for r in row.saturating_sub(1)..=(row + 1).min(last_row) {
            for c in col.saturating_sub(1)..=(col + 1).min(width - 1) {
                let j = r * width + c;
                // NaN (not visited) never passes.
                let free = grown.get(j) == Some(&false);
                if free && residuals.get(j).is_some_and(|v| v.abs() > edge(j)) {
                    grown[j] = true;
                    stack.push(j);
                }
            }
        }
    }
    grown
}

/// The frozen weights of `step`, the freezing sweep, with the pixels that its outliers cover
/// ([`outlier_extents`]) at 0: a pixel joins an outlier where its residual exceeds
/// [`OUTLIER_EDGE`] times the local scale, the larger of the residual's robust σ and the
/// typical RMS of the cells around its own ([`local_residual_scale`]). Smooth model error (a
/// tilt, vignetting) raises the local scale with it and does not grow.
fn frozen_weights(step: &mut Step, cutoff: Option<f64>, mask: &NodeMask, width: usize) -> Vec<f32> {
    let mut weights = std::mem::take(&mut step.frozen);
    let Some(cutoff) = cutoff else {
        return weights;
    };
    let scale = local_residual_scale(&step.cells, &cell_rms(&step.cells), mask.dims);
    let scale = scale.unwrap_or_default();
    let edge = |j: usize| {
        let local = step
            .frozen_cells
            .get(j)
            .and_then(|&c| scale.get(c as usize));
        (OUTLIER_EDGE * local.copied().unwrap_or(0.0).max(step.residual_std)) as f32
    };
    let outliers = outlier_extents(&step.frozen_residuals, width, cutoff as f32, edge);
    for (w, _) in weights.iter_mut().zip(outliers).filter(|(_, o)| *o) {
        *w = 0.0;
    }
    weights
}

/// Sets the biweight's cut-off and the cells' weights from the residuals of `step`'s sweep.
fn set_robust_weights(model: &mut Model, step: &Step, mask: &NodeMask) {
    let floor = MIN_CUTOFF * model.contrast();
    model.cutoff = Some((TUKEY_BIWEIGHT * step.residual_std).max(floor)).filter(|c| *c > 0.0);
    model.cells = cell_weights(&step.cells, mask.dims);
}

/// A harmonic's amplitude correction from its demodulation `y = 2·Σw·r·e^{−iθ}/Σw` of the
/// residual `r` (θ = h·φ), given its overlap with its own conjugate `ρ = Σw·e^{2iθ}/Σw`:
/// the least-squares fit of `Re(dA·e^{iθ})` to `r`. Demodulation alone is that fit where the
/// pixels average `e^{2iθ}` away (`ρ ≈ 0`); near the Nyquist frequency they do not (`2θ`
/// hardly turns from pixel to pixel) and the term is nearly a cosine of fixed phase. In the
/// eigenbasis of the 2 × 2 normal matrix `1 ± |ρ|` (directions `e^{−iψ/2}` and `i·e^{−iψ/2}`,
/// `ψ = arg ρ`), each part of `y` is divided by its eigenvalue; a direction with no
/// information left (`1 − |ρ|` at the rounding of the sums, single precision) keeps its
/// amplitude: the phase of a harmonic sampled exactly at the Nyquist frequency is not seen.
fn amplitude_step(y: Complex64, overlap: Complex64) -> Complex64 {
    /// Relative eigenvalue below which a direction holds no information: ~10³ times the
    /// rounding of the single-precision overlap sums.
    const NO_INFORMATION: f64 = 1e-4;
    let magnitude = overlap.norm();
    if magnitude == 0.0 {
        return y;
    }
    let axis = Complex64::from_polar(1.0, -0.5 * overlap.arg());
    let along = y * axis.conj();
    let weak = 1.0 - magnitude;
    let across = if weak > NO_INFORMATION {
        along.im / weak
    } else {
        0.0
    };
    axis * Complex64::new(along.re / (1.0 + magnitude), across)
}

/// The starting model: background, fundamentals and every harmonic demodulated under the
/// layout weight (exact for a periodic field, whose terms the weight keeps orthogonal; a
/// harmonic near the Nyquist frequency with its overlap, [`amplitude_step`]); the
/// harmonics above [`MIN_HARMONIC`] of the fundamental are kept. The same sweep centres the
/// field's normalised coordinates on its layout weight (`Σw·X = Σw·Y = 0`), which the
/// demodulation does not use.
#[inline(always)]
fn first_model(
    image: &GreyImage,
    field: &mut FieldBox,
    mask: &NodeMask,
    planes: [PhasePlane; 2],
    unaliased: bool,
) -> Option<Model> {
    let side = field.cols.len().min(field.rows.len()) as f64;
    let all: Vec<((i32, i32), Complex64)> = resolvable_harmonics(&planes, side, unaliased)
        .into_iter()
        .map(|h| (h, Complex64::default()))
        .collect();
    let mut bank = HarmonicBank::new(&all, &planes);
    let mut fundamentals = [Complex64::default(); 2];
    let (mut total, mut mean, mut sum_x, mut sum_y) = (0.0, 0.0, 0.0, 0.0);
    for p in field.pixels(image, &planes, mask, &[]) {
        bank.move_to(&p);
        total += p.w;
        sum_x += p.w * p.xn;
        sum_y += p.w * p.yn;
        mean += p.w * p.g;
        let d = p.w * p.g;
        bank.demodulate(d);
        bank.add_overlap(p.w);
        fundamentals[0] += d * p.z[0].conj();
        fundamentals[1] += d * p.z[1].conj();
    }
    if total <= 0.0 {
        return None;
    }
    let (x0, y0, scale) = field.frame;
    field.frame = (
        x0 + scale * sum_x / total,
        y0 + scale * sum_y / total,
        scale,
    );
    let mut linear = SVector::zeros();
    linear[0] = mean / total;
    linear[3] = 2.0 * fundamentals[0].re / total;
    linear[6] = 2.0 * fundamentals[1].re / total;
    let contrast = 0.5 * (linear[3].abs() + linear[6].abs());
    let (harmonics, overlaps) = all
        .iter()
        .zip(bank.sums())
        .zip(bank.overlaps())
        .map(|((&(h, _), sum), overlap)| {
            let overlap = overlap / total;
            ((h, amplitude_step(2.0 * sum / total, overlap)), overlap)
        })
        .filter(|((_, a), _)| a.norm() >= MIN_HARMONIC * contrast)
        .unzip();
    Some(Model {
        planes,
        linear,
        harmonics,
        overlaps,
        cutoff: None,
        tied: false,
        cells: Vec::new(),
        frozen: Vec::new(),
    })
}

/// One sweep's normal equations: the plain unknowns, or with the tilt's four columns as well
/// when the fit measures the field's tilt ([`Tilt`]). The tilted system's first [`UNKNOWNS`]
/// rows and columns are the plain system's, entry for entry (each entry is its own dot
/// product of the same columns), so measuring the tilt leaves the fit's steps as they are.
// One per sweep, on the stack: the variants' sizes differ by design.
#[allow(clippy::large_enum_variant)]
enum Equations {
    Plain(NormalEquations<UNKNOWNS>),
    Tilted(NormalEquations<TILTED>),
}

impl Equations {
    /// Adds an observation; `tilt_columns` gives the tilt's four basis functions, asked for
    /// only when measured.
    #[inline(always)]
    fn add(
        &mut self,
        basis: &[f64; UNKNOWNS],
        data: f64,
        weight: f64,
        tilt_columns: impl FnOnce() -> [f64; 4],
    ) {
        match self {
            Equations::Plain(e) => e.add(basis, data, weight),
            Equations::Tilted(e) => {
                let extra = tilt_columns();
                let row: [f64; TILTED] = std::array::from_fn(|i| match i {
                    i if i < UNKNOWNS => basis[i],
                    i => extra[i - UNKNOWNS],
                });
                e.add(&row, data, weight);
            }
        }
    }

    /// The plain normal matrix and right-hand side, and the tilted ones when measured.
    #[allow(clippy::type_complexity)]
    fn finish(
        self,
    ) -> (
        SMatrix<f64, UNKNOWNS, UNKNOWNS>,
        SVector<f64, UNKNOWNS>,
        Option<(SMatrix<f64, TILTED, TILTED>, SVector<f64, TILTED>)>,
    ) {
        match self {
            Equations::Plain(e) => {
                let (n, r) = e.finish();
                (n, r, None)
            }
            Equations::Tilted(e) => {
                let (n, r) = e.finish();
                let plain = n.fixed_view::<UNKNOWNS, UNKNOWNS>(0, 0).into_owned();
                (
                    plain,
                    r.fixed_rows::<UNKNOWNS>(0).into_owned(),
                    Some((n, r)),
                )
            }
        }
    }
}

/// The tilt of a field about its centre (docs/design.md#tilt-centre), measured by one
/// Gauss–Newton step of a homography's phase: lattice coordinates `u = v/(1 − p·v)`, `v`
/// linear in the image (the planes, about the centre) and `p` the perspective per period, as
/// [`crate::hpcode`]'s dot grid has it. Linear planes fitted to a tilted field take in the
/// mean of its curvature and miss its centre by about `Σ·p` periods (`Σ` the field's second
/// moments, `h²/3` per axis on a square field); here `p` is estimated with every other
/// unknown, and the planes move by what `p` moves them.
#[derive(Clone, Copy, Debug)]
struct Tilt {
    /// Estimated perspective `p`, per period.
    perspective: Vector2<f64>,
    /// Its information (the Schur complement of the other unknowns, weighted squares per unit
    /// of `p` squared).
    information: Matrix2<f64>,
    /// How much of `p` the planes take, in `[0, 1)`: the soft threshold `1 − χ²₀/χ²` of its
    /// Mahalanobis square `χ² = pᵀ·I·p/s` (`s` the residual's scale, model error included)
    /// above [`TEST_LIMIT_TWO_DOF`] `χ²₀`, zero below. On an untilted field `p` is noise,
    /// which must not move the planes; on a tilted one `χ²` runs into the thousands and nearly
    /// all of `p` is taken. Continuous, so the planes do not jump where a tilt becomes
    /// significant.
    weight: f64,
    /// How the other unknowns (the linear ones, then the plane corrections) change per unit
    /// of `p`, each re-solved with it.
    response: SMatrix<f64, UNKNOWNS, 2>,
}

impl Tilt {
    /// The tilt from a sweep's tilted normal equations `normal·x = rhs`
    /// (`harmonic_offsets`: the model has free harmonics, whose phase offsets are unknowns
    /// too; tied ones have none of their own), `scale` the variance of a unit-weight
    /// observation times `Σw²/Σw`. The other unknowns are eliminated (Schur complement), so
    /// that `p` is estimated with them.
    fn estimate(
        normal: &SMatrix<f64, TILTED, TILTED>,
        rhs: &SVector<f64, TILTED>,
        harmonic_offsets: bool,
        scale: f64,
    ) -> Option<Tilt> {
        let tilt = [UNKNOWNS, UNKNOWNS + 1];
        let offsets = if harmonic_offsets {
            UNKNOWNS + 2..TILTED
        } else {
            0..0
        };
        let others: Vec<usize> = (0..UNKNOWNS).chain(offsets).collect();
        let m = others.len();
        let own = Matrix2::from_fn(|i, j| normal[(tilt[i], tilt[j])]);
        let cross = DMatrix::from_fn(m, 2, |i, j| normal[(others[i], tilt[j])]);
        let rest = DMatrix::from_fn(m, m, |i, j| normal[(others[i], others[j])]);
        let response = rest.cholesky()?.solve(&cross);
        let reduced = own - Matrix2::from_iterator((cross.transpose() * &response).iter().copied());
        let rhs_rest = DVector::from_fn(m, |i, _| rhs[others[i]]);
        let pulled = response.transpose() * rhs_rest;
        let perspective = reduced.try_inverse()?
            * Vector2::new(rhs[tilt[0]] - pulled[0], rhs[tilt[1]] - pulled[1]);
        let chi2 = perspective.dot(&(reduced * perspective)) / scale;
        let weight = if chi2.is_finite() && chi2 > TEST_LIMIT_TWO_DOF {
            1.0 - TEST_LIMIT_TWO_DOF / chi2
        } else {
            0.0
        };
        perspective.iter().all(|v| v.is_finite()).then(|| Tilt {
            perspective,
            information: reduced,
            weight,
            response: SMatrix::from_fn(|i, j| response[(i, j)]),
        })
    }

    /// The perspective the planes take: `p` times [`Tilt::weight`].
    fn taken(&self) -> Vector2<f64> {
        self.perspective * self.weight
    }

    /// The plane corrections `(α₁, β₁, γ₁, α₂, β₂, γ₂)` that taking [`Tilt::taken`] makes (the
    /// other unknowns re-solved with it): to first order, the fixed point of the fit with
    /// this tilt in its phase.
    fn planes_shift(&self) -> Vector6<f64> {
        -(self.response.fixed_rows::<6>(LINEAR) * self.taken())
    }

    /// The weighted squares of the residual that taking [`Tilt::taken`] removes (the whole
    /// estimate would remove `pᵀ·I·p`, `I` its information).
    fn explained_squares(&self) -> f64 {
        let (p, t) = (self.perspective, self.taken());
        (2.0 * t.dot(&(self.information * p)) - t.dot(&(self.information * t))).max(0.0)
    }

    /// Covariance of the plane corrections added by taking the tilt, per unit variance of a
    /// weighted observation: `w²·R·I⁻¹·Rᵀ` (`R` the response, `I` the information, `w` the
    /// weight).
    fn planes_covariance(&self) -> Matrix6<f64> {
        let weight = self.weight;
        let planes = self.response.fixed_rows::<6>(LINEAR);
        match self.information.try_inverse() {
            Some(inverse) => planes * inverse * planes.transpose() * (weight * weight),
            None => Matrix6::zeros(),
        }
    }
}

/// Output of one iteration.
struct Step {
    linear: SVector<f64, LINEAR>,
    /// `(α₁, β₁, γ₁, α₂, β₂, γ₂)`.
    delta: Vector6<f64>,
    /// Correction of each modelled harmonic's amplitude.
    harmonics: Vec<Complex64>,
    covariance: Matrix6<f64>,
    /// Residual scale over white-noise σ, ≥ 1.
    model_error_ratio: f64,
    /// Robust standard deviation of the residuals before the step.
    residual_std: f64,
    inlier_fraction: f64,
    pixels: usize,
    /// `(Σ w_L·r², Σ w_L)` of each cell (per node of the mask).
    cells: Vec<[f64; 2]>,
    /// The pixels' robust weights of this iteration, when asked to freeze them.
    frozen: Vec<f32>,
    /// With them, each pixel's residual (NaN where the sweep did not go) and cell (the
    /// index of its nearest node in per-node arrays, `u32::MAX` outside the mask), row-major
    /// over the box.
    frozen_residuals: Vec<f32>,
    frozen_cells: Vec<u32>,
    /// Centroid `(X̄, Ȳ)` of the demodulation's weights (normalised coordinates): where the
    /// harmonics' corrections are measured.
    centroid: [f64; 2],
    /// Variance of the real and of the imaginary part of a demodulated amplitude under the
    /// white noise, `2σ²·Σw²/(Σw)²`, intensity units².
    amplitude_variance: f64,
    /// The field's tilt as this sweep measured it, when asked ([`Goal::tilt_centre`]).
    tilt: Option<Tilt>,
    /// The mean square residual that taking the tilt removes, over the white noise's variance.
    tilt_misfit: f64,
}

/// One sweep over the field: residuals of the current model, their robust weights, the
/// weighted normal equations of the linearised model (solved), and the harmonics' correction:
/// the demodulated *clipped residual* `ψ(r) = r·w_T(r)` under the layout weight — a Newton step
/// towards the M-estimate that keeps the harmonics orthogonal (reweighting the demodulation
/// itself would mix them).
#[inline(always)]
fn iterate(
    image: &GreyImage,
    field: &FieldBox,
    mask: &NodeMask,
    model: &Model,
    freeze: bool,
    goal: &Goal,
) -> Option<Step> {
    let mut frozen = if freeze {
        vec![0.0f32; field.rows.len() * field.cols.len()]
    } else {
        Vec::new()
    };
    let mut frozen_residuals = vec![f32::NAN; frozen.len()];
    let mut frozen_cells = vec![u32::MAX; frozen.len()];
    // The tilt is probed on the fixed problem of frozen weights, where the fit converges.
    let tilt_centre = goal.tilt_centre.filter(|_| !model.frozen.is_empty());
    let mut equations = match tilt_centre {
        Some(_) => Equations::Tilted(NormalEquations::new()),
        None => Equations::Plain(NormalEquations::new()),
    };
    let mut slopes = [0.0f64; 2];
    let (mut sum_w, mut sum_w2, mut sum_layout, mut pixels) = (0.0, 0.0, 0.0, 0usize);
    let mut residuals = Vec::new();
    let mut cells = vec![[0.0f64; 2]; mask.len()];
    let mut sum_wr2 = 0.0;
    let (mut sum_wx, mut sum_wy) = (0.0, 0.0);
    let mut basis = [0.0f64; UNKNOWNS];
    let mut bank = HarmonicBank::new(&model.harmonics, &model.planes);
    for p in field.pixels(image, &model.planes, mask, &model.cells) {
        bank.move_to(&p);
        let (h, h_slope) = bank.evaluate();
        let gain = model.gain(&p);
        let data = p.g - h;
        let r = p.g - gain * h - model.linear_at(&p);
        let robust = match model.frozen.get(p.index) {
            Some(&w) => w as f64,
            None => model.robust(r),
        };
        if let Some(slot) = frozen.get_mut(p.index) {
            *slot = robust as f32;
            if let (Some(q), Some(c)) = (
                frozen_residuals.get_mut(p.index),
                frozen_cells.get_mut(p.index),
            ) {
                *q = r as f32;
                *c = p.cell.map_or(u32::MAX, |c| c as u32);
            }
        }
        pixels += 1;
        sum_layout += p.layout;
        if p.w >= 0.5 {
            residuals.push(r.abs());
        }
        if let Some(cell) = p.cell.and_then(|i| cells.get_mut(i)) {
            cell[0] += p.layout * r * r;
            cell[1] += p.layout;
        }
        bank.demodulate(p.w * r * robust);
        let w = p.w * robust;
        if w <= 0.0 {
            continue;
        }
        sum_w += w;
        sum_wx += w * p.xn;
        sum_wy += w * p.yn;
        sum_w2 += w * w;
        sum_wr2 += w * r * r;
        let m = &model.linear;
        basis[0] = 1.0;
        basis[1] = p.xn;
        basis[2] = p.yn;
        let mut fundamentals = [0.0; 2];
        for l in 0..2 {
            let (c, sn) = (p.z[l].re, p.z[l].im);
            basis[3 + 3 * l] = c;
            basis[4 + 3 * l] = p.xn * c;
            basis[5 + 3 * l] = p.yn * c;
            // ∂g/∂φ_l at the current amplitudes, fundamental and harmonics. Tied harmonics
            // inform the offsets γ_l as well as the slopes; free ones only the slopes (their
            // phases absorb any common move, `Model::update_harmonics`). X and Y are centred
            // on the field's weight, so ramp and offset decouple.
            let amplitude = m[3 + 3 * l] + m[4 + 3 * l] * p.xn + m[5 + 3 * l] * p.yn;
            fundamentals[l] = -amplitude * sn;
            slopes[l] = fundamentals[l] + gain * h_slope[l];
        }
        // Along the planes' linear phases: through the warp's Jacobian (the identity without
        // one, which leaves every term as it is to the last bit).
        let j = &p.jacobian;
        for m in 0..2 {
            let d = slopes[0] * j[0][m] + slopes[1] * j[1][m];
            let fundamental = fundamentals[0] * j[0][m] + fundamentals[1] * j[1][m];
            basis[LINEAR + 3 * m] = d * p.xn;
            basis[LINEAR + 3 * m + 1] = d * p.yn;
            basis[LINEAR + 3 * m + 2] = if model.tied { d } else { fundamental };
        }
        basis[9] = p.xn * h;
        basis[10] = p.yn * h;
        equations.add(&basis, data, w, || {
            let c = tilt_centre.unwrap_or_default();
            let v = [p.linear[0] - c[0], p.linear[1] - c[1]];
            // ∂g/∂p_k = Σ_l ∂g/∂φ_l · 2π·v_l·v_k/D² (u = v/(1 − p·v), φ_l = 2π·u_l, at the
            // warp's p or at 0); then the harmonics' own phase shift per plane, which free
            // harmonics take apart from the offsets (their amplitudes hold the mean of a
            // tilt's curvature).
            let along = TAU * (slopes[0] * v[0] + slopes[1] * v[1]) * p.inverse_square;
            [
                along * v[0],
                along * v[1],
                gain * h_slope[0],
                gain * h_slope[1],
            ]
        });
    }
    if sum_w <= 0.0 || sum_layout <= 0.0 {
        return None;
    }
    let (normal, rhs, tilted) = equations.finish();
    let inverse = normal.cholesky()?.inverse();
    let x = inverse * rhs;
    let residual_std = robust_sigma(&mut residuals);
    // Weighted least squares under white noise σ²: Cov = σ²·N⁻¹(Σw²bbᵀ)N⁻¹ ≈ σ²·N⁻¹·Σw²/Σw.
    // The residual's scale: the smaller of the kept pixels' weighted mean square residual and
    // the robust (median) one. It holds the white noise and the static model error (dot
    // edges, aliased harmonics, sharp dots' detail beyond the modelled orders), which does not
    // scatter the result from frame to frame but may bias it. σ² is the white noise alone: the
    // model-free estimate `white` when smaller, at least the engine's floor.
    let misfit_variance = (sum_wr2 / sum_w).min(residual_std * residual_std);
    // The tilt's significance is judged on the residual's scale, model error included: a
    // static misfit must not pass for a tilt.
    let tilt_scale = misfit_variance * sum_w2 / sum_w;
    let free_harmonics = !model.tied && !model.harmonics.is_empty();
    let tilt = tilted.and_then(|(n, r)| Tilt::estimate(&n, &r, free_harmonics, tilt_scale));
    // The part of the residual that the tilt taken explains is no model error once the
    // planes take the tilt (the weighted squares it removes, a fraction of all).
    let explained = match tilt {
        Some(t) if sum_wr2 > 0.0 => t.explained_squares() / sum_wr2,
        _ => 0.0,
    };
    let residual_variance = misfit_variance * (1.0 - explained).clamp(0.0, 1.0);
    let noise_variance = residual_variance
        .min(goal.white.unwrap_or(f64::INFINITY))
        .max(MIN_NOISE_STD * MIN_NOISE_STD);
    let unit = noise_variance * goal.sampling.noise_colour * sum_w2 / sum_w;
    let mut covariance = inverse.fixed_view::<6, 6>(LINEAR, LINEAR).into_owned() * unit;
    if let Some(t) = &tilt {
        // The planes will move with the tilt taken ([`Tilt::planes_shift`]), and take its
        // noise with them.
        covariance += t.planes_covariance() * unit;
    }
    let model_error_ratio = (residual_variance / noise_variance).max(1.0).sqrt();
    let tilt_misfit = tilt.map_or(0.0, |t| t.explained_squares() / sum_w / noise_variance);
    Some(Step {
        tilt,
        tilt_misfit,
        model_error_ratio,
        linear: x.fixed_rows::<LINEAR>(0).into_owned(),
        delta: x.fixed_rows::<6>(LINEAR).into_owned(),
        harmonics: (bank.sums().into_iter().zip(&model.overlaps))
            .map(|(d, &overlap)| amplitude_step(2.0 * d / sum_w, overlap))
            .collect(),
        covariance,
        residual_std,
        inlier_fraction: sum_w / sum_layout,
        pixels,
        cells,
        frozen,
        frozen_residuals,
        frozen_cells,
        centroid: [sum_wx / sum_w, sum_wy / sum_w],
        amplitude_variance: 2.0 * residual_variance.max(noise_variance) * sum_w2 / (sum_w * sum_w),
    })
}

/// Robust weight of each cell from its RMS residual `ρ` against the median `m` of the cells
/// around it (within [`CELL_NEIGHBOURHOOD`] nodes, those with at least half a cell of layout
/// weight; at most `CELL_FULL` times the field's median, so that a neighbourhood spoiled as a
/// whole is still judged): 1 up to `CELL_FULL·m`, 0 beyond `CELL_ZERO·m`, cos² in between.
/// Dust and hair stand out from their neighbours; model error that varies smoothly over the
/// field (vignetting, a slow change of focus) does not. `sums` holds `(Σ w_L·r², Σ w_L)` per
/// node of a `dims` mask.
fn cell_weights(sums: &[[f64; 2]], dims: (usize, usize)) -> Vec<f64> {
    let rms = cell_rms(sums);
    let Some(typical) = local_residual_scale(sums, &rms, dims) else {
        return vec![1.0; sums.len()];
    };
    (0..rms.len())
        .map(|i| {
            let t = rms[i] / typical[i].max(f64::MIN_POSITIVE);
            if t <= CELL_FULL {
                1.0
            } else if t >= CELL_ZERO {
                0.0
            } else {
                let c = (0.5 * PI * (t - CELL_FULL) / (CELL_ZERO - CELL_FULL)).cos();
                c * c
            }
        })
        .collect()
}

/// RMS residual of each cell (`sums`: `(Σ w_L·r², Σ w_L)` per node; 0 where it has no weight).
fn cell_rms(sums: &[[f64; 2]]) -> Vec<f64> {
    sums.iter()
        .map(|&[r2, w]| if w > 0.0 { (r2 / w).sqrt() } else { 0.0 })
        .collect()
}

/// The typical RMS residual around each cell ([`cell_weights`]): the median over the whole
/// cells within [`CELL_NEIGHBOURHOOD`] nodes, at most `CELL_FULL` times the field's median
/// (the field's median where fewer than 9 are whole); `rms` is [`cell_rms`] of `sums`. `None`
/// where the field's median is 0.
fn local_residual_scale(sums: &[[f64; 2]], rms: &[f64], dims: (usize, usize)) -> Option<Vec<f64>> {
    let full = whole_cells(sums);
    let mut all: Vec<f64> = (0..rms.len())
        .filter(|&i| full(i))
        .map(|i| rms[i])
        .collect();
    let global = median(&mut all).unwrap_or(0.0);
    if global <= 0.0 {
        return None;
    }
    let reach = CELL_NEIGHBOURHOOD as i64;
    let (n1, n2) = (dims.0 as i64, dims.1 as i64);
    let mut local = Vec::new();
    let scale = (0..rms.len())
        .map(|i| {
            let (a, b) = ((i / dims.1.max(1)) as i64, (i % dims.1.max(1)) as i64);
            local.clear();
            for da in -reach..=reach {
                for db in -reach..=reach {
                    let (p, q) = (a + da, b + db);
                    if p >= 0 && q >= 0 && p < n1 && q < n2 {
                        let j = (p * n2 + q) as usize;
                        if full(j) {
                            local.push(rms[j]);
                        }
                    }
                }
            }
            if local.len() >= 9 {
                median(&mut local).unwrap_or(global).min(CELL_FULL * global)
            } else {
                global
            }
        })
        .collect();
    Some(scale)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dot grid `g = 0.5 + Σ harmonics` with planes `planes`, `n × n` pixels.
    fn grid(n: usize, planes: &[PhasePlane; 2], dot: impl Fn(f64, f64) -> f64) -> GreyImage {
        let (cx, cy) = ((n / 2) as f64, (n / 2) as f64);
        let mut px = Vec::with_capacity(n * n);
        for r in 0..n {
            for c in 0..n {
                let (x, y) = (c as f64 - cx, r as f64 - cy);
                px.push(dot(planes[0].at(x, y), planes[1].at(x, y)) as f32);
            }
        }
        GreyImage::new(n, n, px).unwrap()
    }

    /// A square field of dots at nodes `−r..=r` per axis, without the `missing` ones.
    fn dots(r: i64, missing: &[(i64, i64)]) -> NodeMask {
        NodeMask::from_cells(-r..=r, -r..=r, |v1, v2| {
            let node = (v1.div_euclid(2), v2.div_euclid(2));
            v1 % 2 == 0
                && v2 % 2 == 0
                && node.0.abs() <= r
                && node.1.abs() <= r
                && !missing.contains(&node)
        })
    }

    fn planes(angle: f64, period: f64, offset: [f64; 2]) -> [PhasePlane; 2] {
        let k = TAU / period;
        let (s, c) = angle.sin_cos();
        [
            PhasePlane {
                a: k * c,
                b: k * s,
                c: offset[0],
            },
            PhasePlane {
                a: -k * s,
                b: k * c,
                c: offset[1],
            },
        ]
    }

    /// Asserts that `fit` found the `truth` planes: offsets within `offset` rad, slopes within
    /// `slope` rad per pixel.
    fn assert_planes(fit: &FieldFit, truth: &[PhasePlane; 2], offset: f64, slope: f64) {
        for (f, t) in fit.planes.iter().zip(truth) {
            assert!((f.c - t.c).abs() < offset, "{f:?} {t:?}");
            assert!(
                (f.a - t.a).abs() < slope && (f.b - t.b).abs() < slope,
                "{f:?} {t:?}"
            );
        }
    }

    /// `image` with uniform noise over `range` (standard deviation `range/√12`; a linear
    /// congruential sequence from `seed`).
    fn with_noise(mut image: GreyImage, range: f32, seed: u64) -> GreyImage {
        let mut state = seed;
        for v in image.pixels_mut() {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            *v += range * ((state >> 40) as f32 / (1u64 << 24) as f32 - 0.5);
        }
        image
    }

    /// Sharp-ish dots: a raised power of the product of cosines (many harmonics).
    fn sharp(p1: f64, p2: f64) -> f64 {
        let v = (0.5 + 0.5 * p1.cos()) * (0.5 + 0.5 * p2.cos());
        0.2 + 0.6 * v.powi(3)
    }

    #[test]
    fn recovers_the_planes_of_a_harmonic_rich_grid_from_a_rough_start() {
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let image = grid(160, &truth, sharp);
        let mask = dots(6, &[]);
        let mut start = truth;
        start[0].c += 0.05;
        start[1].a *= 1.002;
        let fit = fit_dot_field(&image, start, &mask).unwrap();
        assert_planes(&fit, &truth, 1e-6, 1e-8);
        assert!(fit.inlier_fraction > 0.95, "{}", fit.inlier_fraction);
    }

    #[test]
    fn steps_that_shrink_by_pairs_contract() {
        // Judged against the 20 sweeps left after a few: slow when it cannot converge in them.
        let slow = |(last, fastest): (f64, f64), s: f64| {
            (
                sweeps_to_converge(s, last) > 20.0,
                sweeps_to_converge(s, fastest) > 20.0,
            )
        };
        let mut steps = StepHistory::default();
        assert!(steps.contraction(1e-2).is_none());
        // A hair-crossed marker's frozen sweeps: each pair contracts 5×, its second step grows.
        let mut judged = Vec::new();
        for s in [1.3e-2, 2.3e-3, 2.5e-3, 4.4e-4, 5.0e-4, 8.7e-5] {
            if let Some(c) = steps.contraction(s) {
                judged.push(slow(c, s));
            }
            steps.push(s);
        }
        assert_eq!(judged[1], (true, false), "2.5e-3 after 2.3e-3 and 1.3e-2");
        assert!(judged.iter().all(|&(_, slow)| !slow));
        // Steps that stay put are slow either way.
        let mut flat = StepHistory::default();
        for s in [2e-3, 1.9e-3] {
            flat.push(s);
        }
        let c = flat.contraction(1.8e-3).expect("a previous step");
        assert_eq!(slow(c, 1.8e-3), (true, true));
        // A steady contraction by 0.6 (hair across a 4.5-px stamp, stress scene 82938)
        // reaches 1e-5 rad from 1.3e-2 in 15 sweeps: slow, but not given up.
        let mut steady = StepHistory::default();
        for s in [1.3e-2, 1.1e-2] {
            steady.push(s);
        }
        let c = steady.contraction(6.2e-3).expect("a previous step");
        assert_eq!(slow(c, 6.2e-3), (false, false));
        assert!((sweeps_to_converge(1e-3, 0.1) - 2.0).abs() < 1e-12);
        assert_eq!(sweeps_to_converge(1e-3, 1.0), f64::INFINITY);
        assert_eq!(sweeps_to_converge(1e-6, 1.0), 0.0);
    }

    #[test]
    fn fits_the_harmonics_at_the_nyquist_frequency() {
        // An 8-px grid along the pixel axes: the order-4 harmonics fall on the Nyquist
        // frequency, where a harmonic overlaps its own conjugate (sampled as a cosine of fixed
        // phase), and sharp dots give them weight. Demodulated as if they did not overlap,
        // their amplitudes never settled and the fit was refused.
        let truth = planes(0.0, 8.0, [0.4, -1.1]);
        let sharper = |p1: f64, p2: f64| {
            let v = (0.5 + 0.5 * p1.cos()) * (0.5 + 0.5 * p2.cos());
            0.2 + 0.6 * v.powi(6)
        };
        let image = grid(120, &truth, sharper);
        for miss in [0.05, 0.2] {
            let mut start = truth;
            start[0].c += miss;
            start[1].c -= miss;
            start[1].a *= 1.002;
            let fit = fit_dot_field(&image, start, &dots(6, &[])).expect("fit");
            // The harmonics' unseen phases leave up to 1.6e-6 rad of offset.
            assert_planes(&fit, &truth, 5e-6, 1e-8);
        }
    }

    #[test]
    fn ties_the_harmonics_of_point_symmetric_dots_only() {
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let mask = dots(6, &[]);
        let mut start = truth;
        start[0].c += 0.05;
        start[1].c -= 0.03;
        let symmetric = fit_dot_field(&grid(160, &truth, sharp), start, &mask).unwrap();
        assert!(symmetric.harmonics_tied);
        // Skewed dots (a second, offset layer: the harmonics' phases are not the dot centres'):
        // the offsets follow the fundamentals, whose phase is the planes' by construction.
        let skewed = |p1: f64, p2: f64| {
            sharp(p1, p2) + 0.04 * (2.0 * p1 + 0.5).cos() + 0.03 * (p1 + p2 - 0.7).cos()
        };
        let fit = fit_dot_field(&grid(160, &truth, skewed), start, &mask).unwrap();
        assert!(!fit.harmonics_tied);
        assert_planes(&fit, &truth, 1e-6, 1e-8);
    }

    #[test]
    fn a_fit_that_cannot_beat_its_rival_stops_and_one_that_can_is_unchanged() {
        // Sharp dots with 1 % noise (uniform, from a linear congruential sequence): no cell
        // stands out of the others, none is spoiled.
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let image = with_noise(grid(160, &truth, sharp), 0.0346, 12345);
        let mask = dots(6, &[]);
        let mut start = truth;
        start[0].c += 0.05;
        let plain = fit_dot_field(&image, start, &mask).unwrap();
        assert_eq!(plain.spoiled_cells, 0);
        let at = (3.0, -2.0);
        let rival = |std: f64| Rival {
            phase_std: [std / std::f64::consts::SQRT_2; 2],
            at,
        };
        let own = rival(0.0).field_std(&plain.covariance, plain.frame, plain.model_error_ratio);
        assert!(own > 0.0);
        // A window 100 times better: the fit stops once its weights settle.
        assert!(
            fit_dot_field_against(&image, start, &mask, Some(rival(own / 100.0)), None).is_none()
        );
        // A window it beats, or loses to by less than `HOPELESS`: the fit of `fit_dot_field`.
        // (With free harmonics, on the first sweep on settled weights, σ is twice `own` here.)
        for std in [10.0 * own, own / 2.0, own / 4.0] {
            let against =
                fit_dot_field_against(&image, start, &mask, Some(rival(std)), None).unwrap();
            assert_eq!(against.planes, plain.planes);
            assert_eq!(against.iterations, plain.iterations);
        }
    }

    #[test]
    fn ignores_a_blotch_and_irregular_nodes() {
        let truth = planes(-0.2, 11.0, [1.0, 2.0]);
        let mut image = grid(180, &truth, sharp);
        // A dark blotch over several dots, and a missing dot at a masked node.
        let (w, _) = (image.width(), image.height());
        for r in 60..80 {
            for c in 100..125 {
                image.pixels_mut()[r * w + c] = 0.05;
            }
        }
        let mask = dots(5, &[(0, 0)]);
        let fit = fit_dot_field(&image, truth, &mask).unwrap();
        // Noise-free, the blotch's rim (the pixels beside it that the biweight keeps, whose
        // residual still stands out) goes with it (`outlier_extents`): nothing is left to
        // make the harmonics' phases inconsistent, they are tied, and the offsets are 5.6e-8
        // and 4.3e-7 rad off. With the rim kept, the phases were inconsistent and the
        // fundamentals alone were 2.3e-5 and 8.8e-5 rad off.
        assert!(fit.harmonics_tied);
        assert_planes(&fit, &truth, 2e-6, 1e-8);
        assert!(fit.inlier_fraction < 0.99, "{}", fit.inlier_fraction);
    }

    #[test]
    fn an_outlier_grows_along_its_edge_and_nowhere_else() {
        // 6 × 4 residuals: a rejected core (9), its edge (4, 3.5) above the threshold 3, a
        // pixel above it but not joined to the core, and a pixel the sweep did not visit.
        let nan = f32::NAN;
        #[rustfmt::skip]
        let residuals = [
            0.0, 0.0, 0.0, 0.0, 0.0, 5.0,
            9.0, -4.0, 3.5, 1.0, 0.0, 0.0,
            0.0, 0.0, 0.0, 2.9, 0.0, 0.0,
            nan, 0.0, 0.0, 0.0, 0.0, 0.0,
        ];
        let grown = outlier_extents(&residuals, 6, 8.0, |_| 3.0);
        let which: Vec<usize> = (0..grown.len()).filter(|&i| grown[i]).collect();
        assert_eq!(which, [6, 7, 8]);
        // Every pixel is an edge where nothing reaches the cut-off: none grows.
        assert!(!outlier_extents(&residuals, 6, 10.0, |_| 0.0).contains(&true));
    }

    #[test]
    fn refuses_a_start_that_is_not_the_grid() {
        let truth = planes(0.1, 10.0, [0.0, 0.0]);
        let image = grid(128, &truth, sharp);
        let mask = dots(4, &[]);
        let wrong = planes(0.1, 13.0, [0.0, 0.0]);
        assert!(fit_dot_field(&image, wrong, &mask).is_none());
    }

    /// Where `planes` put the lattice node `(0, 0)`, image frame.
    fn centre_of(planes: &[PhasePlane; 2]) -> Vector2<f64> {
        let m = Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
        m.try_inverse().unwrap() * Vector2::new(-planes[0].c, -planes[1].c)
    }

    #[test]
    fn a_tilted_field_s_centre_is_where_its_tilt_leaves_it() {
        // Lattice coordinates u = v/(1 − p·v), v linear in the image (the `truth` planes):
        // node (0, 0) is where the truth planes vanish; linear planes fitted to the field miss
        // it by about Σ·p (0.03 period here). Sharp dots (free harmonics) and dots with no
        // harmonics at all.
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let p = Vector2::new(0.0015, -0.001);
        let smooth = |p1: f64, p2: f64| 0.5 + 0.2 * (p1.cos() + p2.cos());
        for dot in [sharp as fn(f64, f64) -> f64, smooth] {
            let image = tilted_grid(160, &truth, p, dot);
            let mask = dots(6, &[]);
            let centre = centre_of(&truth);
            let linear = fit_dot_field_against(&image, truth, &mask, None, None).unwrap();
            let tilted =
                fit_dot_field_against(&image, truth, &mask, None, Some(TiltStart::default()))
                    .unwrap();
            let missed = (centre_of(&linear.planes) - centre).norm();
            let left = (centre_of(&tilted.planes) - centre).norm();
            assert!(linear.perspective.is_none());
            let measured = tilted.perspective.unwrap();
            assert!(
                (measured - p).norm() < 0.15 * p.norm(),
                "{measured:?} for {p:?}"
            );
            assert!(tilted.tilt_weight > 0.99, "{}", tilted.tilt_weight);
            assert!(missed > 0.1, "the linear planes' bias: {missed} px");
            assert!(left < 0.1 * missed, "{left} px left of {missed}");
        }
    }

    /// An `n × n` render of `dot` on the lattice `u = v/(1 − p·v)`, `v` the linear lattice
    /// coordinates of `truth` (node (0, 0) where the truth planes vanish).
    fn tilted_grid(
        n: usize,
        truth: &[PhasePlane; 2],
        p: Vector2<f64>,
        dot: fn(f64, f64) -> f64,
    ) -> GreyImage {
        let (cx, cy) = ((n / 2) as f64, (n / 2) as f64);
        let mut px = Vec::with_capacity(n * n);
        for r in 0..n {
            for c in 0..n {
                let (x, y) = (c as f64 - cx, r as f64 - cy);
                let v = Vector2::new(truth[0].at(x, y), truth[1].at(x, y)) / TAU;
                let u = v / (1.0 - p.dot(&v));
                px.push(dot(TAU * u.x, TAU * u.y) as f32);
            }
        }
        GreyImage::new(n, n, px).unwrap()
    }

    #[test]
    fn a_steep_tilt_is_fitted_in_the_phase_to_its_centre() {
        // p·v up to 0.06 at the field's edge: one linear step leaves the centre a tenth of a
        // pixel off; with the tilt in the phase model the passes converge on it, from the flat
        // fit's step or from a coarse measure of the tilt 20 % off.
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let p = Vector2::new(0.006, -0.004);
        let image = tilted_grid(160, &truth, p, sharp);
        let mask = dots(6, &[]);
        let centre = centre_of(&truth);
        for prior in [Vector2::zeros(), p * 0.8] {
            let tilt = TiltStart {
                centre: [0.0, 0.0],
                perspective: prior,
            };
            let fit = fit_dot_field_against(&image, truth, &mask, None, Some(tilt)).unwrap();
            let measured = fit.perspective.unwrap();
            let off = (centre_of(&fit.planes) - centre).norm();
            assert!(
                (measured - p).norm() < 0.01 * p.norm(),
                "{measured:?} for {p:?}"
            );
            assert!(off < 1e-3, "centre {off:.2e} px off (prior {prior:?})");
        }
    }

    #[test]
    fn an_untilted_field_s_planes_are_not_moved_by_the_tilt_probe() {
        // Sharp dots with 2 % noise: the measured perspective is noise, which moves nothing.
        let truth = planes(0.3, 9.3, [0.4, -1.1]);
        let image = with_noise(grid(160, &truth, sharp), 0.0693, 777);
        let mask = dots(6, &[]);
        let plain = fit_dot_field_against(&image, truth, &mask, None, None).unwrap();
        let probed =
            fit_dot_field_against(&image, truth, &mask, None, Some(TiltStart::default())).unwrap();
        assert!(probed.perspective.is_some());
        assert_eq!(probed.tilt_weight, 0.0);
        for (a, b) in plain.planes.iter().zip(&probed.planes) {
            assert_eq!((a.a, a.b, a.c), (b.a, b.b, b.c));
        }
    }

    #[test]
    fn clearance_keeps_off_missing_dots_and_the_edge() {
        // Dots at nodes −3..=3 without (0, 0): cell (0, 0) is discrepant, and so is every dot
        // cell beyond the edge (node ±4, cell ±8).
        let mask = dots(3, &[(0, 0)]);
        let at = |v1: f64, v2: f64| mask.clearance([v1, v2]);
        let taper = |d: f64| (0.5 * PI * d / MIN_CLEARANCE).sin().powi(2);
        assert_eq!(at(0.2, -0.4), 0.0);
        assert!((at(1.0, 0.0) - taper(0.5)).abs() < 1e-12);
        assert!((at(1.5, 1.5) - taper(2.0f64.sqrt())).abs() < 1e-12);
        assert_eq!(at(2.5, 0.0), 1.0);
        assert_eq!(at(4.0, 4.0), 1.0);
        assert!((at(6.0, 2.0) - taper(1.5)).abs() < 1e-12);
        assert_eq!(at(7.6, 2.0), 0.0);
    }

    #[test]
    fn layout_weight_is_a_partition_of_unity() {
        let mask = dots(3, &[]);
        let plain = NodeWeights::new(&mask, &[]);
        let weight = |u: [f64; 2]| plain.weight(u, u.map(|v| (PI * v).cos())).0;
        for &(u1, u2) in &[(0.0, 0.0), (0.3, -1.7), (2.49, 1.01), (-2.2, 2.9)] {
            assert!((weight([u1, u2]) - 1.0).abs() < 1e-12);
        }
        assert_eq!(weight([4.0, 0.0]), 0.0);
        assert!((weight([3.5, 0.0]) - 0.5).abs() < 1e-12);
        // Lower weight near a node whose robust weight is 0, none at it.
        let nodes: Vec<f64> = (0..mask.len())
            .map(|i| if i == 24 { 0.0 } else { 1.0 })
            .collect();
        let robust = NodeWeights::new(&mask, &nodes);
        let at = |u: [f64; 2]| robust.weight(u, u.map(|v| (PI * v).cos())).1;
        assert_eq!(at([0.0, 0.0]), 0.0);
        assert!((at([0.5, 0.0]) - 0.5).abs() < 1e-12 && at([1.0, 0.0]) == 1.0);
    }
}
