//! The fit's model between sweeps ([`Model`]): which harmonics are modelled, their powers,
//! the start sweep that measures them ([`first_model`]) and the harmonics' amplitude step.

use super::*;

/// The harmonics `(h₁, h₂)` of order ≤ [`MAX_ORDER`] other than the fundamentals, one of each
/// `±h` pair (`h₁ > 0`, or `h₁ = 0 < h₂`).
pub(super) fn all_harmonics() -> Vec<(i32, i32)> {
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
pub(super) fn resolvable_harmonics(
    planes: &[PhasePlane; 2],
    side: f64,
    unaliased: bool,
) -> Vec<(i32, i32)> {
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
pub(super) struct Model {
    pub(super) planes: [PhasePlane; 2],
    /// μ, μ_X, μ_Y, B₁, E₁, F₁, B₂, E₂, F₂, η_X, η_Y.
    pub(super) linear: SVector<f64, LINEAR>,
    /// The modelled harmonics and their complex amplitudes.
    pub(super) harmonics: Vec<((i32, i32), Complex64)>,
    /// Each harmonic's overlap with its own conjugate under the layout weight,
    /// `Σw·e^{2ih·φ}/Σw` ([`amplitude_step`]), in the order of `harmonics`.
    pub(super) overlaps: Vec<Complex64>,
    /// Tukey cut-off `c·σ`, intensity units; `None` before the first residuals.
    pub(super) cutoff: Option<f64>,
    /// Harmonics tied to the dot centres (real amplitudes).
    pub(super) tied: bool,
    /// Robust weight of each cell (per node of the mask); empty before the first residuals.
    pub(super) cells: Vec<f64>,
    /// Tukey weight of each pixel of the box (row-major), frozen after the robust iterations:
    /// the last iterations then solve one fixed weighted least-squares problem, at the
    /// quadratic rate of Gauss–Newton (reweighting every pixel each time, as IRLS does,
    /// converges only linearly). Empty while the weights still move; on a tracked fit's first
    /// sweep, the last frame's ([`CarriedWeights`]), NaN where they do not reach.
    pub(super) frozen: Vec<f32>,
}

impl Model {
    /// Applies a step's harmonic corrections. Tied harmonics keep real amplitudes (the
    /// imaginary part of the correction is the offset error that the step's `γ` has taken
    /// already). Free ones take the whole correction, measured at the demodulation's centroid,
    /// and are turned back by the planes' move there, `A_h ← (A_h + d_h)·e^{−ih·δφ̄}`: the
    /// step does not move them, as the offsets' equations (fundamentals only) assume. The
    /// overlaps `Σw·e^{2ih·φ}/Σw` turn the other way, twice as fast.
    pub(super) fn update_harmonics(&mut self, step: &Step) {
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
    pub(super) fn tie(&mut self, shift: [f64; 2]) {
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
    pub(super) fn gain(&self, p: &Pixel) -> f64 {
        1.0 + self.linear[9] * p.xn + self.linear[10] * p.yn
    }

    /// Background plus fundamentals at a pixel (the linear part of the model).
    pub(super) fn linear_at(&self, p: &Pixel) -> f64 {
        let m = &self.linear;
        let mut v = m[0] + m[1] * p.xn + m[2] * p.yn;
        for l in 0..2 {
            v += (m[3 + 3 * l] + m[4 + 3 * l] * p.xn + m[5 + 3 * l] * p.yn) * p.z[l].re;
        }
        v
    }

    /// Tukey weight `(1 − (r/c)²)²` of a pixel's residual `r` (1 before the first
    /// residuals).
    pub(super) fn robust(&self, r: f64) -> f64 {
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
    pub(super) fn contrast(&self) -> f64 {
        0.5 * (self.linear[3].abs() + self.linear[6].abs())
    }
}

/// `e^{ikφ_l}` for `k = 0..=MAX_ORDER`, per lobe.
pub(super) type Powers = [[Complex64; MAX_ORDER + 1]; 2];

/// The powers up to order `top` (those above it are left at 1: no harmonic asks for them).
pub(super) fn powers(z: &[Complex64; 2], top: usize) -> Powers {
    let mut p = [[Complex64::new(1.0, 0.0); MAX_ORDER + 1]; 2];
    for (pl, zl) in p.iter_mut().zip(z) {
        for k in 1..=top.min(MAX_ORDER) {
            pl[k] = pl[k - 1] * zl;
        }
    }
    p
}

/// The highest order along either axis among `orders`.
pub(super) fn top_order(orders: &[(i32, i32)]) -> usize {
    orders
        .iter()
        .map(|&(h1, h2)| h1.unsigned_abs().max(h2.unsigned_abs()) as usize)
        .max()
        .unwrap_or(1)
}

/// `e^{ih·φ}` of each harmonic of `orders`, `z` being `e^{iφ_l}`, into `(re, im)`; `top`:
/// at least [`top_order`] of `orders`.
#[inline(always)]
pub(super) fn exponentials(
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
pub(super) fn harmonic(p: &Powers, h1: i32, h2: i32) -> Complex64 {
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

/// A harmonic's amplitude correction from its demodulation `y = 2·Σw·r·e^{−iθ}/Σw` of the
/// residual `r` (θ = h·φ), given its overlap with its own conjugate `ρ = Σw·e^{2iθ}/Σw`:
/// the least-squares fit of `Re(dA·e^{iθ})` to `r`. Demodulation alone is that fit where the
/// pixels average `e^{2iθ}` away (`ρ ≈ 0`); near the Nyquist frequency they do not (`2θ`
/// hardly turns from pixel to pixel) and the term is nearly a cosine of fixed phase. In the
/// eigenbasis of the 2 × 2 normal matrix `1 ± |ρ|` (directions `e^{−iψ/2}` and `i·e^{−iψ/2}`,
/// `ψ = arg ρ`), each part of `y` is divided by its eigenvalue; a direction with no
/// information left (`1 − |ρ|` at the rounding of the sums, single precision) keeps its
/// amplitude: the phase of a harmonic sampled exactly at the Nyquist frequency is not seen.
pub(super) fn amplitude_step(y: Complex64, overlap: Complex64) -> Complex64 {
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
pub(super) fn first_model(
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
