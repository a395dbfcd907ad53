//! `vernier bag` on damaged recordings (issue 16): a bad frame is skipped and counted (exit 0,
//! non-zero with `--strict`), and corrupted chunk bytes are caught by the chunk CRCs before any
//! of their messages reaches the detector; the replay resumes at the next chunk. The recordings are written here with the `mcap`
//! crate (no Python needed).

mod common;

use common::{run as vernier, s, scratch};
use std::collections::BTreeMap;
use std::path::Path;
use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions};
use vernier::Pose;

/// A `sensor_msgs/msg/Image` in little-endian CDR (mono8).
fn image_cdr(frame_id: &str, width: u32, height: u32, data: &[u8]) -> Vec<u8> {
    let mut out = vec![0, 1, 0, 0];
    let mut body: Vec<u8> = Vec::new();
    let align = |b: &mut Vec<u8>, n: usize| {
        while b.len() % n != 0 {
            b.push(0);
        }
    };
    let string = |b: &mut Vec<u8>, text: &str| {
        b.extend_from_slice(&(text.len() as u32 + 1).to_le_bytes());
        b.extend_from_slice(text.as_bytes());
        b.push(0);
    };
    body.extend_from_slice(&1_700_000_000i32.to_le_bytes());
    body.extend_from_slice(&0u32.to_le_bytes());
    string(&mut body, frame_id);
    align(&mut body, 4);
    body.extend_from_slice(&height.to_le_bytes());
    body.extend_from_slice(&width.to_le_bytes());
    string(&mut body, "mono8");
    body.push(0);
    align(&mut body, 4);
    body.extend_from_slice(&width.to_le_bytes());
    body.extend_from_slice(&(data.len() as u32).to_le_bytes());
    body.extend_from_slice(data);
    out.extend(body);
    out
}

fn frame(i: usize) -> Vec<u8> {
    let layout = PeriodicLayout::new(10.0, 21, 21).unwrap();
    let mut options = RenderOptions::new(96, 96);
    options.bit_depth = Some(8);
    let pose = Pose::planar(1.0 + 0.1 * i as f64, -0.5, 0.2, 1.0);
    let image = render(&layout, &pose, &options).unwrap();
    let bytes: Vec<u8> = image
        .pixels()
        .iter()
        .map(|v| (v * 255.0).round() as u8)
        .collect();
    image_cdr(&format!("frame-{i}"), 96, 96, &bytes)
}

/// Writes `payloads` on `/camera/image_raw`, one chunk per message, uncompressed.
fn write_bag(path: &Path, payloads: &[Vec<u8>]) {
    let file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    let mut writer = mcap::WriteOptions::new()
        .profile("ros2")
        .compression(None)
        .chunk_size(Some(1024))
        .create(file)
        .unwrap();
    let schema = writer
        .add_schema("sensor_msgs/msg/Image", "ros2msg", b"")
        .unwrap();
    let channel = writer
        .add_channel(schema, "/camera/image_raw", "cdr", &BTreeMap::new())
        .unwrap();
    for (i, payload) in payloads.iter().enumerate() {
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: i as u32,
            log_time: 1_000 + i as u64,
            publish_time: 1_000 + i as u64,
        };
        writer.write_to_known_channel(&header, payload).unwrap();
    }
    writer.finish().unwrap();
}

fn replay(bag: &Path, out: &Path, strict: bool) -> std::process::Output {
    let mut args = vec![
        "bag",
        "--input",
        s(bag),
        "--period",
        "10",
        "--output",
        s(out),
    ];
    if strict {
        args.push("--strict");
    }
    vernier(&args)
}

#[test]
fn bad_frames_are_skipped_and_counted() {
    let dir = scratch("bag_skip");
    let bag = dir.join("rec.mcap");
    write_bag(&bag, &[frame(0), frame(1), vec![1, 2, 3], frame(3)]);
    let out = dir.join("poses.csv");
    let run = replay(&bag, &out, false);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stderr.contains("1 of 4 frames skipped"), "{stderr}");
    let csv = std::fs::read_to_string(&out).unwrap();
    assert_eq!(csv.lines().count(), 5, "{csv}");
    let strict = replay(&bag, &out, true);
    assert_eq!(strict.status.code(), Some(1));
}

#[test]
fn corrupted_chunks_never_reach_the_detector() {
    let dir = scratch("bag_crc");
    let bag = dir.join("rec.mcap");
    write_bag(&bag, &[frame(0), frame(1), frame(2), frame(3)]);
    let mut bytes = std::fs::read(&bag).unwrap();
    // Flip one pixel of frame 1: every record still parses, only the chunk CRC is wrong.
    let marker = b"frame-1\0";
    let at = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .unwrap();
    bytes[at + 200] ^= 0x40;
    std::fs::write(&bag, &bytes).unwrap();
    let out = dir.join("poses.csv");
    let run = replay(&bag, &out, false);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(
        stderr.contains("chunk 2 of 4 is damaged") && stderr.to_lowercase().contains("crc"),
        "{stderr}"
    );
    // Frames 0, 2 and 3 were measured (the replay resumes after the damaged chunk); the
    // corrupted pixels of frame 1 were never used.
    let csv = std::fs::read_to_string(&out).unwrap();
    assert_eq!(csv.lines().count(), 4, "{csv}");
    assert_eq!(replay(&bag, &out, true).status.code(), Some(1));
}
