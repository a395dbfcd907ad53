//! `vernier calibrate`: the pixel size of a microscope, with its uncertainty and its variation
//! across the field, from one or more images of markers (docs/design.md#calibrated-scale).
//!
//! Every marker found gives a scale sample at its position; with `--tiles N` the images are
//! also cut into `N × N` tiles measured on their own (for a periodic or Megarena pattern that
//! fills the field). The samples are pooled by [`vernier::calibration::calibrate`]. Give the
//! printed pixel size back to `vernier detect --pixel-size` or the node's `pixel_size`.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use vernier::calibration::{calibrate, tile_samples, Calibration, ScaleSample};
use vernier::{DecodeLimits, DetectorConfig, GreyImage};

use crate::batch::progress_bar;
use crate::detector_flags::DetectorFlags;

/// Arguments of `vernier calibrate`.
#[derive(Parser)]
pub struct CalibrateArgs {
    #[command(flatten)]
    detector: DetectorFlags,
    /// Also measure `N × N` tiles of each image on their own (a periodic or Megarena pattern
    /// filling the field): the scale's variation across the field. Default: 3 for periodic
    /// patterns, else 0 (markers only). A Megarena tile must show ~40 periods per side to be
    /// decoded.
    #[arg(long, value_name = "N")]
    tiles: Option<usize>,
    /// Print JSON (the calibration and every sample) instead of text.
    #[arg(long)]
    json: bool,
    /// Largest image read, pixels (`100M`, `2.5G`, `4000000`).
    #[arg(long, value_parser = crate::parse_max_pixels, default_value = "100M")]
    max_pixels: u64,
    /// Image files, folders or quoted glob patterns (as for `vernier detect`).
    #[arg(required = true)]
    images: Vec<PathBuf>,
}

/// One sample and where it came from.
#[derive(serde::Serialize)]
struct Sourced {
    image: String,
    /// `marker ID`, or `tile` (its position says which).
    source: String,
    #[serde(flatten)]
    sample: ScaleSample,
}

/// Runs `vernier calibrate`.
pub fn run(args: &CalibrateArgs) -> Result<ExitCode, String> {
    let settings = args.detector.settings();
    if settings.pixel_size.is_some() {
        return Err("--pixel-size is what `calibrate` measures: leave it out".into());
    }
    // One configuration (the pattern file read once) for the detector and the tile default;
    // no calibrated scale to apply (refused above).
    let config = settings.to_config().map_err(|e| e.to_string())?;
    let mut detector = vernier::Detector::new(config.clone()).map_err(|e| e.to_string())?;
    let tiles = args
        .tiles
        .unwrap_or(if matches!(config, DetectorConfig::Periodic(_)) {
            3
        } else {
            0
        });
    let images = crate::inputs::expand_inputs(&args.images)?;
    let limits = DecodeLimits::with_max_pixels(args.max_pixels);
    let progress = progress_bar(images.len() as u64, "images");
    let mut samples = Vec::new();
    for path in &images {
        let name = path.display().to_string();
        let image =
            GreyImage::open_with_limits(path, &limits).map_err(|e| format!("{name}: {e}"))?;
        let (found, failures) = image_samples(&mut detector, &image, tiles);
        for e in failures {
            progress.suspend(|| eprintln!("vernier: {name}: {e}"));
        }
        samples.extend(found.into_iter().map(|(source, sample)| Sourced {
            image: name.clone(),
            source,
            sample,
        }));
        progress.inc(1);
    }
    progress.finish_and_clear();
    let pooled: Vec<ScaleSample> = samples.iter().map(|s| s.sample).collect();
    let fit = calibrate(&pooled).map_err(|e| e.to_string())?;
    if args.json {
        let out = serde_json::json!({ "calibration": fit, "samples": samples });
        println!("{out:#}");
    } else {
        print_text(&fit, &samples);
    }
    Ok(ExitCode::SUCCESS)
}

/// The scale samples of one image, named (`marker ID`, `tile`): its markers, then its
/// `tiles × tiles` tiles (none for 0); and what failed.
fn image_samples(
    detector: &mut vernier::Detector,
    image: &GreyImage,
    tiles: usize,
) -> (Vec<(String, ScaleSample)>, Vec<String>) {
    let (mut found, mut failures) = (Vec::new(), Vec::new());
    match detector.detect(image) {
        Ok(markers) => found.extend(markers.iter().filter_map(|m| {
            ScaleSample::from_marker(m, (image.width(), image.height()))
                .map(|s| (format!("marker {}", m.id), s))
        })),
        Err(e) => failures.push(e.to_string()),
    }
    if tiles > 0 {
        match tile_samples(image, detector, tiles) {
            Ok(t) => found.extend(t.into_iter().map(|s| ("tile".to_string(), s))),
            Err(e) => failures.push(e.to_string()),
        }
    }
    (found, failures)
}

fn print_text(fit: &Calibration, samples: &[Sourced]) {
    println!("image\tsource\tx_px\ty_px\tpixel_size\tstd");
    for s in samples {
        let p = &s.sample;
        println!(
            "{}\t{}\t{:.1}\t{:.1}\t{:.9}\t{:.2e}",
            s.image, s.source, p.position_px.x, p.position_px.y, p.pixel_size, p.std
        );
    }
    println!();
    println!(
        "pixel size: {:.9} ± {:.2e} pattern units per pixel (relative σ {:.1e}), {} samples",
        fit.pixel_size,
        fit.pixel_size_std,
        fit.pixel_size_std / fit.pixel_size,
        fit.samples
    );
    if let Some(r) = fit.chi2_per_dof {
        println!(
            "χ²/dof: {r:.2}{}",
            if r > 1.0 {
                " (samples scatter more than their σ: σ inflated by √(χ²/dof))"
            } else {
                ""
            }
        );
    }
    match (fit.gradient, fit.gradient_std) {
        (Some(g), Some(s)) => println!(
            "scale gradient across the field: x {:.2e} ± {:.1e}, y {:.2e} ± {:.1e} per pixel \
             ({:.1e} relative change over 1000 px)",
            g.x,
            s.x,
            g.y,
            s.y,
            1000.0 * g.norm()
        ),
        _ => println!(
            "scale gradient: not measured (needs ≥ 4 samples spread over the field; try \
             --tiles)"
        ),
    }
}
