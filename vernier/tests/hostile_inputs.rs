//! Regression tests of issue 16 (hostile and broken input), in process: decompression bombs are
//! refused from their header, truncated files are errors, every setting is range-checked on
//! every detector, renders are bounded. The same files run through the CLI under a 4 GiB
//! memory cap in `vernier-cli/tests/hostile_corpus.rs`.

mod common;

use std::path::{Path, PathBuf};
use vernier::detector::{DetectorSettings, MarkerKind};
use vernier::layout::{MegarenaLayout, PeriodicLayout};
use vernier::pattern_file::Pattern;
use vernier::render::{render, RenderOptions};
use vernier::{DecodeLimits, Detector, Error, GreyImage, Pose};

fn crc_chunk(kind: &[u8], data: &[u8]) -> Vec<u8> {
    let mut out = (data.len() as u32).to_be_bytes().to_vec();
    let mut body = kind.to_vec();
    body.extend_from_slice(data);
    out.extend_from_slice(&body);
    out.extend_from_slice(&crc32(&body).to_be_bytes());
    out
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// A well-formed PNG whose header declares `width × height` (a decompression bomb's header).
fn png_header(width: u32, height: u32, depth: u8, color: u8) -> Vec<u8> {
    let mut ihdr = width.to_be_bytes().to_vec();
    ihdr.extend_from_slice(&height.to_be_bytes());
    ihdr.extend_from_slice(&[depth, color, 0, 0, 0]);
    let mut out = b"\x89PNG\r\n\x1a\n".to_vec();
    out.extend(crc_chunk(b"IHDR", &ihdr));
    // A stored (uncompressed) zlib block of 8 zero bytes.
    let idat = [
        0x78, 0x01, 0x01, 0x08, 0x00, 0xF7, 0xFF, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
    ];
    out.extend(crc_chunk(b"IDAT", &idat));
    out.extend(crc_chunk(b"IEND", b""));
    out
}

fn scratch_file(name: &str, bytes: &[u8]) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vernier_hostile_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

fn open_err(path: &Path) -> String {
    GreyImage::open(path).unwrap_err().to_string()
}

#[test]
fn decompression_bombs_are_refused_from_the_header() {
    for (name, w, h, depth, color) in [
        ("square_2g.png", (1u32 << 31) - 1, (1u32 << 31) - 1, 8, 0),
        ("square_100000.png", 100_000, 100_000, 8, 0),
        ("rgba16_60000.png", 60_000, 60_000, 16, 6),
        ("strip_16x2e9.png", 16, 2_000_000_000, 8, 0),
    ] {
        let path = scratch_file(name, &png_header(w, h, depth, color));
        let e = open_err(&path);
        assert!(
            e.contains(&format!("{w}×{h}")) && e.contains("--max-pixels"),
            "{name}: {e}"
        );
    }
    // The exact message of the issue.
    let path = scratch_file("square_100000.png", &png_header(100_000, 100_000, 8, 0));
    assert!(open_err(&path).contains("image is 100000×100000 = 10000 MP, above --max-pixels"));
    // A JPEG whose frame header says 65000².
    let mut jpeg = std::fs::read(common::data_dir().join("hpcode/code18.jpg")).unwrap();
    let mut i = 2;
    while !(0xC0..=0xC2).contains(&jpeg[i + 1]) {
        i += 2 + u16::from_be_bytes([jpeg[i + 2], jpeg[i + 3]]) as usize;
    }
    jpeg[i + 5..i + 9].copy_from_slice(&[0xFD, 0xE8, 0xFD, 0xE8]);
    let e = open_err(&scratch_file("jpeg_65000.jpg", &jpeg));
    assert!(
        e.contains("65000×65000") && e.contains("--max-pixels"),
        "{e}"
    );
    // The limit is a setting; stamp bitmaps go through the same decoder.
    let small = scratch_file("small.png", &png_header(64, 64, 8, 0));
    let e = GreyImage::open_with_limits(&small, &DecodeLimits::with_max_pixels(1000))
        .unwrap_err()
        .to_string();
    assert!(e.contains("64×64") && e.contains("0.004 MP"), "{e}");
    let bomb = scratch_file("bitmap_bomb.png", &png_header(100_000, 100_000, 8, 0));
    let e = vernier::layout::BitmapLayout::from_image_file(15.0, &bomb)
        .unwrap_err()
        .to_string();
    assert!(e.contains("--max-pixels"), "{e}");
}

#[test]
fn truncated_and_corrupted_images_are_errors() {
    let data = common::data_dir();
    let jpeg = std::fs::read(data.join("hpcode/code18.jpg")).unwrap();
    assert!(GreyImage::open(data.join("hpcode/code18.jpg")).is_ok());
    let e = open_err(&scratch_file("quarter.jpg", &jpeg[..jpeg.len() / 4]));
    assert!(e.contains("truncated JPEG"), "{e}");
    // Trailing zero padding after the end marker is fine.
    let mut padded = jpeg.clone();
    padded.extend_from_slice(&[0; 16]);
    assert!(GreyImage::open(scratch_file("padded.jpg", &padded)).is_ok());

    let png = std::fs::read(data.join("hpcode/code19.png")).unwrap();
    let e = open_err(&scratch_file("no_iend.png", &png[..png.len() - 12]));
    assert!(e.contains("IEND"), "{e}");
    let e = open_err(&scratch_file("quarter.png", &png[..png.len() / 4]));
    assert!(e.contains("truncated PNG"), "{e}");
    let mut flipped = png.clone();
    let middle = flipped.len() / 2;
    flipped[middle] ^= 0x55;
    let e = open_err(&scratch_file("flipped.png", &flipped));
    assert!(e.contains("CRC"), "{e}");

    // TIFF and PNM carry no end marker: their decoders fail on missing pixel data.
    let tiff = std::fs::read(data.join("hpcode/code22.tif")).unwrap();
    assert!(GreyImage::open(data.join("hpcode/code22.tif")).is_ok());
    open_err(&scratch_file("quarter.tif", &tiff[..tiff.len() / 4]));
    let mut pgm = b"P5\n64 64\n255\n".to_vec();
    pgm.extend((0..64 * 64).map(|i| (i % 251) as u8));
    assert!(GreyImage::open(scratch_file("whole.pgm", &pgm)).is_ok());
    open_err(&scratch_file("quarter.pgm", &pgm[..pgm.len() / 4]));
}

fn settings(kind: MarkerKind) -> DetectorSettings {
    DetectorSettings {
        pattern_type: kind,
        period: Some(15.5),
        code_size: Some(33),
        code_depth: Some(8),
        bitmaps: vec![common::data_dir().join("layouts/stamp69x69.png")],
        ..Default::default()
    }
}

#[test]
fn invalid_settings_are_errors_on_every_detector() {
    let kinds = [
        MarkerKind::Periodic,
        MarkerKind::HpCode,
        MarkerKind::Stamp,
        MarkerKind::Megarena,
    ];
    for kind in kinds {
        for (change, name) in [
            (
                (|s: &mut DetectorSettings| s.period = Some(5e-324)) as fn(&mut DetectorSettings),
                "period",
            ),
            (|s| s.period = Some(f64::INFINITY), "period"),
            (|s| s.period = Some(1e300), "period"),
            (|s| s.code_size = Some(1_000_001), "code_size"),
            (|s| s.code_size = Some(35), "code_size"),
            (|s| s.code_depth = Some(40), "code_depth"),
            (|s| s.window_size = Some(4_294_967_295), "window_size"),
            (|s| s.window_size = Some(1_000_000), "window_size"),
        ] {
            let mut s = settings(kind);
            change(&mut s);
            let e = s.to_config().unwrap_err().to_string();
            assert!(e.contains(name), "{kind:?}: {e}");
        }
    }
    // A window larger than the image: an error, not an empty list.
    let image = GreyImage::new(300, 200, vec![0.5; 300 * 200]).unwrap();
    for kind in [MarkerKind::HpCode, MarkerKind::Stamp] {
        let mut s = settings(kind);
        s.window_size = Some(512);
        let mut d = Detector::new(s.to_config().unwrap()).unwrap();
        let e = d.detect(&image).unwrap_err().to_string();
        assert!(e.contains("window_size") && e.contains("300×200"), "{e}");
        s.window_size = Some(256);
        let mut d = Detector::new(s.to_config().unwrap()).unwrap();
        assert!(d.detect(&image).unwrap().is_empty());
    }
    // Direct construction goes through the same ranges.
    let p = vernier::hpcode::HpCodeParams::new(5e-324, 33);
    assert!(vernier::hpcode::HpCodeDetector::new(p).is_err());
    let mut p = vernier::hpcode::HpCodeParams::new(15.5, 33);
    p.window_size = Some(1 << 20);
    assert!(vernier::hpcode::HpCodeDetector::new(p).is_err());
    // Pattern files: the same period range.
    let e = Pattern::from_json_str(
        r#"{"PeriodicPattern": {"period": 5e-324, "nRows": 3, "nCols": 3}}"#,
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("period"), "{e}");
    let e = Pattern::from_json_str(r#"{"MegarenaPattern": {"period": 1e-9, "codeDepth": 12}}"#)
        .unwrap_err()
        .to_string();
    assert!(e.contains("period"), "{e}");
}

#[test]
fn windows_never_overflow() {
    let image = GreyImage::new(4, 4, vec![0.0; 16]).unwrap();
    let e = image.window(0, 0, usize::MAX, 2, 0.0).unwrap_err();
    assert!(matches!(e, Error::InvalidImage(_)), "{e}");
    assert!(image.window(0, 0, 1 << 20, 1 << 20, 0.0).is_err());
}

#[test]
fn renders_are_bounded() {
    let layout = PeriodicLayout::new(15.0, 9, 9).unwrap();
    let pose = Pose::planar(0.0, 0.0, 0.0, 1.0);
    let e = render(&layout, &pose, &RenderOptions::new(65536, 65536))
        .unwrap_err()
        .to_string();
    assert!(e.contains("size"), "{e}");
    let mut blurred = RenderOptions::new(64, 64);
    blurred.blur_sigma = 1e9;
    let e = render(&layout, &pose, &blurred).unwrap_err().to_string();
    assert!(e.contains("blur_sigma"), "{e}");
    blurred.blur_sigma = 1.0;
    blurred.width = 20_000;
    blurred.height = 20_000;
    assert!(render(&layout, &pose, &blurred).is_err());
    // A period of 1e-6 pixels: refused, not billions of dots.
    let fine = MegarenaLayout::new(1e-6, 12).unwrap();
    let e = render(&fine, &pose, &RenderOptions::new(64, 64))
        .unwrap_err()
        .to_string();
    assert!(e.contains("pixels per period"), "{e}");
}

#[test]
fn huge_angles_render_as_their_wrapped_value() {
    let layout = PeriodicLayout::new(15.0, 9, 9).unwrap();
    let options = RenderOptions::new(96, 80);
    let alpha: f64 = 1e15;
    let wrapped = alpha.rem_euclid(std::f64::consts::TAU);
    let a = render(&layout, &Pose::planar(1.0, 2.0, alpha, 1.0), &options).unwrap();
    let b = render(&layout, &Pose::planar(1.0, 2.0, wrapped, 1.0), &options).unwrap();
    let c = render(
        &layout,
        &Pose::planar(1.0, 2.0, wrapped - std::f64::consts::TAU, 1.0),
        &options,
    )
    .unwrap();
    assert!(
        a.pixels() == b.pixels(),
        "1e15 rad and its wrapped value differ"
    );
    assert!(
        a.pixels() == c.pixels(),
        "1e15 rad and its value − 2π differ"
    );
}

#[test]
fn full_disks_are_write_errors() {
    if !Path::new("/dev/full").exists() {
        return;
    }
    let image = GreyImage::new(8, 8, vec![0.5; 64]).unwrap();
    let e = image.save_png("/dev/full", 8).unwrap_err().to_string();
    assert!(e.contains("No space left"), "{e}");
    let pattern = Pattern::Periodic(PeriodicLayout::new(15.0, 3, 3).unwrap());
    assert!(pattern.save("/dev/full").is_err());
}

#[test]
fn export_estimates_bound_the_real_size() {
    use vernier::export::{estimate_bytes, export_bytes, ExportFormat};
    let mut files: Vec<PathBuf> = std::fs::read_dir(common::data_dir().join("patterns"))
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .collect();
    files.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/periodic_p15.json"));
    for file in files {
        let pattern = Pattern::from_file(&file).unwrap();
        for format in ExportFormat::ALL {
            let Ok(bytes) = export_bytes(&pattern, format) else {
                continue;
            };
            let estimate = estimate_bytes(&pattern, format);
            assert!(
                estimate >= bytes.len() as f64,
                "{} {format:?}: {} bytes, estimate {estimate}",
                file.display(),
                bytes.len()
            );
        }
    }
}
