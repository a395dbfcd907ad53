//! One pass of the fit ([`fit_pass`]): Gauss–Newton sweeps to convergence ([`converge`]),
//! the robust weights frozen between them, and the test that ties the harmonics to the dot
//! centres ([`symmetric_shift`]).

use super::*;

/// One pass of the whole-field fit from `start`, with `warp` in its phase model if given and
/// from the last frame's model `warm` if given: the fit, and the mean square residual its
/// tilt explains over the white noise's variance.
#[inline(always)]
pub(super) fn fit_pass(
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
        // both (the centre moved with the lattice), and the weights that its final sweeps
        // froze, moved with the nodes.
        Some(warm) => {
            let nodes = mask.centroid_at(&start)?;
            let (mut model, (x0, y0)) = warm.moved_to(&start, field.frame.2, nodes)?;
            field.frame = (x0, y0, field.frame.2);
            if let Some(weights) = &warm.weights {
                model.frozen = weights.moved_into(&field, nodes);
            }
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
    let (step, free_settled) = match converge(image, &field, mask, &mut model, goal, &mut run) {
        Ok(step) => (step, true),
        Err(Stall::AtLimit(step)) if !model.tied => (*step, false),
        Err(_) => return None,
    };
    let (mut model, step) = tie_harmonics(
        image,
        (&field, mask),
        goal,
        &mut run,
        (model, step),
        free_settled,
    )?;
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
    let nodes = mask.centroid_at(&converged)?;
    let fit = finished_fit(
        model,
        &step,
        (&field, nodes),
        start,
        converged,
        run.iterations,
    );
    Some((fit, step.tilt_misfit))
}

/// A free stage's model and last step `free` tied to the dot centres where the harmonics'
/// phases show point-symmetric dots ([`symmetric_shift`]), and settled again; the free ones
/// where they do not, or where the tied fit does not settle and the free one did
/// (`free_settled`). `None` when neither settled.
#[inline(always)]
fn tie_harmonics(
    image: &GreyImage,
    (field, mask): (&FieldBox, &NodeMask),
    goal: &Goal,
    run: &mut Run,
    (model, step): (Model, Step),
    free_settled: bool,
) -> Option<(Model, Step)> {
    let shift = if model.tied {
        None
    } else {
        symmetric_shift(&model, &step)
    };
    let Some(shift) = shift else {
        return free_settled.then_some((model, step));
    };
    let mut tied = model.clone();
    tied.tie(shift);
    // Not a closure: it would be compiled apart from the AVX2 caller, without its target
    // features.
    let settled = match run.add_shift(shift.map(f64::abs)) {
        Some(()) => converge(image, field, mask, &mut tied, goal, run),
        None => Err(Stall::Failed),
    };
    match settled {
        Ok(tied_step) => Some((tied, tied_step)),
        // A tied fit that does not settle leaves the free one standing, if it settled.
        Err(_) => free_settled.then_some((model, step)),
    }
}

/// The fit of a pass that converged on `model` (its planes moved to where the tilt leaves
/// them at the centre) over `field` with last sweep `step`, from `start`, after `iterations`
/// sweeps; `converged`: the planes the sweeps converged to, where the next frame's fit starts,
/// and `nodes` the mask's nodes' centroid there.
fn finished_fit(
    mut model: Model,
    step: &Step,
    (field, nodes): (&FieldBox, Vector2<f64>),
    start: [PhasePlane; 2],
    converged: [PhasePlane; 2],
    iterations: usize,
) -> FieldFit {
    let (perspective, tilt_weight) = step
        .tilt
        .map_or((None, 0.0), |t| (Some(t.perspective), t.weight));
    let weights = (!model.frozen.is_empty()).then(|| CarriedWeights {
        values: std::mem::take(&mut model.frozen),
        width: field.cols.len(),
        origin_from_nodes: field.origin() - nodes,
    });
    FieldFit {
        perspective,
        perspective_covariance: step.tilt.map(|t| t.covariance),
        tilt_weight,
        start,
        planes: model.planes,
        amplitudes: [model.linear[3].abs(), model.linear[6].abs()],
        residual_std: step.residual_std,
        inlier_fraction: step.inlier_fraction,
        spoiled_cells: spoiled_cells(&model.cells, &step.cells),
        pixels: step.pixels,
        iterations,
        harmonics: model.harmonics.len(),
        harmonics_tied: model.tied,
        covariance: step.covariance,
        model_error_ratio: step.model_error_ratio,
        frame: field.frame,
        warm: Box::new(WarmModel {
            model: Model {
                planes: converged,
                ..model
            },
            weights,
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
    }
}

/// What a fit works against: the white noise measured apart from the model (intensity
/// variance, see [`iterate`]) and the window fit it must beat, if any.
pub(super) struct Goal {
    pub(super) white: Option<f64>,
    pub(super) rival: Option<Rival>,
    /// Lattice coordinates of the marker centre, periods (the planes' numbering), when the fit
    /// is to measure the field's tilt about it ([`Tilt`]).
    pub(super) tilt_centre: Option<[f64; 2]>,
    /// The perspective the coarse step measured ([`TiltStart::perspective`]).
    pub(super) prior: Vector2<f64>,
    /// How the fitted image was sampled from the input.
    pub(super) sampling: Sampling,
}

/// How the fitted image was sampled from the input (docs/design.md#anti-aliased-binning).
#[derive(Clone, Copy)]
pub(super) struct Sampling {
    /// Binned through the anti-aliasing filter: nothing folds, and harmonics beyond the
    /// Nyquist square are not modelled ([`resolvable_harmonics`]).
    pub(super) unaliased: bool,
    /// The noise variance at the planes' frequencies over the image's total noise variance,
    /// which the noise estimates measure: 1 for the input's own (white) noise, more where
    /// the filter took the noise's upper band away ([`crate::decimate::noise_gain`]).
    pub(super) noise_colour: f64,
}

impl Sampling {
    /// The input's own pixels.
    pub(super) const DIRECT: Sampling = Sampling {
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
    pub(super) fn hopeless(&self, model: &Model, step: &Step, field: &FieldBox) -> bool {
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
pub(super) const HOPELESS: f64 = 10.0;

/// Iteration state of one fit, across its free and tied stages.
#[derive(Default)]
pub(super) struct Run<'a> {
    /// The last frame's model, when tracking: its robust weights are frozen on the first
    /// sweep if that sweep shows the same field ([`WarmModel::still_fits`]).
    pub(super) warm: Option<&'a WarmModel>,
    /// Sweeps run (the start's not counted).
    pub(super) iterations: usize,
    /// How far each plane moved in all, `Σ(|α| + |β| + |γ|)`, radians.
    pub(super) total_shift: [f64; 2],
    /// The iteration that froze the weights; every iteration before it updated them.
    pub(super) frozen_at: Option<usize>,
}

/// Why a stage of the fit stopped before converging.
pub(super) enum Stall {
    /// Still contracting after [`MAX_ITERATIONS`]: the last sweep's output.
    AtLimit(Box<Step>),
    /// Not contracting, or refused (the planes moved too far, a singular step).
    Failed,
}

impl Run<'_> {
    /// Adds a move of each plane (radians); `None` (the fit refused) once a plane has moved by
    /// [`MAX_CORRECTION`] in all, or a move was not a number.
    pub(super) fn add_shift(&mut self, moved: [f64; 2]) -> Option<()> {
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
pub(super) fn converge(
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
        let moved = move_planes(&mut model.planes, &step, field.frame);
        let largest = moved[0].max(moved[1]);
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
            // A warm first sweep that showed another field drops the carried weights too.
            model.frozen.clear();
            set_robust_weights(model, &step, mask);
        }
        // With the weights frozen, the iterations solve one fixed problem and contract
        // geometrically. One that cannot reach convergence in the iterations left is given up
        // at once when its step is large, or when it happens twice running (one slow
        // iteration is a weakly determined harmonic settling). A slow but steady one runs on.
        let contraction = steps.contraction(largest);
        let left = (MAX_ITERATIONS - stage_iteration) as f64;
        let slow = run.frozen_at.is_some_and(|f| iteration > f + 1)
            && too_slow(contraction, largest, left);
        if slow && (largest > GIVE_UP_STEP || slow_before) {
            log::debug!(
                "whole-field fit not contracting: step {largest:.1e} rad after {:.1e}",
                steps.previous
            );
            return Err(Stall::Failed);
        }
        slow_before = slow;
        let tail = match run.frozen_at {
            Some(f) if iteration > f => steps_to_come(contraction, largest),
            _ => f64::INFINITY,
        };
        steps.push(largest);
        let converged = largest < CONVERGED || tail < tail_tolerance(&step.covariance);
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

/// Whether a frozen problem whose steps contract as `contraction` shows (over the last sweep
/// or the last two, [`StepHistory::contraction`]) cannot bring its step `largest` under
/// [`CONVERGED`] in the `left` sweeps remaining: a field the model does not describe, or
/// harmonics that swap residual with the planes, would use them all up and still be refused.
fn too_slow(contraction: Option<(f64, f64)>, largest: f64, left: f64) -> bool {
    contraction.is_some_and(|(_, fastest)| sweeps_to_converge(largest, fastest) > left)
        && largest >= CONVERGED
}

/// The steps still to come after a step `largest` of the frozen problem: the geometric tail of
/// its contraction over the last sweep (infinite without a previous step of this stage, or
/// without contraction). Gauss–Newton speeds up as it converges, so the last sweep's
/// contraction is the one still to come; where a pair of sweeps contracts and its second step
/// grows, the next pair's first step is large again and the test waits for it.
fn steps_to_come(contraction: Option<(f64, f64)>, largest: f64) -> f64 {
    match contraction {
        Some((last, _)) if last < 1.0 => largest * last / (1.0 - last),
        _ => f64::INFINITY,
    }
}

/// Moves each plane by its correction in `step` (normalised coordinates of `frame`); how far
/// each moved, `|α| + |β| + |γ|`, radians.
fn move_planes(planes: &mut [PhasePlane; 2], step: &Step, frame: (f64, f64, f64)) -> [f64; 2] {
    let mut moved = [0.0; 2];
    for (l, p) in planes.iter_mut().enumerate() {
        let d = [
            step.delta[3 * l],
            step.delta[3 * l + 1],
            step.delta[3 * l + 2],
        ];
        correct_plane(p, d, frame);
        moved[l] = d[0].abs() + d[1].abs() + d[2].abs();
    }
    moved
}

/// The steps still to come below which a fit has converged: [`CONVERGED_TAIL_OF_SIGMA`] of
/// the planes' σ (the smaller plane's, summed over its three terms, from `covariance`), at
/// least [`CONVERGED_TAIL`] of [`CONVERGED`].
fn tail_tolerance(covariance: &Matrix6<f64>) -> f64 {
    let sigma = [0, 1]
        .map(|l| {
            (0..3)
                .map(|k| covariance[(3 * l + k, 3 * l + k)])
                .sum::<f64>()
        })
        .into_iter()
        .fold(f64::INFINITY, f64::min)
        .sqrt();
    (CONVERGED_TAIL * CONVERGED).max(CONVERGED_TAIL_OF_SIGMA * sigma)
}

/// The largest plane steps of a stage's last two iterations, radians (infinite before there
/// are any).
pub(super) struct StepHistory {
    pub(super) previous: f64,
    pub(super) before_previous: f64,
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
    pub(super) fn contraction(&self, largest: f64) -> Option<(f64, f64)> {
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

    pub(super) fn push(&mut self, largest: f64) {
        self.before_previous = self.previous;
        self.previous = largest;
    }
}

/// Sweeps a fit whose steps contract by `q` per sweep needs from a step `step` (radians)
/// until its step is below [`CONVERGED`]: `ln(CONVERGED/step)/ln q`, infinite when it does
/// not contract (`q ≥ 1`, or not a number).
pub(super) fn sweeps_to_converge(step: f64, q: f64) -> f64 {
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
pub(super) fn correct_plane(plane: &mut PhasePlane, d: [f64; 3], (x0, y0, s): (f64, f64, f64)) {
    plane.a += d[0] / s;
    plane.b += d[1] / s;
    plane.c += d[2] - d[0] * x0 / s - d[1] * y0 / s;
}

/// Level of the fit's tests (the two point-symmetry tests of [`symmetric_shift`], the tilt's
/// significance, [`Tilt::weight`]): 10⁻³. `−2·ln 10⁻³` is the upper quantile of χ² with two
/// degrees of freedom; [`SYMMETRY_TEST_Z`] the standard normal one, for other degrees of
/// freedom.
pub(super) const TEST_LIMIT_TWO_DOF: f64 = 13.815_510_557_964_274;

/// Standard normal quantile at `1 − 10⁻³`.
pub(super) const SYMMETRY_TEST_Z: f64 = 3.090_232_306_167_813;

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
pub(super) fn symmetric_shift(model: &Model, step: &Step) -> Option<[f64; 2]> {
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
pub(super) fn chi_square_quantile(dof: f64, z: f64) -> f64 {
    let v = 2.0 / (9.0 * dof);
    dof * (1.0 - v + z * v.sqrt()).powi(3)
}

/// Number of whole cells (at least half the largest cell's layout weight: clear of the
/// layout's other features) whose robust weight is below 1. `sums`: `(Σ w_L·r², Σ w_L)` per
/// node.
pub(super) fn spoiled_cells(weights: &[f64], sums: &[[f64; 2]]) -> usize {
    let whole = whole_cells(sums);
    (0..weights.len())
        .filter(|&i| weights[i] < 1.0 && whole(i))
        .count()
}

/// Whether cell `i` is whole: at least half the largest cell's layout weight (`sums`:
/// `(Σ w_L·r², Σ w_L)` per node), i.e. clear of the layout's other features and of the field's
/// edge.
pub(super) fn whole_cells(sums: &[[f64; 2]]) -> impl Fn(usize) -> bool + '_ {
    let largest = sums.iter().map(|s| s[1]).fold(0.0, f64::max);
    move |i| sums.get(i).is_some_and(|s| s[1] >= 0.5 * largest)
}

/// The pixels that an outlier covers, from a sweep's `residuals` (row-major, `width` per row,
/// NaN where the sweep did not go): each pixel whose residual reaches the biweight's `cutoff`
/// (weight 0 already), grown by hysteresis, as Canny grows edges (Canny 1986), into the
/// 8-connected pixels `j` whose residual exceeds `edge(j)` in magnitude. The biweight gives the
/// soft, blurred edge of a hair or of dust almost full weight; that edge is not point-symmetric
/// about the dots it crosses and pulls their centres.
pub(super) fn outlier_extents(
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
pub(super) fn frozen_weights(
    step: &mut Step,
    cutoff: Option<f64>,
    mask: &NodeMask,
    width: usize,
) -> Vec<f32> {
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
pub(super) fn set_robust_weights(model: &mut Model, step: &Step, mask: &NodeMask) {
    let floor = MIN_CUTOFF * model.contrast();
    model.cutoff = Some((TUKEY_BIWEIGHT * step.residual_std).max(floor)).filter(|c| *c > 0.0);
    model.cells = cell_weights(&step.cells, mask.dims);
}
