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
    let images: Vec<String> = (96..=105)
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
        "--format",
        "csv",
    ]);
    detect.args(&images);
    std::fs::write(dir.join("ours.csv"), stdout_of_success(&mut detect)).unwrap();
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
