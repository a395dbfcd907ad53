//! `vernier stats A B [C …]`: several estimates of the same frames (this program at several
//! settings, another program's results) compared per marker, per relative pair of markers and
//! per quantity: each series' noise, the noise of each pairwise difference and the correlation
//! of the second differences, and each estimator's own noise by the N-cornered hat
//! ([`super::hat`]).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::hat::{
    correlation_interval, effective_samples, hat_intervals, n_cornered_hat, pair_variances, LEVEL,
};
use super::reference::{is_reference_csv, parse_reference_csv};
use super::{noise_figure_spread, second_difference_noise, second_differences, Samples};
use crate::pose_table::{read_table, PoseRow};
use vernier::phase::wrap_angle;

/// How the frames of the series are matched.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MatchBy {
    /// By image: the number in the image's file name (`Image96.png` and the original's `96`
    /// match) when every row has one, else the file name without extension.
    Name,
    /// By frame index (the `frame` column; the row's order in the original's CSV).
    Frame,
}

/// Most series compared at once (labelled A to Z).
const MAX_SERIES: usize = 26;

/// One input: its label, file and pose rows.
struct Input {
    label: char,
    path: PathBuf,
    rows: Vec<PoseRow>,
}

/// Reads a pose table of `detect`/`bag` or the original's CSV; a note on the original's
/// renumbered rows goes to `notes`.
fn load(label: char, path: &Path, notes: &mut Vec<String>) -> Result<Input, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let rows = if is_reference_csv(&text) {
        let (rows, renumbered) = parse_reference_csv(&text, path)?;
        if renumbered > 0 {
            notes.push(format!(
                "{label}: {renumbered} rows of {} repeat a marker ID: their markers are \
                 numbered in the row's order (0, 1, …)",
                path.display()
            ));
        }
        rows
    } else {
        read_table(&text).map_err(|e| format!("{}: {e}", path.display()))?
    };
    Ok(Input {
        label,
        path: path.to_path_buf(),
        rows,
    })
}

/// The key that matches a frame across series.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Key {
    Number(u64),
    Stem(String),
    Frame(u64),
}

/// The file name of `source` without folder and extension.
fn stem(source: &str) -> &str {
    Path::new(source)
        .file_stem()
        .and_then(|s| s.to_str())
        .unwrap_or(source)
}

/// The last group of digits of `name`, if any (`Image96` → 96).
fn image_number(name: &str) -> Option<u64> {
    let end = name.rfind(|c: char| c.is_ascii_digit())? + 1;
    let start = name[..end]
        .rfind(|c: char| !c.is_ascii_digit())
        .map_or(0, |i| i + 1);
    name[start..end].parse().ok()
}

/// A marker's poses in one series: per key, the row's frame (for ordering), `(x, y, α)` and
/// their predicted σ (`x_std`, `y_std`, `alpha_std`; NaN where the table has none).
type Poses = BTreeMap<Key, (u64, [f64; 3], [f64; 3])>;

/// Every series' poses per marker ID, and how many rows were left out because their marker
/// appears twice in one frame. Fails when two frames of a table share an image name (a bag
/// topic, a table without `source`): they need `--match frame`.
fn poses_by_marker(
    inputs: &[Input],
    by: MatchBy,
) -> Result<(Vec<BTreeMap<u64, Poses>>, usize), String> {
    let posed = |r: &&PoseRow| r.id.is_some() && r.x.is_some() && r.y.is_some();
    let numbered = inputs
        .iter()
        .flat_map(|i| i.rows.iter().filter(posed))
        .all(|r| image_number(stem(&r.source)).is_some());
    let key = |r: &PoseRow| match by {
        MatchBy::Frame => Key::Frame(r.frame),
        MatchBy::Name if numbered => Key::Number(image_number(stem(&r.source)).unwrap_or(0)),
        MatchBy::Name => Key::Stem(stem(&r.source).to_string()),
    };
    let mut left_out = 0;
    let all = inputs
        .iter()
        .map(|input| {
            let mut markers: BTreeMap<u64, Poses> = BTreeMap::new();
            let mut twice: BTreeSet<(u64, Key)> = BTreeSet::new();
            for r in input.rows.iter().filter(posed) {
                let (Some(id), Some(x), Some(y), Some(alpha)) = (r.id, r.x, r.y, r.alpha) else {
                    continue;
                };
                let k = key(r);
                let poses = markers.entry(id).or_default();
                let std = [r.x_std, r.y_std, r.alpha_std].map(|s| s.unwrap_or(f64::NAN));
                if let Some((frame, ..)) = poses.insert(k.clone(), (r.frame, [x, y, alpha], std)) {
                    if frame != r.frame {
                        return Err(format!(
                            "{}: frames {frame} and {} have the same image name `{}`: match \
                             them with --match frame",
                            input.path.display(),
                            r.frame,
                            stem(&r.source)
                        ));
                    }
                    twice.insert((id, k));
                }
            }
            for (id, k) in twice {
                left_out += 2;
                if let Some(poses) = markers.get_mut(&id) {
                    poses.remove(&k);
                }
            }
            Ok(markers)
        })
        .collect::<Result<_, String>>()?;
    Ok((all, left_out))
}

/// What is compared: a marker, or marker `b` in marker `a`'s frame.
#[derive(Clone, Copy)]
enum Subject {
    Marker(u64),
    Pair(u64, u64),
}

impl Subject {
    fn name(self) -> String {
        match self {
            Subject::Marker(id) => format!("marker {id}"),
            Subject::Pair(a, b) => format!("marker {b} in marker {a}"),
        }
    }

    /// Each series' samples of the subject at `keys` ([`Subject::keys`]).
    fn samples(self, series: &[BTreeMap<u64, Poses>], keys: &[Key]) -> Vec<Samples> {
        series
            .iter()
            .map(|m| {
                let mut s = Samples::new(String::new());
                for [x, y, alpha] in keys.iter().filter_map(|k| self.pose_at(m, k)) {
                    s.push(x, y, alpha);
                }
                s
            })
            .collect()
    }

    /// Each series' median predicted σ of `(x, y, α)` at `keys` ([`Subject::keys`]): a
    /// marker's own (NaN where its table has none); NaN for a pair, whose σ the tables do not
    /// give.
    fn predicted(self, series: &[BTreeMap<u64, Poses>], keys: &[Key]) -> Vec<[f64; 3]> {
        series
            .iter()
            .map(|m| match self {
                Subject::Marker(id) => [0, 1, 2].map(|q| {
                    let mut v: Vec<f64> = keys
                        .iter()
                        .filter_map(|k| m.get(&id)?.get(k).map(|(.., std)| std[q]))
                        .filter(|s| s.is_finite())
                        .collect();
                    v.sort_by(f64::total_cmp);
                    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
                }),
                Subject::Pair(..) => [f64::NAN; 3],
            })
            .collect()
    }

    /// The keys where every series has the subject, in the first series' frame order.
    fn keys(self, series: &[BTreeMap<u64, Poses>]) -> Vec<Key> {
        let first_id = match self {
            Subject::Marker(id) | Subject::Pair(id, _) => id,
        };
        let mut keys: Vec<(u64, &Key)> = series
            .first()
            .and_then(|m| m.get(&first_id))
            .map(|p| p.iter().map(|(k, (frame, ..))| (*frame, k)).collect())
            .unwrap_or_default();
        keys.retain(|(_, k)| series.iter().all(|m| self.pose_at(m, k).is_some()));
        keys.sort();
        keys.into_iter().map(|(_, k)| k.clone()).collect()
    }

    /// The subject's `(x, y, α)` at key `k` in one series: a marker's pose, or marker `b` in
    /// marker `a`'s frame.
    fn pose_at(self, m: &BTreeMap<u64, Poses>, k: &Key) -> Option<[f64; 3]> {
        let pose = |id: u64| -> Option<[f64; 3]> { m.get(&id)?.get(k).map(|(_, p, _)| *p) };
        match self {
            Subject::Marker(id) => pose(id),
            Subject::Pair(a, b) => {
                let ([xa, ya, aa], [xb, yb, ab]) = (pose(a)?, pose(b)?);
                let (dx, dy) = (xb - xa, yb - ya);
                let (s, c) = aa.sin_cos();
                Some([c * dx + s * dy, -s * dx + c * dy, wrap_angle(ab - aa)])
            }
        }
    }
}

/// A number with four significant digits, plain between 1e-3 and 1e6.
fn fmt(v: f64) -> String {
    let a = v.abs();
    if !v.is_finite() {
        "-".into()
    } else if a == 0.0 {
        "0".into()
    } else if (1e-3..1e6).contains(&a) {
        let decimals = (3 - a.log10().floor() as i32).clamp(0, 6) as usize;
        format!("{v:.decimals$}")
    } else {
        format!("{v:.3e}")
    }
}

/// The [`LEVEL`] interval of the true σ behind a noise figure `sigma` from `n` samples.
fn noise_interval(sigma: f64, n: usize) -> String {
    match noise_figure_spread(n) {
        Some([q05, _, _, q95]) => format!("[{}, {}]", fmt(sigma / q95), fmt(sigma / q05)),
        None => "-".into(),
    }
}

/// Prints the comparison of one quantity of one subject: `values[i]` is series `i`'s series
/// and `predicted[i]` its median predicted σ (NaN: none), both in the printed unit.
fn print_quantity(title: &str, labels: &[char], values: &[&[f64]], predicted: &[f64]) {
    let n = values.first().map_or(0, |v| v.len());
    println!("{title} · {n} frames");
    let hat = pair_variances(values).and_then(|pair| {
        let own = n_cornered_hat(&pair)?;
        let intervals = hat_intervals(&own, n)?;
        Some((pair, own, intervals))
    });
    println!(
        "  {:<8} {:>10} {:<22} {:>10} {:<22}",
        "series", "noise", "(90 % interval)", "own noise", "(90 % interval, hat)"
    );
    for (i, (label, v)) in labels.iter().zip(values).enumerate() {
        let noise = second_difference_noise(v).unwrap_or(f64::NAN);
        let mut cell = match &hat {
            Some((pair, own, intervals)) => own_cell(i, labels, pair, own[i], intervals[i]),
            None => String::new(),
        };
        if let Some(&p) = predicted.get(i).filter(|p| p.is_finite()) {
            cell.push_str(&format!("   predicted σ {}", fmt(p)));
            if let Some((_, own, _)) = hat.as_ref().filter(|(_, own, _)| own[i] > 0.0) {
                cell.push_str(&format!(" (own/predicted {:.2})", own[i].sqrt() / p));
            }
        }
        println!(
            "  {label:<8} {:>10} {:<22} {cell}",
            fmt(noise),
            noise_interval(noise, n)
        );
    }
    println!(
        "  {:<8} {:>10} {:<22} {:>10} {:<22}",
        "pair", "diff noise", "(90 % interval)", "2nd-d corr", "(95 % interval)"
    );
    for i in 0..values.len() {
        for j in i + 1..values.len() {
            print_pair(labels, values, i, j);
        }
    }
}

/// The hat's cell of series `i`: its own noise and interval, or the negative variance and the
/// series it most likely shares errors with (the smallest pair difference).
fn own_cell(
    i: usize,
    labels: &[char],
    pair: &[Vec<f64>],
    var: f64,
    (lo, hi): (f64, f64),
) -> String {
    if var >= 0.0 {
        let (lo, hi) = (lo.max(0.0).sqrt(), hi.max(0.0).sqrt());
        return format!("{:>10} [{}, {}]", fmt(var.sqrt()), fmt(lo), fmt(hi));
    }
    let partner = (0..pair.len())
        .filter(|&j| j != i)
        .min_by(|&a, &b| pair[i][a].total_cmp(&pair[i][b]))
        .and_then(|j| labels.get(j))
        .map_or(String::new(), |l| {
            format!(": errors correlated with another series' (closest: {l})")
        });
    let bound = if hi > 0.0 {
        format!(", σ ≤ {}", fmt(hi.sqrt()))
    } else {
        String::new()
    };
    format!("{:>10} (σ² = {}{bound}){partner}", "< 0", fmt(var))
}

/// Gaussian efficiency of the median absolute value as a scale estimator: a robust
/// correlation from `n` pairs is as uncertain as Pearson's from about `0.37·n`.
const MEDIAN_EFFICIENCY: f64 = 0.37;

/// Correlation of the second differences of `a` and `b` from their robust noise figures and
/// that of their difference `diff_noise` (Gnanadesikan and Kettenring's identity
/// `ρ = (σ²_a + σ²_b − σ²_{a−b}) / (2 σ_a σ_b)`), so that one bad frame, which the noise
/// figures ignore, does not decide it as it does Pearson's; within `[−1, 1]`.
fn robust_correlation(a: &[f64], b: &[f64], diff_noise: f64) -> Option<f64> {
    let (sa, sb) = (second_difference_noise(a)?, second_difference_noise(b)?);
    let r = (sa * sa + sb * sb - diff_noise * diff_noise) / (2.0 * sa * sb);
    r.is_finite().then(|| r.clamp(-1.0, 1.0))
}

/// Prints the pair row of series `i` and `j`: the noise of their difference and the
/// correlation of their second differences ([`robust_correlation`]), each with its interval.
fn print_pair(labels: &[char], values: &[&[f64]], i: usize, j: usize) {
    let diff: Vec<f64> = values[i]
        .iter()
        .zip(values[j])
        .map(|(a, b)| a - b)
        .collect();
    let noise = second_difference_noise(&diff).unwrap_or(f64::NAN);
    let (da, db): (Vec<f64>, Vec<f64>) = (
        second_differences(values[i]).collect(),
        second_differences(values[j]).collect(),
    );
    let mut opposite = false;
    let corr = match robust_correlation(values[i], values[j], noise) {
        Some(r) => {
            let n_eff = effective_samples(&da, &db) * MEDIAN_EFFICIENCY;
            let (lo, hi) = correlation_interval(r, n_eff);
            opposite = hi < 0.0;
            format!("{r:>10.3} [{lo:.3}, {hi:.3}]")
        }
        None => format!("{:>10}", "-"),
    };
    let name = format!("{} − {}", labels[i], labels[j]);
    println!(
        "  {name:<8} {:>10} {:<22} {corr}",
        fmt(noise),
        noise_interval(noise, diff.len())
    );
    if opposite {
        println!(
            "  note: {} and {} move in opposite directions: opposite sign conventions? The \
             difference then holds the motion twice; negate one table's column first",
            labels[i], labels[j]
        );
    }
}

/// Runs the comparison of `paths` (two or more), matching frames `by`; `pairs` as in
/// `vernier stats` (empty: every pair of at most `max_markers` markers).
pub fn run(
    paths: &[PathBuf],
    by: MatchBy,
    pairs: &[(u64, u64)],
    max_markers: usize,
) -> Result<(), String> {
    if paths.len() > MAX_SERIES {
        return Err(format!(
            "{} tables: at most {MAX_SERIES} are compared at once",
            paths.len()
        ));
    }
    let mut notes = Vec::new();
    let inputs = paths
        .iter()
        .zip('A'..='Z')
        .map(|(p, label)| load(label, p, &mut notes))
        .collect::<Result<Vec<_>, _>>()?;
    let (series, left_out) = poses_by_marker(&inputs, by)?;
    let common: Vec<u64> = series
        .first()
        .map(|m| m.keys().copied())
        .into_iter()
        .flatten()
        .filter(|id| series.iter().all(|m| m.contains_key(id)))
        .collect();
    if common.is_empty() {
        return Err("no marker ID is in every table".into());
    }
    let pairs: Vec<(u64, u64)> = if !pairs.is_empty() {
        pairs.to_vec()
    } else if common.len() <= max_markers {
        common
            .iter()
            .enumerate()
            .flat_map(|(i, &a)| common[i + 1..].iter().map(move |&b| (a, b)))
            .collect()
    } else {
        Vec::new()
    };
    if let Some((a, b)) = pairs
        .iter()
        .find(|(a, b)| !common.contains(a) || !common.contains(b))
    {
        return Err(format!(
            "--pair {a}:{b}: marker {a} or {b} is not in every table"
        ));
    }
    print_header(&inputs, &series, &common, by, left_out, &notes);
    let subjects = common
        .iter()
        .map(|&id| Subject::Marker(id))
        .chain(pairs.iter().map(|&(a, b)| Subject::Pair(a, b)));
    for subject in subjects {
        print_subject(subject, &series, &inputs);
    }
    Ok(())
}

/// Prints the tables of one subject, one per quantity.
fn print_subject(subject: Subject, series: &[BTreeMap<u64, Poses>], inputs: &[Input]) {
    let keys = subject.keys(series);
    let samples = subject.samples(series, &keys);
    let labels: Vec<char> = inputs.iter().map(|i| i.label).collect();
    let name = subject.name();
    if samples.first().map_or(0, |s| s.x.len()) < 3 {
        println!("\n{name}: fewer than 3 frames in every table, nothing to compare");
        return;
    }
    let micro = |v: &[f64]| -> Vec<f64> { v.iter().map(|a| a * 1e6).collect() };
    let alpha: Vec<Vec<f64>> = samples.iter().map(|s| micro(&s.alpha)).collect();
    let quantities: [(&str, Vec<&[f64]>); 3] = [
        (
            "x (pattern units)",
            samples.iter().map(|s| s.x.as_slice()).collect(),
        ),
        (
            "y (pattern units)",
            samples.iter().map(|s| s.y.as_slice()).collect(),
        ),
        ("alpha (µrad)", alpha.iter().map(Vec::as_slice).collect()),
    ];
    let predicted = subject.predicted(series, &keys);
    for (q, (quantity, values)) in quantities.into_iter().enumerate() {
        // Alpha is printed in µrad.
        let unit = if q == 2 { 1e6 } else { 1.0 };
        let predicted: Vec<f64> = predicted.iter().map(|p| p[q] * unit).collect();
        println!();
        print_quantity(
            &format!("{name} · {quantity}"),
            &labels,
            &values,
            &predicted,
        );
    }
}

/// Prints the series, how frames were matched and the method in one line each.
fn print_header(
    inputs: &[Input],
    series: &[BTreeMap<u64, Poses>],
    common: &[u64],
    by: MatchBy,
    left_out: usize,
    notes: &[String],
) {
    for (input, markers) in inputs.iter().zip(series) {
        let frames: BTreeSet<&Key> = markers.values().flat_map(|p| p.keys()).collect();
        println!(
            "series {}: {} ({} frames, markers {:?})",
            input.label,
            input.path.display(),
            frames.len(),
            markers.keys().collect::<Vec<_>>()
        );
    }
    let by = match by {
        MatchBy::Name => "image name (the number in the file name, else the name)",
        MatchBy::Frame => "frame index",
    };
    println!("frames matched by {by}; markers in every table: {common:?}");
    for note in notes {
        println!("note: {note}");
    }
    if left_out > 0 {
        println!("note: {left_out} rows left out: their marker appears twice in one frame");
    }
    println!(
        "noise: robust second-difference σ (1.4826·median|v[n+1] − 2v[n] + v[n−1]|/√6); diff \
         noise: the same of the difference of two series (the motion cancels); own noise: \
         {}; intervals: {:.0} % for noise, 95 % for correlations",
        if inputs.len() >= 3 {
            "least-squares N-cornered hat over all pairs (three-cornered hat for three series), \
             assuming independent estimators"
        } else {
            "needs three or more series"
        },
        LEVEL * 100.0
    );
    println!("units: x, y in pattern units (µm for a period in µm), alpha in µrad");
    if inputs
        .iter()
        .any(|i| i.rows.iter().any(|r| r.alpha_std.is_some()))
    {
        println!(
            "predicted σ: the median over the frames of the σ a table gives (`x_std`, `y_std`, \
             `alpha_std`: detect --format jsonl or json); honest when own/predicted is near 1"
        );
    }
}
