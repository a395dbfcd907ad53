//! Lobe (spectral peak) search, docs/design.md#phase-lobes, on the half spectrum.
//!
//! Differences from the original, on purpose:
//! * the ring band-pass defaults to 4 bins (not 20), so small windows with few periods work;
//! * lobes are ranked by the energy of their 3×3 neighbourhood instead of a blurred magnitude:
//!   it varies by < 15 % with the sub-bin position of the lobe, so a fundamental lying between
//!   bins is never outranked by an on-bin harmonic;
//! * a lobe must stand out of the ring's RMS amplitude by `min_peak_prominence`, so pure noise is
//!   reported as "not found" instead of yielding a random pose;
//! * a diagonal harmonic picked instead of a fundamental is detected and replaced
//!   (`fundamentals`);
//! * one streaming pass over the stored half spectrum keeps the strongest few local maxima;
//!   3×3 energies are only evaluated there (≈ 0.5 ms for a 1024² spectrum).

use super::spectrum::HalfSpectrum;

/// One spectral lobe: integer bin frequency in the half plane `ky > 0 or (ky = 0, kx > 0)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lobe {
    /// Frequency along columns, cycles per image width.
    pub kx: i64,
    /// Frequency along rows, cycles per image height.
    pub ky: i64,
    /// Root of the 3×3 neighbourhood energy divided by the pixel count (the original's "peak
    /// power" up to the smoothing kernel).
    pub power: f64,
    /// Root of the 3×3 energy over that of an average 3×3 neighbourhood of the ring
    /// (dimensionless; ≈ 1–2 for the strongest bin of white noise).
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

/// Where the two lobes are expected (see [`super::LobePrior`]), in bins.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Guide {
    /// Expected signed bin frequency `(kx, ky)` of each lobe.
    pub expected: [[f64; 2]; 2],
    /// Search radius around each, bins.
    pub radius: [f64; 2],
    pub min_prominence: f64,
}

/// Why the search failed.
#[derive(Debug)]
pub(crate) enum LobeError {
    NoFirstPeak { power: f64, prominence: f64 },
    NoSecondPeak { power: f64, prominence: f64 },
}

/// Number of local maxima kept by the streaming pass.
const CANDIDATES: usize = 16;

/// A raw local maximum found by the scan, stored half-plane coordinates (`kx ≥ 0`).
#[derive(Clone, Copy, Debug)]
struct Candidate {
    kx: i64,
    ky: i64,
    energy: f32,
}

/// Inserts `c` into the descending list `top`, merging it with any kept maximum within 2 bins.
fn insert_candidate(top: &mut Vec<Candidate>, c: Candidate) {
    if let Some(pos) = top
        .iter()
        .position(|t| (t.kx - c.kx).abs() <= 2 && (t.ky - c.ky).abs() <= 2)
    {
        if top[pos].energy >= c.energy {
            return;
        }
        top.remove(pos);
    }
    let at = top
        .iter()
        .position(|t| t.energy < c.energy)
        .unwrap_or(top.len());
    top.insert(at, c);
    top.truncate(CANDIDATES);
}

/// Returns the two lobes, ordered so that lobe 1 has the larger `kx` (direction in `[0°, 90°)`),
/// lobe 2 the other one (direction in `[90°, 180°)`).
/// With a `guide`, each lobe is the strongest bin near where it is expected.
pub(crate) fn find_lobes(
    spectrum: &HalfSpectrum<'_>,
    search: &LobeSearch,
    guide: Option<&Guide>,
) -> Result<(Lobe, Lobe), LobeError> {
    let (rows, cols) = (spectrum.rows as i64, spectrum.cols as i64);
    let ring = Ring::new(search, rows, cols);
    let (top, mean_bin_energy) = strongest_bins(spectrum, &ring);
    let pixels = (rows * cols) as f64;

    // 3×3 neighbourhood energy at any signed frequency (0 outside the ring).
    let strength = |kx: i64, ky: i64| -> f64 {
        if !ring.contains(kx.abs(), if kx < 0 { -ky } else { ky }) {
            return 0.0;
        }
        let mut e = 0.0f64;
        for dy in -1..=1 {
            for dx in -1..=1 {
                e += spectrum.at(kx + dx, ky + dy).norm_sqr() as f64;
            }
        }
        e.sqrt()
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
            prominence: if mean_bin_energy > 0.0 {
                v / (9.0 * mean_bin_energy).sqrt()
            } else {
                0.0
            },
        }
    };
    if let Some(guide) = guide {
        return guided_lobes(guide, search.min_peak_power, &strength, &to_lobe);
    }
    let ranked: Vec<Lobe> = {
        let mut v: Vec<Lobe> = top
            .iter()
            .map(|c| to_lobe((c.kx, c.ky, strength(c.kx, c.ky))))
            .collect();
        v.sort_by(|a, b| b.power.total_cmp(&a.power));
        v
    };
    let (first, second) = strongest_pair(&ranked, search)?;
    let (first, second) = fundamentals(first, second, (rows, cols), &strength, &to_lobe);
    Ok(if first.kx >= second.kx {
        (first, second)
    } else {
        (second, first)
    })
}

/// The search ring in frequency bins: `min_radius < |k| ≤ max_radius`, within the
/// spectrum's half sizes.
struct Ring {
    min_r2: f64,
    max_r2: f64,
    kx_max: i64,
    ky_max: i64,
}

impl Ring {
    fn new(search: &LobeSearch, rows: i64, cols: i64) -> Ring {
        let max_r = search
            .max_radius
            .min((cols / 2) as f64)
            .min((rows / 2) as f64)
            .max(0.0);
        Ring {
            min_r2: search.min_radius.powi(2),
            max_r2: max_r.powi(2),
            kx_max: (max_r.floor() as i64).min(cols / 2),
            ky_max: (max_r.floor() as i64).min(rows / 2),
        }
    }

    fn contains(&self, kx: i64, ky: i64) -> bool {
        let r2 = (kx * kx + ky * ky) as f64;
        r2 > self.min_r2 && r2 <= self.max_r2 && kx.abs() <= self.kx_max && ky.abs() <= self.ky_max
    }
}

/// Streaming pass over the stored half (kx ≥ 0) of the ring: its strongest local maxima
/// and the mean energy of its bins.
fn strongest_bins(spectrum: &HalfSpectrum<'_>, ring: &Ring) -> (Vec<Candidate>, f64) {
    let rows = spectrum.rows as i64;
    let mut top: Vec<Candidate> = Vec::with_capacity(CANDIDATES + 1);
    let mut ring_energy = 0.0f64;
    let mut ring_count = 0usize;
    for kx in 0..=ring.kx_max {
        let column = &spectrum.bins[kx as usize * rows as usize..(kx as usize + 1) * rows as usize];
        // Rows of this column inside the outer radius: |ky| ≤ sqrt(max_r² − kx²).
        let ky_lim =
            ((ring.max_r2 - (kx * kx) as f64).max(0.0).sqrt().floor() as i64).min(ring.ky_max);
        for ky in -ky_lim..=ky_lim {
            if (kx == 0 && ky <= 0) || !ring.contains(kx, ky) {
                continue; // (0, −ky) mirrors (0, ky)
            }
            let e = column[ky.rem_euclid(rows) as usize].norm_sqr();
            ring_energy += e as f64;
            ring_count += 1;
            if top.len() < CANDIDATES || e > top[top.len() - 1].energy {
                insert_candidate(&mut top, Candidate { kx, ky, energy: e });
            }
        }
    }
    let mean_bin_energy = if ring_count > 0 {
        ring_energy / ring_count as f64
    } else {
        0.0
    };
    (top, mean_bin_energy)
}

/// The strongest lobe of `ranked` (strongest first) and the strongest outside an angular
/// cut around its direction, each accepted by the search's power and prominence limits.
fn strongest_pair(ranked: &[Lobe], search: &LobeSearch) -> Result<(Lobe, Lobe), LobeError> {
    let accept =
        |l: &Lobe| l.power > search.min_peak_power && l.prominence >= search.min_peak_prominence;

    let Some(&first) = ranked.first() else {
        return Err(LobeError::NoFirstPeak {
            power: 0.0,
            prominence: 0.0,
        });
    };
    if !accept(&first) {
        return Err(LobeError::NoFirstPeak {
            power: first.power,
            prominence: first.prominence,
        });
    }
    // Angular cut around the first lobe's direction and its opposite: |sin(Δθ)| ≤ sin(h).
    let rho2 = (first.kx * first.kx + first.ky * first.ky) as f64;
    let half_width = (3.0 * search.sigma).atan2(rho2.sqrt());
    let sin2_h = half_width.sin().powi(2);
    let outside_cut = |l: &Lobe| {
        let cross = (first.kx * l.ky - first.ky * l.kx) as f64;
        let len2 = (l.kx * l.kx + l.ky * l.ky) as f64;
        cross * cross > sin2_h * rho2 * len2
    };
    let Some(&second) = ranked.iter().find(|l| outside_cut(l)) else {
        return Err(LobeError::NoSecondPeak {
            power: 0.0,
            prominence: 0.0,
        });
    };
    if !accept(&second) {
        return Err(LobeError::NoSecondPeak {
            power: second.power,
            prominence: second.prominence,
        });
    }
    Ok((first, second))
}

/// The strongest bin within each guided disc, if it is strong and prominent enough.
fn guided_lobes(
    guide: &Guide,
    min_power: f64,
    strength: &dyn Fn(i64, i64) -> f64,
    to_lobe: &dyn Fn((i64, i64, f64)) -> Lobe,
) -> Result<(Lobe, Lobe), LobeError> {
    let near = |i: usize| -> Result<Lobe, LobeError> {
        let ([ex, ey], r) = (guide.expected[i], guide.radius[i]);
        let mut best = (0i64, 0i64, 0.0f64);
        for ky in (ey - r).floor() as i64..=(ey + r).ceil() as i64 {
            for kx in (ex - r).floor() as i64..=(ex + r).ceil() as i64 {
                let (dx, dy) = (kx as f64 - ex, ky as f64 - ey);
                if dx * dx + dy * dy > r * r || (kx, ky) == (0, 0) {
                    continue;
                }
                let v = strength(kx, ky);
                if v > best.2 {
                    best = (kx, ky, v);
                }
            }
        }
        let lobe = to_lobe(best);
        if lobe.power > min_power && lobe.prominence >= guide.min_prominence {
            return Ok(lobe);
        }
        let (power, prominence) = (lobe.power, lobe.prominence);
        Err(if i == 0 {
            LobeError::NoFirstPeak { power, prominence }
        } else {
            LobeError::NoSecondPeak { power, prominence }
        })
    };
    let (a, b) = (near(0)?, near(1)?);
    if (a.kx, a.ky) == (b.kx, b.ky) {
        return Err(LobeError::NoSecondPeak {
            power: b.power,
            prominence: b.prominence,
        });
    }
    Ok(if a.kx >= b.kx { (a, b) } else { (b, a) })
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
    let floor = 0.4 * p.power.min(q.power);
    let mut candidates: Vec<(i64, i64)> = vec![(p.kx, p.ky), (q.kx, q.ky)];
    for (sx, sy) in [(p.kx + q.kx, p.ky + q.ky), (p.kx - q.kx, p.ky - q.ky)] {
        candidates.push((sx, sy));
        if sx % 2 == 0 && sy % 2 == 0 {
            candidates.push((sx / 2, sy / 2));
        }
    }
    let mut strong: Vec<Lobe> = candidates
        .into_iter()
        .filter(|&(kx, ky)| (kx, ky) != (0, 0))
        .map(|(kx, ky)| to_lobe((kx, ky, strength(kx, ky))))
        .filter(|l| l.power > 0.0 && l.power >= floor)
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
