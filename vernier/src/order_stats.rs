//! Order statistics shared by the coarse steps: the median, the robust level and scale of
//! dot and background samples, edge offsets and residuals.

use std::cmp::Ordering;

/// A sample type with a total order (NaN sorts last) and a midpoint.
pub(crate) trait Sample: Copy {
    /// Total order.
    fn total(&self, other: &Self) -> Ordering;
    /// Mean of two values.
    fn midpoint(a: Self, b: Self) -> Self;
}

impl Sample for f32 {
    fn total(&self, other: &Self) -> Ordering {
        self.total_cmp(other)
    }
    fn midpoint(a: Self, b: Self) -> Self {
        0.5 * (a + b)
    }
}

impl Sample for f64 {
    fn total(&self, other: &Self) -> Ordering {
        self.total_cmp(other)
    }
    fn midpoint(a: Self, b: Self) -> Self {
        0.5 * (a + b)
    }
}

/// A Gaussian's standard deviation over the median of its absolute values.
pub(crate) const MAD_TO_SIGMA: f64 = 1.4826;
/// Tukey's biweight tuning constant, in robust standard deviations (95 % efficiency on
/// Gaussian noise).
pub(crate) const TUKEY_BIWEIGHT: f64 = 4.685;

/// Robust standard deviation `1.4826·median|r|` of absolute residuals (reordered in place);
/// 0 when empty.
pub(crate) fn robust_sigma(absolute_residuals: &mut [f64]) -> f64 {
    MAD_TO_SIGMA * median(absolute_residuals).unwrap_or(0.0)
}

/// Median of `values`, reordered in place (selection, not a full sort): the middle value, or
/// the mean of the two middle values for an even count; `None` when empty.
pub(crate) fn median<T: Sample>(values: &mut [T]) -> Option<T> {
    let n = values.len();
    if n == 0 {
        return None;
    }
    let (lower, upper, _) = values.select_nth_unstable_by(n / 2, T::total);
    let upper = *upper;
    if n % 2 == 1 {
        return Some(upper);
    }
    let below = lower.iter().copied().max_by(T::total)?;
    Some(T::midpoint(below, upper))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_even_and_no_values() {
        assert_eq!(median::<f64>(&mut []), None);
        assert_eq!(median(&mut [3.0f32]), Some(3.0));
        assert_eq!(median(&mut [4.0f32, 1.0, 9.0]), Some(4.0));
        assert_eq!(median(&mut [4.0f32, 1.0, 9.0, 2.0]), Some(3.0));
        let mut many: Vec<f64> = (0..101).rev().map(f64::from).collect();
        assert_eq!(median(&mut many), Some(50.0));
    }
}
