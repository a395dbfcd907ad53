//! Megarena detector timing: `cargo bench -p vernier --bench megarena` (`-- --quick` for a
//! short run).
//!
//! Prints ms per frame of the whole detector (phase engine + lattice sampling, orientation,
//! dot-wise refinement, decoding) and of the phase engine alone on the same frame (calls
//! interleaved, medians, plans warm), hence the cost of the Megarena-specific steps. Frames:
//! 12-bit code, ~10 px per period, 8-bit quantisation, 1 % noise. Reference: the original
//! C++ takes 144–157 ms per 1024² frame on the project's 2-core machine (46 ms at 512²,
//! docs/design.md#speed).

use std::time::Instant;
use vernier::layout::MegarenaLayout;
use vernier::megarena::{MegarenaDetector, MegarenaParams};
use vernier::render::{render, RenderOptions};
use vernier::{PhaseEngine, PhaseParams, Pose};

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn time_ms(f: impl FnOnce()) -> f64 {
    let t = Instant::now();
    f();
    t.elapsed().as_secs_f64() * 1e3
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    println!(
        "{:<10} {:>10} {:>10} {:>12} {:>12} {:>10}",
        "image", "detect ms", "engine ms", "megarena ms", "original ms", "speed-up"
    );
    for (size, original_ms) in [(512usize, 46.0), (1024, 150.0)] {
        let period = 10.0;
        let layout = MegarenaLayout::new(period, 12).expect("layout");
        let mut opts = RenderOptions::new(size, size);
        opts.noise_std = 0.01;
        opts.bit_depth = Some(8);
        opts.background = 0.05;
        opts.foreground = 0.95;
        let truth = Pose::planar(-51_234.5, -43_210.9, 0.4, 1.0);
        let image = render(&layout, &truth, &opts).expect("render");
        let mut detector = MegarenaDetector::new(MegarenaParams::new(period, 12).expect("params"))
            .expect("detector");
        let mut engine = PhaseEngine::new();
        let params = PhaseParams::default();
        let found = detector.detect(&image).expect("warm-up");
        engine.analyze(&image, &params).expect("warm-up");
        let error_px = (found.pose.x - truth.x).hypot(found.pose.y - truth.y) / truth.pixel_size;
        let runs = if quick {
            5
        } else if size <= 512 {
            200
        } else {
            60
        };
        let (mut whole, mut alone) = (Vec::new(), Vec::new());
        for _ in 0..runs {
            whole.push(time_ms(|| {
                std::hint::black_box(detector.detect(&image).expect("detect"));
            }));
            alone.push(time_ms(|| {
                std::hint::black_box(engine.analyze(&image, &params).expect("analyze"));
            }));
        }
        let (detect_ms, engine_ms) = (median_ms(whole), median_ms(alone));
        println!(
            "{:<10} {:>10.3} {:>10.3} {:>12.3} {:>12.1} {:>9.1}x   (error {:.1e} px, {} dots refined)",
            format!("{size}x{size}"),
            detect_ms,
            engine_ms,
            detect_ms - engine_ms,
            original_ms,
            original_ms / detect_ms,
            error_px,
            found.refined_dots
        );
    }
}
