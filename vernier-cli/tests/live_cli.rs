//! `vernier live` (cargo feature `opencv`): videos written by OpenCV's `VideoWriter` from the
//! project's renders at known poses, and a GStreamer pipeline of 16-bit raw frames, read back
//! through `vernier live`; the error paths of missing sources and of `--display` without a
//! screen. `cargo test -p vernier-cli --features opencv --test live_cli`.
#![cfg(feature = "opencv")]

mod common;

use common::{s, scratch, vernier};
use std::path::{Path, PathBuf};
use std::process::Output;

use opencv::core::{Mat, Size};
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture, VideoWriter};
use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions};
use vernier::Pose;

/// Frames per video.
const FRAMES: usize = 8;
/// Frame side, pixels.
const SIDE: usize = 256;
/// Grid period, µm (1 µm per pixel).
const PERIOD: f64 = 10.0;

/// Largest position error against the truth, µm, and angle error, rad. FFV1 is lossless:
/// the frames read back are the rendered ones (checked bit for bit against `vernier detect`
/// on PNGs of the same frames: identical poses), so this is the detector's own error on these
/// renders. Measured (8 frames, blur 0.5 px): 1.24e-4 µm and 1.45e-6 rad in 8 bit, 3.7e-7 µm
/// and 5.7e-9 rad in 16 bit; the tolerances are 8× and 7× the 8-bit errors.
const POSITION_TOLERANCE_UM: f64 = 1e-3;
const ANGLE_TOLERANCE_RAD: f64 = 1e-5;

/// The pose of frame `i`: within half a period of the origin (a periodic grid's position is
/// only known modulo the period), 1 µm per pixel.
fn truth(i: usize) -> Pose {
    let i = i as f64;
    Pose::planar(1.0 + 0.37 * i, -2.0 + 0.23 * i, 0.2 + 0.01 * i, 1.0)
}

/// Frame `i` rendered at `bits` (8 or 16), as row-major samples in a `u16` each.
fn render_frame(i: usize, bits: u32) -> Vec<u16> {
    let layout = PeriodicLayout::new(PERIOD, 41, 41).unwrap();
    let mut options = RenderOptions::new(SIDE, SIDE);
    options.blur_sigma = 0.5;
    options.bit_depth = Some(bits);
    render(&layout, &truth(i), &options)
        .unwrap()
        .quantized(bits)
}

/// An OpenCV frame of 8-bit samples, grey or (each sample repeated) BGR.
fn mat8(samples: &[u16], colour: bool) -> Mat {
    let bytes: Vec<u8> = samples
        .iter()
        .flat_map(|&v| {
            let v = u8::try_from(v).unwrap();
            if colour {
                vec![v, v, v]
            } else {
                vec![v]
            }
        })
        .collect();
    let side = SIDE as i32;
    let flat = Mat::new_rows_cols_with_data(side, side * if colour { 3 } else { 1 }, &bytes)
        .unwrap()
        .try_clone()
        .unwrap();
    flat.reshape(if colour { 3 } else { 1 }, side)
        .unwrap()
        .try_clone()
        .unwrap()
}

/// Writes the frames as a lossless FFV1 video (`.avi`), grey or colour, at `fps`.
fn write_video(path: &Path, colour: bool, fps: f64) {
    let fourcc = VideoWriter::fourcc('F', 'F', 'V', '1').unwrap();
    let size = Size::new(SIDE as i32, SIDE as i32);
    let mut writer = VideoWriter::new(path, fourcc, fps, size, colour).unwrap();
    assert!(writer.is_opened().unwrap(), "OpenCV cannot write FFV1");
    for i in 0..FRAMES {
        writer.write(&mat8(&render_frame(i, 8), colour)).unwrap();
    }
    writer.release().unwrap();
}

/// Runs `vernier live ARGS --period 10`.
fn live(args: &[&str]) -> Output {
    vernier()
        .arg("live")
        .args(args)
        .args(["--period", "10"])
        .output()
        .unwrap()
}

fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The JSON Lines records of a run.
fn json_lines(out: &Output) -> Vec<serde_json::Value> {
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// Largest position (µm) and angle (rad) errors of the records against the truth of their
/// frame; every record must hold one marker, with `latency_ms`.
fn errors(records: &[serde_json::Value]) -> (f64, f64) {
    let (mut position, mut angle) = (0.0f64, 0.0f64);
    for r in records {
        let frame = r["frame"].as_u64().unwrap() as usize;
        let t = truth(frame);
        let value = |k: &str| r[k].as_f64().unwrap_or_else(|| panic!("no {k} in {r}"));
        position = position
            .max((value("x") - t.x).abs())
            .max((value("y") - t.y).abs());
        angle = angle.max((value("alpha") - t.alpha).abs());
        assert!(value("latency_ms") >= value("time_ms"), "{r}");
    }
    (position, angle)
}

fn assert_close(records: &[serde_json::Value]) {
    let (position, angle) = errors(records);
    eprintln!("measured error: position {position:.2e} µm, angle {angle:.2e} rad");
    assert!(
        position < POSITION_TOLERANCE_UM,
        "position error {position} µm"
    );
    assert!(angle < ANGLE_TOLERANCE_RAD, "angle error {angle} rad");
}

#[test]
fn grey_video_gives_the_rendered_poses_frame_by_frame() {
    let dir = scratch("live_grey");
    let video = dir.join("grey.avi");
    write_video(&video, false, 10.0);
    let out = live(&["--video", s(&video)]);
    assert!(out.status.success(), "{}", stderr(&out));
    let records = json_lines(&out);
    // A file waits for the detector: every frame, in order.
    let frames: Vec<u64> = records
        .iter()
        .map(|r| r["frame"].as_u64().unwrap())
        .collect();
    assert_eq!(frames, (0..FRAMES as u64).collect::<Vec<_>>());
    assert!(records.iter().all(|r| r["source"] == s(&video)));
    assert_close(&records);
    let summary = stderr(&out);
    assert!(
        summary.contains("256x256 8-bit BGR frames, 8 captured, 8 analysed, 0 dropped"),
        "{summary}"
    );
    // The codec's share of the error: none. The frames decode to the rendered samples bit
    // for bit, and the poses are `detect`'s on PNGs of the same frames up to the rounding of
    // the grey → BGR → grey round trip (measured 1.2e-9 µm).
    assert_decodes_to_the_renders(&video);
    let pngs: Vec<PathBuf> = (0..FRAMES)
        .map(|i| {
            let png = dir.join(format!("frame{i}.png"));
            save_png8(&render_frame(i, 8), &png);
            png
        })
        .collect();
    let detect = vernier()
        .args(["detect", "--period", "10", "--format", "jsonl"])
        .args(&pngs)
        .output()
        .unwrap();
    assert!(detect.status.success(), "{}", stderr(&detect));
    let from_png = json_lines(&detect);
    assert_eq!(from_png.len(), FRAMES);
    for (live, png) in records.iter().zip(&from_png) {
        for k in ["x", "y", "alpha", "pixel_size"] {
            let (a, b) = (live[k].as_f64().unwrap(), png[k].as_f64().unwrap());
            assert!((a - b).abs() < 1e-8, "{k}: {live} vs {png}");
        }
    }
    // FFmpeg cannot hand over FFV1's own pixel format: a clear error, not a misread frame.
    let raw = live(&["--video", s(&video), "--raw"]);
    assert_one_line_error(&raw, "--raw");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Reads the video back with OpenCV: every frame's samples (each BGR channel) are the
/// rendered ones.
fn assert_decodes_to_the_renders(video: &Path) {
    let mut capture = VideoCapture::from_file(video, videoio::CAP_FFMPEG).unwrap();
    for i in 0..FRAMES {
        let mut frame = Mat::default();
        assert!(capture.read(&mut frame).unwrap(), "frame {i} missing");
        let decoded = frame.data_bytes().unwrap();
        let expected = render_frame(i, 8);
        assert_eq!(decoded.len(), 3 * expected.len());
        let differ = decoded
            .chunks_exact(3)
            .zip(&expected)
            .filter(|(bgr, &v)| bgr.iter().any(|&c| u16::from(c) != v))
            .count();
        assert_eq!(differ, 0, "frame {i}: {differ} pixels changed by the codec");
    }
}

/// Saves 8-bit samples as an 8-bit PNG.
fn save_png8(samples: &[u16], path: &Path) {
    let bytes: Vec<u8> = samples.iter().map(|&v| v as u8).collect();
    vernier::GreyImage::from_u8(SIDE, SIDE, &bytes)
        .unwrap()
        .save_png(path, 8)
        .unwrap();
}

#[test]
fn colour_video_as_csv_has_the_detect_columns_then_latency() {
    let dir = scratch("live_colour");
    let video = dir.join("colour.avi");
    write_video(&video, true, 10.0);
    let live_out = live(&["--video", s(&video), "--format", "csv"]);
    assert!(live_out.status.success(), "{}", stderr(&live_out));
    let text = String::from_utf8(live_out.stdout).unwrap();
    // `vernier detect --format csv` on a PNG of frame 0: the same columns, in order.
    let png = dir.join("frame0.png");
    save_png8(&render_frame(0, 8), &png);
    let detect = vernier()
        .args(["detect", "--period", "10", "--format", "csv", s(&png)])
        .output()
        .unwrap();
    assert!(detect.status.success(), "{}", stderr(&detect));
    let detect_text = String::from_utf8(detect.stdout).unwrap();
    let header = text.lines().next().unwrap();
    let detect_header = detect_text.lines().next().unwrap();
    assert_eq!(header, format!("{detect_header},latency_ms"));
    let columns: Vec<&str> = header.split(',').collect();
    let rows: Vec<serde_json::Value> = text
        .lines()
        .skip(1)
        .map(|line| {
            let fields: Vec<&str> = line.split(',').collect();
            let mut record = serde_json::Map::new();
            for (name, field) in columns.iter().zip(fields) {
                let value = match (field.parse::<u64>(), field.parse::<f64>()) {
                    (Ok(n), _) => n.into(),
                    (_, Ok(v)) => v.into(),
                    _ => field.into(),
                };
                record.insert(name.to_string(), value);
            }
            serde_json::Value::Object(record)
        })
        .collect();
    assert_eq!(rows.len(), FRAMES, "{text}");
    assert_close(&rows);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn realtime_replay_drops_frames_but_keeps_their_order_and_poses() {
    let dir = scratch("live_realtime");
    let video = dir.join("fast.avi");
    // 1000 frames/s: faster than the detector, so frames are replaced while it works.
    write_video(&video, false, 1000.0);
    let out = live(&["--video", s(&video), "--realtime"]);
    assert!(out.status.success(), "{}", stderr(&out));
    let records = json_lines(&out);
    assert!(!records.is_empty());
    let frames: Vec<u64> = records
        .iter()
        .map(|r| r["frame"].as_u64().unwrap())
        .collect();
    assert!(frames.windows(2).all(|w| w[0] < w[1]), "{frames:?}");
    assert_close(&records);
    // Every captured frame is either analysed or dropped.
    let summary = stderr(&out);
    let dropped = FRAMES - records.len();
    let expected = format!(
        "frames, {FRAMES} captured, {} analysed, {dropped} dropped",
        records.len()
    );
    assert!(
        summary.contains(&expected),
        "{summary}\nexpected {expected}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn sixteen_bit_gstreamer_frames_keep_their_depth_and_a_pipeline_end_is_a_lost_stream() {
    let dir = scratch("live_gst16");
    let raw = dir.join("frames.gray16");
    let bytes: Vec<u8> = (0..FRAMES)
        .flat_map(|i| render_frame(i, 16))
        .flat_map(u16::to_le_bytes)
        .collect();
    std::fs::write(&raw, bytes).unwrap();
    let pipeline = format!(
        "filesrc location={} ! rawvideoparse format=gray16-le width={SIDE} height={SIDE} \
         framerate=10/1 ! videoconvert ! video/x-raw,format=GRAY16_LE ! appsink",
        s(&raw)
    );
    let out = live(&["--gstreamer", &pipeline]);
    let records = json_lines(&out);
    assert_eq!(records.len(), FRAMES, "{}", stderr(&out));
    assert_close(&records);
    // A live source that stops is an error, on one line, after the summary.
    assert!(!out.status.success());
    let text = stderr(&out);
    assert!(text.contains("256x256 16-bit mono frames"), "{text}");
    let last = text.lines().last().unwrap_or_default();
    assert!(
        last.starts_with("vernier: lost the stream of GStreamer pipeline"),
        "{text}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// One line on stderr starting with `vernier:`, and a failure status.
fn assert_one_line_error(out: &Output, needle: &str) {
    let text = stderr(out);
    assert!(!out.status.success(), "{text}");
    assert_eq!(text.lines().count(), 1, "{text}");
    assert!(
        text.starts_with("vernier: ") && text.contains(needle),
        "{text}"
    );
    assert!(out.stdout.is_empty());
}

#[test]
fn missing_sources_are_one_line_errors() {
    let out = live(&["--device", "/dev/video_does_not_exist"]);
    assert_one_line_error(&out, "/dev/video_does_not_exist");
    let missing = PathBuf::from("/nonexistent/vernier/video.avi");
    assert_one_line_error(&live(&["--video", s(&missing)]), "no such file");
    let dir = scratch("live_not_video");
    let text = dir.join("notes.avi");
    std::fs::write(&text, "not a video").unwrap();
    assert_one_line_error(&live(&["--video", s(&text)]), "cannot open video");
    // A camera index no device has.
    assert_one_line_error(&live(&["--camera", "99"]), "camera 99");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn display_without_a_screen_is_an_error_before_capture() {
    // Checked before the source is opened (the GUI toolkit would abort the process later).
    let out = vernier()
        .args([
            "live",
            "--period",
            "10",
            "--display",
            "--video",
            "missing.avi",
        ])
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    assert_one_line_error(&out, "graphical session");
}

#[test]
fn live_takes_the_detect_flags() {
    let help = vernier().args(["live", "--help"]).output().unwrap();
    let text = String::from_utf8_lossy(&help.stdout);
    for flag in [
        "--pattern",
        "--hpcode",
        "--megarena",
        "--code-size",
        "--window-size",
        "--pose-3d",
        "--track",
        "--reacquire-every",
        "--polarity",
        "--pixel-size",
    ] {
        assert!(text.contains(flag), "{flag} missing from:\n{text}");
    }
    // Exactly one source.
    let none = live(&[]);
    assert_eq!(none.status.code(), Some(2));
    let two = live(&["--camera", "0", "--video", "x.avi"]);
    assert_eq!(two.status.code(), Some(2));
}

#[test]
fn ctrl_c_ends_a_live_run_cleanly() {
    use std::io::{BufRead, BufReader};
    use std::process::Stdio;
    // An endless live pipeline: only SIGINT ends it.
    let mut child = vernier()
        .args(["live", "--period", "10", "--format", "csv", "--gstreamer"])
        .arg(
            "videotestsrc is-live=true ! video/x-raw,format=GRAY8,width=64,height=64,\
             framerate=30/1 ! appsink",
        )
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = BufReader::new(child.stdout.take().unwrap());
    let mut lines = Vec::new();
    // The header, then a first frame's row: the run is under way.
    for _ in 0..2 {
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        lines.push(line);
    }
    // The shell's own `kill` (no procps needed).
    let status = std::process::Command::new("sh")
        .args(["-c", &format!("kill -INT {}", child.id())])
        .status()
        .unwrap();
    assert!(status.success());
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut rest).unwrap();
    let out = child.wait_with_output().unwrap();
    let text = stderr(&out);
    assert!(out.status.success(), "{text}");
    assert!(
        text.starts_with("live: gstreamer: 64x64 8-bit mono frames"),
        "{text}"
    );
    // Every row written is whole (flushed, not cut off), with the header's column count.
    assert!(lines[0].starts_with("frame,stamp,") && lines[0].ends_with(",latency_ms\n"));
    let columns = lines[0].split(',').count();
    for row in lines[1..].iter().map(String::as_str).chain(rest.lines()) {
        let row = row.trim_end();
        // The error column (no pattern in the test image) is quoted: count outside quotes.
        let unquoted: String = row.split('"').step_by(2).collect();
        assert_eq!(unquoted.split(',').count(), columns, "{row}");
    }
}
