//! Stamp detector timing: `cargo bench -p vernier --bench stamp` (add `-- --quick` for a short
//! run).
//!
//! Image: `stamp/stampPatternImage_15um.jpg` (1655×762, 2 stamps) with P = 15 µm and the
//! `layouts/stamp69x69.png` bitmap, the original's example settings. Reference: the original
//! C++ takes 245–290 ms per frame on the project's 2-core machine (square detector ≈ 35 ms,
//! ≈ 115 ms per stamp with its 820² window). Prints the median ms per frame and the cost of
//! each stage (plans and buffers warm). The data folder is `$VERNIER_DATA_DIR`, else
//! `../shared/data` beside the workspace.

use std::path::PathBuf;
use std::time::Instant;
use vernier::layout::BitmapLayout;
use vernier::phase::{PhaseEngine, PhaseParams};
use vernier::snapshot::Snapshot;
use vernier::stamp::{StampDetection, StampDetector, StampParams};
use vernier::GreyImage;

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn time_ms(runs: usize, mut f: impl FnMut()) -> f64 {
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

/// Cores the default `threads: 0` uses.
fn parallel_threads() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let runs = if quick { 5 } else { 40 };
    let data = std::env::var_os("VERNIER_DATA_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"));
    let image = GreyImage::open(data.join("stamp/stampPatternImage_15um.jpg")).expect("image");
    let bitmap =
        BitmapLayout::from_image_file(15.0, data.join("layouts/stamp69x69.png")).expect("bitmap");
    let params = StampParams::new(15.0, vec![bitmap]);
    let mut detector = StampDetector::new(params.clone()).expect("detector");
    let found = detector.detect(&image).expect("warm-up");
    assert_eq!(found.len(), 2, "both stamps must be found");
    // The same frame with the stamps' whole-field fits on one thread (the scaling).
    let mut sequential = StampDetector::new(StampParams {
        threads: 1,
        ..params
    })
    .expect("detector");
    sequential.detect(&image).expect("warm-up");
    let one_thread = time_ms(runs, || {
        std::hint::black_box(sequential.detect(&image).expect("detect"));
    });

    let total = time_ms(runs, || {
        std::hint::black_box(detector.detect(&image).expect("detect"));
    });
    let frames = time_ms(runs, || {
        std::hint::black_box(detector.find_frames(&image));
    });
    println!(
        "stampPatternImage_15um.jpg ({}x{}, {} stamps)",
        image.width(),
        image.height(),
        found.len()
    );
    println!(
        "{:<44} {:>10} {:>12} {:>10}",
        "stage", "ms", "original ms", "speed-up"
    );
    println!(
        "{:<44} {:>10.2} {:>12.0} {:>9.1}x",
        "frame (quadrilateral) search",
        frames,
        35.0,
        35.0 / frames
    );
    print_stamp_stages(&image, &mut detector, &found, runs);
    println!(
        "{:<44} {:>10.2} {:>12} {:>9.1}x (vs 245)",
        format!("total per frame ({} threads)", parallel_threads()),
        total,
        "245-290",
        245.0 / total
    );
    println!(
        "{:<44} {:>10.2} {:>12} {:>9.1}x (vs 245)",
        "total per frame, one thread",
        one_thread,
        "245-290",
        245.0 / one_thread
    );
}

/// Times and prints each found stamp's measurement: all stages, and the phase engine's share.
fn print_stamp_stages(
    image: &GreyImage,
    detector: &mut StampDetector,
    found: &[StampDetection],
    runs: usize,
) {
    let mut engine = PhaseEngine::new();
    let params = PhaseParams::default();
    for (k, d) in found.iter().enumerate() {
        let size = d.window_size;
        let mut snapshot = Snapshot::extract(image, d.window_center, size).expect("snapshot");
        snapshot.apodize(4.0);
        engine.analyze(&snapshot.image, &params).expect("phase");
        let phase = time_ms(runs, || {
            std::hint::black_box(engine.analyze(&snapshot.image, &params).expect("phase"));
        });
        let whole = time_ms(runs, || {
            std::hint::black_box(
                detector
                    .measure_at(image, d.window_center, Some(size))
                    .expect("measure"),
            );
        });
        println!(
            "{:<44} {:>10.2} {:>12.0} {:>9.1}x",
            format!("stamp {k}: window {size}², all stages"),
            whole,
            115.0,
            115.0 / whole
        );
        println!(
            "{:<44} {:>10.2}",
            format!("stamp {k}:   of which phase engine"),
            phase
        );
        println!(
            "{:<44} {:>10.2}",
            format!("stamp {k}:   of which window, thumbnail, match, pose"),
            whole - phase
        );
    }
}
