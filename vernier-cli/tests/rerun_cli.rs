//! `vernier detect --rerun`: without the `rerun` feature the flag explains how to get it; with
//! it, a run writes a recording (`cargo test -p vernier-cli --features rerun`).

mod common;

use common::{example_pattern, scratch, vernier};
use std::path::PathBuf;

/// Renders `count` frames of the example grid drifting by 0.1 µm per frame.
fn render_frames(dir: &std::path::Path, count: usize) -> Vec<PathBuf> {
    (0..count)
        .map(|i| {
            let image = dir.join(format!("frame_{i}.png"));
            let status = vernier()
                .args(["render", "--pattern"])
                .arg(example_pattern())
                .args(["--pose", &format!("{},1.0,0.2", 0.1 * i as f64)])
                .args(["--pixel-size", "1.2", "--size", "256x200", "--blur", "0.5"])
                .arg(&image)
                .status()
                .unwrap();
            assert!(status.success());
            image
        })
        .collect()
}

#[test]
fn bad_target_is_a_usage_error() {
    let out = vernier()
        .args(["detect", "--period", "15", "--rerun", "run.txt", "x.png"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("FILE.rrd"), "{stderr}");
}

#[cfg(not(feature = "rerun"))]
#[test]
fn without_the_feature_the_flag_says_how_to_rebuild() {
    let dir = scratch("rerun_off");
    let frames = render_frames(&dir, 1);
    let rrd = dir.join("run.rrd");
    let out = vernier()
        .args(["detect", "--pattern"])
        .arg(example_pattern())
        .arg("--rerun")
        .arg(&rrd)
        .args(&frames)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--features rerun"), "{stderr}");
    assert!(!rrd.exists(), "nothing is written without the feature");
}

#[cfg(feature = "rerun")]
#[test]
fn writes_a_recording_with_every_frame() {
    let dir = scratch("rerun_on");
    let frames = render_frames(&dir, 3);
    let rrd = dir.join("run.rrd");
    let out = vernier()
        .args(["detect", "--format", "csv", "--pattern"])
        .arg(example_pattern())
        .arg("--rerun")
        .arg(&rrd)
        .args(&frames)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The poses still go to stdout: header + one row per frame.
    assert_eq!(String::from_utf8_lossy(&out.stdout).lines().count(), 4);
    let bytes = std::fs::read(&rrd).unwrap();
    // An RRD stream starts with the "RRF2" magic; three frames of images, spectra and two
    // phase maps make well over 100 kB even compressed.
    assert_eq!(&bytes[..4], b"RRF2", "not an RRD file");
    assert!(bytes.len() > 100_000, "{} bytes", bytes.len());
}
