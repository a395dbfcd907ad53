//! One sweep over the field ([`iterate`]): residuals, robust weights, the weighted normal
//! equations (with the tilt's columns when measured, [`Tilt`]) and the cells' weights.

use super::*;

/// One sweep's normal equations: the plain unknowns, or with the tilt's four columns as well
/// when the fit measures the field's tilt ([`Tilt`]). The tilted system's first [`UNKNOWNS`]
/// rows and columns are the plain system's, entry for entry (each entry is its own dot
/// product of the same columns), so measuring the tilt leaves the fit's steps as they are.
// One per sweep, on the stack: the variants' sizes differ by design.
#[allow(clippy::large_enum_variant)]
pub(super) enum Equations {
    Plain(NormalEquations<UNKNOWNS>),
    Tilted(NormalEquations<TILTED>),
}

impl Equations {
    /// Adds an observation; `tilt_columns` gives the tilt's four basis functions, asked for
    /// only when measured.
    #[inline(always)]
    pub(super) fn add(
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
    pub(super) fn finish(
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
pub(super) struct Tilt {
    /// Estimated perspective `p`, per period.
    pub(super) perspective: Vector2<f64>,
    /// Its information (the Schur complement of the other unknowns, weighted squares per unit
    /// of `p` squared).
    pub(super) information: Matrix2<f64>,
    /// Covariance of `p`, per period squared: `s·I⁻¹`, model error included (`s` as in
    /// [`Tilt::weight`]).
    pub(super) covariance: Matrix2<f64>,
    /// How much of `p` the planes take, in `[0, 1)`: the soft threshold `1 − χ²₀/χ²` of its
    /// Mahalanobis square `χ² = pᵀ·I·p/s` (`s` the residual's scale, model error included)
    /// above [`TEST_LIMIT_TWO_DOF`] `χ²₀`, zero below. On an untilted field `p` is noise,
    /// which must not move the planes; on a tilted one `χ²` runs into the thousands and nearly
    /// all of `p` is taken. Continuous, so the planes do not jump where a tilt becomes
    /// significant.
    pub(super) weight: f64,
    /// How the other unknowns (the linear ones, then the plane corrections) change per unit
    /// of `p`, each re-solved with it.
    pub(super) response: SMatrix<f64, UNKNOWNS, 2>,
}

impl Tilt {
    /// The tilt from a sweep's tilted normal equations `normal·x = rhs`
    /// (`harmonic_offsets`: the model has free harmonics, whose phase offsets are unknowns
    /// too; tied ones have none of their own), `scale` the variance of a unit-weight
    /// observation times `Σw²/Σw`. The other unknowns are eliminated (Schur complement), so
    /// that `p` is estimated with them.
    pub(super) fn estimate(
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
        let inverse = reduced.try_inverse()?;
        let perspective =
            inverse * Vector2::new(rhs[tilt[0]] - pulled[0], rhs[tilt[1]] - pulled[1]);
        let chi2 = perspective.dot(&(reduced * perspective)) / scale;
        let weight = if chi2.is_finite() && chi2 > TEST_LIMIT_TWO_DOF {
            1.0 - TEST_LIMIT_TWO_DOF / chi2
        } else {
            0.0
        };
        perspective.iter().all(|v| v.is_finite()).then(|| Tilt {
            perspective,
            information: reduced,
            covariance: inverse * scale,
            weight,
            response: SMatrix::from_fn(|i, j| response[(i, j)]),
        })
    }

    /// The perspective the planes take: `p` times [`Tilt::weight`].
    pub(super) fn taken(&self) -> Vector2<f64> {
        self.perspective * self.weight
    }

    /// The plane corrections `(α₁, β₁, γ₁, α₂, β₂, γ₂)` that taking [`Tilt::taken`] makes (the
    /// other unknowns re-solved with it): to first order, the fixed point of the fit with
    /// this tilt in its phase.
    pub(super) fn planes_shift(&self) -> Vector6<f64> {
        -(self.response.fixed_rows::<6>(LINEAR) * self.taken())
    }

    /// The weighted squares of the residual that taking [`Tilt::taken`] removes (the whole
    /// estimate would remove `pᵀ·I·p`, `I` its information).
    pub(super) fn explained_squares(&self) -> f64 {
        let (p, t) = (self.perspective, self.taken());
        (2.0 * t.dot(&(self.information * p)) - t.dot(&(self.information * t))).max(0.0)
    }

    /// Covariance of the plane corrections added by taking the tilt, per unit variance of a
    /// weighted observation: `w²·R·I⁻¹·Rᵀ` (`R` the response, `I` the information, `w` the
    /// weight).
    pub(super) fn planes_covariance(&self) -> Matrix6<f64> {
        let weight = self.weight;
        let planes = self.response.fixed_rows::<6>(LINEAR);
        match self.information.try_inverse() {
            Some(inverse) => planes * inverse * planes.transpose() * (weight * weight),
            None => Matrix6::zeros(),
        }
    }
}

/// Output of one iteration.
pub(super) struct Step {
    pub(super) linear: SVector<f64, LINEAR>,
    /// `(α₁, β₁, γ₁, α₂, β₂, γ₂)`.
    pub(super) delta: Vector6<f64>,
    /// Correction of each modelled harmonic's amplitude.
    pub(super) harmonics: Vec<Complex64>,
    pub(super) covariance: Matrix6<f64>,
    /// Residual scale over white-noise σ, ≥ 1.
    pub(super) model_error_ratio: f64,
    /// Robust standard deviation of the residuals before the step.
    pub(super) residual_std: f64,
    pub(super) inlier_fraction: f64,
    pub(super) pixels: usize,
    /// `(Σ w_L·r², Σ w_L)` of each cell (per node of the mask).
    pub(super) cells: Vec<[f64; 2]>,
    /// The pixels' robust weights of this iteration, when asked to freeze them.
    pub(super) frozen: Vec<f32>,
    /// With them, each pixel's residual (NaN where the sweep did not go) and cell (the
    /// index of its nearest node in per-node arrays, `u32::MAX` outside the mask), row-major
    /// over the box.
    pub(super) frozen_residuals: Vec<f32>,
    pub(super) frozen_cells: Vec<u32>,
    /// Centroid `(X̄, Ȳ)` of the demodulation's weights (normalised coordinates): where the
    /// harmonics' corrections are measured.
    pub(super) centroid: [f64; 2],
    /// Variance of the real and of the imaginary part of a demodulated amplitude under the
    /// white noise, `2σ²·Σw²/(Σw)²`, intensity units².
    pub(super) amplitude_variance: f64,
    /// The field's tilt as this sweep measured it, when asked ([`Goal::tilt_centre`]).
    pub(super) tilt: Option<Tilt>,
    /// The mean square residual that taking the tilt removes, over the white noise's variance.
    pub(super) tilt_misfit: f64,
}

/// One sweep over the field: residuals of the current model, their robust weights, the
/// weighted normal equations of the linearised model (solved), and the harmonics' correction:
/// the demodulated *clipped residual* `ψ(r) = r·w_T(r)` under the layout weight — a Newton step
/// towards the M-estimate that keeps the harmonics orthogonal (reweighting the demodulation
/// itself would mix them).
#[inline(always)]
pub(super) fn iterate(
    image: &GreyImage,
    field: &FieldBox,
    mask: &NodeMask,
    model: &Model,
    freeze: bool,
    goal: &Goal,
) -> Option<Step> {
    // The tilt is probed on the fixed problem of frozen weights, where the fit converges.
    let tilt_centre = goal.tilt_centre.filter(|_| !model.frozen.is_empty());
    let mut sums = SweepSums::new(field, mask, freeze, tilt_centre.is_some());
    let mut bank = HarmonicBank::new(&model.harmonics, &model.planes);
    for p in field.pixels(image, &model.planes, mask, &model.cells) {
        sums.add(&p, &mut bank, model, tilt_centre);
    }
    sums.solve(model, goal, bank)
}

/// What one sweep accumulates over the field's pixels, before its solve ([`iterate`]).
struct SweepSums {
    equations: Equations,
    /// `Σw`, `Σw²` and `Σw·r²` of the robust weights `w`, and `Σw_L` of the layout's.
    sum_w: f64,
    sum_w2: f64,
    sum_wr2: f64,
    sum_layout: f64,
    /// `Σw·X`, `Σw·Y`: the demodulation's centroid.
    sum_wx: f64,
    sum_wy: f64,
    pixels: usize,
    /// `|r|` of the pixels of at least half weight: the robust scale's sample.
    residuals: Vec<f64>,
    /// `(Σ w_L·r², Σ w_L)` per node of the mask.
    cells: Vec<[f64; 2]>,
    /// When freezing: each pixel's robust weight, residual and cell ([`Step::frozen`]).
    frozen: Vec<f32>,
    frozen_residuals: Vec<f32>,
    frozen_cells: Vec<u32>,
}

impl SweepSums {
    /// Empty sums for a sweep of `field`; `tilted` adds the tilt's columns to the equations.
    fn new(field: &FieldBox, mask: &NodeMask, freeze: bool, tilted: bool) -> Self {
        let frozen = if freeze {
            vec![0.0f32; field.rows.len() * field.cols.len()]
        } else {
            Vec::new()
        };
        SweepSums {
            equations: match tilted {
                true => Equations::Tilted(NormalEquations::new()),
                false => Equations::Plain(NormalEquations::new()),
            },
            sum_w: 0.0,
            sum_w2: 0.0,
            sum_wr2: 0.0,
            sum_layout: 0.0,
            sum_wx: 0.0,
            sum_wy: 0.0,
            pixels: 0,
            residuals: Vec::new(),
            cells: vec![[0.0f64; 2]; mask.len()],
            frozen_residuals: vec![f32::NAN; frozen.len()],
            frozen_cells: vec![u32::MAX; frozen.len()],
            frozen,
        }
    }

    /// Adds pixel `p`: its residual under `model` (the bank moved to it), its robust weight,
    /// its demodulation and its row of the normal equations.
    #[inline(always)]
    fn add(
        &mut self,
        p: &Pixel,
        bank: &mut HarmonicBank,
        model: &Model,
        tilt_centre: Option<[f64; 2]>,
    ) {
        bank.move_to(p);
        let (h, h_slope) = bank.evaluate();
        let gain = model.gain(p);
        let r = p.g - gain * h - model.linear_at(p);
        // NaN: a pixel that a tracked fit's carried weights do not cover.
        let frozen = model.frozen.get(p.index).filter(|w| !w.is_nan());
        let robust = frozen.map_or_else(|| model.robust(r), |&w| w as f64);
        if let Some(slot) = self.frozen.get_mut(p.index) {
            // The weights freeze on this sweep's own judgment: a tracked fit's first sweep
            // solves on the last frame's weights but freezes this frame's.
            *slot = match frozen {
                Some(_) => model.robust(r),
                None => robust,
            } as f32;
            if let (Some(q), Some(c)) = (
                self.frozen_residuals.get_mut(p.index),
                self.frozen_cells.get_mut(p.index),
            ) {
                *q = r as f32;
                *c = p.cell.map_or(u32::MAX, |c| c as u32);
            }
        }
        self.pixels += 1;
        self.sum_layout += p.layout;
        if p.w >= 0.5 {
            self.residuals.push(r.abs());
        }
        if let Some(cell) = p.cell.and_then(|i| self.cells.get_mut(i)) {
            cell[0] += p.layout * r * r;
            cell[1] += p.layout;
        }
        bank.demodulate(p.w * r * robust);
        let w = p.w * robust;
        if w <= 0.0 {
            return;
        }
        self.sum_w += w;
        self.sum_wx += w * p.xn;
        self.sum_wy += w * p.yn;
        self.sum_w2 += w * w;
        self.sum_wr2 += w * r * r;
        let (basis, slopes) = basis_at(p, model, h, h_slope, gain);
        // The residual, `g − h` less the basis times the current linear unknowns (the
        // corrections' columns at 0): [`SweepSums::solve`] adds the model back.
        self.equations.add(&basis, r, w, || {
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

    /// Solves the sweep's normal equations: the step, its covariance under the white noise,
    /// the tilt measured, and the harmonics' corrections from `bank`'s demodulation sums.
    fn solve(mut self, model: &Model, goal: &Goal, mut bank: HarmonicBank) -> Option<Step> {
        let (sum_w, sum_w2, sum_wr2) = (self.sum_w, self.sum_w2, self.sum_wr2);
        if sum_w <= 0.0 || self.sum_layout <= 0.0 {
            return None;
        }
        let (normal, residual_rhs, tilted) = self.equations.finish();
        // The equations hold the residuals: the solution is a correction of the current linear
        // unknowns (the plane corrections and the tilt's unknowns are corrections of 0, so the
        // tilt's estimate is the same as from `g − h`).
        let current = SVector::<f64, UNKNOWNS>::from_fn(|i, _| match i {
            i if i < LINEAR => model.linear[i],
            _ => 0.0,
        });
        let inverse = normal.cholesky()?.inverse();
        let x = current + inverse * residual_rhs;
        let residual_std = robust_sigma(&mut self.residuals);
        // Weighted least squares under white noise σ²: Cov = σ²·N⁻¹(Σw²bbᵀ)N⁻¹ ≈ σ²·N⁻¹·Σw²/Σw.
        // The residual's scale: the smaller of the kept pixels' weighted mean square residual
        // and the robust (median) one. It holds the white noise and the static model error
        // (dot edges, aliased harmonics, sharp dots' detail beyond the modelled orders), which
        // does not scatter the result from frame to frame but may bias it. σ² is the white
        // noise alone: the model-free estimate `white` when smaller, at least the engine's
        // floor.
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
            inlier_fraction: sum_w / self.sum_layout,
            pixels: self.pixels,
            cells: self.cells,
            frozen: self.frozen,
            frozen_residuals: self.frozen_residuals,
            frozen_cells: self.frozen_cells,
            centroid: [self.sum_wx / sum_w, self.sum_wy / sum_w],
            amplitude_variance: 2.0 * residual_variance.max(noise_variance) * sum_w2
                / (sum_w * sum_w),
        })
    }
}

/// The row of the normal equations at pixel `p` (the model's basis functions and its
/// derivatives along the plane corrections), and `∂g/∂φ_l` per plane; `h`, `h_slope`: the
/// harmonics' sum and its derivatives there, `gain` their illumination gain.
#[inline(always)]
fn basis_at(
    p: &Pixel,
    model: &Model,
    h: f64,
    h_slope: [f64; 2],
    gain: f64,
) -> ([f64; UNKNOWNS], [f64; 2]) {
    let mut basis = [0.0f64; UNKNOWNS];
    let mut slopes = [0.0f64; 2];
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
        // ∂g/∂φ_l at the current amplitudes, fundamental and harmonics. Tied harmonics inform
        // the offsets γ_l as well as the slopes; free ones only the slopes (their phases
        // absorb any common move, `Model::update_harmonics`). X and Y are centred on the
        // field's weight, so ramp and offset decouple.
        let amplitude = m[3 + 3 * l] + m[4 + 3 * l] * p.xn + m[5 + 3 * l] * p.yn;
        fundamentals[l] = -amplitude * sn;
        slopes[l] = fundamentals[l] + gain * h_slope[l];
    }
    // Along the planes' linear phases: through the warp's Jacobian (the identity without one,
    // which leaves every term as it is to the last bit).
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
    (basis, slopes)
}

/// Robust weight of each cell from its RMS residual `ρ` against the median `m` of the cells
/// around it (within [`CELL_NEIGHBOURHOOD`] nodes, those with at least half a cell of layout
/// weight; at most `CELL_FULL` times the field's median, so that a neighbourhood spoiled as a
/// whole is still judged): 1 up to `CELL_FULL·m`, 0 beyond `CELL_ZERO·m`, cos² in between.
/// Dust and hair stand out from their neighbours; model error that varies smoothly over the
/// field (vignetting, a slow change of focus) does not. `sums` holds `(Σ w_L·r², Σ w_L)` per
/// node of a `dims` mask.
pub(super) fn cell_weights(sums: &[[f64; 2]], dims: (usize, usize)) -> Vec<f64> {
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
pub(super) fn cell_rms(sums: &[[f64; 2]]) -> Vec<f64> {
    sums.iter()
        .map(|&[r2, w]| if w > 0.0 { (r2 / w).sqrt() } else { 0.0 })
        .collect()
}

/// The typical RMS residual around each cell ([`cell_weights`]): the median over the whole
/// cells within [`CELL_NEIGHBOURHOOD`] nodes, at most `CELL_FULL` times the field's median
/// (the field's median where fewer than 9 are whole); `rms` is [`cell_rms`] of `sums`. `None`
/// where the field's median is 0.
pub(super) fn local_residual_scale(
    sums: &[[f64; 2]],
    rms: &[f64],
    dims: (usize, usize),
) -> Option<Vec<f64>> {
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
