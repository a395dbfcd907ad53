//! Weighted linear least squares, accumulated a block of observations at a time.
//!
//! The normal equations `Σ w·b·bᵀ · x = Σ w·b·d` of `N` unknowns cost `N²` multiply-adds per
//! observation when each observation is added as a rank-one update, and the update keeps the
//! whole matrix in flight through memory. Here observations are buffered in columns of
//! [`BLOCK`] (one column per unknown, plus the data), and each flush takes the upper triangle's
//! entries as dot products of whole columns: `N(N+1)/2 + N` products of [`BLOCK`] terms, with
//! independent SIMD lanes and no store per term (a symmetric rank-`BLOCK` update, the blocking
//! of BLAS `syrk`).
//!
//! The buffered columns and each block's products are single precision (eight lanes to a
//! register instead of four), the sums over blocks double. The right-hand side is meant to
//! hold the *residuals* of the current solution, so that single precision rounds a term of the
//! size of the noise rather than of the data: the caller solves for the correction (or adds
//! `N·x₀` back in double precision, [`NormalEquations::finish`]'s matrix times its `x₀`).
//! Rounding the normal matrix to ~1e-7 leaves the fixed point of an iteration that re-forms
//! the residuals each time where it is; only its rate of convergence sees it.

use nalgebra::{SMatrix, SVector};

/// Observations buffered per flush: 4 lanes of 16 (two AVX registers per chain).
const BLOCK: usize = 64;
/// Independent partial sums per dot product.
const LANES: usize = 16;
/// Partial sums kept per entry across blocks, double precision (half of [`LANES`]: one fold,
/// no horizontal sum per product).
const KEPT: usize = LANES / 2;

/// Accumulator of the weighted normal equations of `N` unknowns.
pub(crate) struct NormalEquations<const N: usize> {
    /// `columns[i][k]`: basis function `i` at buffered observation `k`.
    columns: [[f32; BLOCK]; N],
    data: [f32; BLOCK],
    weights: [f32; BLOCK],
    buffered: usize,
    /// Upper triangle of `Σ w·b·bᵀ` (row-major, the lower part unused) …
    gram: [[[f64; KEPT]; N]; N],
    /// … and `Σ w·b·d`, in [`KEPT`] partial sums each.
    rhs: [[f64; KEPT]; N],
}

impl<const N: usize> NormalEquations<N> {
    /// Empty equations.
    pub(crate) fn new() -> Self {
        NormalEquations {
            columns: [[0.0; BLOCK]; N],
            data: [0.0; BLOCK],
            weights: [0.0; BLOCK],
            buffered: 0,
            gram: [[[0.0; KEPT]; N]; N],
            rhs: [[0.0; KEPT]; N],
        }
    }

    /// Adds observation `data = basis·x` with weight `weight` (≥ 0).
    #[inline(always)]
    pub(crate) fn add(&mut self, basis: &[f64; N], data: f64, weight: f64) {
        let k = self.buffered;
        for (column, b) in self.columns.iter_mut().zip(basis) {
            column[k] = *b as f32;
        }
        self.data[k] = data as f32;
        self.weights[k] = weight as f32;
        self.buffered += 1;
        if self.buffered == BLOCK {
            self.flush();
        }
    }

    /// Folds the buffered observations into the sums. Unused slots of a partial block have
    /// weight 0 (their stale columns are finite values of earlier observations, or zeros).
    #[inline(always)]
    fn flush(&mut self) {
        self.weights[self.buffered..].fill(0.0);
        for i in 0..N {
            let weighted: [f32; BLOCK] =
                std::array::from_fn(|k| self.weights[k] * self.columns[i][k]);
            add_lanes(&mut self.rhs[i], dot(&weighted, &self.data));
            for j in i..N {
                add_lanes(&mut self.gram[i][j], dot(&weighted, &self.columns[j]));
            }
        }
        self.buffered = 0;
    }

    /// The normal matrix (symmetric) and right-hand side of the observations added.
    pub(crate) fn finish(mut self) -> (SMatrix<f64, N, N>, SVector<f64, N>) {
        if self.buffered > 0 {
            self.flush();
        }
        let total = |lanes: &[f64; KEPT]| lanes.iter().sum::<f64>();
        let gram = SMatrix::from_fn(|i, j| total(&self.gram[i.min(j)][i.max(j)]));
        (gram, SVector::from(self.rhs.map(|r| total(&r))))
    }
}

/// `Σ a_k·b_k` in [`LANES`] partial sums (lane-wise arithmetic vectorises; one running sum
/// would not, its order being fixed), folded to [`KEPT`] in double precision.
#[inline(always)]
fn dot(a: &[f32; BLOCK], b: &[f32; BLOCK]) -> [f64; KEPT] {
    let mut partial = [0.0f32; LANES];
    // Constant indices: no iterator to build, no bounds to check (zipped chunk iterators were
    // built out of line, once per product, in the AVX2 sweep).
    for chunk in 0..BLOCK / LANES {
        for (lane, sum) in partial.iter_mut().enumerate() {
            let k = chunk * LANES + lane;
            *sum += a[k] * b[k];
        }
    }
    std::array::from_fn(|k| (partial[k] + partial[k + KEPT]) as f64)
}

/// `sum += lanes`, lane by lane.
#[inline(always)]
fn add_lanes(sum: &mut [f64; KEPT], lanes: [f64; KEPT]) {
    for (s, l) in sum.iter_mut().zip(lanes) {
        *s += l;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matches_the_rank_one_sums_over_partial_blocks() {
        const M: usize = 3;
        for count in [0usize, 1, BLOCK - 1, BLOCK, BLOCK + 5, 3 * BLOCK + 17] {
            let mut equations = NormalEquations::<M>::new();
            let mut gram = SMatrix::<f64, M, M>::zeros();
            let mut rhs = SVector::<f64, M>::zeros();
            for k in 0..count {
                let t = k as f64 * 0.37;
                let basis = [1.0, t.sin(), (1.3 * t).cos() * t];
                let (data, weight) = (t.cos() - 0.2, (k % 7) as f64 / 6.0);
                equations.add(&basis, data, weight);
                let b = SVector::from(basis);
                gram += weight * b * b.transpose();
                rhs += weight * data * b;
            }
            let (g, r) = equations.finish();
            // Single-precision blocks.
            assert!((g - gram).norm() <= 1e-6 * gram.norm().max(1.0), "{count}");
            assert!((r - rhs).norm() <= 1e-6 * rhs.norm().max(1.0), "{count}");
            assert_eq!(g, g.transpose());
        }
    }
}
