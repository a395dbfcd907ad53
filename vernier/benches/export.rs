//! Layout export timing: `cargo bench -p vernier --bench export` (`-- --quick` for 1 run).
//!
//! Prints ms and bytes per format for Megarena regions of 2·10⁴ to 5·10⁵ dots. SVG writes one
//! element per dot, so its time is the per-dot baseline that the GDSII/OASIS array
//! decomposition is compared with (ratio within this run).

use std::time::Instant;
use vernier::export::{export_bytes, ExportFormat};
use vernier::layout::{MegarenaLayout, Rect};
use vernier::pattern_file::Pattern;

fn median_ms(mut samples: Vec<f64>) -> f64 {
    samples.sort_by(f64::total_cmp);
    samples[samples.len() / 2]
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let runs = if quick { 1 } else { 5 };
    let cases = [
        (
            "12-bit P=14 3x2 mm",
            14.0,
            12,
            Rect::new(0.0, 0.0, 3000.0, 2000.0),
        ),
        (
            "12-bit P=5 3x2 mm",
            5.0,
            12,
            Rect::new(20_000.0, 15_000.0, 3000.0, 2000.0),
        ),
        (
            "8-bit P=5 whole",
            5.0,
            8,
            Rect::new(0.0, 0.0, 3930.0, 3930.0),
        ),
    ];
    println!(
        "{:<30} {:>6} {:>10} {:>12} {:>12} {:>14}",
        "region", "format", "ms", "bytes", "ms/1e5 dots", "SVG ms / this"
    );
    for (name, period, depth, roi) in cases {
        let layout = MegarenaLayout::new(period, depth)
            .and_then(|l| l.with_region_of_interest(roi))
            .expect("layout");
        let pattern = Pattern::from(layout);
        let mut dots = 0usize;
        pattern
            .layout()
            .visit_rects(&pattern.layout().bounds(), &mut |_| dots += 1);
        let mut svg_ms = f64::NAN;
        for format in [
            ExportFormat::Svg,
            ExportFormat::Gds,
            ExportFormat::Oasis,
            ExportFormat::Png,
        ] {
            let mut bytes = 0;
            let samples: Vec<f64> = (0..runs)
                .map(|_| {
                    let t = Instant::now();
                    let out = export_bytes(&pattern, format).expect("export");
                    let ms = t.elapsed().as_secs_f64() * 1e3;
                    bytes = out.len();
                    ms
                })
                .collect();
            let ms = median_ms(samples);
            if format == ExportFormat::Svg {
                svg_ms = ms;
            }
            println!(
                "{:<30} {:>6} {:>10.2} {:>12} {:>12.2} {:>13.1}x",
                format!("{name} ({dots})"),
                format.extension(),
                ms,
                bytes,
                ms * 1e5 / dots as f64,
                svg_ms / ms
            );
        }
    }
}
