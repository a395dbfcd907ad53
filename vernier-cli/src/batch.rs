//! Runs a detector over many image files, writing a pose time series (CSV or JSON Lines)
//! on stdout with a progress bar on stderr.

use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::{Instant, UNIX_EPOCH};

use indicatif::{ProgressBar, ProgressStyle};
use vernier::{DecodeLimits, Detector, GreyImage};

use crate::pose_table::{PoseRow, TableFormat, TableWriter};
use crate::rerun_log::{FrameLog, RerunLog};

/// Runs shorter than this many frames get no progress bar.
const PROGRESS_MIN_FRAMES: u64 = 10;

/// A progress bar on stderr for `total` items (hidden for short runs and, by indicatif,
/// when stderr is not a terminal).
pub fn progress_bar(total: u64, unit: &str) -> ProgressBar {
    if total < PROGRESS_MIN_FRAMES {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    let template = format!("{{bar:40}} {{pos}}/{{len}} {unit} {{per_sec}} eta {{eta}}");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar
}

/// Modification time of a file, seconds since the Unix epoch (the `stamp` of frames read
/// from files).
fn modified_seconds(path: &Path) -> Option<f64> {
    let modified = std::fs::metadata(path).ok()?.modified().ok()?;
    Some(modified.duration_since(UNIX_EPOCH).ok()?.as_secs_f64())
}

/// Detects markers in every image, in order; each image is frame `i` of the series. Returns
/// the number of images that failed (each reported on stderr, and as a row with `error`).
/// With `rerun`, every readable image and its result are also logged there. Images above
/// `limits` are failures (decoded only after their header passed). With `track`
/// (`Some(reacquire_every)`), the images are one stream and markers are tracked
/// ([`Detector::detect_next`]).
pub fn detect_files(
    detector: &mut Detector,
    images: &[PathBuf],
    limits: &DecodeLimits,
    format: TableFormat,
    track: Option<usize>,
    mut rerun: Option<&mut RerunLog>,
) -> Result<usize, String> {
    let stdout = std::io::stdout().lock();
    let io_error = |e: std::io::Error| format!("cannot write the results: {e}");
    let mut table = TableWriter::new(BufWriter::new(stdout), format).map_err(io_error)?;
    let progress = progress_bar(images.len() as u64, "images");
    let mut failures = 0;
    for (frame, path) in images.iter().enumerate() {
        let start = Instant::now();
        let image = GreyImage::open_with_limits(path, limits).map_err(|e| e.to_string());
        let result = image.as_ref().map_err(Clone::clone).and_then(|image| {
            match track {
                Some(every) => detector.detect_next(image, every),
                None => detector.detect(image),
            }
            .map_err(|e| e.to_string())
        });
        let time_ms = start.elapsed().as_secs_f64() * 1e3;
        if let (Some(log), Ok(image)) = (rerun.as_deref_mut(), &image) {
            log.log_frame(&FrameLog {
                frame: frame as u64,
                image,
                result: &result,
            })?;
        }
        if let Err(e) = &result {
            progress.suspend(|| eprintln!("vernier: {}: {e}", path.display()));
            failures += 1;
        }
        let rows = PoseRow::from_result(
            frame as u64,
            modified_seconds(path),
            &path.display().to_string(),
            &result,
            time_ms,
        );
        table.write(&rows).map_err(io_error)?;
        progress.inc(1);
    }
    progress.finish_and_clear();
    table.finish().map_err(io_error)?;
    Ok(failures)
}
