//! `vernier export` end to end: flags, file names, errors.

mod common;

use common::{run as vernier, scratch};
use std::path::Path;

use vernier::export::{export_bytes, ExportFormat};
use vernier::layout::{HpCodeLayout, MegarenaLayout, Rect};
use vernier::pattern_file::Pattern;

fn write(path: &Path, text: &str) -> String {
    std::fs::write(path, text).unwrap();
    path.to_str().unwrap().to_string()
}

#[test]
fn exports_hp_code_with_id_and_megarena_region() {
    let dir = scratch("ok");
    let hp = write(
        &dir.join("hp.json"),
        r#"{"HPCodePattern": {"period": 10.0, "size": 17}}"#,
    );
    let out = dir.join("marker");
    let run = vernier(&[
        "export",
        "--pattern",
        &hp,
        "--format",
        "gds",
        "--id",
        "37",
        out.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // The extension is added, and the file is what the library writes for that ID. Without a
    // metadata date the library and structure dates are the current time, which may tick
    // between the two exports: compare everything but those dates.
    let written = std::fs::read(dir.join("marker.gds")).unwrap();
    let expected = export_bytes(
        &Pattern::from(HpCodeLayout::new(10.0, 17).unwrap().with_id(37).unwrap()),
        ExportFormat::Gds,
    )
    .unwrap();
    assert_eq!(without_gds_dates(&written), without_gds_dates(&expected));
    assert_eq!(
        String::from_utf8_lossy(&run.stdout).trim(),
        dir.join("marker.gds").to_str().unwrap()
    );

    let megarena = write(
        &dir.join("megarena.json"),
        r#"{"MegarenaPattern": {"codeDepth": 12, "period": 14.0}}"#,
    );
    let png = dir.join("region.png");
    let run = vernier(&[
        "export",
        "--pattern",
        &megarena,
        "--roi",
        "1400,700,280,140",
        png.to_str().unwrap(),
    ]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let image = image_size(&png);
    assert_eq!(image, (40, 20), "20 × 10 dots, two pixels each");
    let expected = export_bytes(
        &Pattern::from(
            MegarenaLayout::new(14.0, 12)
                .unwrap()
                .with_region_of_interest(Rect::new(1400.0, 700.0, 280.0, 140.0))
                .unwrap(),
        ),
        ExportFormat::Png,
    )
    .unwrap();
    assert_eq!(std::fs::read(&png).unwrap(), expected);
}

/// Width and height from a PNG's IHDR chunk.
/// `gds` with the payloads of its BGNLIB and BGNSTR records (modification and access dates)
/// zeroed. Each GDSII record is a big-endian `u16` length (header included), then its type.
fn without_gds_dates(gds: &[u8]) -> Vec<u8> {
    const DATED: [[u8; 2]; 2] = [[0x01, 0x02], [0x05, 0x02]];
    let mut out = gds.to_vec();
    let mut at = 0;
    while let Some(header) = out.get(at..at + 4) {
        let length = usize::from(u16::from_be_bytes([header[0], header[1]]));
        if length < 4 {
            break;
        }
        if DATED.contains(&[header[2], header[3]]) {
            let end = (at + length).min(out.len());
            out[at + 4..end].fill(0);
        }
        at += length;
    }
    out
}

fn image_size(path: &Path) -> (u32, u32) {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(&bytes[1..4], b"PNG");
    let be = |i: usize| u32::from_be_bytes([bytes[i], bytes[i + 1], bytes[i + 2], bytes[i + 3]]);
    (be(16), be(20))
}

#[test]
fn bad_requests_fail_with_one_line() {
    let dir = scratch("bad");
    let periodic = write(
        &dir.join("periodic.json"),
        r#"{"PeriodicPattern": {"period": 10.0, "nRows": 5, "nCols": 5}}"#,
    );
    let custom = write(
        &dir.join("custom.json"),
        r#"{"CustomPattern": {"dots": [[0.0, 0.0, 1.0, 1.0, 1.0]]}}"#,
    );
    let target = |name: &str| dir.join(name).to_str().unwrap().to_string();
    for (args, message) in [
        (
            vec!["--id", "3", &target("a.gds")],
            "--id applies to HPCodePattern",
        ),
        (
            vec!["--roi", "0,0,1,1", &target("a.gds")],
            "--roi applies to MegarenaPattern",
        ),
        (
            vec!["--format", "gds", &target("a.oas")],
            "has the extension of oas",
        ),
        (vec![&target("a")], "cannot tell the format"),
        (
            vec!["--format", "dxf", &target("a")],
            "unknown export format",
        ),
    ] {
        let mut all = vec!["export", "--pattern", &periodic];
        all.extend(args.iter().copied());
        let run = vernier(&all);
        let stderr = String::from_utf8_lossy(&run.stderr);
        assert!(!run.status.success(), "{all:?}");
        assert!(
            stderr.starts_with("vernier: ") && stderr.contains(message),
            "{all:?}: {stderr}"
        );
        assert_eq!(stderr.trim_end().lines().count(), 1, "{stderr}");
    }
    let run = vernier(&["export", "--pattern", &custom, &target("c.png")]);
    assert!(!run.status.success());
    assert!(String::from_utf8_lossy(&run.stderr).contains("CustomPattern"));
    // Fewer than 100 rectangles (the original divided by zero,
    // docs/design.md#defect-export-progress).
    let run = vernier(&["export", "--pattern", &custom, &target("c.svg")]);
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}
