//! `vernier stats`: the noise table of a pose series, and `--against` another estimate of the
//! same frames (the motion cancels in their difference). On the real repeatability sequence
//! (`Image96`–`Image105`) against the original's results: prints the table
//! (`cargo test --release -p vernier-cli --test stats_cli -- --nocapture`).

mod common;

use common::{s, scratch, stdout_of_success, vernier};

/// The row of `table` (the output of `vernier stats`) that starts with `name`, as numbers
/// after the name's words.
fn row(table: &str, name: &str) -> Vec<f64> {
    let line = table
        .lines()
        .find(|l| l.starts_with(name))
        .unwrap_or_else(|| panic!("no row `{name}` in\n{table}"));
    line[name.len()..]
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(f64::NAN))
        .collect()
}

/// The correlation rows of the `--against` table (after its header), by marker.
fn correlation(table: &str, id: u64) -> [f64; 3] {
    let after = table
        .split("correlation of the second differences")
        .nth(1)
        .unwrap_or_else(|| panic!("no correlation table in\n{table}"));
    let values = row(
        after.split_once('\n').map_or("", |(_, t)| t),
        &format!("{id} "),
    );
    [values[0], values[1], values[2]]
}

/// The output of `vernier stats OURS --against OTHER`, which must succeed.
fn stats_against(ours: &std::path::Path, other: &std::path::Path) -> String {
    let out = stdout_of_success(vernier().args(["stats", s(ours), "--against", s(other)]));
    String::from_utf8_lossy(&out).into_owned()
}

/// Writes a pose table of `(frame, id, x, y, alpha)` rows.
fn write_table(path: &std::path::Path, rows: &[(u64, u64, f64, f64, f64)]) {
    let mut text = String::from("frame,id,x,y,alpha\n");
    for (frame, id, x, y, alpha) in rows {
        text.push_str(&format!("{frame},{id},{x},{y},{alpha}\n"));
    }
    std::fs::write(path, text).unwrap();
}

#[test]
fn against_another_estimate_the_motion_cancels() {
    // Uneven motion that both tables see, and noise ±ε alternating in the first one only:
    // its second differences are ±4ε, so the difference's noise is 1.4826·4ε/√6 exactly,
    // while the table's own noise is the motion's.
    let dir = scratch("stats_against");
    let (eps, eps_alpha) = (1e-3, 2e-6);
    let motion = |n: u64| {
        let t = n as f64;
        (
            3.0 * (1.7 * t).sin(),
            2.0 * (0.9 * t * t).cos(),
            1e-3 * (2.3 * t).sin(),
        )
    };
    let (mut ours, mut other) = (Vec::new(), Vec::new());
    for n in 0..20u64 {
        let (x, y, a) = motion(n);
        let sign = if n % 2 == 0 { 1.0 } else { -1.0 };
        ours.push((n, 4, x + sign * eps, y - sign * eps, a + sign * eps_alpha));
        other.push((n, 4, x, y, a));
    }
    // A frame that only one table has is left out of the difference.
    other.push((20, 4, 0.0, 0.0, 0.0));
    write_table(&dir.join("ours.csv"), &ours);
    write_table(&dir.join("other.csv"), &other);
    let table = stats_against(&dir.join("ours.csv"), &dir.join("other.csv"));
    let expected = 1.4826 * 4.0 / 6f64.sqrt();
    // samples, x std, x noise, y std, y noise, alpha std, alpha noise (µrad).
    let own = row(&table, "4 ");
    assert!(own[2] > 100.0 * expected * eps, "{table}");
    let diff = row(&table, "4 − other");
    assert_eq!(diff[0], 20.0, "{table}");
    for (got, want) in [
        (diff[2], expected * eps),
        (diff[4], expected * eps),
        (diff[6], expected * eps_alpha * 1e6),
    ] {
        assert!(
            (got / want - 1.0).abs() < 1e-3,
            "{got} against {want}\n{table}"
        );
    }
    // Motion 10³ times the noise: the second differences are the motion's.
    assert!(correlation(&table, 4).iter().all(|r| *r > 0.99), "{table}");
    // A marker the other table lacks is named, not an error.
    write_table(&dir.join("other_id.csv"), &[(0, 5, 0.0, 0.0, 0.0)]);
    let table = stats_against(&dir.join("ours.csv"), &dir.join("other_id.csv"));
    assert!(table.contains("(not in"), "{table}");
    // An unreadable other table fails before any output.
    let failed = common::run(&[
        "stats",
        s(&dir.join("ours.csv")),
        "--against",
        s(&dir.join("missing.csv")),
    ]);
    assert!(!failed.status.success() && failed.stdout.is_empty());
}

/// The original's results `Image96-105_reference.csv` (one row per image, both markers'
/// `no;x;y;alpha;pixelSize`, ids 0 and 1 in that order: data README) as a pose table.
fn reference_as_pose_table(path: &std::path::Path) {
    let text = std::fs::read_to_string(common::data_dir().join("hpcode/Image96-105_reference.csv"))
        .expect("reference results");
    let mut rows = Vec::new();
    for line in text.lines().skip(1).filter(|l| !l.trim().is_empty()) {
        let f: Vec<f64> = line
            .split(';')
            .map(|v| v.parse().unwrap_or(f64::NAN))
            .collect();
        let frame = f[0] as u64 - 96;
        rows.push((frame, 0, f[2], f[3], f[4]));
        rows.push((frame, 1, f[7], f[8], f[9]));
    }
    write_table(path, &rows);
}

#[test]
fn the_real_sequence_against_the_original() {
    let dir = scratch("stats_real");
    detect_sequence(&dir.join("ours.csv"), 96..=105, &[]);
    reference_as_pose_table(&dir.join("original.csv"));
    let table = stats_against(&dir.join("ours.csv"), &dir.join("original.csv"));
    println!("{table}");
    // Positions follow the original's motion (issue target: second differences correlate
    // at 0.95 or more).
    for id in [0, 1] {
        let [x, y, _] = correlation(&table, id);
        assert!(x >= 0.95 && y >= 0.95, "marker {id}\n{table}");
    }
    // Marker 1 sits on the moving part: its alpha second differences are motion that both
    // estimators see (correlation near 1), and the difference of the two holds their own noise
    // alone, far below the series' own figure.
    let [_, _, alpha] = correlation(&table, 1);
    assert!(alpha > 0.95, "{table}");
    let own = row(&table, "1 ");
    let diff = row(&table, "1 − other");
    assert!(diff[6] < 60.0 && diff[6] < 0.25 * own[6], "{table}");
}

/// The cells of the row of series `label` in the block `title` of a comparison (`vernier
/// stats A B C …`): the words after the label, up to the next block.
fn series_row(table: &str, title: &str, label: &str) -> Vec<String> {
    let block = table
        .split("\n\n")
        .find(|b| b.starts_with(title))
        .unwrap_or_else(|| panic!("no block `{title}` in\n{table}"));
    let line = block
        .lines()
        .find(|l| l.trim_start().starts_with(&format!("{label} ")))
        .unwrap_or_else(|| panic!("no row `{label}` in block `{title}`\n{table}"));
    line.split_whitespace()
        .skip(1)
        .map(str::to_string)
        .collect()
}

/// The own noise of series `label` and its interval, `(σ, lo, hi)`, or `None` when the hat
/// reports a negative variance.
fn own_noise(table: &str, title: &str, label: &str) -> Option<(f64, f64, f64)> {
    let cells = series_row(table, title, label);
    // noise, [lo, hi], own, [lo, hi]
    let number = |s: &str| -> f64 {
        s.trim_matches(|c| c == '[' || c == ']' || c == ',')
            .parse()
            .unwrap_or_else(|_| panic!("`{s}` in row {label} of `{title}`\n{table}"))
    };
    if cells.get(3).map(String::as_str) == Some("<") {
        return None;
    }
    Some((number(&cells[3]), number(&cells[4]), number(&cells[5])))
}

/// Writes `count` pose tables of `frames` frames (markers 0 and 1, file names `ImageN.png`):
/// one shared random-walk motion, and white noise of deviation `sigma[i]` (x, y in pattern
/// units; alpha in µrad) in table `i`. Seeded.
fn write_noisy_tables(dir: &std::path::Path, sigma: &[f64], frames: u64, seed: u64) -> Vec<String> {
    use rand::{rngs::SmallRng, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut normal = move || -> f64 { StandardNormal.sample(&mut rng) };
    let mut motion = [[0.0f64; 3]; 2];
    let mut tables: Vec<String> = sigma
        .iter()
        .map(|_| String::from("frame,source,id,x,y,alpha\n"))
        .collect();
    for frame in 0..frames {
        for (id, m) in motion.iter_mut().enumerate() {
            // Steps 20 times the largest noise: the raw series cannot separate it.
            for v in m.iter_mut() {
                *v += 20.0 * normal();
            }
            for (table, s) in tables.iter_mut().zip(sigma) {
                let [x, y, a] = m.map(|v| v + s * normal());
                table.push_str(&format!(
                    "{frame},/data/Image{}.png,{id},{x},{y},{}\n",
                    frame + 7,
                    a * 1e-6
                ));
            }
        }
    }
    tables
        .iter()
        .enumerate()
        .map(|(i, text)| {
            let path = dir.join(format!("series{i}.csv"));
            std::fs::write(&path, text).unwrap();
            path.to_string_lossy().into_owned()
        })
        .collect()
}

#[test]
fn the_hat_recovers_known_noise() {
    // Three and four estimators of one random walk, each with white noise of its own known σ:
    // the printed 90 % interval of each own noise must hold the true σ nine times in ten.
    // Over the 2 markers × 3 quantities × (3 + 4) series = 42 intervals, at least 33 must
    // hold it (expected 37.8; fewer than 33 has a chance of about 1 % for honest intervals),
    // and none may be wider than 3σ.
    let dir = scratch("stats_hat");
    let (mut held, mut total) = (0, 0);
    for (sigma, seed) in [(&[1.0, 0.5, 1.0][..], 11), (&[1.0, 0.5, 0.8, 0.3][..], 12)] {
        let paths = write_noisy_tables(&dir, sigma, 400, seed);
        let mut command = vernier();
        command.arg("stats").args(&paths);
        let table = String::from_utf8_lossy(&stdout_of_success(&mut command)).into_owned();
        let labels = ["A", "B", "C", "D"];
        for subject in ["marker 0", "marker 1"] {
            for quantity in ["x (pattern units)", "y (pattern units)", "alpha (µrad)"] {
                let title = format!("{subject} · {quantity}");
                for (label, s) in labels.iter().zip(sigma) {
                    // A negative hat (an interval of its own kind) counts as not holding σ.
                    if let Some((_, lo, hi)) = own_noise(&table, &title, label) {
                        assert!(hi < 3.0 * s, "{title} {label}\n{table}");
                        held += usize::from(lo <= *s && *s <= hi);
                    }
                    total += 1;
                }
            }
        }
    }
    assert_eq!(total, 42);
    println!("{held} of {total} intervals hold the true σ");
    assert!(held >= 33, "{held} of {total} intervals hold the true σ");
}

#[test]
fn several_tables_need_common_markers_and_no_against() {
    let dir = scratch("stats_several");
    let paths = write_noisy_tables(&dir, &[1.0, 1.0], 10, 1);
    // Two tables: pairs only, no hat.
    let mut command = vernier();
    command.arg("stats").args(&paths).args(["--match", "frame"]);
    let table = String::from_utf8_lossy(&stdout_of_success(&mut command)).into_owned();
    assert!(table.contains("needs three or more series"), "{table}");
    assert!(table.contains("A − B"), "{table}");
    let failed = common::run(&["stats", &paths[0], &paths[1], "--against", &paths[0]]);
    assert!(!failed.status.success() && failed.stdout.is_empty());
    write_table(&dir.join("other_id.csv"), &[(0, 5, 0.0, 0.0, 0.0)]);
    let failed = common::run(&["stats", &paths[0], s(&dir.join("other_id.csv"))]);
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert!(!failed.status.success() && stderr.contains("no marker ID is in every table"));
    // Tables without image names match by frame only; an opposite sign convention is named.
    let motion = |n: u64, sign: f64| {
        let t = n as f64;
        (n, 0, t.sin(), t.cos(), sign * 1e-3 * (t * t).sin())
    };
    let table = |sign: f64| -> Vec<(u64, u64, f64, f64, f64)> {
        (0..60).map(|n| motion(n, sign)).collect()
    };
    write_table(&dir.join("plus.csv"), &table(1.0));
    write_table(&dir.join("minus.csv"), &table(-1.0));
    let (plus, minus) = (dir.join("plus.csv"), dir.join("minus.csv"));
    let failed = common::run(&["stats", s(&plus), s(&minus)]);
    let stderr = String::from_utf8_lossy(&failed.stderr);
    assert!(
        !failed.status.success() && stderr.contains("--match frame"),
        "{stderr}"
    );
    let mut command = vernier();
    command.args(["stats", s(&plus), s(&minus), "--match", "frame"]);
    let table = String::from_utf8_lossy(&stdout_of_success(&mut command)).into_owned();
    assert!(table.contains("opposite sign conventions"), "{table}");
}

/// `vernier detect` of the real sequence's `frames` (`Image96`–`Image125`) with `extra`
/// options, as a table in `path` (JSON Lines for a `.jsonl` path, with the predicted σ;
/// else CSV).
fn detect_sequence(path: &std::path::Path, frames: std::ops::RangeInclusive<u32>, extra: &[&str]) {
    let images: Vec<String> = frames
        .map(|n| {
            let path = common::data_dir().join(format!("hpcode/Image{n}.png"));
            path.to_string_lossy().into_owned()
        })
        .collect();
    let mut detect = vernier();
    detect.args([
        "detect",
        "--hpcode",
        "--period",
        "15.5",
        "--code-size",
        "33",
    ]);
    let format = match path.extension().and_then(|e| e.to_str()) {
        Some("jsonl") => "jsonl",
        _ => "csv",
    };
    detect.args(["--format", format]).args(extra).args(&images);
    std::fs::write(path, stdout_of_success(&mut detect)).unwrap();
}

#[test]
fn the_real_sequence_three_cornered_hat() {
    // The default, a fixed 512-px window and the original's results (its own CSV format,
    // matched by image number) on the 30 frames: every marker, the relative pair and every
    // quantity get each series' noise and an own-noise figure (or a reported negative one).
    // Precision figures are printed, not asserted (docs/accuracy.md states them). The
    // default's predicted σ (its JSON Lines carry them) is honest: never below the 90 %
    // interval of its own noise by the hat, for each marker and quantity.
    let dir = scratch("stats_hat_real");
    detect_sequence(&dir.join("default.jsonl"), 96..=125, &[]);
    detect_sequence(
        &dir.join("w512.csv"),
        96..=125,
        &["--window-size", "512", "--no-field-fit"],
    );
    let reference = common::data_dir().join("hpcode/Image96-125_reference.csv");
    let mut command = vernier();
    command.args([
        "stats",
        s(&dir.join("default.jsonl")),
        s(&dir.join("w512.csv")),
    ]);
    command.arg(&reference);
    let table = String::from_utf8_lossy(&stdout_of_success(&mut command)).into_owned();
    println!("{table}");
    for subject in ["marker 0", "marker 1", "marker 1 in marker 0"] {
        for quantity in ["x (pattern units)", "y (pattern units)", "alpha (µrad)"] {
            let title = format!("{subject} · {quantity} · 30 frames");
            for label in ["A", "B", "C"] {
                let cells = series_row(&table, &title, label);
                let noise: f64 = cells[0].parse().unwrap_or(f64::NAN);
                assert!(noise > 0.0, "{title} {label}\n{table}");
                if let Some((own, lo, hi)) = own_noise(&table, &title, label) {
                    assert!(lo <= own && own <= hi, "{title} {label}\n{table}");
                    if let (Some(predicted), "A", "marker 0" | "marker 1") =
                        (predicted_sigma(&table, &title, label), label, subject)
                    {
                        assert!(predicted >= lo && predicted <= hi, "{title}\n{table}");
                    }
                } else {
                    assert!(cells.iter().any(|c| c.contains("σ²")), "{title}\n{table}");
                }
            }
            for pair in ["A − B", "A − C", "B − C"] {
                // "−", "B", diff noise, [lo, hi], correlation, [lo, hi].
                let cells = series_row(&table, &title, pair);
                let r: f64 = cells[5].parse().unwrap_or(f64::NAN);
                assert!((-1.0..=1.0).contains(&r), "{title} {pair}\n{table}");
            }
        }
    }
}

/// The predicted σ printed on series `label`'s row of the table `title`, if any.
fn predicted_sigma(table: &str, title: &str, label: &str) -> Option<f64> {
    let cells = series_row(table, title, label);
    let at = cells.iter().position(|c| c == "σ")?;
    cells.get(at + 1)?.parse().ok()
}

/// `vernier stats … | head`: a reader that closes the pipe early ends the program as it ends
/// other Unix tools (SIGPIPE), never with a panic.
#[test]
fn a_closed_pipe_ends_stats_without_a_panic() {
    use std::process::Stdio;
    let dir = scratch("stats_closed_pipe");
    let rows: Vec<_> = (0..200u64)
        .flat_map(|n| (0..40u64).map(move |id| (n, id, n as f64, 0.5 * n as f64, 1e-3)))
        .collect();
    write_table(&dir.join("many.csv"), &rows);
    let mut child = vernier()
        .args(["stats", s(&dir.join("many.csv"))])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run vernier: {e}"));
    // Close our end of its stdout before it writes.
    drop(child.stdout.take());
    let out = child
        .wait_with_output()
        .unwrap_or_else(|e| panic!("cannot wait for vernier: {e}"));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_ne!(out.status.code(), Some(101), "{stderr}");
}
