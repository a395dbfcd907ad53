//! FFT sizes that rustfft transforms fast: `2^a·3^b·5^c` (its radix-2, -3 and -5 butterflies;
//! other factors fall back to slower algorithms). The one rule of every window and grid size.

/// Whether `n ≥ 1` is `2^a·3^b·5^c`.
pub(crate) fn is_fast(mut n: usize) -> bool {
    if n == 0 {
        return false;
    }
    for p in [2, 3, 5] {
        while n % p == 0 {
            n /= p;
        }
    }
    n == 1
}

/// Smallest fast size `≥ n` (1 for `n ≤ 1`).
pub(crate) fn at_least(n: usize) -> usize {
    (n.max(1)..).find(|&v| is_fast(v)).unwrap_or(n)
}

/// Largest fast size `≤ n` (0 for `n = 0`).
pub(crate) fn at_most(n: usize) -> usize {
    (1..=n).rev().find(|&v| is_fast(v)).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_are_five_smooth() {
        assert_eq!(at_least(1), 1);
        assert_eq!(at_least(36), 36);
        assert_eq!(at_least(37), 40);
        assert_eq!(at_least(100), 100);
        assert_eq!(at_least(101), 108);
        assert_eq!(at_most(0), 0);
        assert_eq!(at_most(1), 1);
        assert_eq!(at_most(473), 450);
        assert_eq!(at_most(512), 512);
        assert_eq!(at_most(1023), 1000);
        assert!(!is_fast(7) && !is_fast(0) && is_fast(750));
    }
}
