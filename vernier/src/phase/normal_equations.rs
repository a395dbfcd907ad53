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
        self.buffered = 0;
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                // SAFETY: the CPU supports the features the kernel is compiled for.
                unsafe {
                    avx2::flush(
                        &self.columns,
                        &self.weights,
                        &self.data,
                        &mut self.gram,
                        &mut self.rhs,
                    )
                };
                return;
            }
        }
        for i in 0..N {
            let weighted: [f32; BLOCK] =
                std::array::from_fn(|k| self.weights[k] * self.columns[i][k]);
            add_lanes(&mut self.rhs[i], dot(&weighted, &self.data));
            for j in i..N {
                add_lanes(&mut self.gram[i][j], dot(&weighted, &self.columns[j]));
            }
        }
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

/// [`NormalEquations::flush`] in AVX2 registers with fused multiply-adds (Rust does not fuse
/// `a·b + c` by itself, and the portable loops compiled to half-width vectors).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::{BLOCK, KEPT};
    use std::arch::x86_64::*;

    /// Registers per buffered column.
    const V: usize = BLOCK / 8;

    /// Adds the block's products to `gram` (upper triangle) and `rhs`, [`KEPT`] lanes each.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn flush<const N: usize>(
        columns: &[[f32; BLOCK]; N],
        weights: &[f32; BLOCK],
        data: &[f32; BLOCK],
        gram: &mut [[[f64; KEPT]; N]; N],
        rhs: &mut [[f64; KEPT]; N],
    ) {
        let w = registers(weights);
        for i in 0..N {
            let column = registers(&columns[i]);
            let mut weighted = [_mm256_setzero_ps(); V];
            for k in 0..V {
                weighted[k] = _mm256_mul_ps(w[k], column[k]);
            }
            accumulate(&mut rhs[i], dot(&weighted, data));
            for j in i..N {
                accumulate(&mut gram[i][j], dot(&weighted, &columns[j]));
            }
        }
    }

    /// The block's values in registers.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn registers(v: &[f32; BLOCK]) -> [__m256; V] {
        let mut out = [_mm256_setzero_ps(); V];
        for (k, o) in out.iter_mut().enumerate() {
            // SAFETY: lanes 8k..8k + 8 lie within the block.
            *o = unsafe { _mm256_loadu_ps(v.as_ptr().add(8 * k)) };
        }
        out
    }

    /// `Σ a_k·b_k` in two chains of eight lanes, folded to [`KEPT`] double-precision lanes.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn dot(a: &[__m256; V], b: &[f32; BLOCK]) -> [__m256d; 2] {
        let b = registers(b);
        let (mut even, mut odd) = (_mm256_mul_ps(a[0], b[0]), _mm256_mul_ps(a[1], b[1]));
        for k in (2..V).step_by(2) {
            even = _mm256_fmadd_ps(a[k], b[k], even);
            odd = _mm256_fmadd_ps(a[k + 1], b[k + 1], odd);
        }
        let sum = _mm256_add_ps(even, odd);
        [
            _mm256_cvtps_pd(_mm256_castps256_ps128(sum)),
            _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(sum)),
        ]
    }

    /// `sum += lanes`.
    #[inline]
    #[target_feature(enable = "avx2,fma")]
    fn accumulate(sum: &mut [f64; KEPT], lanes: [__m256d; 2]) {
        const _: () = assert!(KEPT == 8, "two registers of four lanes");
        let p = sum.as_mut_ptr();
        // SAFETY: lanes 0..8 of `sum`.
        unsafe {
            _mm256_storeu_pd(p, _mm256_add_pd(_mm256_loadu_pd(p), lanes[0]));
            _mm256_storeu_pd(p.add(4), _mm256_add_pd(_mm256_loadu_pd(p.add(4)), lanes[1]));
        }
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
