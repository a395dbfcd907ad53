//! The harmonic bank of the sweep: the modelled harmonics' exponentials advanced column by
//! column, in single-precision SIMD lanes, with their demodulation sums.

use super::*;

/// Lanes of the harmonic bank's vectors: 16 single-precision numbers, two AVX2 registers, so
/// that the sums of [`HarmonicBank::evaluate`] run as two independent chains (one chain waits
/// on the FMA latency). Single precision halves the work of the sweep's costliest part; its
/// rounding (~1e-7 of the harmonics' amplitudes, ~1e-5 rad of phase drift over a row of
/// advances) is far below the noise, and the demodulation sums go to double precision at the
/// end of every row.
pub(super) const LANES: usize = 16;

/// Longest gap, in columns, that the harmonic bank advances across; beyond it the bank is
/// seeded afresh (about the cost of this many advances).
pub(super) const MAX_ADVANCE: usize = 8;

/// [`Pixel::advance`] of a pixel where the bank is seeded afresh within a row: a warped
/// field's steps are recomputed exactly every [`WARP_EXACT_COLUMNS`] columns.
pub(super) const RESEED: usize = usize::MAX;

/// Columns over which a warped field's phases are advanced by their quadratic recurrence
/// (step and chirp, [`FieldPixels`]) before they are computed exactly again: the cubic term
/// of `u = v/(1 − p·v)` leaves ~3e-5 rad over them on the steepest tilts of the stress
/// suite (`p` 6e-3 per period at 30 px), far below the noise of such a fit.
pub(super) const WARP_EXACT_COLUMNS: usize = 16;

/// Capacity of the harmonic bank: [`MAX_HARMONICS`] rounded up to whole [`LANES`].
pub(super) const BANK: usize = MAX_HARMONICS.div_ceil(LANES) * LANES;

/// The modelled harmonics' exponentials `e^{ih·φ}` at the current pixel, advanced column by
/// column along a row (one complex product per harmonic instead of a power product), with
/// their amplitudes and demodulation sums; structure of arrays padded to whole SIMD lanes
/// (the padding has zero amplitude), so every loop runs over whole lanes and vectorises.
pub(super) struct HarmonicBank {
    /// Harmonics modelled.
    pub(super) n: usize,
    /// `n` rounded up to whole lanes: the loops' length.
    pub(super) padded: usize,
    /// Highest order of the harmonics along either axis ([`top_order`]).
    pub(super) top: usize,
    pub(super) orders: [(i32, i32); BANK],
    pub(super) re: Lanes,
    pub(super) im: Lanes,
    pub(super) step_re: [f32; BANK],
    pub(super) step_im: [f32; BANK],
    pub(super) amp_re: Lanes,
    pub(super) amp_im: Lanes,
    /// `h_l·A_h` (re, im) for the slopes along `φ₁` and `φ₂`.
    pub(super) slope1_re: Lanes,
    pub(super) slope1_im: Lanes,
    pub(super) slope2_re: Lanes,
    pub(super) slope2_im: Lanes,
    /// A warped field's per-harmonic turn of the step per column, `e^{ih·Δ²φ}`
    /// ([`FieldPixels::chirp`]); `None` on a flat field, whose steps are constant.
    pub(super) chirp: Option<[[f32; BANK]; 2]>,
    /// `Σ ψ·e^{−ih·φ}`: the demodulation sums.
    pub(super) demodulated: RowSums,
    /// `Σ w·e^{2ih·φ}`: each harmonic's overlap with its own conjugate ([`amplitude_step`]),
    /// on the sweep that measures it ([`HarmonicBank::add_overlap`]) only.
    pub(super) overlap: Option<RowSums>,
}

/// Complex sums per harmonic (re, im), kept in single precision over the current row (the
/// vectorised sweep) and in double precision over the rows before it.
pub(super) struct RowSums {
    pub(super) row: [[f32; BANK]; 2],
    pub(super) total: [[f64; BANK]; 2],
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
    pub(super) fn flush_row(&mut self, n: usize) {
        let written = (n.div_ceil(LANES) * LANES).min(BANK);
        for (total, row) in self.total.iter_mut().zip(&mut self.row) {
            for (t, r) in total[..n].iter_mut().zip(&row[..n]) {
                *t += *r as f64;
            }
            row[..written].fill(0.0);
        }
    }

    /// The totals of the first `n` harmonics as complex numbers (current row included).
    pub(super) fn complex(&mut self, n: usize) -> Vec<Complex64> {
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
pub(super) fn tree_sum(v: [f32; LANES]) -> f64 {
    const _: () = assert!(LANES == 16, "tree_sum is written for 16 lanes");
    let eight: [f32; 8] = std::array::from_fn(|k| v[k] + v[k + 8]);
    let four: [f32; 4] = std::array::from_fn(|k| eight[k] + eight[k + 4]);
    let two = [four[0] + four[2], four[1] + four[3]];
    (two[0] + two[1]) as f64
}

/// A bank's values in whole lanes: indexing a chunk checks its bounds once for all its
/// lanes, and the lane loops compile to vector arithmetic with no iterator to build (zipped
/// chunk iterators were built out of line, per pixel, in the AVX2 sweep).
pub(super) type Lanes = [[f32; LANES]; BANK / LANES];

/// The `k`-th value of `v`.
#[inline(always)]
pub(super) fn lane_mut(v: &mut Lanes, k: usize) -> &mut f32 {
    &mut v[k / LANES][k % LANES]
}

impl HarmonicBank {
    /// The bank of `harmonics` (orders and amplitudes) for `planes`.
    pub(super) fn new(harmonics: &[((i32, i32), Complex64)], planes: &[PhasePlane; 2]) -> Self {
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
    pub(super) fn seed(&mut self, z: &[Complex64; 2]) {
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
    pub(super) fn seed_warped(&mut self, p: &Pixel) {
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
    pub(super) fn move_to(&mut self, p: &Pixel) {
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
    pub(super) fn flush_row(&mut self) {
        self.demodulated.flush_row(self.n);
        if let Some(overlap) = &mut self.overlap {
            overlap.flush_row(self.n);
        }
    }

    /// Exponentials `columns` pixels further along the row.
    #[inline(always)]
    pub(super) fn advance(&mut self, columns: usize) {
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
    pub(super) fn advance_warped(&mut self, columns: usize) {
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
    pub(super) fn evaluate(&self) -> (f64, [f64; 2]) {
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
    pub(super) fn demodulate(&mut self, psi: f64) {
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
    pub(super) fn add_overlap(&mut self, w: f64) {
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
    pub(super) fn overlaps(&mut self) -> Vec<Complex64> {
        let n = self.n;
        self.overlap.get_or_insert_with(RowSums::default).complex(n)
    }

    /// The demodulation sums as complex numbers, in the harmonics' order.
    pub(super) fn sums(&mut self) -> Vec<Complex64> {
        self.demodulated.complex(self.n)
    }
}
