//! Layout export (docs/design.md#export) checked with independent readers: GDSII and OASIS with
//! PyPI `gdstk` (installed in `.venv/` by `scripts/setup_test_tools.sh`), SVG rendered by
//! `resvg` and compared with the PNG export, PNG against the original's layout bitmaps.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use common::data_dir;
use vernier::export::{
    dot_arrays, export_bytes, export_file, layout_image, write_svg, ExportFormat, ExportFrame,
};
use vernier::layout::{
    BitmapLayout, CustomDot, CustomLayout, FingerprintLayout, HpCodeLayout, Margins,
    MegarenaLayout, Metadata, PeriodicLayout, Rect,
};
use vernier::pattern_file::Pattern;

/// The Python of the test venv; panics with the fix when it is missing.
fn venv_python() -> PathBuf {
    let python = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python");
    assert!(
        python.exists(),
        "{} is missing: run `bash scripts/setup_test_tools.sh` first (it installs gdstk, the \
         independent GDSII/OASIS reader of these tests, into .venv/)",
        python.display()
    );
    python
}

/// Scratch folder of one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vernier_export_{}_{name}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// What gdstk reads from a GDSII or OASIS file (see tests/py/read_layout.py).
struct GdstkView {
    json: serde_json::Value,
    /// `[x0, y0, x1, y1]` bounding boxes (µm, y up) of the flattened top cell's polygons on
    /// layer 1 / datatype 1, sorted.
    dots: Vec<[f64; 4]>,
}

fn read_with_gdstk(path: &Path) -> GdstkView {
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/py/read_layout.py");
    let output = Command::new(venv_python())
        .arg(&script)
        .arg(path)
        .output()
        .expect("cannot run the venv python");
    assert!(
        output.status.success(),
        "gdstk failed on {}: {}",
        path.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let json: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(json["top"].as_array().unwrap().len(), 1, "{}", json["top"]);
    let mut dots = Vec::new();
    for p in json["polygons"].as_array().unwrap() {
        let v: Vec<f64> = p
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        let (layer, datatype) = (v[5] as i64, v[6] as i64);
        if (layer, datatype) != (1, 1) {
            continue;
        }
        // A rectangle: 4 vertices and the area of its bounding box.
        assert_eq!(v[4], 4.0, "polygon with {} vertices", v[4]);
        let bbox_area = (v[2] - v[0]) * (v[3] - v[1]);
        assert!((v[7] - bbox_area).abs() < 1e-6, "not a rectangle: {v:?}");
        dots.push([v[0], v[1], v[2], v[3]]);
    }
    dots.sort_by(|a, b| a.partial_cmp(b).unwrap());
    GdstkView { json, dots }
}

/// The rectangles of `pattern` as GDSII should hold them: export coordinates (margins added),
/// v negated, µm, sorted.
fn expected_dots(pattern: &Pattern) -> Vec<[f64; 4]> {
    let frame = ExportFrame::of(pattern);
    let mut out = Vec::new();
    frame.visit_rects(pattern.layout(), &mut |r| {
        out.push([r.x, -r.bottom(), r.right(), -r.y]);
    });
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out.dedup();
    out
}

/// Compares dot lists; tolerance 1 nm (positions are rounded to the 1 nm database grid).
fn assert_same_dots(read: &[[f64; 4]], expected: &[[f64; 4]], what: &str) {
    assert_eq!(read.len(), expected.len(), "{what}: dot count");
    let worst = read
        .iter()
        .zip(expected)
        .flat_map(|(a, b)| (0..4).map(move |i| (a[i] - b[i]).abs()))
        .fold(0.0, f64::max);
    assert!(worst <= 1e-3, "{what}: a dot is {worst} µm off");
}

fn metadata_with_margins(margins: Margins) -> Metadata {
    Metadata {
        description: "export test".into(),
        date: "2025-03-17 08:40:25".into(),
        author: "FEMTO-ST".into(),
        unit: "um".into(),
        margins,
    }
}

/// One layout of every class, several with margins.
fn sample_patterns() -> Vec<(&'static str, Pattern)> {
    let margins = Margins {
        left: 12.5,
        right: 3.0,
        top: 7.25,
        bottom: 20.0,
    };
    let periodic = PeriodicLayout::new(10.0, 7, 9)
        .unwrap()
        .with_metadata(metadata_with_margins(margins));
    let hp = HpCodeLayout::new(15.5, 17)
        .unwrap()
        .with_id(0b1_0010_0101)
        .unwrap()
        .with_metadata(metadata_with_margins(Margins::default()));
    let stamp = Pattern::from_file(data_dir().join("patterns/stampPattern.json")).unwrap();
    let fingerprint = FingerprintLayout::from_rows(
        8.0,
        &[[1u8, 0, 1], [0, 1, 1], [1, 1, 0], [1, 0, 1], [0, 1, 1]],
    )
    .unwrap();
    let megarena = MegarenaLayout::new(14.0, 8)
        .unwrap()
        .with_region_of_interest(Rect::new(140.0, 70.0, 700.0, 560.0))
        .unwrap()
        .with_metadata(metadata_with_margins(margins));
    // Fewer than 100 rectangles: the original divided by zero here
    // (docs/design.md#defect-export-progress).
    let custom = CustomLayout::new(vec![
        CustomDot::new(0.0, 0.0, 4.0, 2.0, 1.0),
        CustomDot::new(10.0, 3.3333, 2.0, 2.0, 1.0),
    ])
    .unwrap();
    vec![
        ("periodic", periodic.into()),
        ("hpcode", hp.into()),
        ("stamp", stamp),
        ("fingerprint", fingerprint.into()),
        ("megarena", megarena.into()),
        ("custom", custom.into()),
    ]
}

#[test]
fn gds_and_oasis_hold_the_layout_dots() {
    let dir = scratch("all");
    for (name, pattern) in sample_patterns() {
        let expected = expected_dots(&pattern);
        assert!(!expected.is_empty(), "{name}");
        for format in [ExportFormat::Gds, ExportFormat::Oasis] {
            let path = dir.join(format!("{name}.{}", format.extension()));
            export_file(&pattern, format, &path).unwrap();
            let view = read_with_gdstk(&path);
            let what = format!("{name}.{}", format.extension());
            assert_same_dots(&view.dots, &expected, &what);
            let j = &view.json;
            assert_eq!(j["unit"].as_f64(), Some(1e-6), "{what}: user unit");
            assert!(
                (j["precision"].as_f64().unwrap() - 1e-9).abs() < 1e-21,
                "{what}: database unit {}",
                j["precision"]
            );
            assert_eq!(j["top"][0], pattern.class_name(), "{what}: top cell name");
            if format == ExportFormat::Oasis {
                assert_eq!(j["valid"], true, "{what}: CRC-32 validation");
            }
            // The label: layer 2 / texttype 0, below the canvas, naming the class.
            let labels = j["labels"].as_array().unwrap();
            assert!(!labels.is_empty(), "{what}: no label");
            assert!(labels.iter().all(|l| l["layer"] == 2 && l["texttype"] == 0));
            assert!(
                labels[0]["text"]
                    .as_str()
                    .unwrap()
                    .contains(pattern.class_name()),
                "{what}: {}",
                labels[0]["text"]
            );
            let canvas = ExportFrame::of(&pattern).canvas;
            assert!(labels[0]["y"].as_f64().unwrap() < -canvas.bottom());
        }
    }
}

#[test]
fn margins_shift_the_dots() {
    let pattern = &sample_patterns()[0].1;
    let dots = expected_dots(pattern);
    // Periodic 7 × 9 at P = 10, dot 5, left margin 12.5, top 7.25: the second dot of the top
    // row (the first one is omitted) starts at u = 10 + 12.5, v = 0 + 7.25.
    assert!(
        dots.contains(&[22.5, -12.25, 27.5, -7.25]),
        "{:?}",
        &dots[..3]
    );
    let frame = ExportFrame::of(pattern);
    assert_eq!(frame.canvas, Rect::new(0.0, 0.0, 85.0 + 15.5, 65.0 + 27.25));
}

#[test]
fn hp_code_export_has_complete_finders_and_id() {
    // docs/design.md#defect-hp-layout: the original's GDS lacked the top-left finder's corner cell.
    let hp = HpCodeLayout::new(10.0, 17).unwrap().with_id(3).unwrap();
    let pattern = Pattern::from(hp);
    let dots = expected_dots(&pattern);
    assert_eq!(dots.len(), 17 * 17 + 3 * 17 - 2, "two ID dots removed");
    assert!(dots.contains(&[0.0, -5.0, 5.0, 0.0]), "corner cell present");
    let dir = scratch("hp");
    let path = dir.join("hp.gds");
    export_file(&pattern, ExportFormat::Gds, &path).unwrap();
    assert_same_dots(&read_with_gdstk(&path).dots, &dots, "hp.gds");
    // The PNG has the same cells.
    let png = layout_image(&pattern).unwrap();
    let set = png.pixels().filter(|p| p.0[0] == 255).count();
    assert_eq!(set, dots.len());
}

#[test]
fn megarena_12bit_regions_export_as_arrays() {
    // The shipped example (12-bit, P = 14 µm, region of interest 3 mm × 2 mm, 2·10⁴ dots)
    // and the same region size at P = 5 µm away from the pattern's corner (10⁵ dots).
    let example = Pattern::from_file(data_dir().join("patterns/megarenaPattern.json")).unwrap();
    let dense = MegarenaLayout::new(5.0, 12)
        .unwrap()
        .with_region_of_interest(Rect::new(20_000.0, 15_000.0, 3000.0, 2000.0))
        .unwrap();
    let dir = scratch("megarena");
    for (name, pattern, min_dots) in [
        ("example", example, 20_000),
        ("dense", Pattern::from(dense), 100_000),
    ] {
        let expected = expected_dots(&pattern);
        assert!(
            expected.len() >= min_dots,
            "{name}: {} dots in 3 mm × 2 mm",
            expected.len()
        );
        let frame = ExportFrame::of(&pattern);
        let start = Instant::now();
        let arrays = dot_arrays(&pattern, &frame).unwrap();
        let decompose_time = start.elapsed();
        let covered: usize = arrays.iter().map(|a| a.len()).sum();
        assert_eq!(covered, expected.len(), "{name}");
        // Arrays, not one polygon per dot.
        assert!(
            arrays.len() * 50 < expected.len(),
            "{name}: {} arrays for {} dots",
            arrays.len(),
            expected.len()
        );
        for format in [ExportFormat::Gds, ExportFormat::Oasis] {
            let start = Instant::now();
            let bytes = export_bytes(&pattern, format).unwrap();
            let export_time = start.elapsed();
            let path = dir.join(format!("{name}.{}", format.extension()));
            std::fs::write(&path, &bytes).unwrap();
            let view = read_with_gdstk(&path);
            assert_same_dots(&view.dots, &expected, path.to_str().unwrap());
            let j = &view.json;
            let top_elements =
                j["top_polygons"].as_u64().unwrap() + j["top_references"].as_u64().unwrap();
            assert!(
                top_elements as usize <= arrays.len(),
                "{name}: {top_elements} elements"
            );
            eprintln!(
                "megarena 12-bit 3 mm x 2 mm {name}: {} dots, {} arrays (found in {:?}), \
                 {}: {} bytes in {:?}",
                expected.len(),
                arrays.len(),
                decompose_time,
                format.extension(),
                bytes.len(),
                export_time
            );
        }
    }
}

/// Renders an SVG export with resvg, `cols × rows` pixels over its viewBox; returns the
/// coverage (alpha) of each pixel.
fn render_svg(svg: &str, cols: u32, rows: u32) -> Vec<u8> {
    let tree = resvg::usvg::Tree::from_str(svg, &resvg::usvg::Options::default()).unwrap();
    let size = tree.size();
    let mut pixmap = resvg::tiny_skia::Pixmap::new(cols, rows).unwrap();
    let transform = resvg::tiny_skia::Transform::from_scale(
        cols as f32 / size.width(),
        rows as f32 / size.height(),
    );
    resvg::render(&tree, transform, &mut pixmap.as_mut());
    pixmap.pixels().iter().map(|p| p.alpha()).collect()
}

#[test]
fn svg_rendered_by_resvg_matches_png_export() {
    let mut patterns: Vec<(&str, Pattern)> = sample_patterns()
        .into_iter()
        .filter(|(name, _)| *name != "custom")
        .collect();
    patterns.push((
        "megarena_12bit",
        Pattern::from_file(data_dir().join("patterns/megarenaPattern.json")).unwrap(),
    ));
    for (name, mut pattern) in patterns {
        // The PNG has no margins: compare without them.
        let meta = Metadata {
            margins: Margins::default(),
            ..pattern.metadata().clone()
        };
        pattern = match pattern {
            Pattern::Periodic(l) => l.with_metadata(meta).into(),
            Pattern::Megarena(l) => l.with_metadata(meta).into(),
            other => other,
        };
        let png = layout_image(&pattern).unwrap();
        let (cols, rows) = png.dimensions();
        let svg = write_svg(&pattern);
        let coverage = render_svg(&svg, cols, rows);
        let mismatches: Vec<(u32, u32)> = png
            .enumerate_pixels()
            .filter(|(c, r, p)| {
                let dot = coverage[(r * cols + c) as usize] > 127;
                dot != (p.0[0] == 255)
            })
            .map(|(c, r, _)| (c, r))
            .take(10)
            .collect();
        assert!(
            mismatches.is_empty(),
            "{name}: SVG and PNG differ at (col, row) {mismatches:?}"
        );
        // Edges fall on pixel boundaries: no partially covered pixel.
        let partial = coverage.iter().filter(|&&a| a > 8 && a < 247).count();
        assert_eq!(partial, 0, "{name}: {partial} partially covered pixels");
        let set = png.pixels().filter(|p| p.0[0] == 255).count();
        assert!(set > 0, "{name}: empty export");
    }
}

#[test]
fn svg_has_physical_size_and_metadata() {
    let pattern = &sample_patterns()[0].1;
    let svg = write_svg(pattern);
    // 85 + 15.5 µm wide, 65 + 27.25 µm high.
    assert!(
        svg.contains("width=\"0.1005mm\" height=\"0.09225mm\" viewBox=\"0 0 100.5 92.25\""),
        "{}",
        &svg[..400]
    );
    assert!(svg.contains("<title>export test</title>"));
    for key in [
        "class: PeriodicPattern",
        "originX: 42.5",
        "leftMargin: 12.5",
    ] {
        assert!(svg.contains(key), "missing `{key}`");
    }
    assert_eq!(svg.matches("<rect ").count(), 7 * 9 - 1);
    assert!(svg.contains("<rect x=\"22.5\" y=\"7.25\" width=\"5\" height=\"5\" fill=\"black\" />"));
}

#[test]
fn png_reproduces_the_original_layout_bitmaps() {
    // The original's PNG exports of HP codes with ID 0 (docs/design.md#export-png).
    for (file, size) in [("HPCode33x33.png", 17), ("HPCode37x37.png", 19)] {
        let original = image::open(data_dir().join("layouts").join(file))
            .unwrap()
            .to_luma8();
        let pattern = Pattern::from(HpCodeLayout::new(15.5, size).unwrap());
        let png = layout_image(&pattern).unwrap();
        assert_eq!(png.dimensions(), original.dimensions(), "{file}");
        let diff = png
            .pixels()
            .zip(original.pixels())
            .filter(|(a, b)| (a.0[0] > 127) != (b.0[0] > 127))
            .count();
        assert_eq!(diff, 0, "{file}: {diff} pixels differ");
    }
    // A stamp bitmap comes back cell for cell.
    let path = data_dir().join("layouts/stamp69x69.png");
    let stamp = BitmapLayout::from_image_file(20.0, &path).unwrap();
    let png = layout_image(&Pattern::from(stamp.clone())).unwrap();
    assert_eq!(png.dimensions(), (69, 69));
    for (c, r, p) in png.enumerate_pixels() {
        assert_eq!(p.0[0] == 255, stamp.cell(r as usize, c as usize));
    }
}

#[test]
fn png_sizes_follow_the_spec() {
    let periodic = Pattern::from_file(data_dir().join("patterns/periodicPattern.json")).unwrap();
    // 37 rows × 31 columns → (2·37 − 1) × (2·31 − 1).
    assert_eq!(layout_image(&periodic).unwrap().dimensions(), (61, 73));
    // Megarena, P = 14, ROI 3000 × 2000: dots 0..214 × 0..142 (the ROI rule of
    // docs/design.md#layout-megarena), two pixels per dot. (The original drew 285 rows: one more
    // pixel row, half of the dot row 142 that its own rectangle export leaves out.)
    let megarena = Pattern::from_file(data_dir().join("patterns/megarenaPattern.json")).unwrap();
    assert_eq!(layout_image(&megarena).unwrap().dimensions(), (428, 284));
    // Bytes are a real PNG.
    let bytes = export_bytes(&periodic, ExportFormat::Png).unwrap();
    let back = image::load_from_memory(&bytes).unwrap().to_luma8();
    assert_eq!(back, layout_image(&periodic).unwrap());
}

#[test]
fn tiny_and_unsupported_exports_fail_cleanly() {
    let custom =
        Pattern::from(CustomLayout::new(vec![CustomDot::new(1.0, 2.0, 3.0, 4.0, 1.0)]).unwrap());
    for format in [ExportFormat::Svg, ExportFormat::Gds, ExportFormat::Oasis] {
        let bytes = export_bytes(&custom, format).unwrap();
        assert!(!bytes.is_empty());
    }
    let e = export_bytes(&custom, ExportFormat::Png)
        .unwrap_err()
        .to_string();
    assert!(e.contains("CustomPattern"), "{e}");
    // A region of interest outside the pattern exports nothing, without error.
    let empty = MegarenaLayout::new(10.0, 4)
        .unwrap()
        .with_region_of_interest(Rect::new(1e6, 1e6, 100.0, 100.0))
        .unwrap();
    let empty = Pattern::from(empty);
    assert!(expected_dots(&empty).is_empty());
    let e = export_bytes(&empty, ExportFormat::Png)
        .unwrap_err()
        .to_string();
    assert!(e.contains("PNG of 0 × 0"), "{e}");
    assert!(export_bytes(&empty, ExportFormat::Gds).is_ok());
    assert!(export_bytes(&empty, ExportFormat::Oasis).is_ok());
}
