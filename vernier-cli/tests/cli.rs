//! End-to-end tests of the `vernier` binary: render → detect round trip and error handling.

mod common;

use common::{example_pattern, s, scratch, stdout_of_success, vernier};

#[test]
fn render_then_detect_round_trip_json_and_csv() {
    let dir = scratch("roundtrip");
    let image = dir.join("grid.png");
    let status = vernier()
        .args(["render", "--pattern"])
        .arg(example_pattern())
        .args([
            "--pose",
            "-2.5,4.0,0.3",
            "--pixel-size",
            "1.1",
            "--size",
            "301x240",
            "--bits",
            "16",
            "--blur",
            "0.5",
        ])
        .arg(&image)
        .status()
        .unwrap();
    assert!(status.success());
    let out = stdout_of_success(
        vernier()
            .args(["detect", "--pattern"])
            .arg(example_pattern())
            .arg(&image),
    );
    let line = String::from_utf8(out).unwrap();
    let json: serde_json::Value = serde_json::from_str(line.trim()).unwrap();
    // Default format: one JSON object per image.
    assert_eq!(json["image"].as_str().unwrap(), image.display().to_string());
    assert!(json["time_ms"].as_f64().unwrap() >= 0.0);
    let marker = &json["markers"][0];
    for key in [
        "id",
        "x",
        "y",
        "z",
        "alpha",
        "beta",
        "gamma",
        "pixel_size",
        "x_px",
        "y_px",
        "quality",
    ] {
        assert!(marker.get(key).is_some(), "missing {key} in {line}");
    }
    assert!(json["time_ms"].as_f64().unwrap() >= 0.0);
    // True pose (−2.5, 4.0, 0.3); P = 15 so the grid pose is already in [−P/2, P/2).
    assert!((marker["x"].as_f64().unwrap() + 2.5).abs() < 2e-3, "{line}");
    assert!((marker["y"].as_f64().unwrap() - 4.0).abs() < 2e-3, "{line}");
    assert!(
        (marker["alpha"].as_f64().unwrap() - 0.3).abs() < 1e-5,
        "{line}"
    );
    assert!(
        (marker["pixel_size"].as_f64().unwrap() - 1.1).abs() < 1e-5,
        "{line}"
    );

    let out = vernier()
        .args(["detect", "--format", "csv", "--period", "15"])
        .arg(&image)
        .output()
        .unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    assert!(lines
        .next()
        .unwrap()
        .starts_with("frame,stamp,source,id,x,y,"));
    assert_eq!(lines.next().unwrap().split(',').count(), 18);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn bad_input_gives_one_line_errors_and_failure_codes() {
    let dir = scratch("errors");
    let bad_json = dir.join("bad.json");
    std::fs::write(&bad_json, "{ \"PeriodicPattern\": { \"period\": 15.0, ").unwrap();
    let empty_png = dir.join("empty.png");
    std::fs::write(&empty_png, b"").unwrap();
    let cases: Vec<Vec<std::ffi::OsString>> = vec![
        vec![
            "detect".into(),
            "--pattern".into(),
            bad_json.clone().into(),
            "x.png".into(),
        ],
        vec![
            "detect".into(),
            "--period".into(),
            "15".into(),
            empty_png.clone().into(),
        ],
        vec![
            "detect".into(),
            "--period".into(),
            "15".into(),
            "/nonexistent.png".into(),
        ],
        vec![
            "detect".into(),
            "--period".into(),
            "-3".into(),
            "x.png".into(),
        ],
        vec![
            "render".into(),
            "--pattern".into(),
            example_pattern().into(),
            "--pose".into(),
            "1,2".into(),
            "--pixel-size".into(),
            "1".into(),
            "--size".into(),
            "64x64".into(),
            dir.join("o.png").into(),
        ],
        vec![
            "render".into(),
            "--pattern".into(),
            example_pattern().into(),
            "--pose".into(),
            "1,2,0".into(),
            "--pixel-size".into(),
            "1".into(),
            "--size".into(),
            "0x64".into(),
            dir.join("o.png").into(),
        ],
    ];
    for args in cases {
        let out = vernier().args(&args).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} should fail");
        assert!(stderr.starts_with("vernier: "), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn usage_errors_name_what_is_missing_and_where_to_read_more() {
    // `vernier detect` without an image names the missing argument and the subcommand's help.
    let out = vernier()
        .args(["detect", "--period", "15"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    assert!(stderr.contains("<IMAGES>"), "{stderr}");
    assert!(stderr.contains("`vernier detect --help`"), "{stderr}");
    // Bare `vernier` shows the help (commands listed), not its description as an error.
    let out = vernier().output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let text =
        String::from_utf8_lossy(&out.stderr).to_string() + &String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("Usage:") && text.contains("detect"), "{text}");
    assert!(!text.starts_with("vernier: "), "{text}");
}

#[test]
fn detect_pose_3d_prints_the_out_of_plane_angles() {
    use vernier::layout::MegarenaLayout;
    use vernier::render::{render, RenderOptions};
    // A depth-8 Megarena (P = 10) tilted by beta = 0.25, gamma = -0.15 rad (orthographic
    // render: the sign of both angles is the mirror ambiguity's, their magnitudes are exact).
    let dir = scratch("pose3d");
    let image = dir.join("tilted.png");
    let layout = MegarenaLayout::new(10.0, 8).unwrap();
    let truth = vernier::Pose {
        x: -3000.0,
        y: -4200.0,
        z: 0.0,
        alpha: 0.6,
        beta: 0.25,
        gamma: -0.15,
        pixel_size: 1.2,
    };
    let options = RenderOptions {
        blur_sigma: 0.5,
        bit_depth: Some(16),
        ..RenderOptions::new(512, 512)
    };
    render(&layout, &truth, &options)
        .unwrap()
        .save_png(&image, 16)
        .unwrap();
    let detect = |extra: &[&str]| {
        let out = vernier()
            .args([
                "detect",
                "--megarena",
                "--period",
                "10",
                "--code-depth",
                "8",
            ])
            .args(extra)
            .arg(&image)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8(out.stdout).unwrap()
    };
    let line = detect(&["--pose-3d"]);
    let json: serde_json::Value = serde_json::from_str(line.trim()).unwrap();
    let marker = &json["markers"][0];
    let (beta, gamma) = (
        marker["beta"].as_f64().unwrap(),
        marker["gamma"].as_f64().unwrap(),
    );
    assert!(beta != 0.0 && gamma != 0.0, "{line}");
    // One of the two mirror solutions (0.25, −0.15) / (−0.25, 0.15).
    assert!((beta.abs() - 0.25).abs() < 1e-3, "{line}");
    assert!(
        (gamma.abs() - 0.15).abs() < 1e-3 && beta * gamma < 0.0,
        "{line}"
    );
    let cue = marker["pose_3d_cue_strength"].as_f64().unwrap();
    assert!((0.0..=1.0).contains(&cue), "{line}");
    // CSV carries the same angles.
    let csv = detect(&["--pose-3d", "--format", "csv"]);
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let row: Vec<&str> = lines.next().unwrap().split(',').collect();
    let field = |name: &str| -> f64 {
        let k = header.iter().position(|h| *h == name).unwrap();
        row[k].parse().unwrap()
    };
    // (serde_json's float parsing is not correctly rounded: compare to 1e-12.)
    assert!((field("beta") - beta).abs() < 1e-12, "{csv}");
    assert!((field("gamma") - gamma).abs() < 1e-12, "{csv}");
    // Without the flag: planar pose, no cue strength.
    let line = detect(&[]);
    let json: serde_json::Value = serde_json::from_str(line.trim()).unwrap();
    let marker = &json["markers"][0];
    assert_eq!(marker["beta"].as_f64(), Some(0.0), "{line}");
    assert_eq!(marker["gamma"].as_f64(), Some(0.0), "{line}");
    assert!(marker.get("pose_3d_cue_strength").is_none(), "{line}");
}

/// A 16-bit PNG at `path` of `layout` rendered at `truth` (`size` px square, blur 0.5 px).
fn save_render(
    layout: &dyn vernier::layout::Layout,
    truth: &vernier::Pose,
    size: usize,
    path: &std::path::Path,
) {
    let options = vernier::render::RenderOptions {
        blur_sigma: 0.5,
        bit_depth: Some(16),
        ..vernier::render::RenderOptions::new(size, size)
    };
    vernier::render::render(layout, truth, &options)
        .unwrap()
        .save_png(path, 16)
        .unwrap();
}

#[test]
fn detect_pose_3d_on_a_periodic_grid() {
    use vernier::layout::PeriodicLayout;
    // A periodic grid (P = 10) tilted by beta = 0.2, gamma = 0.1 rad, orthographic render: one
    // of the two mirror solutions, magnitudes exact.
    let dir = scratch("pose3d_periodic");
    let image = dir.join("tilted.png");
    let truth = vernier::Pose {
        x: 1.0,
        y: -2.0,
        z: 0.0,
        alpha: 0.4,
        beta: 0.2,
        gamma: 0.1,
        pixel_size: 1.1,
    };
    save_render(
        &PeriodicLayout::new(10.0, 61, 61).unwrap(),
        &truth,
        256,
        &image,
    );
    let out = vernier()
        .args(["detect", "--period", "10", "--pose-3d"])
        .arg(&image)
        .output()
        .unwrap();
    let line = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json: serde_json::Value = serde_json::from_str(line.trim()).unwrap();
    let marker = &json["markers"][0];
    let (beta, gamma) = (
        marker["beta"].as_f64().unwrap(),
        marker["gamma"].as_f64().unwrap(),
    );
    assert!(
        (beta.abs() - 0.2).abs() < 1e-3 && (gamma.abs() - 0.1).abs() < 1e-3,
        "{line}"
    );
    assert!(beta * gamma > 0.0, "{line}");
    assert!(marker["pose_3d_cue_strength"].as_f64().is_some(), "{line}");
}

#[test]
fn detect_pose_3d_on_an_hp_code_with_and_without_a_focal_length() {
    use vernier::layout::HpCodeLayout;
    // An HP code (P = 10, W = 33) tilted by beta = 0.2, gamma = -0.25 rad at the image centre,
    // orthographic render: the angles and their σ; with a focal length, z = pixel size × focal
    // (the tangent map at the optical axis is the same) and its σ.
    let dir = scratch("pose3d_hpcode");
    let image = dir.join("tilted.png");
    let truth = vernier::Pose {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        alpha: 0.4,
        beta: 0.2,
        gamma: -0.25,
        pixel_size: 0.9,
    };
    let layout = HpCodeLayout::from_code_size(10.0, 33)
        .unwrap()
        .with_id(5)
        .unwrap();
    save_render(&layout, &truth, 320, &image);
    let detect = |extra: &[&str]| {
        let out = vernier()
            .args(["detect", "--hpcode", "--period", "10", "--code-size", "33"])
            .args(extra)
            .arg(&image)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let line = String::from_utf8_lossy(&out.stdout).to_string();
        let json: serde_json::Value = serde_json::from_str(line.trim()).unwrap();
        (json["markers"][0].clone(), line)
    };
    let (marker, line) = detect(&["--pose-3d"]);
    let (beta, gamma) = (
        marker["beta"].as_f64().unwrap(),
        marker["gamma"].as_f64().unwrap(),
    );
    assert!(
        (beta.abs() - 0.2).abs() < 1e-3 && (gamma.abs() - 0.25).abs() < 1e-3,
        "{line}"
    );
    assert!(beta * gamma < 0.0, "{line}");
    for key in ["beta_std", "gamma_std", "pose_3d_cue_strength"] {
        assert!(marker[key].as_f64().is_some(), "{key}: {line}");
    }
    assert!(
        marker.get("z_std").is_none(),
        "no focal length, no depth: {line}"
    );
    assert_eq!(marker["z"].as_f64(), Some(0.0), "{line}");
    let (marker, line) = detect(&["--pose-3d", "--focal-length-px", "8000"]);
    let z = marker["z"].as_f64().unwrap();
    assert!((z / (0.9 * 8000.0) - 1.0).abs() < 1e-3, "{line}");
    let z_std = marker["z_std"].as_f64().unwrap();
    assert!(z_std > 0.0 && z_std < 1.0, "{line}");
    // A focal length is for the out-of-plane pose only.
    let refused = vernier()
        .args(["detect", "--hpcode", "--period", "10", "--code-size", "33"])
        .args(["--focal-length-px", "8000"])
        .arg(&image)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        !refused.status.success() && stderr.contains("pose-3d"),
        "{stderr}"
    );
}

#[test]
fn calibrate_pools_tiles_and_detect_takes_the_calibrated_pixel_size() {
    // A grid filling 640 × 480 px at 0.9 units per pixel, 1 % noise, seen twice.
    let dir = scratch("calibrate");
    let pattern = dir.join("grid.json");
    std::fs::write(
        &pattern,
        r#"{"PeriodicPattern": {"unit": "um", "period": 12.0, "nRows": 61, "nCols": 61}}"#,
    )
    .unwrap();
    let mut images = Vec::new();
    for (k, pose) in ["1.0,2.0,0.2", "-3.0,0.5,0.21"].iter().enumerate() {
        let image = dir.join(format!("grid{k}.png"));
        let status = vernier()
            .args(["render", "--pattern", s(&pattern), "--pose", pose])
            .args(["--pixel-size", "0.9", "--size", "640x480", "--bits", "16"])
            .args(["--blur", "1", "--noise", "0.01", "--seed", &k.to_string()])
            .arg(&image)
            .status()
            .unwrap();
        assert!(status.success());
        images.push(image);
    }
    let out = stdout_of_success(
        vernier()
            .args(["calibrate", "--json", "--pattern", s(&pattern)])
            .args(&images),
    );
    let json: serde_json::Value = serde_json::from_slice(&out).unwrap();
    let fit = &json["calibration"];
    let (size, std) = (
        fit["pixel_size"].as_f64().unwrap(),
        fit["pixel_size_std"].as_f64().unwrap(),
    );
    // Two whole images and 2 × 9 tiles.
    assert_eq!(json["samples"].as_array().unwrap().len(), 20, "{json}");
    assert!((size - 0.9).abs() < 4.0 * std && std < 1e-5, "{fit}");
    assert!(fit["gradient"].is_array(), "{fit}");

    // detect --pixel-size: positions with the given scale, the measured one beside it.
    let out = vernier()
        .args(["detect", "--pattern", s(&pattern), "--pixel-size", "0.9"])
        .arg(&images[0])
        .output()
        .unwrap();
    assert!(out.status.success());
    let json: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let marker = &json["markers"][0];
    assert_eq!(marker["pixel_size"].as_f64(), Some(0.9));
    let measured = marker["measured_pixel_size"].as_f64().unwrap();
    let measured_std = marker["pixel_size_std"].as_f64().unwrap();
    assert!((measured - 0.9).abs() < 5.0 * measured_std && measured_std > 0.0);
    // A calibrated pixel size out of range is a one-line error.
    let out = vernier()
        .args(["detect", "--pattern", s(&pattern), "--pixel-size", "-1"])
        .arg(&images[0])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("pixel_size"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn independent_images_run_in_parallel_and_print_in_input_order() {
    // Renders of a grid at eight poses, one unreadable file among them: `--jobs 3` (three
    // images at once) gives the rows of `--jobs 1`, in the images' order, the bad file's
    // error in its place, and the same failure exit code.
    let dir = scratch("jobs");
    let mut images = Vec::new();
    for k in 0..8 {
        let image = dir.join(format!("grid_{k}.png"));
        let pose = format!("{:.2},{:.2},0.{k}", 0.5 * k as f64, -0.3 * k as f64);
        let status = vernier()
            .args(["render", "--pattern"])
            .arg(example_pattern())
            .args(["--pose", &pose, "--pixel-size", "1.1", "--size", "200x160"])
            .arg(&image)
            .status()
            .unwrap();
        assert!(status.success());
        images.push(image);
    }
    images.insert(5, dir.join("missing.png"));
    let rows = |jobs: &str| {
        let output = vernier()
            .args(["detect", "--format", "csv", "--jobs", jobs, "--pattern"])
            .arg(example_pattern())
            .args(&images)
            .output()
            .unwrap();
        assert_eq!(output.status.code(), Some(1), "{jobs} jobs");
        // Every column but the time each image took.
        let text = String::from_utf8(output.stdout).unwrap();
        let header: Vec<&str> = text.lines().next().unwrap().split(',').collect();
        let time = header.iter().position(|c| *c == "time_ms").unwrap();
        text.lines()
            .map(|line| {
                let mut cells: Vec<&str> = line.split(',').collect();
                cells.remove(time);
                cells.join(",")
            })
            .collect::<Vec<_>>()
    };
    let (one, three) = (rows("1"), rows("3"));
    assert_eq!(one, three);
    assert_eq!(one.len(), 1 + images.len(), "{one:#?}");
    for (row, image) in one.iter().skip(1).zip(&images) {
        assert!(row.contains(s(image)), "{row} is not {}", image.display());
    }
}
