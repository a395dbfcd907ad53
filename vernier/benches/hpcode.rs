//! HP code detector timing: `cargo bench -p vernier --bench hpcode` (`-- --quick` for a smoke
//! run).
//!
//! Prints ms per frame (median, plans warm) on the full 2456×2054 `hpcode/Image100.png` and on a
//! 1024×1024 crop of it holding both markers, for the default settings (window inside each
//! marker, then the whole-field fit), the window's planes alone, and the original's 512-px
//! window, plus the cost of the finder
//! search alone and the rest per marker (grouping, window, phase engine — once or twice, see
//! `HpCodeDetector` —, ID), with the markers measured on one thread and on every core, and
//! in tracking mode (`HpCodeDetector::track`: no finder search, as between reacquisitions).
//! Reference: the original C++ takes 94 ms (full frame) and 61 ms (crop) on the
//! project's 2-core machine (W 33, window 512). Images come from `$VERNIER_DATA_DIR`, else
//! `../shared/data`.

use std::path::PathBuf;
use std::time::Instant;
use vernier::hpcode::{HpCodeDetector, HpCodeParams};
use vernier::GreyImage;

fn data_dir() -> PathBuf {
    std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"))
}

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

/// Median ms of `runs` calls of `f` after one warm-up call.
fn time(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    median_ms(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect(),
    )
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let runs = if quick { 3 } else { 40 };
    let path = data_dir().join("hpcode/Image100.png");
    let full = match GreyImage::open(&path) {
        Ok(image) => image,
        Err(e) => {
            eprintln!("hpcode bench: {e} (set VERNIER_DATA_DIR to the shared/data folder)");
            std::process::exit(1);
        }
    };
    // Both markers are near (637, 947) and (1323, 985), about 260 px wide.
    let crop = match full.crop(468, 454, 1024, 1024) {
        Ok(image) => image,
        Err(e) => {
            eprintln!("hpcode bench: {e}");
            std::process::exit(1);
        }
    };
    println!(
        "{:<22} {:>10} {:>14} {:>10} {:>12} {:>9} {:>8}",
        "image / window",
        "finders ms",
        "rest/marker ms",
        "total ms",
        "original ms",
        "speed-up",
        "markers"
    );
    for (name, image, original_ms) in [("2456x2054", &full, 94.0), ("1024x1024 crop", &crop, 61.0)]
    {
        // Markers measured on 1 thread, then on every core (`HpCodeParams::threads` 0).
        // Default: whole-field fit after decoding; "window" rows keep the window's planes.
        for (window, size, threads, field_fit) in [
            ("auto, 1 thread", None, 1, true),
            ("auto", None, 0, true),
            ("auto, window", None, 0, false),
            ("512, window", Some(512), 0, false),
        ] {
            let mut params = HpCodeParams::new(15.5, 33);
            params.window_size = size;
            params.threads = threads;
            params.field_fit = field_fit;
            let mut detector = match HpCodeDetector::new(params) {
                Ok(d) => d,
                Err(e) => {
                    eprintln!("hpcode bench: {e}");
                    std::process::exit(1);
                }
            };
            let mut markers = 0;
            let finders_ms = time(runs, || {
                std::hint::black_box(detector.find_finders(image));
            });
            let total_ms = time(runs, || {
                markers = detector.detect(image).map_or(0, |m| m.len());
            });
            println!(
                "{:<22} {:>10.2} {:>14.2} {:>10.2} {:>12.0} {:>8.1}x {:>8}",
                format!("{name} / {window}"),
                finders_ms,
                (total_ms - finders_ms) / markers.max(1) as f64,
                total_ms,
                original_ms,
                original_ms / total_ms,
                markers
            );
            if size.is_none() && threads == 0 && field_fit {
                print_tracking(&mut detector, image, name, original_ms, runs);
            }
        }
    }
}

/// Tracking: the markers of `image` measured again from their last positions, no search;
/// prints the row `name / tracking`.
fn print_tracking(
    detector: &mut HpCodeDetector,
    image: &GreyImage,
    name: &str,
    original_ms: f64,
    runs: usize,
) {
    let previous = detector.detect(image).unwrap_or_default();
    let predicted: Vec<_> = previous.iter().map(|m| m.origin_px).collect();
    let tracked_ms = time(runs, || {
        std::hint::black_box(detector.track(image, &previous, &predicted).ok());
    });
    println!(
        "{:<22} {:>10} {:>14.2} {:>10.2} {:>12.0} {:>8.1}x {:>8}",
        format!("{name} / tracking"),
        "-",
        tracked_ms / previous.len().max(1) as f64,
        tracked_ms,
        original_ms,
        original_ms / tracked_ms,
        previous.len()
    );
}
