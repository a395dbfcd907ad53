//! Layout classes and JSON pattern files against the shipped data (docs/design.md#layouts,
//! docs/design.md#pattern-file) and the original's reference values.

mod common;

use std::path::{Path, PathBuf};

use common::data_dir;
use vernier::layout::{
    BitmapLayout, CustomLayout, FingerprintLayout, HpCodeLayout, Layout, Margins, MegarenaLayout,
    Metadata, PeriodicLayout, Rect,
};
use vernier::pattern_file::Pattern;
use vernier::Error;

fn patterns_dir() -> PathBuf {
    data_dir().join("patterns")
}

fn layouts_dir() -> PathBuf {
    data_dir().join("layouts")
}

/// Files of `dir` with extension `ext`, sorted.
fn files_with_extension(dir: &Path, ext: &str) -> Vec<PathBuf> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap_or_else(|e| panic!("cannot list {}: {e}", dir.display()))
        .map(|entry| entry.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == ext))
        .collect();
    files.sort();
    files
}

/// Metadata as the original writes it for a generated layout.
fn generated_metadata() -> Metadata {
    Metadata {
        description: "Layout generated with the Vernier library".into(),
        date: "2025-03-17 08:40:25".into(),
        author: "FEMTO-ST".into(),
        unit: "um".into(),
        margins: Margins::default(),
    }
}

/// JSON → Pattern → JSON gives the same text and the same pattern.
fn assert_round_trip(pattern: &Pattern) {
    let json = pattern.to_json_string();
    let again = Pattern::from_json_str(&json).unwrap_or_else(|e| {
        panic!(
            "{}: cannot re-read own output: {e}\n{json}",
            pattern.class_name()
        )
    });
    assert_eq!(&again, pattern, "{}: pattern changed", pattern.class_name());
    assert_eq!(
        again.to_json_string(),
        json,
        "{}: text changed",
        pattern.class_name()
    );
}

/// The marker's half-period cells as rendered by the intensity (value > 0.5 at cell centres,
/// as the PNG export samples them).
fn rendered_cells(layout: &dyn Layout, rows: usize, cols: usize) -> Vec<Vec<bool>> {
    let b = layout.bounds();
    let half = layout.period() / 2.0;
    (0..rows)
        .map(|r| {
            (0..cols)
                .map(|c| {
                    let x = b.x + c as f64 * half + half / 2.0;
                    let y = b.y + r as f64 * half + half / 2.0;
                    layout.intensity(x, y) > 0.5
                })
                .collect()
        })
        .collect()
}

/// The half-period cells covered by the layout's rectangles (each rectangle is one cell).
fn rect_cells(layout: &dyn Layout, rows: usize, cols: usize) -> Vec<Vec<bool>> {
    let b = layout.bounds();
    let half = layout.period() / 2.0;
    let mut cells = vec![vec![false; cols]; rows];
    for r in layout.rects_in(&b) {
        assert!((r.width - half).abs() < 1e-9 && (r.height - half).abs() < 1e-9);
        let col = ((r.x - b.x) / half).round() as usize;
        let row = ((r.y - b.y) / half).round() as usize;
        assert!(!cells[row][col], "two rectangles on cell ({row}, {col})");
        cells[row][col] = true;
    }
    cells
}

/// Reads the ID of an HP marker from its `W × W` half-period cells (docs/design.md#hp-id-encoding):
/// bit k is the top-row dot at dot column n − 5 − k, a missing dot means 1.
fn read_hp_id(cells: &[Vec<bool>]) -> u64 {
    let n = cells.len().div_ceil(2);
    (0..n - 8)
        .filter(|&k| !cells[0][2 * (n - 5 - k)])
        .map(|k| 1u64 << k)
        .sum()
}

#[test]
fn every_shipped_pattern_file_loads() {
    let files = files_with_extension(&patterns_dir(), "json");
    assert_eq!(files.len(), 4, "{files:?}");
    for path in &files {
        let pattern = Pattern::from_file(path)
            .unwrap_or_else(|e| panic!("{} does not load: {e}", path.display()));
        assert_round_trip(&pattern);
    }
}

#[test]
fn periodic_pattern_file() {
    let p = Pattern::from_file(patterns_dir().join("periodicPattern.json")).unwrap();
    let Pattern::Periodic(l) = &p else {
        panic!("expected PeriodicPattern, got {}", p.class_name())
    };
    assert_eq!((l.period(), l.n_rows(), l.n_cols()), (15.0, 37, 31));
    let meta = l.metadata();
    assert_eq!(meta.description, "Example of periodic pattern");
    assert_eq!(
        (meta.author.as_str(), meta.unit.as_str()),
        ("FEMTO-ST", "micrometer")
    );
    assert_eq!(meta.margins, Margins::default());
}

#[test]
fn megarena_pattern_file() {
    let p = Pattern::from_file(patterns_dir().join("megarenaPattern.json")).unwrap();
    let Pattern::Megarena(l) = &p else {
        panic!("expected MegarenaPattern, got {}", p.class_name())
    };
    assert_eq!((l.period(), l.code_depth(), l.n_dots()), (14.0, 12, 12318));
    assert_eq!(l.region_of_interest(), Rect::new(0.0, 0.0, 3000.0, 2000.0));
    assert_eq!(l.metadata().unit, "µm");
    // The original's SVG of this file holds 20 864 rectangles; 12-bit, P = 14 → 172.445 mm.
    assert_eq!(l.rects_in(&l.bounds()).len(), 20_864);
    assert!((l.bounds().width - 172_445.0).abs() < 1e-6);
}

#[test]
fn bitmap_pattern_files_match_their_png_sources() {
    for (json, png, period, (rows, cols)) in [
        ("bitmapPattern.json", "femto117x45.png", 9.0, (45, 117)),
        ("stampPattern.json", "stamp69x69.png", 20.0, (69, 69)),
    ] {
        let p = Pattern::from_file(patterns_dir().join(json)).unwrap();
        let Pattern::Bitmap(l) = &p else {
            panic!("{json}: expected BitmapPattern, got {}", p.class_name())
        };
        assert_eq!(l.period(), period, "{json}");
        assert_eq!((l.cell_rows(), l.cell_cols()), (rows, cols), "{json}");
        let from_png = BitmapLayout::from_image_file(period, layouts_dir().join(png)).unwrap();
        assert_eq!(from_png.cells(), l.cells(), "{json} differs from {png}");
    }
}

#[test]
fn writer_reproduces_the_shipped_bitmap_files() {
    for name in ["bitmapPattern.json", "stampPattern.json"] {
        let path = patterns_dir().join(name);
        let text = std::fs::read_to_string(&path).unwrap();
        let written = Pattern::from_json_str(&text).unwrap().to_json_string();
        assert_eq!(written, text, "{name}");
    }
}

#[test]
fn layout_bitmaps_load_with_dims_one_mod_four() {
    let files = files_with_extension(&layouts_dir(), "png");
    assert_eq!(files.len(), 9, "{files:?}");
    for path in &files {
        let l = BitmapLayout::from_image_file(10.0, path)
            .unwrap_or_else(|e| panic!("{} does not load: {e}", path.display()));
        assert_eq!(l.cell_rows() % 4, 1, "{}", path.display());
        assert_eq!(l.cell_cols() % 4, 1, "{}", path.display());
        assert!(l.cells().iter().any(|&c| c) && l.cells().iter().any(|&c| !c));
    }
}

#[test]
fn hp_code_bitmaps_equal_the_generated_markers() {
    for w in [33, 37] {
        let path = layouts_dir().join(format!("HPCode{w}x{w}.png"));
        let from_png = BitmapLayout::from_image_file(10.0, &path).unwrap();
        let generated = HpCodeLayout::from_code_size(10.0, w).unwrap();
        assert_eq!(from_png.cells(), generated.to_bitmap().cells(), "W = {w}");
        let cells: Vec<Vec<bool>> = from_png
            .rows()
            .iter()
            .map(|r| r.iter().map(|&v| v == 1).collect())
            .collect();
        assert_eq!(read_hp_id(&cells), 0, "the test bitmaps have ID 0");
    }
}

#[test]
fn round_trips_of_section_8_2() {
    let meta = generated_metadata();
    let image = |name: &str| layouts_dir().join(name);
    let patterns = [
        Pattern::from(
            PeriodicLayout::new(9.0, 17, 17)
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(
            HpCodeLayout::new(10.0, 37)
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(
            MegarenaLayout::new(4.5, 6)
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(
            BitmapLayout::from_image_file(9.0, image("femto117x45.png"))
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(
            BitmapLayout::from_image_file(20.0, image("stamp69x69.png"))
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(
            FingerprintLayout::from_image_file(9.0, image("vernier37x37.png"))
                .unwrap()
                .with_metadata(meta.clone()),
        ),
    ];
    for p in &patterns {
        assert_round_trip(p);
    }
    let hp = patterns[1].to_json_string();
    assert!(
        hp.contains("        \"period\": 10.000000000000000,\n        \"size\": 37,\n"),
        "{hp}"
    );
}

#[test]
fn round_trips_of_extensions_and_metadata() {
    let meta = Metadata {
        margins: Margins {
            left: 10.0,
            right: 0.5,
            top: 0.0,
            bottom: 1e-3,
        },
        ..generated_metadata()
    };
    let megarena = MegarenaLayout::new(14.0, 12)
        .unwrap()
        .with_dot_size(6.0)
        .unwrap()
        .with_region_of_interest(Rect::new(140.0, 28.0, 3000.0, 2000.0))
        .unwrap()
        .with_metadata(meta.clone());
    for p in [
        Pattern::from(
            PeriodicLayout::with_dot_size(9.0, 5, 7, 3.0)
                .unwrap()
                .with_metadata(meta.clone()),
        ),
        Pattern::from(HpCodeLayout::new(8.0, 19).unwrap().with_id(1234).unwrap()),
        Pattern::from(megarena),
    ] {
        assert_round_trip(&p);
    }
}

#[test]
fn custom_layout_from_hp_csv_round_trips() {
    // The CSV (docs/design.md#layout-custom) of an HP code (layout coordinates, header line first).
    let hp = HpCodeLayout::new(10.0, 17).unwrap();
    let (ox, oy) = hp.origin();
    let mut csv = String::from("x;y;width;height:intensity\n");
    for r in hp.rects_in(&hp.bounds()) {
        csv += &format!("{};{};{};{};1\n", r.x + ox, r.y + oy, r.width, r.height);
    }
    let custom = CustomLayout::from_csv_str(&csv)
        .unwrap()
        .with_metadata(generated_metadata());
    assert_eq!(custom.dots().len(), 17 * 17 + 3 * 17);
    assert_eq!(custom.bounds(), Rect::new(0.0, 0.0, 165.0, 165.0));
    // Dot centres are bright, the gap between dots dark.
    assert!((custom.intensity(ox, oy) - 1.0).abs() < 1e-12);
    assert!(custom.intensity(ox + 5.0, oy + 5.0) < 1e-12);
    assert_round_trip(&Pattern::from(custom));
}

#[test]
fn hp_code_id_round_trip() {
    for w in [33usize, 37] {
        let max_id = (1u64 << ((w - 15) / 2)) - 1;
        for id in [0, 1, 2, 8, 16, 32, 0b1_0101_0101, max_id] {
            let l = HpCodeLayout::from_code_size(8.0, w)
                .unwrap()
                .with_id(id)
                .unwrap();
            let rendered = rendered_cells(&l, w, w);
            assert_eq!(read_hp_id(&rendered), id, "W = {w}");
            // Exported geometry and intensity agree cell for cell (corner cell included).
            assert_eq!(rect_cells(&l, w, w), rendered, "W = {w}, id = {id}");
            assert!(rendered[0][0], "top-left finder corner");
            let json = Pattern::from(l).to_json_string();
            let Pattern::HpCode(back) = Pattern::from_json_str(&json).unwrap() else {
                panic!("wrong class")
            };
            assert_eq!(back.id(), id);
        }
        let e = HpCodeLayout::from_code_size(8.0, w)
            .unwrap()
            .with_id(max_id + 1)
            .unwrap_err();
        assert!(
            matches!(e, Error::InvalidPattern { ref key, .. } if key == "id"),
            "{e}"
        );
    }
}

#[test]
fn bitmap_intensity_reproduces_the_bitmap() {
    let l = BitmapLayout::from_image_file(9.0, layouts_dir().join("femto117x45.png")).unwrap();
    let cells: Vec<Vec<bool>> = l
        .rows()
        .iter()
        .map(|r| r.iter().map(|&v| v == 1).collect())
        .collect();
    assert_eq!(rendered_cells(&l, 45, 117), cells);
    assert_eq!(rect_cells(&l, 45, 117), cells);
}

#[test]
fn megarena_dot_rule() {
    let l = MegarenaLayout::new(10.0, 12).unwrap();
    // s[37] and s[46] are the first zeros of the 12-bit line sequence.
    for (row, col, exists) in [
        (0, 0, false), // 3×3 orientation rule
        (3, 3, false), // idem
        (0, 1, true),
        (1, 1, true),
        (2, 2, true),
        (37, 2, false), // zero coding row
        (2, 46, false), // zero coding column
        (38, 2, true),
        (36, 46, false),
        (12317, 12317, true),
        (12318, 1, false), // outside
    ] {
        assert_eq!(l.dot_exists(row, col), exists, "dot ({row}, {col})");
        if row < 12318 {
            let i = l.intensity(col as f64 * 10.0, row as f64 * 10.0);
            assert!(
                (i - if exists { 1.0 } else { 0.0 }).abs() < 1e-9,
                "({row}, {col}): {i}"
            );
        }
    }
    // Dot (0, 1) is centred at pattern (P, 0); the pattern origin is dot (0, 0)'s centre.
    assert_eq!(l.origin(), (2.5, 2.5));
    let near = l.rects_in(&Rect::new(9.0, -1.0, 2.0, 2.0));
    assert_eq!(near, vec![Rect::new(7.5, -2.5, 5.0, 5.0)]);
}

#[test]
fn error_cases_name_the_key() {
    let message = |text: &str| Pattern::from_json_str(text).unwrap_err().to_string();
    // Malformed JSON: line and column.
    let e = Pattern::from_json_str(
        "{\n  \"PeriodicPattern\": {\n    \"period\": 9.0\n    \"nRows\": 3\n}",
    )
    .unwrap_err();
    assert!(matches!(e, Error::Json { path: None, .. }), "{e}");
    assert!(e.to_string().contains("line 4 column 5"), "{e}");
    // Wrong types.
    let e = message(r#"{"PeriodicPattern": {"period": "9", "nRows": 3, "nCols": 3}}"#);
    assert!(
        e.contains("key `period`") && e.contains("must be a number"),
        "{e}"
    );
    let e = message(r#"{"HPCodePattern": {"period": 9.0, "size": 17.5}}"#);
    assert!(e.contains("key `size`") && e.contains("integer"), "{e}");
    let e = message(r#"{"BitmapPattern": {"period": 9.0, "bitmap": [1, 0]}}"#);
    assert!(e.contains("key `bitmap`") && e.contains("row 0"), "{e}");
    // Even dimensions.
    let e = message(r#"{"PeriodicPattern": {"period": 9.0, "nRows": 3, "nCols": 4}}"#);
    assert!(
        e.contains("key `nCols`: must be a positive odd integer, got 4"),
        "{e}"
    );
    let e = message(r#"{"HPCodePattern": {"period": 9.0, "size": 18}}"#);
    assert!(e.contains("key `size`") && e.contains("18"), "{e}");
    let rows = vec![vec![0u8; 7]; 5];
    let json = format!(r#"{{"BitmapPattern": {{"period": 9.0, "bitmap": {rows:?}}}}}"#);
    let e = message(&json);
    assert!(
        e.contains("key `bitmap`") && e.contains("mod 4") && e.contains("7 columns"),
        "{e}"
    );
    let e = message(r#"{"FingerprintPattern": {"period": 9.0, "bitmap": [[1, 1]]}}"#);
    assert!(e.contains("key `bitmap`") && e.contains("odd"), "{e}");
    // Missing required keys.
    let e = message(r#"{"PeriodicPattern": {"period": 9.0, "nRows": 3}}"#);
    assert!(e.contains("key `nCols`: required key is missing"), "{e}");
    let e = message(r#"{"BitmapPattern": {"period": 9.0}}"#);
    assert!(e.contains("key `bitmap`: required key is missing"), "{e}");
    let e = message(r#"{"MegarenaPattern": {"codeDepth": 8}}"#);
    assert!(e.contains("key `period`: required key is missing"), "{e}");
    let e = message(r#"{"CustomPattern": {}}"#);
    assert!(e.contains("key `dots`"), "{e}");
    // Unknown class.
    let e = message(r#"{"StampPattern": {"period": 9.0}}"#);
    assert!(
        e.contains("`StampPattern`") && e.contains("unknown pattern class"),
        "{e}"
    );
    // Files: the path appears in JSON errors, I/O errors are reported as such.
    let missing = data_dir().join("patterns/does-not-exist.json");
    assert!(matches!(
        Pattern::from_file(&missing),
        Err(Error::Io { .. })
    ));
    let png = layouts_dir().join("HPCode33x33.png");
    let e = Pattern::from_file(&png).unwrap_err();
    assert!(
        matches!(e, Error::Io { .. } | Error::Json { path: Some(_), .. }),
        "{e}"
    );
}

#[test]
fn fingerprint_layout_of_vernier_bitmap() {
    let l =
        FingerprintLayout::from_image_file(9.0, layouts_dir().join("vernier37x37.png")).unwrap();
    assert_eq!((l.n_rows(), l.n_cols()), (37, 37));
    assert_eq!(l.bounds(), Rect::new(-164.25, -164.25, 328.5, 328.5));
    let dots: usize = l.rows().iter().flatten().map(|&v| usize::from(v)).sum();
    assert_eq!(l.rects_in(&l.bounds()).len(), dots);
    // Intensity is the period-P raised cosine on present dots only.
    for r in 0..37 {
        for c in 0..37 {
            let i = l.intensity((c as f64 - 18.0) * 9.0, (r as f64 - 18.0) * 9.0);
            let expected = if l.dot(r, c) { 1.0 } else { 0.0 };
            assert!((i - expected).abs() < 1e-9, "dot ({r}, {c})");
        }
    }
}
