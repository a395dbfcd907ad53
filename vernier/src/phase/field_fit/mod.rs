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
//!
//! **Files, by stage** (data flows down the list): `mask` (the layout and its clearance),
//! `pixels` (the field's box, its tilt warp and the pixels a sweep visits), `model` (the
//! harmonics and the start sweep), `bank` (the harmonics' SIMD bank), `sweep` (one sweep's
//! residuals and normal equations), `converge` (a pass of sweeps to convergence, robust
//! weights, tying), `warm` (the tracked fit's start); this file holds the entry points, the
//! passes over a tilted field and [`FieldFit`].

mod bank;
mod converge;
mod mask;
mod model;
mod pixels;
mod sweep;
#[cfg(test)]
mod tests;
mod warm;

use super::noise::{quantisation_variance_in, tilted_white_noise_variance, with_plan, LatticeTilt};
use super::normal_equations::NormalEquations;
use super::plane::{wrap_to_pi, PhasePlane};
use super::MIN_NOISE_STD;
use crate::grey_image::GreyImage;
use crate::order_stats::{median, robust_sigma, TUKEY_BIWEIGHT};
use bank::*;
use converge::*;
pub use mask::NodeMask;
use mask::*;
use model::*;
use nalgebra::{DMatrix, DVector, Matrix2, Matrix4, Matrix6, SMatrix, SVector, Vector2, Vector6};
use num_complex::Complex64;
use pixels::*;
use std::f64::consts::{PI, SQRT_2, TAU};
use sweep::*;
use warm::*;

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
/// by a tenth of its σ at most, which adds at most 0.5 % to its variance (the error left is
/// independent of the noise's), and saves the sweeps a fixed tolerance would run: 15 % of a
/// tracked fit's sweeps on the real sequence `Image96`–`Image125`, which moved its poses by
/// at most 0.04 mpx and 0.8 µrad (σ ≈ 1 mpx and 5–15 µrad).
const CONVERGED_TAIL_OF_SIGMA: f64 = 0.1;

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
    /// Covariance of [`FieldFit::perspective`], per period squared, with the residual's
    /// model error counted (its last pass's estimate; what earlier passes took into the phase
    /// model is a constant of that pass). `None` with `perspective`.
    pub perspective_covariance: Option<Matrix2<f64>>,
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

    /// Covariance of the planes' gradients `(a₁, b₁, a₂, b₂)` (`∂φ_l/∂col`, `∂φ_l/∂row`,
    /// image frame), (rad/pixel)², white noise alone as [`FieldFit::phase_std_at`].
    pub fn gradient_covariance(&self) -> Matrix4<f64> {
        let s = self.frame.2;
        // (α_l, β_l, γ_l) = (x slope, y slope, offset) in normalised coordinates.
        let slopes = [0, 1, 3, 4];
        Matrix4::from_fn(|i, j| self.covariance[(slopes[i], slopes[j])] / (s * s))
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
    let sub = SubImage::new(image, &field, binning_factor(&start))?;
    let start_sub = start.map(|p| sub.plane_in_sub(&p));
    let goal = sub.goal(&start_sub, rival, tilt);
    let warm = match warm {
        Some(w) => Some(w.in_sub_frame(sub.factor, sub.offset)?),
        None => None,
    };
    let fit = fit_dot_field_dispatch(&sub.image, start_sub, mask, goal, warm.as_ref())?;
    sub.fit_in_image(fit, window, mask)
}

/// The binning factor of a field fitted from `start`: 2 while the binned period stays at
/// least [`MIN_BINNED_PERIOD`], else 1.
fn binning_factor(start: &[PhasePlane; 2]) -> usize {
    let period = start
        .iter()
        .map(|p| p.pixel_period())
        .fold(f64::INFINITY, f64::min);
    if period / 2.0 >= MIN_BINNED_PERIOD {
        2
    } else {
        1
    }
}

/// The image a field is fitted on: the field's box, binned 2×2 (`factor` 2) or as it is.
struct SubImage {
    image: GreyImage,
    /// The binning factor `f`, 1 or 2.
    factor: usize,
    /// The input's rounding variance, per pixel of `sub`.
    rounding: f64,
    sampling: Sampling,
    /// Image-frame `x, y` of `sub`'s frame origin: `x = f·x_s + offset` for sub-image frame
    /// coordinate `x_s = i − w_s div 2` and binning factor `f`.
    offset: [f64; 2],
}

impl SubImage {
    /// The sub-image of `field`'s box in `image`, binned by `factor` (1 or 2).
    fn new(image: &GreyImage, field: &FieldBox, factor: usize) -> Option<SubImage> {
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
        Some(SubImage {
            image: sub,
            factor,
            rounding,
            sampling,
            offset,
        })
    }

    /// Plane `p` of the input image's frame in the sub-image's frame.
    fn plane_in_sub(&self, p: &PhasePlane) -> PhasePlane {
        let (f, offset) = (self.factor as f64, self.offset);
        PhasePlane {
            a: f * p.a,
            b: f * p.b,
            c: p.c + p.a * offset[0] + p.b * offset[1],
        }
    }

    /// Plane `p` of the sub-image's frame in the input image's frame.
    fn plane_in_image(&self, p: PhasePlane) -> PhasePlane {
        let (f, offset) = (self.factor as f64, self.offset);
        let (a, b) = (p.a / f, p.b / f);
        PhasePlane {
            a,
            b,
            c: p.c - a * offset[0] - b * offset[1],
        }
    }

    /// What the fit from `start_sub` (the sub-image's frame) works against: the white noise
    /// measured apart from the model, and `rival` moved to the sub-image's frame.
    fn goal(
        &self,
        start_sub: &[PhasePlane; 2],
        rival: Option<Rival>,
        tilt: Option<TiltStart>,
    ) -> Goal {
        let (f, offset, sub) = (self.factor as f64, self.offset, &self.image);
        // White noise measured apart from the model (lattice second differences): where the
        // model stops short of the dots' detail (sharp dots many pixels wide), the residual
        // is static model error, which does not scatter the result from frame to frame.
        // On a steeply tilted field, read only where the lattice still matches the planes
        // (near the tilt's centre): the dots' edges elsewhere would read as noise and hide
        // the tilt.
        let lattice_tilt = tilt.map(|t| LatticeTilt {
            centre: t.centre,
            perspective: [t.perspective.x, t.perspective.y],
        });
        let white = with_plan(sub.height(), sub.width(), |plan| {
            tilted_white_noise_variance(sub.pixels(), start_sub, plan, lattice_tilt)
        })
        .map(|v| v.max(self.rounding));
        // The rival's point in the (binned) sub-image frame.
        let rival = rival.map(|r| Rival {
            at: ((r.at.0 - offset[0]) / f, (r.at.1 - offset[1]) / f),
            ..r
        });
        Goal {
            white,
            rival,
            tilt_centre: tilt.map(|t| t.centre),
            prior: tilt.map_or(Vector2::zeros(), |t| t.perspective),
            sampling: self.sampling,
        }
    }

    /// `fit`, made on the sub-image from the planes `window` (input image frame), in the input
    /// image's frame, with what the next frame's tracked fit starts from.
    fn fit_in_image(
        &self,
        mut fit: FieldFit,
        window: [PhasePlane; 2],
        mask: &NodeMask,
    ) -> Option<FieldFit> {
        let (f, offset) = (self.factor as f64, self.offset);
        fit.planes = fit.planes.map(|p| self.plane_in_image(p));
        fit.start = window;
        let (x0, y0, s) = fit.frame;
        fit.frame = (f * x0 + offset[0], f * y0 + offset[1], f * s);
        let converged = fit.warm.model.planes.map(|p| self.plane_in_image(p));
        fit.warm.model.planes = converged;
        fit.warm.correction = [0, 1].map(|l| PhasePlane {
            a: converged[l].a - window[l].a,
            b: converged[l].b - window[l].b,
            c: converged[l].c - window[l].c,
        });
        let nodes = mask.centroid_at(&fit.planes)?;
        fit.warm.frame = (fit.frame.0 - nodes.x, fit.frame.1 - nodes.y, fit.frame.2);
        fit.warm.factor = self.factor;
        fit.warm.weights = fit.warm.weights.map(|w| w.scaled(f));
        Some(fit)
    }
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
