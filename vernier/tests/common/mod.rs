//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::f64::consts::{FRAC_PI_2, FRAC_PI_4};
use std::path::PathBuf;
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::{Detector, GreyImage, Pose};

/// Folder of the real test images: `$VERNIER_DATA_DIR`, else `../shared/data` beside the
/// workspace. Panics (test failure, not skip) when it is missing.
pub fn data_dir() -> PathBuf {
    let dir = std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    assert!(
        dir.is_dir(),
        "test data folder {} is missing: set VERNIER_DATA_DIR to the shared/data folder",
        dir.display()
    );
    dir
}

/// Error of a periodic-grid measurement against the truth, invariant under the grid's
/// symmetries: `(translation error in pixels, angle error in radians)`.
///
/// Both poses describe a square lattice of period `period` (pattern units); the translation
/// error is the distance from the measured node to the nearest true node, in pixels.
pub fn lattice_error(
    measured: &Pose,
    truth: &Pose,
    period: f64,
    image_center: (f64, f64),
) -> (f64, f64) {
    let node = |p: &Pose| {
        let o = p.origin_in_image();
        (image_center.0 + o.x, image_center.1 + o.y)
    };
    let (m, t) = (node(measured), node(truth));
    let pitch_px = period / truth.pixel_size;
    let (s, c) = truth.alpha.sin_cos();
    let (dx, dy) = (m.0 - t.0, m.1 - t.1);
    // Offset in lattice units along the true grid axes, reduced to the nearest node.
    let u = (c * dx + s * dy) / pitch_px;
    let v = (-s * dx + c * dy) / pitch_px;
    let (eu, ev) = ((u - u.round()) * pitch_px, (v - v.round()) * pitch_px);
    let mut da = (measured.alpha - truth.alpha).rem_euclid(FRAC_PI_2);
    if da > FRAC_PI_4 {
        da -= FRAC_PI_2;
    }
    (eu.hypot(ev), da.abs())
}

/// `image` written as an 8-bit JPEG of `quality` (1–100) and read back, as a camera or a
/// user's re-encoding would leave it.
pub fn jpeg(image: &GreyImage, quality: u8) -> GreyImage {
    use image::codecs::jpeg::JpegEncoder;
    let bytes: Vec<u8> = image.quantized(8).iter().map(|&v| v as u8).collect();
    let mut encoded = Vec::new();
    JpegEncoder::new_with_quality(&mut encoded, quality)
        .encode(
            &bytes,
            image.width() as u32,
            image.height() as u32,
            image::ExtendedColorType::L8,
        )
        .expect("JPEG encoding");
    let decoded = image::load_from_memory(&encoded).expect("JPEG decoding");
    GreyImage::from_dynamic(&decoded).expect("grey image")
}

/// The HP code detector a user gets from `--hpcode --period PERIOD --code-size W` and nothing
/// else (polarity and window automatic).
pub fn hp_detector(period: f64, code_size: usize) -> Detector {
    let settings = DetectorSettings {
        pattern_type: MarkerKind::HpCode,
        period: Some(period),
        code_size: Some(code_size),
        ..Default::default()
    };
    Detector::new(settings.to_config().expect("HP settings")).expect("HP detector")
}
