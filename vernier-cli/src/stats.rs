//! `vernier stats`: the noise of a pose series, per marker and for each relative pair of
//! markers (the repeatability table of metrologists), from a pose table of `detect` or `bag`.
//!
//! Noise is estimated from robust second differences, `σ ≈ 1.4826·median|v[n+1] − 2v[n] +
//! v[n−1]| / √6`: for white noise of deviation σ on a smooth motion, the second difference has
//! deviation `σ·√6` and removes the motion (a constant velocity exactly, a slow acceleration
//! nearly), and the median makes one bad frame harmless. The plain standard deviation, which
//! includes the motion, is printed beside it.
//!
//! Where the motion is not smooth at the frame rate (vibration, a part stepping unevenly), the
//! second differences hold it too. `--against OTHER` then compares the table with another
//! estimate of the same frames (another estimator, other settings, the original's results):
//! the difference of the two series holds no motion, only the two estimators' own noise
//! combined, an upper bound of each one's; the correlation of their second differences says
//! how much of them is motion both see (1) or noise of their own (0).
//!
//! A noise figure from a short sequence is itself uncertain: from 10 frames (8 second
//! differences) it is within ×0.69–×1.73 of the true σ two times in three. The output ends
//! with that spread for the sample counts of its rows, simulated on white noise
//! ([`noise_figure_spread`]), so that two figures are not read as different when they are not.

use std::collections::{BTreeMap, BTreeSet};
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;

use crate::plot::{mean_std, series};
use crate::pose_table::{read_table_file, PoseRow};
use vernier::phase::wrap_angle;

mod compare;
mod hat;
mod reference;

pub use compare::MatchBy;

/// Arguments of `vernier stats`.
#[derive(Parser)]
pub struct StatsArgs {
    /// Pose table written by `vernier detect` or `vernier bag` (CSV or JSON Lines). Two or
    /// more: estimates of the same frames (other settings, or the original program's result
    /// CSV `image;id;x;y;alpha;pixelSize;…`), compared per marker and relative pair: each
    /// series' noise, the noise of each pairwise difference, the correlation of their second
    /// differences, and each estimator's own noise by the N-cornered hat (three or more).
    #[arg(required = true, num_args = 1.., value_name = "TABLE")]
    inputs: Vec<PathBuf>,
    /// How the frames of several tables are matched: by image name (the number in the file
    /// name, so that `Image96.png` matches the original's `96`) or by frame index.
    #[arg(long = "match", value_enum, default_value = "name")]
    match_by: MatchBy,
    /// Relative pair `A:B` (pose of marker B in marker A's frame); repeat for several.
    /// Default: every pair of the markers in the table (at most 8 markers).
    #[arg(long = "pair", value_parser = parse_pair)]
    pairs: Vec<(u64, u64)>,
    /// Another pose table of the same frames (CSV or JSON Lines, rows matched by frame number
    /// and marker ID): prints the noise of each marker's difference from it (the motion
    /// cancels) and the correlation of the two series' second differences. With one table
    /// only; `vernier stats A B` compares them in full.
    #[arg(long, value_name = "OTHER")]
    against: Option<PathBuf>,
}

/// Most markers whose pairs are all listed by default.
const MAX_DEFAULT_MARKERS: usize = 8;

fn parse_pair(text: &str) -> Result<(u64, u64), String> {
    let (a, b) = text
        .split_once(':')
        .ok_or_else(|| format!("`{text}`: expected A:B (two marker IDs)"))?;
    let id = |s: &str| {
        s.trim()
            .parse::<u64>()
            .map_err(|_| format!("`{text}`: `{s}` is not a marker ID"))
    };
    Ok((id(a)?, id(b)?))
}

/// Robust noise of `v` from its second differences (see the module docs); `None` below 3
/// samples.
pub fn second_difference_noise(v: &[f64]) -> Option<f64> {
    let mut d: Vec<f64> = second_differences(v).map(f64::abs).collect();
    if d.is_empty() {
        return None;
    }
    let mid = d.len() / 2;
    let (_, median, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
    Some(1.4826 * *median / 6f64.sqrt())
}

/// White-noise series simulated per sample count by [`noise_figure_spread`].
const SPREAD_TRIALS: usize = 4000;
/// Longest series simulated; longer ones scale its spread by `√((m − 2)/(n − 2))` (the
/// estimate is then nearly normal, its deviation falling as one over the root of the second
/// differences).
const SPREAD_MAX_SIMULATED: usize = 1000;

/// The spread of [`second_difference_noise`] over series of `n` samples of white noise of
/// unit deviation: its 5, 16, 84 and 95 % quantiles (so the 68 % and 90 % intervals of a
/// noise figure over the true σ). Seeded: the same numbers on every run. `None` below 3
/// samples.
pub fn noise_figure_spread(n: usize) -> Option<[f64; 4]> {
    use rand::{rngs::SmallRng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};
    if n < 3 {
        return None;
    }
    let m = n.min(SPREAD_MAX_SIMULATED);
    let mut rng = SmallRng::seed_from_u64(0x5eed);
    let mut series = vec![0.0; m];
    let mut figures: Vec<f64> = (0..SPREAD_TRIALS)
        .filter_map(|_| {
            for v in &mut series {
                *v = StandardNormal.sample(&mut rng);
            }
            second_difference_noise(&series)
        })
        .collect();
    figures.sort_by(f64::total_cmp);
    let scale = ((m - 2) as f64 / (n - 2) as f64).sqrt();
    let quantile = |q: f64| {
        let i = ((q * figures.len() as f64) as usize).min(figures.len().saturating_sub(1));
        1.0 + (figures.get(i).copied().unwrap_or(f64::NAN) - 1.0) * scale
    };
    Some([0.05, 0.16, 0.84, 0.95].map(quantile))
}

/// Most sample counts whose spread is printed; beyond, the smallest and the largest (the
/// others lie between).
const MAX_SPREAD_LINES: usize = 4;

/// Prints [`noise_figure_spread`] for the sample counts of `counts`.
fn print_spread(counts: &BTreeSet<usize>) {
    let shown: Vec<usize> = if counts.len() > MAX_SPREAD_LINES {
        counts
            .first()
            .into_iter()
            .chain(counts.last())
            .copied()
            .collect()
    } else {
        counts.iter().copied().collect()
    };
    for n in shown {
        if let Some([q05, q16, q84, q95]) = noise_figure_spread(n) {
            println!(
                "a noise figure from {n} samples of white noise is within ×{q16:.2}–×{q84:.2} of \
                 the true σ two times in three, ×{q05:.2}–×{q95:.2} nine times in ten"
            );
        }
    }
}

/// `v[n+1] − 2v[n] + v[n−1]` for every inner sample.
fn second_differences(v: &[f64]) -> impl Iterator<Item = f64> + '_ {
    v.windows(3).map(|w| w[2] - 2.0 * w[1] + w[0])
}

/// One row of the table: a name and its samples of x, y (pattern units) and alpha (rad).
struct Samples {
    name: String,
    x: Vec<f64>,
    y: Vec<f64>,
    alpha: Vec<f64>,
}

impl Samples {
    fn new(name: String) -> Self {
        Samples {
            name,
            x: Vec::new(),
            y: Vec::new(),
            alpha: Vec::new(),
        }
    }

    /// Adds a sample; alpha continues the series across ±π (unwrapped), so that a yaw that
    /// crosses it is not read as a jump of 2π.
    fn push(&mut self, x: f64, y: f64, alpha: f64) {
        let alpha = match self.alpha.last() {
            Some(&previous) => previous + wrap_angle(alpha - previous),
            None => alpha,
        };
        self.x.push(x);
        self.y.push(y);
        self.alpha.push(alpha);
    }

    /// Prints the row and adds its sample count to `counts` (for [`print_spread`]).
    fn print(&self, counts: &mut BTreeSet<usize>) {
        counts.insert(self.x.len());
        let cell = |v: &[f64], scale: f64| {
            let scaled: Vec<f64> = v.iter().map(|x| x * scale).collect();
            let (_, std) = mean_std(&scaled);
            let noise = second_difference_noise(&scaled).unwrap_or(f64::NAN);
            format!("{std:>12.4e} {noise:>12.4e}")
        };
        println!(
            "{:<14} {:>7} {} {} {}",
            self.name,
            self.x.len(),
            cell(&self.x, 1.0),
            cell(&self.y, 1.0),
            cell(&self.alpha, 1e6)
        );
    }
}

/// The poses `(x, y, alpha)` of `a` and `b` in the frames where both have one, in `a`'s order.
fn matched<'r>(
    a: &'r [&PoseRow],
    b: &'r [&PoseRow],
) -> impl Iterator<Item = ([f64; 3], [f64; 3])> + 'r {
    let by_frame: BTreeMap<u64, &PoseRow> = b.iter().map(|r| (r.frame, *r)).collect();
    let pose = |r: &PoseRow| Some([r.x?, r.y?, r.alpha?]);
    a.iter()
        .filter_map(move |ra| Some((pose(ra)?, pose(by_frame.get(&ra.frame)?)?)))
}

/// Pose of marker `b` in marker `a`'s frame, per frame where both are seen: position
/// `Rz(−α_a)·(p_b − p_a)` (pattern units), angle `α_b − α_a` wrapped to `[−π, π)`.
fn relative(a: &[&PoseRow], b: &[&PoseRow], name: String) -> Samples {
    let mut out = Samples::new(name);
    for ([xa, ya, aa], [xb, yb, ab]) in matched(a, b) {
        let (dx, dy) = (xb - xa, yb - ya);
        let (s, c) = aa.sin_cos();
        out.push(c * dx + s * dy, -s * dx + c * dy, wrap_angle(ab - aa));
    }
    out
}

/// A marker's pose minus its pose in another table, per frame where both have one: position
/// difference (pattern units) and angle difference wrapped to `[−π, π)`; and the two series
/// over those frames, for their second differences' correlation.
fn difference(ours: &[&PoseRow], other: &[&PoseRow], name: String) -> (Samples, [Samples; 2]) {
    let mut diff = Samples::new(name);
    let mut both = [Samples::new("this".into()), Samples::new("other".into())];
    for ([xa, ya, aa], [xb, yb, ab]) in matched(ours, other) {
        diff.push(xa - xb, ya - yb, wrap_angle(aa - ab));
        both[0].push(xa, ya, aa);
        both[1].push(xb, yb, ab);
    }
    (diff, both)
}

/// Pearson correlation of the second differences of `a` and `b` (same length); `None` below
/// two second differences or when either has none of its own.
fn second_difference_correlation(a: &[f64], b: &[f64]) -> Option<f64> {
    let (da, db): (Vec<f64>, Vec<f64>) = (
        second_differences(a).collect(),
        second_differences(b).collect(),
    );
    if da.len() < 2 || da.len() != db.len() {
        return None;
    }
    let ((ma, sa), (mb, sb)) = (mean_std(&da), mean_std(&db));
    let n = (da.len() - 1) as f64;
    let covariance = da
        .iter()
        .zip(&db)
        .map(|(x, y)| (x - ma) * (y - mb))
        .sum::<f64>()
        / n;
    Some(covariance / (sa * sb)).filter(|r| r.is_finite())
}

/// Prints the tables of `--against` for the markers of `by_id` found in `other`; the sample
/// counts of its rows go to `counts`.
fn print_against(
    by_id: &BTreeMap<u64, &[&PoseRow]>,
    other: &[PoseRow],
    path: &std::path::Path,
    counts: &mut BTreeSet<usize>,
) {
    let (other_markers, _, _) = series(other);
    let other_by_id: BTreeMap<u64, &[&PoseRow]> = other_markers
        .iter()
        .map(|s| (s.id, s.rows.as_slice()))
        .collect();
    println!();
    println!(
        "against {}: the difference per marker (the motion both see cancels; its noise is both \
         estimators' own noise combined)",
        path.display()
    );
    let mut correlations = Vec::new();
    for (id, rows) in by_id {
        let Some(other_rows) = other_by_id.get(id) else {
            println!(
                "{:<14} {:>7} (not in {})",
                format!("{id} − other"),
                0,
                path.display()
            );
            continue;
        };
        let (diff, [a, b]) = difference(rows, other_rows, format!("{id} − other"));
        if diff.x.is_empty() {
            println!("{:<14} {:>7} (no frame in common)", diff.name, 0);
            continue;
        }
        diff.print(counts);
        let r = |x: &[f64], y: &[f64]| {
            second_difference_correlation(x, y).map_or("-".to_string(), |r| format!("{r:.3}"))
        };
        correlations.push((*id, [r(&a.x, &b.x), r(&a.y, &b.y), r(&a.alpha, &b.alpha)]));
    }
    println!("correlation of the second differences with the other table (1: motion both see)");
    println!("{:<14} {:>12} {:>12} {:>12}", "marker", "x", "y", "alpha");
    for (id, [x, y, alpha]) in correlations {
        println!("{id:<14} {x:>12} {y:>12} {alpha:>12}");
    }
}

/// Runs `vernier stats`.
pub fn run(args: &StatsArgs) -> Result<ExitCode, String> {
    let input = match args.inputs.as_slice() {
        [input] => input,
        [] => return Err("no pose table given".into()),
        several => {
            if args.against.is_some() {
                return Err(
                    "--against takes one table; with several, each is compared with each".into(),
                );
            }
            compare::run(several, args.match_by, &args.pairs, MAX_DEFAULT_MARKERS)?;
            return Ok(ExitCode::SUCCESS);
        }
    };
    let rows = read_table_file(input)?;
    let other = match &args.against {
        Some(path) => Some((read_table_file(path)?, path)),
        None => None,
    };
    let (markers, _, _) = series(&rows);
    if markers.is_empty() {
        return Err(format!("{}: no pose in the table", input.display()));
    }
    let by_id: BTreeMap<u64, &[&PoseRow]> =
        markers.iter().map(|s| (s.id, s.rows.as_slice())).collect();
    let pairs = pairs_to_report(&args.pairs, &by_id)?;
    print_table_header();
    // Sample counts of the printed rows, for the spread at the end.
    let mut counts = BTreeSet::new();
    for s in &markers {
        let mut own = Samples::new(format!("{}", s.id));
        for r in &s.rows {
            if let (Some(x), Some(y), Some(alpha)) = (r.x, r.y, r.alpha) {
                own.push(x, y, alpha);
            }
        }
        own.print(&mut counts);
    }
    print_pairs(&pairs, &by_id, &mut counts)?;
    if let Some((other, path)) = other {
        print_against(&by_id, &other, path, &mut counts);
    }
    println!();
    print_spread(&counts);
    Ok(ExitCode::SUCCESS)
}

/// The relative pairs `(a, b)` to report: those asked for (`--pair`), else every pair of
/// the table's markers when they are at most [`MAX_DEFAULT_MARKERS`], else none; an error
/// when an asked-for marker is not in the table.
fn pairs_to_report(
    asked: &[(u64, u64)],
    by_id: &BTreeMap<u64, &[&PoseRow]>,
) -> Result<Vec<(u64, u64)>, String> {
    let pairs: Vec<(u64, u64)> = if !asked.is_empty() {
        asked.to_vec()
    } else if by_id.len() <= MAX_DEFAULT_MARKERS {
        let ids: Vec<u64> = by_id.keys().copied().collect();
        ids.iter()
            .enumerate()
            .flat_map(|(i, &a)| ids[i + 1..].iter().map(move |&b| (a, b)))
            .collect()
    } else {
        Vec::new()
    };
    if let Some((a, b)) = pairs
        .iter()
        .find(|(a, b)| !by_id.contains_key(a) || !by_id.contains_key(b))
    {
        return Err(format!(
            "--pair {a}:{b}: marker {a} or {b} is not in the table"
        ));
    }
    Ok(pairs)
}

/// Prints the noise formula and the column headings, with units.
fn print_table_header() {
    println!(
        "noise = 1.4826·median|v[n+1] − 2v[n] + v[n−1]|/√6 (white noise on a smooth motion); \
         std includes the motion"
    );
    println!(
        "{:<14} {:>7} {:>12} {:>12} {:>12} {:>12} {:>12} {:>12}",
        "marker / pair",
        "samples",
        "x std",
        "x noise",
        "y std",
        "y noise",
        "alpha std",
        "alpha noise"
    );
    println!(
        "{:<14} {:>7} {:>25} {:>25} {:>25}",
        "", "", "(pattern units)", "(pattern units)", "(µrad)"
    );
}

/// Prints a row per relative pair (`b` in `a`'s frame), adding its sample count to
/// `counts`; a pair never seen together gets a row saying so.
fn print_pairs(
    pairs: &[(u64, u64)],
    by_id: &BTreeMap<u64, &[&PoseRow]>,
    counts: &mut BTreeSet<usize>,
) -> Result<(), String> {
    for &(a, b) in pairs {
        let (Some(ra), Some(rb)) = (by_id.get(&a), by_id.get(&b)) else {
            return Err(format!(
                "--pair {a}:{b}: marker {a} or {b} is not in the table"
            ));
        };
        let rel = relative(ra, rb, format!("{b} in {a}"));
        if rel.x.is_empty() {
            println!("{:<14} {:>7} (never seen together)", rel.name, 0);
        } else {
            rel.print(counts);
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn second_differences_see_the_noise_not_the_motion() {
        // Smooth motion of 50 units plus ±σ noise from a fixed pseudo-random sequence.
        let sigma = 0.01;
        let mut state = 12345u64;
        let mut gauss = || {
            // Sum of 12 uniforms − 6: unit variance.
            (0..12)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    (state >> 11) as f64 / (1u64 << 53) as f64
                })
                .sum::<f64>()
                - 6.0
        };
        let v: Vec<f64> = (0..4000)
            .map(|n| 50.0 * (n as f64 / 4000.0 * 3.0).sin() + sigma * gauss())
            .collect();
        let noise = second_difference_noise(&v).unwrap();
        assert!((noise / sigma - 1.0).abs() < 0.1, "{noise}");
        let (_, std) = mean_std(&v);
        assert!(std > 100.0 * sigma);
        assert_eq!(second_difference_noise(&v[..2]), None);
    }

    #[test]
    fn the_spread_of_a_noise_figure_narrows_with_the_samples() {
        let [q05, q16, q84, q95] = noise_figure_spread(10).expect("10 samples");
        assert!(
            q05 < q16 && q16 < 1.0 && 1.0 < q84 && q84 < q95,
            "{q05} {q16} {q84} {q95}"
        );
        // Eight second differences: a wide spread.
        assert!(q16 < 0.8 && q84 > 1.2, "{q16} {q84}");
        // Simulated (1000) and scaled (40 000) counts: the median's deviation over n − 2
        // correlated second differences, about 1.4/√(n − 2) of σ (±4.5 % at 1000 samples).
        for n in [1000, 40_000] {
            let [_, lo, hi, _] = noise_figure_spread(n).expect("many samples");
            let half = 0.5 * (hi - lo);
            let expected = 1.4 / ((n - 2) as f64).sqrt();
            assert!((half / expected - 1.0).abs() < 0.3, "{n}: {lo} {hi}");
        }
        assert_eq!(noise_figure_spread(2), None);
        assert_eq!(noise_figure_spread(10), noise_figure_spread(10));
    }

    #[test]
    fn relative_pose_is_in_the_first_markers_frame() {
        let row = |frame, x, y, alpha| PoseRow {
            frame,
            id: Some(0),
            x: Some(x),
            y: Some(y),
            alpha: Some(alpha),
            ..PoseRow::default()
        };
        let a = [row(0, 1.0, 1.0, std::f64::consts::FRAC_PI_2)];
        let b = [
            row(0, 1.0, 3.0, std::f64::consts::PI),
            row(1, 0.0, 0.0, 0.0),
        ];
        let ra: Vec<&PoseRow> = a.iter().collect();
        let rb: Vec<&PoseRow> = b.iter().collect();
        let rel = relative(&ra, &rb, "b in a".into());
        // b is 2 units along a's +x (a is turned by 90°), turned by another 90°.
        assert_eq!(rel.x.len(), 1);
        assert!((rel.x[0] - 2.0).abs() < 1e-12 && rel.y[0].abs() < 1e-12);
        assert!((rel.alpha[0] - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
    }

    #[test]
    fn alpha_series_continue_across_pi() {
        let mut s = Samples::new("yaw".into());
        for alpha in [3.1, -3.1, -3.0, 3.12] {
            s.push(0.0, 0.0, alpha);
        }
        let tau = std::f64::consts::TAU;
        let expected = [3.1, tau - 3.1, tau - 3.0, 3.12];
        for (got, want) in s.alpha.iter().zip(expected) {
            assert!((got - want).abs() < 1e-12, "{:?}", s.alpha);
        }
    }

    #[test]
    fn pairs_parse() {
        assert_eq!(parse_pair("0:1"), Ok((0, 1)));
        assert!(parse_pair("0-1").is_err());
        assert!(parse_pair("a:1").is_err());
    }
}
