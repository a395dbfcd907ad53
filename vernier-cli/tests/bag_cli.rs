//! `vernier bag` round trip: PyPI `rosbags` writes a rosbag2 MCAP of synthetic images with
//! known poses, the project replays it with the node's parameter file, and `rosbags` reads
//! the MCAP output back (PoseStamped and MarkerPoseArray with their ros2msg schemas).
//! Needs `.venv/` from `scripts/setup_test_tools.sh`.

mod common;

use common::{run as vernier, s, scratch};
use std::path::{Path, PathBuf};
use std::process::Command;

use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions};
use vernier::Pose;

fn venv_python() -> PathBuf {
    let python = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `bash scripts/setup_test_tools.sh` first (it installs rosbags, \
         the independent rosbag2 writer and reader of this test, into .venv/)",
        python.display()
    );
    python
}

fn python(script: &str, args: &[&Path]) -> String {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/py")
        .join(script);
    let out = Command::new(venv_python())
        .arg(path)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{script} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

/// The poses of the synthetic frames: µm and rad, 1 µm per pixel.
fn truth(i: usize) -> Pose {
    let i = i as f64;
    Pose::planar(1.0 + 0.2 * i, -2.0 + 0.1 * i, 0.2 + 0.01 * i, 1.0)
}

const FRAMES: usize = 6;

/// Renders the frames (mono8 256×256, period 10 µm as in params/detector.yaml) and has
/// rosbags write them into a rosbag2 MCAP folder.
fn make_bag(dir: &Path) -> PathBuf {
    let layout = PeriodicLayout::new(10.0, 41, 41).unwrap();
    let mut frames = Vec::new();
    for i in 0..FRAMES {
        let mut options = RenderOptions::new(256, 256);
        options.blur_sigma = 0.5;
        options.bit_depth = Some(8);
        let image = render(&layout, &truth(i), &options).unwrap();
        let bytes: Vec<u8> = image
            .pixels()
            .iter()
            .map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
            .collect();
        let file = dir.join(format!("frame{i}.raw"));
        std::fs::write(&file, bytes).unwrap();
        frames.push(serde_json::json!({
            "file": s(&file), "sec": 1_700_000_000 + i, "nanosec": 250_000_000,
        }));
    }
    let manifest = serde_json::json!({
        "topic": "/camera/image_raw", "frame_id": "microscope", "width": 256, "height": 256,
        "encoding": "mono8", "step": 256, "frames": frames,
    });
    let manifest_path = dir.join("manifest.json");
    std::fs::write(&manifest_path, manifest.to_string()).unwrap();
    let bag = dir.join("recording");
    python("make_bag.py", &[&manifest_path, &bag]);
    bag
}

#[test]
fn replays_a_rosbags_recording_to_mcap_and_csv() {
    let dir = scratch("bag");
    let bag = make_bag(&dir);
    let params = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../params/detector.yaml");

    // CSV: pattern units, stamps from the image headers.
    let csv_path = dir.join("poses.csv");
    let run = vernier(&[
        "bag",
        "--input",
        s(&bag),
        "--topic",
        "/camera/image_raw",
        "--params",
        s(&params),
        "--output",
        s(&csv_path),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let csv = std::fs::read_to_string(&csv_path).unwrap();
    let rows: Vec<Vec<&str>> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').collect())
        .collect();
    assert_eq!(rows.len(), FRAMES, "{csv}");
    for (i, row) in rows.iter().enumerate() {
        let t = truth(i);
        let value = |k: usize| row[k].parse::<f64>().unwrap();
        assert_eq!(row[2], "/camera/image_raw");
        assert!(
            (value(1) - (1_700_000_000.25 + i as f64)).abs() < 1e-6,
            "stamp {}",
            row[1]
        );
        assert!(
            (value(4) - t.x).abs() < 2e-3,
            "frame {i}: x {} vs {}",
            row[4],
            t.x
        );
        assert!(
            (value(5) - t.y).abs() < 2e-3,
            "frame {i}: y {} vs {}",
            row[5],
            t.y
        );
        assert!(
            (value(7) - t.alpha).abs() < 1e-4,
            "frame {i}: alpha {}",
            row[7]
        );
    }

    // MCAP: SI units, the node's topics, read back by rosbags.
    let mcap_path = dir.join("poses.mcap");
    let run = vernier(&[
        "bag",
        "--input",
        s(&bag),
        "--params",
        s(&params),
        "--output",
        s(&mcap_path),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let lines = python("read_bag.py", &[&mcap_path]);
    let messages: Vec<serde_json::Value> = lines
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let poses: Vec<&serde_json::Value> = messages
        .iter()
        .filter(|m| m["topic"] == "/vernier_detector/marker_0/pose")
        .collect();
    let arrays: Vec<&serde_json::Value> = messages
        .iter()
        .filter(|m| m["topic"] == "/vernier_detector/markers")
        .collect();
    let on = |topic: &str| -> Vec<&serde_json::Value> {
        messages.iter().filter(|m| m["topic"] == topic).collect()
    };
    let detections = on("/vernier_detector/detections");
    let with_covariance = on("/vernier_detector/marker_0/pose_with_covariance");
    assert_eq!(poses.len(), FRAMES, "{lines}");
    assert_eq!(arrays.len(), FRAMES);
    assert_eq!(detections.len(), FRAMES);
    assert_eq!(with_covariance.len(), FRAMES);
    for (i, (pose, array)) in poses.iter().zip(&arrays).enumerate() {
        assert_eq!(pose["type"], "geometry_msgs/msg/PoseStamped");
        assert_eq!(array["type"], "vernier_ros/msg/MarkerPoseArray");
        for m in [pose, array] {
            assert_eq!(m["sec"], 1_700_000_000 + i as u64);
            assert_eq!(m["nanosec"], 250_000_000);
            assert_eq!(m["frame_id"], "microscope");
            assert_eq!(
                m["time"],
                (1_700_000_000 + i as u64) * 1_000_000_000 + 250_000_000
            );
        }
        let expected = truth(i).scaled(1e-6).camera_from_pattern();
        let position: Vec<f64> = pose["pose"]["position"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        for k in 0..3 {
            assert!(
                (position[k] - expected.translation.vector[k]).abs() < 2e-9,
                "frame {i}: position {position:?} vs {:?}",
                expected.translation.vector
            );
        }
        let q = expected.rotation.quaternion();
        let orientation = &pose["pose"]["orientation"];
        for (k, e) in [q.i, q.j, q.k, q.w].into_iter().enumerate() {
            assert!(
                (orientation[k].as_f64().unwrap() - e).abs() < 1e-4,
                "frame {i}: {orientation}"
            );
        }
        let marker = &array["markers"][0];
        assert_eq!(marker["id"], 0);
        assert_eq!(marker["pose"], pose["pose"], "array and PoseStamped agree");
        assert!((marker["pixel_size"].as_f64().unwrap() - 1e-6).abs() < 1e-10);
        let cov = marker["covariance"].as_array().unwrap();
        assert_eq!(cov.len(), 36);
        assert!(
            cov[0].as_f64().unwrap() > 0.0 && cov[0].as_f64().unwrap() < 1e-14,
            "σx² in m²"
        );
        assert_eq!(cov[14].as_f64().unwrap(), 1e6, "z unobserved");
        // The standard types carry the same pose and covariance.
        assert_eq!(detections[i]["type"], "vision_msgs/msg/Detection3DArray");
        let detection = &detections[i]["detections"][0];
        assert_eq!(detection["class_id"], "0");
        assert_eq!(detection["id"], "vernier_marker_0");
        assert_eq!(detection["score"], marker["quality"]);
        assert_eq!(detection["pose"], pose["pose"]);
        assert_eq!(&detection["covariance"], &marker["covariance"]);
        assert_eq!(with_covariance[i]["pose"], pose["pose"]);
        assert_eq!(&with_covariance[i]["covariance"], &marker["covariance"]);
    }
}

#[test]
fn bad_inputs_fail_with_one_line() {
    let dir = scratch("bag_bad");
    std::fs::write(dir.join("old.db3"), b"").unwrap();
    let out = dir.join("o.csv");
    for (args, message) in [
        (vec!["--input", s(&dir), "--period", "10"], "not supported"),
        (
            vec!["--input", s(&dir.join("x.bag")), "--period", "10"],
            "expected an .mcap file",
        ),
    ] {
        let mut all = vec!["bag"];
        all.extend(args);
        all.extend(["--output", s(&out)]);
        let run = vernier(&all);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success());
        assert!(stderr.contains(message), "{all:?}: {stderr}");
    }
}
