//! Fuzz harnesses on stable Rust (proptest): the image decode path, the pattern-file reader and
//! every detector on arbitrary small images must return `Ok` or `Err`, never panic.
//!
//! `cargo test` runs each harness for a fixed number of cases with a fixed seed (the same
//! inputs on every run, a few seconds in all). A longer run is one command:
//!
//! ```sh
//! bash scripts/fuzz_long.sh 100000 7   # this file and the node's harnesses
//! VERNIER_FUZZ_CASES=100000 VERNIER_FUZZ_SEED=7 cargo test --release -p vernier --test fuzz
//! ```
//!
//! A failure prints the (shrunk) input; add it to `tests/hostile_inputs.rs` as a regression
//! test when fixing it.

mod common;

use proptest::prelude::*;
use proptest::test_runner::{Config, RngAlgorithm, TestCaseError, TestRng, TestRunner};
use vernier::detector::DetectorSettings;
use vernier::layout::BitmapLayout;
use vernier::pattern_file::Pattern;
use vernier::{DecodeLimits, Detector, DetectorConfig, GreyImage};

/// Cases per harness: `$VERNIER_FUZZ_CASES`, default `default`.
fn cases(default: u32) -> u32 {
    std::env::var("VERNIER_FUZZ_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A runner with a fixed seed (`$VERNIER_FUZZ_SEED`, default 16) and no failure files.
fn runner(default_cases: u32) -> TestRunner {
    let seed: u64 = std::env::var("VERNIER_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(16);
    let mut bytes = [0u8; 32];
    bytes[..8].copy_from_slice(&seed.to_le_bytes());
    let config = Config {
        cases: cases(default_cases),
        failure_persistence: None,
        ..Config::default()
    };
    TestRunner::new_with_rng(config, TestRng::from_seed(RngAlgorithm::ChaCha, &bytes))
}

fn no_panic<T>(what: &str, f: impl FnOnce() -> T) -> Result<T, TestCaseError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        .map_err(|_| TestCaseError::fail(format!("{what} panicked")))
}

/// Valid files of each format, as seeds for mutations.
fn seed_files() -> Vec<Vec<u8>> {
    let image =
        GreyImage::new(12, 9, (0..108).map(|i| (i % 7) as f32 / 7.0).collect()).expect("image");
    let png = image.encode_png(8).expect("png");
    let png16 = image.encode_png(16).expect("png16");
    let data = common::data_dir();
    let jpeg = std::fs::read(data.join("hpcode/code18.jpg")).expect("jpeg");
    let tiff = std::fs::read(data.join("hpcode/code22.tif")).expect("tiff");
    // Keep the seeds small: the head of each real file (its headers) plus the end marker.
    let head = |b: &[u8], n: usize| b[..n.min(b.len())].to_vec();
    let mut jpeg_head = head(&jpeg, 20000);
    jpeg_head.extend_from_slice(&[0xFF, 0xD9]);
    let pgm = b"P5\n4 3\n255\n\x00\x10\x20\x30\x40\x50\x60\x70\x80\x90\xa0\xb0".to_vec();
    vec![png, png16, jpeg_head, head(&tiff, 4096), pgm]
}

#[test]
fn fuzz_image_decode() {
    let seeds = seed_files();
    let n = seeds.len();
    let strategy = (
        0..n,
        proptest::collection::vec((any::<u16>(), any::<u8>()), 0..16),
        any::<u16>(),
        proptest::collection::vec(any::<u8>(), 0..64),
    );
    let limits = DecodeLimits::with_max_pixels(1 << 22);
    let name = std::path::Path::new("fuzz.img");
    runner(300)
        .run(&strategy, |(which, flips, cut, raw)| {
            let mut bytes = seeds[which].clone();
            for (at, value) in flips {
                let i = at as usize % bytes.len();
                bytes[i] = value;
            }
            if cut % 4 == 0 {
                bytes.truncate(cut as usize % (bytes.len() + 1));
            }
            no_panic("decode of mutated file", || {
                let _ = GreyImage::decode_bytes(&bytes, name, &limits);
            })?;
            no_panic("decode of random bytes", || {
                let _ = GreyImage::decode_bytes(&raw, name, &limits);
            })?;
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
}

#[test]
fn fuzz_pattern_files() {
    let seeds = [
        r#"{"PeriodicPattern": {"period": 15.0, "nRows": 5, "nCols": 5}}"#,
        r#"{"HPCodePattern": {"period": 15.5, "size": 17, "id": 3}}"#,
        r#"{"MegarenaPattern": {"period": 9.0, "codeSize": 8, "codeDepth": 4}}"#,
        r#"{"BitmapPattern": {"period": 1.0, "bitmap": [[1, 0, 1], [0, 1, 0], [1, 0, 1]]}}"#,
        r#"{"FingerprintPattern": {"period": 1.0, "bitmap": [[1, 0], [0, 1]]}}"#,
        r#"{"CustomPattern": {"period": 1.0, "dots": []}}"#,
    ];
    let tokens = [
        "1e308",
        "-1",
        "0",
        "5e-324",
        "1e-9",
        "nan",
        "[]",
        "{}",
        "\"x\"",
        "99999999999",
        "true",
        "null",
        "[[1]]",
        ",",
        "}",
        "17",
        "1000001",
        "-0.0",
    ];
    let strategy = (
        0..seeds.len(),
        proptest::collection::vec((any::<u16>(), 0..tokens.len()), 0..6),
        "\\PC{0,40}",
    );
    runner(400)
        .run(&strategy, |(which, edits, noise)| {
            let mut text = seeds[which].to_string();
            for (at, token) in edits {
                // Replace a number or insert at a char boundary.
                let mut i = at as usize % (text.len() + 1);
                while !text.is_char_boundary(i) {
                    i -= 1;
                }
                text.insert_str(i, tokens[token]);
            }
            no_panic("pattern file", || {
                if let Ok(p) = Pattern::from_json_str(&text) {
                    let _ = p.to_json_string();
                }
                let _ = Pattern::from_json_str(&noise);
            })?;
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
}

fn detectors() -> Vec<Detector> {
    let stamp =
        BitmapLayout::from_image_file(15.0, common::data_dir().join("layouts/stamp69x69.png"))
            .expect("stamp bitmap");
    let mut configs: Vec<DetectorConfig> = vec![];
    for (kind, code_size, depth) in [
        (vernier::detector::MarkerKind::Periodic, None, None),
        (vernier::detector::MarkerKind::HpCode, Some(33), None),
        (vernier::detector::MarkerKind::Megarena, None, Some(6)),
    ] {
        let settings = DetectorSettings {
            pattern_type: kind,
            period: Some(4.0),
            code_size,
            code_depth: depth,
            ..Default::default()
        };
        configs.push(settings.to_config().expect("config"));
    }
    configs.push(DetectorConfig::Stamp(vernier::stamp::StampParams::new(
        15.0,
        vec![stamp],
    )));
    configs
        .into_iter()
        .map(|c| Detector::new(c).expect("detector"))
        .collect()
}

#[test]
fn fuzz_detectors_on_small_images() {
    let detectors = std::cell::RefCell::new(detectors());
    let strategy = (
        1usize..72,
        1usize..72,
        proptest::collection::vec(any::<u8>(), 1..256),
        0u8..4,
    );
    runner(48)
        .run(&strategy, |(w, h, palette, kind)| {
            // Structured content (stripes, dots, constant, noise) from the random palette.
            let pixels: Vec<f32> = (0..w * h)
                .map(|i| {
                    let (c, r) = (i % w, i / w);
                    let p = palette[i % palette.len()] as f32 / 255.0;
                    match kind {
                        0 => p,
                        1 => ((c / 2 + r / 2) % 2) as f32 * p,
                        2 => palette[0] as f32 / 255.0,
                        _ => (((c as f32 * 1.3).sin() * (r as f32 * 1.3).sin()) + 1.0) / 2.0,
                    }
                })
                .collect();
            let image =
                GreyImage::new(w, h, pixels).map_err(|e| TestCaseError::fail(e.to_string()))?;
            for d in detectors.borrow_mut().iter_mut() {
                no_panic("detector", || {
                    let _ = d.detect(&image);
                })?;
            }
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{e}"));
}
