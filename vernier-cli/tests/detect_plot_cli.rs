//! `vernier detect` over a folder and a glob (pose table as CSV / JSON Lines), then
//! `vernier plot` of the table.

mod common;

use common::{s, scratch};
use std::process::Output;

/// Runs `vernier args…`, asserting success.
fn vernier(args: &[&str]) -> Output {
    let out = common::run(args);
    assert!(
        out.status.success(),
        "vernier {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

/// Column `name` of a CSV text, as numbers (empty fields skipped).
fn column(csv: &str, name: &str) -> Vec<f64> {
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let k = header.iter().position(|h| *h == name).unwrap();
    lines
        .filter_map(|l| l.split(',').nth(k).and_then(|v| v.parse().ok()))
        .collect()
}

#[test]
fn detect_folder_then_plot() {
    let dir = scratch("series");
    let frames = dir.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    let pattern = dir.join("periodic.json");
    std::fs::write(
        &pattern,
        r#"{"PeriodicPattern": {"period": 10.0, "nRows": 41, "nCols": 41}}"#,
    )
    .unwrap();
    // 12 frames moving by 0.3 µm steps along x, within half a period of the origin (the
    // periodic detector measures modulo one period) (names without leading zeros: natural
    // order must put frame 10 after frame 9).
    let shifts: Vec<f64> = (0..12).map(|i| 0.3 * i as f64).collect();
    for (i, dx) in shifts.iter().enumerate() {
        let pose = format!("{},{},0.2", 1.0 + dx, -2.0 + 0.1 * dx);
        let file = frames.join(format!("frame{i}.png"));
        vernier(&[
            "render",
            "--pattern",
            s(&pattern),
            "--pose",
            &pose,
            "--pixel-size",
            "1",
            "--size",
            "256x256",
            "--blur",
            "0.5",
            "--bits",
            "16",
            s(&file),
        ]);
    }
    std::fs::write(frames.join("readme.txt"), "not an image").unwrap();

    let csv = vernier(&[
        "detect",
        "--pattern",
        s(&pattern),
        "--format",
        "csv",
        s(&frames),
    ]);
    let csv = String::from_utf8(csv.stdout).unwrap();
    let header = csv.lines().next().unwrap();
    assert!(
        header.starts_with("frame,stamp,source,id,x,y,z,alpha"),
        "{header}"
    );
    assert_eq!(
        column(&csv, "frame"),
        (0..12).map(f64::from).collect::<Vec<_>>()
    );
    let x = column(&csv, "x");
    assert_eq!(x.len(), 12, "{csv}");
    for (i, dx) in shifts.iter().enumerate() {
        let measured = x[i] - x[0];
        assert!(
            (measured - dx).abs() < 2e-3,
            "frame {i}: moved {measured}, truth {dx}"
        );
    }
    assert!(
        column(&csv, "stamp").iter().all(|t| *t > 1.6e9),
        "file times"
    );

    // The same through a glob, as JSON Lines.
    let glob = format!("{}/frame1*.png", s(&frames));
    let jsonl = vernier(&[
        "detect",
        "--pattern",
        s(&pattern),
        "--format",
        "jsonl",
        &glob,
    ]);
    let jsonl = String::from_utf8(jsonl.stdout).unwrap();
    let sources: Vec<String> = jsonl
        .lines()
        .map(|l| {
            serde_json::from_str::<serde_json::Value>(l).unwrap()["source"]
                .as_str()
                .unwrap()
                .to_string()
        })
        .collect();
    assert_eq!(sources.len(), 3, "frame1, frame10, frame11");
    assert!(sources[0].ends_with("frame1.png") && sources[2].ends_with("frame11.png"));

    let table = dir.join("poses.csv");
    std::fs::write(&table, &csv).unwrap();
    let png = dir.join("poses.png");
    let summary = vernier(&[
        "plot",
        s(&table),
        "--output",
        s(&png),
        "--width",
        "900",
        "--height",
        "600",
    ]);
    let summary = String::from_utf8(summary.stdout).unwrap();
    assert!(
        summary.starts_with("id,quantity,unit,samples,mean,std,adev_tau0"),
        "{summary}"
    );
    assert_eq!(
        summary.lines().count(),
        4,
        "x, y, alpha of marker 0:\n{summary}"
    );
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    assert_eq!((be(16), be(20)), (900, 600));
}

#[test]
fn detect_rejects_empty_folder_and_plot_empty_table() {
    let dir = scratch("empty");
    let out = common::run(&["detect", "--period", "10", s(&dir)]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("holds no image"));
    let table = dir.join("t.csv");
    std::fs::write(&table, "frame,stamp,source,id,x,y\n0,,a.png,,,\n").unwrap();
    let out = common::run(&["plot", s(&table), "-o", s(&dir.join("p.png"))]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("no pose to plot"));
}

#[test]
fn tracked_sequence_gives_the_same_poses() {
    // The real repeatability sequence, in order: `--track` (finder search on the first frame
    // only here) prints the markers of the full search, their poses to within the tracked
    // whole-field fit's agreement with the cold one (asserted in units of σ by the library's
    // tests, vernier/tests/hpcode.rs; here, that the CLI takes the tracked path and keeps
    // frames and markers apart: far below a pixel and a milliradian, within 1e-2 px and
    // 1e-4 rad).
    let dir = common::data_dir().join("hpcode");
    let images: Vec<String> = (96..=105)
        .map(|n| {
            dir.join(format!("Image{n}.png"))
                .to_string_lossy()
                .into_owned()
        })
        .collect();
    let run = |extra: &[&str]| {
        let mut args = vec![
            "detect",
            "--type",
            "hpcode",
            "--period",
            "15.5",
            "--code-size",
            "33",
        ];
        args.extend(extra);
        args.extend(["--format", "csv"]);
        args.extend(images.iter().map(String::as_str));
        String::from_utf8_lossy(&vernier(&args).stdout).into_owned()
    };
    // Rows of each frame by marker ID: the order of a frame's markers is not part of the
    // result (tracking keeps the previous frame's; a full search lists them as its rounds of
    // finder triples find them).
    let by_marker = |csv: &str| {
        let columns = ["frame", "id", "x", "y", "alpha", "pixel_size"].map(|n| column(csv, n));
        let mut rows: Vec<Vec<f64>> = (0..columns[0].len())
            .map(|i| columns.iter().map(|c| c[i]).collect())
            .collect();
        rows.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
        rows
    };
    let full = run(&[]);
    let (a, b) = (
        by_marker(&full),
        by_marker(&run(&["--track", "--reacquire-every", "0"])),
    );
    assert_eq!(a.len(), 20, "{full}");
    assert_eq!(a.len(), b.len());
    for (p, q) in a.iter().zip(&b) {
        // frame, id, x, y (pattern units), alpha (rad), pixel size (units per pixel).
        assert_eq!((p[0], p[1]), (q[0], q[1]));
        let px = |v: f64| v / p[5];
        assert!(px((p[2] - q[2]).hypot(p[3] - q[3])) < 1e-2, "{p:?} {q:?}");
        assert!((p[4] - q[4]).abs() < 1e-4, "{p:?} {q:?}");
    }
}
