//! Image input formats, polarity and every bad-input path of the periodic pipeline: clear
//! errors, never a panic.

mod common;

use vernier::layout::PeriodicLayout;
use vernier::pattern_file::Pattern;
use vernier::render::{render, RenderOptions};
use vernier::{
    Error, GreyImage, PeriodicDetector, PeriodicParams, PhaseEngine, PhaseParams, Polarity, Pose,
};

fn test_image(width: usize, height: usize) -> (GreyImage, Pose) {
    let layout = PeriodicLayout::new(9.0, 101, 101).unwrap();
    let pose = Pose::planar(1.7, -2.9, 0.21, 1.0);
    let mut opts = RenderOptions::new(width, height);
    opts.blur_sigma = 0.5;
    opts.background = 0.05;
    opts.foreground = 0.95;
    (render(&layout, &pose, &opts).unwrap(), pose)
}

fn detect(image: &GreyImage, polarity: Polarity) -> vernier::Result<Pose> {
    let mut params = PeriodicParams::new(9.0);
    params.polarity = polarity;
    Ok(PeriodicDetector::new(params)?.detect(image)?.pose)
}

fn assert_close(found: &Pose, truth: &Pose, size: (usize, usize), tolerance_px: f64) {
    let center = ((size.0 / 2) as f64, (size.1 / 2) as f64);
    let (err, _) = common::lattice_error(found, truth, 9.0, center);
    assert!(
        err < tolerance_px,
        "error {err:.2e} px ({found:?} vs {truth:?})"
    );
}

#[test]
fn every_file_format_and_bit_depth_reads_the_same_pose() {
    let (image, truth) = test_image(181, 150); // odd width on purpose
    let dir = std::env::temp_dir().join(format!("vernier-formats-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (w, h) = (image.width() as u32, image.height() as u32);
    let grey8: Vec<u8> = image
        .pixels()
        .iter()
        .map(|v| (v * 255.0).round() as u8)
        .collect();
    let grey16: Vec<u16> = image
        .pixels()
        .iter()
        .map(|v| (v * 65535.0).round() as u16)
        .collect();
    let rgb8: Vec<u8> = grey8.iter().flat_map(|&v| [v, v, v]).collect();
    let rgb16: Vec<u16> = grey16.iter().flat_map(|&v| [v, v, v]).collect();
    let files: Vec<(&str, image::DynamicImage)> = vec![
        (
            "g8.png",
            image::GrayImage::from_raw(w, h, grey8.clone())
                .unwrap()
                .into(),
        ),
        (
            "g16.png",
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, grey16.clone())
                .unwrap()
                .into(),
        ),
        (
            "rgb8.png",
            image::RgbImage::from_raw(w, h, rgb8.clone())
                .unwrap()
                .into(),
        ),
        (
            "rgb16.png",
            image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(w, h, rgb16)
                .unwrap()
                .into(),
        ),
        (
            "g8.tif",
            image::GrayImage::from_raw(w, h, grey8.clone())
                .unwrap()
                .into(),
        ),
        (
            "g16.tif",
            image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, grey16)
                .unwrap()
                .into(),
        ),
        (
            "g8.pgm",
            image::GrayImage::from_raw(w, h, grey8.clone())
                .unwrap()
                .into(),
        ),
        (
            "rgb8.ppm",
            image::RgbImage::from_raw(w, h, rgb8.clone())
                .unwrap()
                .into(),
        ),
        (
            "rgb8.jpg",
            image::RgbImage::from_raw(w, h, rgb8).unwrap().into(),
        ),
    ];
    for (name, picture) in files {
        let path = dir.join(name);
        picture.save(&path).unwrap();
        let loaded = GreyImage::open(&path).unwrap();
        assert_eq!((loaded.width(), loaded.height()), (181, 150), "{name}");
        let pose = detect(&loaded, Polarity::BrightDots).unwrap();
        // JPEG is lossy; the others only quantise (8-bit: 2e-3 px level).
        let tolerance = if name.ends_with(".jpg") { 2e-2 } else { 5e-3 };
        assert_close(&pose, &truth, (181, 150), tolerance);
    }
    // Raw buffers (the ROS encodings).
    let raw = GreyImage::from_raw(181, 150, 181, vernier::PixelFormat::Mono8, &grey8).unwrap();
    assert_close(
        &detect(&raw, Polarity::BrightDots).unwrap(),
        &truth,
        (181, 150),
        5e-3,
    );
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn dark_dots_are_measured_at_the_dot_centres() {
    let (bright, truth) = test_image(200, 160);
    let dark = bright.inverted();
    let pose = detect(&dark, Polarity::DarkDots).unwrap();
    assert_close(&pose, &truth, (200, 160), 1e-4);
    // Without the polarity setting the grid is found half a period away (the original's defect).
    let wrong = detect(&dark, Polarity::BrightDots).unwrap();
    let (err, _) = common::lattice_error(&wrong, &truth, 9.0, (100.0, 80.0));
    assert!(
        (err - 9.0 / 2f64.sqrt()).abs() < 1e-3,
        "half-period diagonal shift expected, got {err}"
    );
}

#[test]
fn bad_images_give_errors_not_panics() {
    // Empty and mismatched buffers.
    assert!(matches!(
        GreyImage::new(0, 0, vec![]),
        Err(Error::InvalidImage(_))
    ));
    assert!(matches!(
        GreyImage::new(3, 3, vec![0.0; 8]),
        Err(Error::InvalidImage(_))
    ));
    // 1×1 and other too-small images.
    let tiny = GreyImage::new(1, 1, vec![0.5]).unwrap();
    let e = detect(&tiny, Polarity::BrightDots).unwrap_err();
    assert!(matches!(e, Error::InvalidImage(_)), "{e}");
    // All black, all white, pure noise: no pattern.
    for image in [
        GreyImage::new(256, 256, vec![0.0; 65536]).unwrap(),
        GreyImage::new(256, 256, vec![1.0; 65536]).unwrap(),
        {
            let mut opts = RenderOptions::new(256, 256);
            opts.noise_std = 0.1;
            opts.background = 0.5;
            opts.foreground = 0.5;
            render(
                &PeriodicLayout::new(9.0, 3, 3).unwrap(),
                &Pose::planar(0.0, 0.0, 0.0, 1.0),
                &opts,
            )
            .unwrap()
        },
    ] {
        let e = detect(&image, Polarity::BrightDots).unwrap_err();
        assert!(matches!(e, Error::PatternNotFound(_)), "{e}");
    }
    // NaN and infinity in float input.
    let mut values = vec![0.25f64; 64 * 64];
    values[100] = f64::NAN;
    let e = GreyImage::from_f64(64, 64, &values)
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a finite number"), "{e}");
    values[100] = f64::INFINITY;
    assert!(GreyImage::from_f64(64, 64, &values).is_err());
    // A missing or corrupt file.
    let e = GreyImage::open("/nonexistent/image.png")
        .unwrap_err()
        .to_string();
    assert!(e.contains("/nonexistent/image.png"), "{e}");
    let corrupt = std::env::temp_dir().join(format!("vernier-corrupt-{}.png", std::process::id()));
    std::fs::write(&corrupt, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    assert!(matches!(
        GreyImage::open(&corrupt),
        Err(Error::ImageRead { .. })
    ));
    std::fs::remove_file(&corrupt).ok();
}

#[test]
fn bad_parameters_are_rejected_with_their_name() {
    let mut params = PeriodicParams::new(-1.0);
    let e = PeriodicDetector::new(params.clone())
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("period"), "{e}");
    params.period = 9.0;
    params.phase.crop_factor = 1.5;
    let e = PeriodicDetector::new(params).err().unwrap().to_string();
    assert!(e.contains("crop_factor"), "{e}");
    let (image, _) = test_image(64, 64);
    let e = PhaseEngine::new()
        .analyze(
            &image,
            &PhaseParams {
                sigma: f64::NAN,
                ..Default::default()
            },
        )
        .unwrap_err()
        .to_string();
    assert!(e.contains("sigma"), "{e}");
}

#[test]
fn malformed_pattern_files_name_the_problem() {
    let e = Pattern::from_json_str("{ \"PeriodicPattern\": { \"period\": 15.0, ")
        .unwrap_err()
        .to_string();
    assert!(e.contains("malformed JSON") && e.contains("line"), "{e}");
    let e =
        Pattern::from_json_str(r#"{"PeriodicPattern": {"period": 15, "nRows": 4, "nCols": 3}}"#)
            .unwrap_err()
            .to_string();
    assert!(e.contains("nRows"), "{e}");
    let e = Pattern::from_json_str(
        r#"{"PeriodicPattern": {"period": "fifteen", "nRows": 3, "nCols": 3}}"#,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("period"), "{e}");
    // Numbers with or without a decimal point are both accepted.
    assert!(Pattern::from_json_str(
        r#"{"PeriodicPattern": {"period": 15, "nRows": 3, "nCols": 3}}"#
    )
    .is_ok());
    assert!(Pattern::from_json_str(
        r#"{"PeriodicPattern": {"period": 15.0, "nRows": 3, "nCols": 3}}"#
    )
    .is_ok());
}
