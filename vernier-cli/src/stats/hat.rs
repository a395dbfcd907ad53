//! The N-cornered hat and the confidence intervals of `vernier stats` with several series.
//!
//! Each of `N` estimators of the same frames sees the same motion plus noise of its own. The
//! difference of two series holds no motion, only both estimators' noise: when their errors are
//! independent, `σ²(A − B) = σ²_A + σ²_B`. With three series these three equations give each
//! one's own variance, `σ²_A = ½(σ²(A−B) + σ²(A−C) − σ²(B−C))` (the three-cornered hat of
//! clock metrology, Gray & Allan 1974). With more, the `N(N−1)/2` pair variances
//! over-determine the `N` unknowns; [`n_cornered_hat`] is their unweighted least-squares
//! solution (the classic N-cornered hat, Barnes 1982), which is the three-cornered hat for
//! `N = 3`. A negative result is a finding, not a failure: that estimator's errors correlate
//! with another's (their difference is too small for independent noise).

use rand::{rngs::SmallRng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

use super::second_difference_noise;

/// Probability that a printed interval holds the true value.
pub const LEVEL: f64 = 0.90;

/// Simulated sets of series behind the interval of [`hat_intervals`].
const HAT_TRIALS: usize = 2000;

/// Own variances `σ²_i` of `N ≥ 3` estimators from the variances of their pairwise differences
/// `pair[i][j] = σ²(i − j)` (symmetric; the diagonal is not read): the least-squares solution
/// of `σ²_i + σ²_j = pair[i][j]` over all pairs, `σ²_i = (S_i − T/(N−1))/(N−2)` with `S_i` the
/// sum of the pairs of `i` and `T` the sum of all pairs. A value may be negative (see the
/// module docs). `None` below three estimators or for a non-square table.
pub fn n_cornered_hat(pair: &[Vec<f64>]) -> Option<Vec<f64>> {
    let n = pair.len();
    if n < 3 || pair.iter().any(|row| row.len() != n) {
        return None;
    }
    let sum_of = |i: usize| -> f64 { (0..n).filter(|&j| j != i).map(|j| pair[i][j]).sum() };
    let total: f64 = (0..n).map(sum_of).sum::<f64>() / 2.0;
    Some(
        (0..n)
            .map(|i| (sum_of(i) - total / (n - 1) as f64) / (n - 2) as f64)
            .collect(),
    )
}

/// Pair variances `σ²(i − j)` of the series of `series` (all the same length) from the robust
/// second-difference noise of each difference; `None` when a series is shorter than 3 samples.
pub fn pair_variances(series: &[&[f64]]) -> Option<Vec<Vec<f64>>> {
    let n = series.len();
    let mut pair = vec![vec![0.0; n]; n];
    let mut diff = Vec::new();
    for i in 0..n {
        for j in i + 1..n {
            diff.clear();
            diff.extend(series[i].iter().zip(series[j]).map(|(a, b)| a - b));
            let s = second_difference_noise(&diff)?;
            pair[i][j] = s * s;
            pair[j][i] = s * s;
        }
    }
    Some(pair)
}

/// The [`LEVEL`] interval of each estimator's own variance, given the hat's estimates `own`
/// from series of `samples` frames: a parametric bootstrap. Independent white noise of the
/// estimated deviations (negative variances taken as 0) is simulated, the hat recomputed from
/// the robust pair noises, and the quantiles of its error `σ̂² − σ²` subtracted from the
/// estimate (the basic bootstrap interval). Seeded: the same numbers on every run. `None`
/// below three estimators or three samples.
pub fn hat_intervals(own: &[f64], samples: usize) -> Option<Vec<(f64, f64)>> {
    let n = own.len();
    if n < 3 || samples < 3 {
        return None;
    }
    let sigma: Vec<f64> = own.iter().map(|v| v.max(0.0).sqrt()).collect();
    let mut rng = SmallRng::seed_from_u64(0x4a7);
    let mut errors = vec![Vec::with_capacity(HAT_TRIALS); n];
    let mut series = vec![vec![0.0; samples]; n];
    for _ in 0..HAT_TRIALS {
        for (s, sd) in series.iter_mut().zip(&sigma) {
            for v in s.iter_mut() {
                let z: f64 = StandardNormal.sample(&mut rng);
                *v = sd * z;
            }
        }
        let refs: Vec<&[f64]> = series.iter().map(Vec::as_slice).collect();
        let estimate = pair_variances(&refs).and_then(|p| n_cornered_hat(&p))?;
        for ((e, est), s) in errors.iter_mut().zip(estimate).zip(&sigma) {
            e.push(est - s * s);
        }
    }
    let tail = (1.0 - LEVEL) / 2.0;
    Some(
        errors
            .iter_mut()
            .zip(own)
            .map(|(e, v)| {
                e.sort_by(f64::total_cmp);
                let q = |p: f64| e[((p * e.len() as f64) as usize).min(e.len() - 1)];
                (v - q(1.0 - tail), v - q(tail))
            })
            .collect(),
    )
}

/// Autocorrelation of `v` at `lag` (biased estimate, as in Bartlett's formula); 0 when `v` has
/// no spread.
fn autocorrelation(v: &[f64], lag: usize) -> f64 {
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    let var: f64 = v.iter().map(|x| (x - mean).powi(2)).sum();
    if var <= 0.0 || lag >= v.len() {
        return 0.0;
    }
    let cov: f64 = v
        .iter()
        .zip(&v[lag..])
        .map(|(a, b)| (a - mean) * (b - mean))
        .sum();
    cov / var
}

/// Effective number of independent pairs behind a correlation of the series `a` and `b`
/// (second differences, so serially correlated): Bartlett's `n / (1 + 2 Σ_k ρ_a(k) ρ_b(k))`
/// over lags 1 and 2, where white noise's second differences correlate (−2/3 and 1/6, which
/// gives `n · 18/35`), kept within `[3, n]`.
pub fn effective_samples(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len()) as f64;
    let sum: f64 = (1..=2)
        .map(|k| autocorrelation(a, k) * autocorrelation(b, k))
        .sum();
    (n / (1.0 + 2.0 * sum).max(1e-9)).clamp(3.0_f64.min(n), n.max(0.0))
}

/// The 95 % interval of a correlation `r` from `n_eff` independent pairs (Fisher's
/// `z = atanh r`, deviation `1/√(n_eff − 3)`); `(−1, 1)` at 4 pairs or fewer.
pub fn correlation_interval(r: f64, n_eff: f64) -> (f64, f64) {
    if n_eff <= 4.0 || !r.is_finite() {
        return (-1.0, 1.0);
    }
    let z = r.clamp(-0.999_999, 0.999_999).atanh();
    let half = 1.959_964 / (n_eff - 3.0).sqrt();
    ((z - half).tanh(), (z + half).tanh())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` series of `samples` frames: one shared random walk (steps of deviation `step`)
    /// plus independent white noise of deviation `sigma[i]` each.
    fn simulated(seed: u64, sigma: &[f64], samples: usize, step: f64) -> Vec<Vec<f64>> {
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut walk = Vec::with_capacity(samples);
        let mut position = 0.0;
        for _ in 0..samples {
            let z: f64 = StandardNormal.sample(&mut rng);
            position += step * z;
            walk.push(position);
        }
        sigma
            .iter()
            .map(|s| {
                walk.iter()
                    .map(|w| {
                        let z: f64 = StandardNormal.sample(&mut rng);
                        w + s * z
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn the_hat_solves_the_pairs_exactly() {
        let own = [4.0, 9.0, 1.0, 16.0];
        let pair: Vec<Vec<f64>> = (0..4)
            .map(|i| (0..4).map(|j| own[i] + own[j]).collect())
            .collect();
        for n in [3, 4] {
            let sub: Vec<Vec<f64>> = pair[..n].iter().map(|r| r[..n].to_vec()).collect();
            let hat = n_cornered_hat(&sub).expect("three or more");
            for (got, want) in hat.iter().zip(own) {
                assert!((got - want).abs() < 1e-12, "{hat:?}");
            }
        }
        // Three-cornered hat by its textbook formula.
        let p = [[0.0, 5.0, 7.0], [5.0, 0.0, 3.0], [7.0, 3.0, 0.0]];
        let pair: Vec<Vec<f64>> = p.iter().map(|r| r.to_vec()).collect();
        let hat = n_cornered_hat(&pair).expect("three");
        assert_eq!(hat, vec![4.5, 0.5, 2.5]);
        assert_eq!(n_cornered_hat(&pair[..2]), None);
    }

    /// Fraction of the trials whose interval holds each series' true σ.
    fn coverage(sigma: &[f64], samples: usize, trials: u64) -> Vec<f64> {
        let mut inside = vec![0usize; sigma.len()];
        for seed in 0..trials {
            let series = simulated(seed, sigma, samples, 50.0 * sigma[0]);
            let refs: Vec<&[f64]> = series.iter().map(Vec::as_slice).collect();
            let pair = pair_variances(&refs).expect("30 frames");
            let own = n_cornered_hat(&pair).expect("three or more");
            let intervals = hat_intervals(&own, samples).expect("three or more");
            for ((count, (lo, hi)), s) in inside.iter_mut().zip(intervals).zip(sigma) {
                if lo <= s * s && s * s <= hi {
                    *count += 1;
                }
            }
        }
        inside.iter().map(|&c| c as f64 / trials as f64).collect()
    }

    #[test]
    fn the_interval_holds_the_true_noise_nine_times_in_ten() {
        // A shared random walk 50 times the noise (which the raw series cannot separate from
        // it) and three or four estimators of different noise, 200 seeded trials each. At 400
        // frames the 90 % interval must hold the true σ in 85–96 % of the trials (binomial
        // spread ±2.1 %); at 30 frames in at least 85 % (there it is conservative: 90–100 %).
        let covered = coverage(&[1.0, 0.5, 0.8, 0.3], 400, 200);
        for c in &covered {
            assert!((0.85..=0.96).contains(c), "400 frames: {covered:?}");
        }
        let covered = coverage(&[1.0, 2.0, 3.0], 30, 200);
        assert!(covered.iter().all(|c| *c >= 0.85), "30 frames: {covered:?}");
    }

    #[test]
    fn a_long_series_recovers_each_noise() {
        let sigma = [1.0, 1.5, 2.0, 1.2];
        let series = simulated(7, &sigma, 100_000, 100.0);
        let refs: Vec<&[f64]> = series.iter().map(Vec::as_slice).collect();
        let own = pair_variances(&refs).and_then(|p| n_cornered_hat(&p));
        for (v, s) in own.expect("four series").iter().zip(sigma) {
            assert!((v.sqrt() / s - 1.0).abs() < 0.1, "{} against {s}", v.sqrt());
        }
    }

    #[test]
    fn correlated_errors_give_a_negative_hat() {
        // A shares half of B's error and has little of its own: σ²(A − B) is small for their
        // deviations, and A's hat, σ²_A − cov(A, B), turns negative (−0.24 expected).
        let mut rng = SmallRng::seed_from_u64(3);
        let mut normal = || -> f64 { StandardNormal.sample(&mut rng) };
        let (mut a, mut b, mut c) = (Vec::new(), Vec::new(), Vec::new());
        for _ in 0..5000 {
            let shared = normal();
            a.push(0.5 * shared + 0.1 * normal());
            b.push(shared + normal());
            c.push(normal());
        }
        let own = pair_variances(&[&a, &b, &c]).and_then(|p| n_cornered_hat(&p));
        let own = own.expect("three series");
        assert!(own[0] < -0.1 && own[1] > 1.0 && own[2] > 1.0, "{own:?}");
    }

    #[test]
    fn correlation_intervals_narrow_with_samples() {
        let (lo, hi) = correlation_interval(0.5, 30.0);
        assert!(lo < 0.5 && 0.5 < hi && hi - lo > 0.4, "{lo} {hi}");
        let (lo2, hi2) = correlation_interval(0.5, 3000.0);
        assert!(hi2 - lo2 < 0.1 && lo2 < 0.5 && 0.5 < hi2);
        assert_eq!(correlation_interval(0.5, 4.0), (-1.0, 1.0));
        // Second differences of white noise: Bartlett's factor 18/35.
        let mut rng = SmallRng::seed_from_u64(9);
        let mut noise = |n: usize| -> Vec<f64> {
            let w: Vec<f64> = (0..n).map(|_| StandardNormal.sample(&mut rng)).collect();
            w.windows(3).map(|x| x[2] - 2.0 * x[1] + x[0]).collect()
        };
        let (a, b) = (noise(100_002), noise(100_002));
        let ratio = effective_samples(&a, &b) / 100_000.0;
        assert!((ratio - 18.0 / 35.0).abs() < 0.01, "{ratio}");
    }
}
