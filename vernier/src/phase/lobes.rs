//! Lobe (spectral peak) search, METHOD.md §4.3, on the half spectrum.
//!
//! Differences from the original, on purpose:
//! * the ring band-pass is given by the user's period range (defaults accept 4 to N/2.2 cycles
//!   per image) instead of a fixed 20-bin inner radius, so small snapshots with few periods work;
//! * besides the absolute power floor, a peak must stand out of the spectrum's mean magnitude in
//!   the ring by `min_peak_prominence`, so pure noise is reported as "not found" instead of
//!   yielding a random pose.

use super::spectrum::HalfSpectrum;
use std::f64::consts::PI;

/// One spectral lobe: integer bin frequency in the half plane `ky > 0 or (ky = 0, kx > 0)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lobe {
    /// Frequency along columns, cycles per image width.
    pub kx: i64,
    /// Frequency along rows, cycles per image height.
    pub ky: i64,
    /// Smoothed magnitude divided by the pixel count (METHOD.md's "peak power").
    pub power: f64,
    /// Smoothed magnitude divided by the mean magnitude in the search ring (dimensionless).
    pub prominence: f64,
}

/// Settings of the search, in bins (cycles per image).
#[derive(Clone, Copy, Debug)]
pub(crate) struct LobeSearch {
    /// Bins with radius ≤ this are ignored.
    pub min_radius: f64,
    /// Bins with radius > this are ignored.
    pub max_radius: f64,
    /// Gaussian band-pass σ in bins; sets the angular cut width `atan2(3σ, ρ)`.
    pub sigma: f64,
    pub min_peak_power: f64,
    pub min_peak_prominence: f64,
}

/// Why the search failed.
#[derive(Debug)]
pub(crate) enum LobeError {
    NoFirstPeak { power: f64, prominence: f64 },
    NoSecondPeak { power: f64, prominence: f64 },
}

/// Returns the two lobes, ordered so that lobe 1 has the larger `kx` (direction in `[0°, 90°)`),
/// lobe 2 the other one (direction in `[90°, 180°)`).
pub(crate) fn find_lobes(
    spectrum: &HalfSpectrum<'_>,
    search: &LobeSearch,
    magnitude: &mut Vec<f32>,
) -> Result<(Lobe, Lobe), LobeError> {
    let (rows, cols) = (spectrum.rows as i64, spectrum.cols as i64);
    // Magnitudes on the signed grid kx ∈ [−1, kx_max+1], ky ∈ [−ky_max−1, ky_max+1] covering the
    // ring, plus one margin bin for the 3×3 smoothing; everything outside the ring is zero.
    let max_r = search
        .max_radius
        .min((cols / 2) as f64)
        .min((rows / 2) as f64)
        .max(0.0);
    let kx_max = (max_r.floor() as i64).min(cols / 2);
    let ky_max = (max_r.floor() as i64).min(rows / 2);
    let width = (kx_max + 3) as usize; // kx from −1 to kx_max + 1
    let height = (2 * ky_max + 3) as usize; // ky from −ky_max−1 to ky_max+1
    magnitude.clear();
    magnitude.resize(width * height, 0.0);
    let (min_r2, max_r2) = (search.min_radius.powi(2), max_r.powi(2));
    let mut ring_sum = 0.0f64;
    let mut ring_count = 0usize;
    for kx in -1..=kx_max + 1 {
        for ky in -ky_max - 1..=ky_max + 1 {
            let r2 = (kx * kx + ky * ky) as f64;
            if r2 <= min_r2 || r2 > max_r2 {
                continue;
            }
            let m = spectrum.at(kx, ky).norm();
            magnitude[(ky + ky_max + 1) as usize * width + (kx + 1) as usize] = m;
            if kx > 0 || (kx == 0 && ky > 0) {
                ring_sum += m as f64;
                ring_count += 1;
            }
        }
    }
    let ring_mean = if ring_count > 0 {
        ring_sum / ring_count as f64
    } else {
        0.0
    };
    let pixels = (rows * cols) as f64;
    // Lobe strength at (kx, ky): root of the energy in the 3×3 neighbourhood. Unlike a single
    // bin (which loses up to 36 % for a lobe between bins) it varies by < 15 % with the sub-bin
    // position, so a fundamental between bins is never outranked by an on-bin harmonic.
    let smoothed = |kx: i64, ky: i64| -> f64 {
        let (x, y) = ((kx + 1) as usize, (ky + ky_max + 1) as usize);
        let mut energy = 0.0f32;
        for dy in 0..3 {
            let row = &magnitude[(y + dy - 1) * width..];
            energy += row[x - 1] * row[x - 1] + row[x] * row[x] + row[x + 1] * row[x + 1];
        }
        (energy as f64).sqrt()
    };
    let in_ring = |kx: i64, ky: i64| {
        let r2 = (kx * kx + ky * ky) as f64;
        r2 > min_r2 && r2 <= max_r2 && kx.abs() <= kx_max && ky.abs() <= ky_max
    };
    // Strength at any signed frequency (mirrored into the stored half plane kx ≥ 0).
    let strength = |kx: i64, ky: i64| -> f64 {
        let (kx, ky) = if kx < 0 { (-kx, -ky) } else { (kx, ky) };
        if in_ring(kx, ky) {
            smoothed(kx, ky)
        } else {
            0.0
        }
    };
    // Scan the half plane kx ≥ 0 (the stored half); each lobe pair appears once there.
    let best = |excluded: &dyn Fn(i64, i64) -> bool| -> Option<(i64, i64, f64)> {
        let mut best: Option<(i64, i64, f64)> = None;
        for kx in 0..=kx_max {
            for ky in -ky_max..=ky_max {
                if kx == 0 && ky <= 0 {
                    continue; // (0, −ky) is the mirror of (0, ky)
                }
                if !in_ring(kx, ky) || excluded(kx, ky) {
                    continue;
                }
                let v = smoothed(kx, ky);
                if best.is_none_or(|b| v > b.2) {
                    best = Some((kx, ky, v));
                }
            }
        }
        best
    };
    let to_lobe = |(kx, ky, v): (i64, i64, f64)| {
        // Representative in the half plane ky > 0 or (ky = 0 and kx > 0).
        let (kx, ky) = if ky < 0 || (ky == 0 && kx < 0) {
            (-kx, -ky)
        } else {
            (kx, ky)
        };
        Lobe {
            kx,
            ky,
            power: v / pixels,
            prominence: if ring_mean > 0.0 { v / ring_mean } else { 0.0 },
        }
    };
    let accept =
        |l: &Lobe| l.power > search.min_peak_power && l.prominence >= search.min_peak_prominence;

    let first = best(&|_, _| false)
        .map(to_lobe)
        .ok_or(LobeError::NoFirstPeak {
            power: 0.0,
            prominence: 0.0,
        })?;
    if !accept(&first) {
        return Err(LobeError::NoFirstPeak {
            power: first.power,
            prominence: first.prominence,
        });
    }
    // Angular cut around the first lobe's direction (and its opposite).
    let theta = (first.ky as f64).atan2(first.kx as f64);
    let rho = ((first.kx * first.kx + first.ky * first.ky) as f64).sqrt();
    let half_width = (3.0 * search.sigma).atan2(rho);
    let excluded = |kx: i64, ky: i64| {
        let mut d = ((ky as f64).atan2(kx as f64) - theta).rem_euclid(PI);
        if d > PI / 2.0 {
            d = PI - d;
        }
        d <= half_width
    };
    let second = best(&excluded)
        .map(to_lobe)
        .ok_or(LobeError::NoSecondPeak {
            power: 0.0,
            prominence: 0.0,
        })?;
    if !accept(&second) {
        return Err(LobeError::NoSecondPeak {
            power: second.power,
            prominence: second.prominence,
        });
    }
    let (first, second) = fundamentals(first, second, (rows, cols), &strength, &to_lobe);
    Ok(if first.kx >= second.kx {
        (first, second)
    } else {
        (second, first)
    })
}

/// Replaces a harmonic picked instead of a fundamental.
///
/// The two strongest lobes `p`, `q` of a square grid are normally its fundamentals `k1`, `k2`,
/// but with noise or sub-bin positions a diagonal harmonic `k1 ± k2` (64 % of a fundamental
/// for square dots) can win. Candidates built from `p` and `q` — themselves, `p ± q` and
/// `(p ± q)/2` — that are strong (≥ 40 % of the weaker pick) are collected; the fundamentals are
/// the shortest strong candidate and the shortest strong one roughly perpendicular to it.
fn fundamentals(
    p: Lobe,
    q: Lobe,
    (rows, cols): (i64, i64),
    strength: &dyn Fn(i64, i64) -> f64,
    to_lobe: &dyn Fn((i64, i64, f64)) -> Lobe,
) -> (Lobe, Lobe) {
    let floor = 0.4 * (p.power.min(q.power));
    let mut candidates: Vec<(i64, i64)> = vec![(p.kx, p.ky), (q.kx, q.ky)];
    for (sx, sy) in [(p.kx + q.kx, p.ky + q.ky), (p.kx - q.kx, p.ky - q.ky)] {
        candidates.push((sx, sy));
        if sx % 2 == 0 && sy % 2 == 0 {
            candidates.push((sx / 2, sy / 2));
        }
    }
    let pixels_per_power = if p.power > 0.0 {
        strength(p.kx, p.ky) / p.power
    } else {
        1.0
    };
    let mut strong: Vec<Lobe> = candidates
        .into_iter()
        .filter(|&(kx, ky)| (kx, ky) != (0, 0))
        .map(|(kx, ky)| to_lobe((kx, ky, strength(kx, ky))))
        .filter(|l| l.power * pixels_per_power > 0.0 && l.power >= floor)
        .collect();
    // Compare in cycles per pixel: bins are anisotropic on non-square images.
    let physical = |l: &Lobe| (l.kx as f64 / cols as f64, l.ky as f64 / rows as f64);
    let len2 = |l: &Lobe| {
        let (fx, fy) = physical(l);
        fx * fx + fy * fy
    };
    strong.sort_by(|u, v| len2(u).total_cmp(&len2(v)));
    let Some(&a) = strong.first() else {
        return (p, q);
    };
    let perpendicular = |l: &Lobe| {
        let ((ax, ay), (lx, ly)) = (physical(&a), physical(l));
        let cos = (ax * lx + ay * ly) / (len2(&a) * len2(l)).sqrt();
        cos.abs() < 0.5 // 60°..120°
    };
    match strong.iter().find(|l| perpendicular(l)) {
        Some(&b) => (a, b),
        None => (p, q),
    }
}
