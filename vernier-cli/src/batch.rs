//! Runs a detector over many image files, writing a pose time series (CSV or JSON Lines)
//! on stdout with a progress bar on stderr.

use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::{Instant, UNIX_EPOCH};

use indicatif::{ProgressBar, ProgressStyle};
use vernier::{DecodeLimits, Detector, FrameReader, GreyImage};

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

/// One image's markers (or why there are none) and the time its reading and detection
/// took, ms.
type Outcome = (Result<Vec<vernier::MarkerPose>, String>, f64);

/// Reads (into `reader`'s buffers, kept from image to image) and detects one image; with
/// `track` (`Some(reacquire_every)`) as the next frame of a stream
/// ([`Detector::detect_next`]). Returns the image too when it could be read.
fn detect_one<'r>(
    detector: &mut Detector,
    reader: &'r mut FrameReader,
    path: &Path,
    limits: &DecodeLimits,
    track: Option<usize>,
) -> (Outcome, Option<&'r GreyImage>) {
    let start = Instant::now();
    let image = reader.read(path, limits).map_err(|e| e.to_string());
    let result = image.as_ref().map_err(Clone::clone).and_then(|image| {
        match track {
            Some(every) => detector.detect_next(image, every),
            None => detector.detect(image),
        }
        .map_err(|e| e.to_string())
    });
    let time_ms = start.elapsed().as_secs_f64() * 1e3;
    ((result, time_ms), image.ok())
}

/// Detects markers in every image; each image is frame `i` of the series, and the rows come
/// out in that order. Returns the number of images that failed (each reported on stderr,
/// and as a row with `error`). With `rerun`, every readable image and its result are also
/// logged there. Images above `limits` are failures (decoded only after their header
/// passed). With `track` (`Some(reacquire_every)`), the images are one stream and markers
/// are tracked ([`Detector::detect_next`]) by the first detector; otherwise each of
/// `detectors` takes the next image not yet taken, on its own thread (independent images;
/// `time_ms` is then each image's own time on its thread).
pub fn detect_files(
    detectors: &mut [Detector],
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
    let period = detectors.first().map_or(f64::NAN, Detector::period);
    let mut write = |frame: usize,
                     (result, time_ms): Outcome,
                     image: Option<&GreyImage>|
     -> Result<(), String> {
        let path = &images[frame];
        if let (Some(log), Some(image)) = (rerun.as_deref_mut(), image) {
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
            period,
        );
        table.write(&rows).map_err(io_error)?;
        progress.inc(1);
        Ok(())
    };
    let sequential = detectors.len() == 1 || track.is_some();
    match detectors {
        [] => return Err("internal: no detector".into()),
        [detector, ..] if sequential => {
            let mut reader = FrameReader::default();
            for (frame, path) in images.iter().enumerate() {
                let (outcome, image) = detect_one(detector, &mut reader, path, limits, track);
                write(frame, outcome, image)?;
            }
        }
        workers => in_parallel(workers, images, limits, &mut |frame, outcome| {
            write(frame, outcome, None)
        })?,
    }
    progress.finish_and_clear();
    table.finish().map_err(io_error)?;
    Ok(failures)
}

/// Each of `workers` takes the next image not yet taken on its own thread; `write` gets the
/// outcomes in the images' order (an outcome waits for those before it).
fn in_parallel(
    workers: &mut [Detector],
    images: &[PathBuf],
    limits: &DecodeLimits,
    write: &mut impl FnMut(usize, Outcome) -> Result<(), String>,
) -> Result<(), String> {
    use std::sync::atomic::{AtomicUsize, Ordering};
    let next = AtomicUsize::new(0);
    std::thread::scope(|scope| {
        let (sender, outcomes) = std::sync::mpsc::channel();
        for detector in workers.iter_mut() {
            let (sender, next) = (sender.clone(), &next);
            scope.spawn(move || {
                let mut reader = FrameReader::default();
                loop {
                    let frame = next.fetch_add(1, Ordering::Relaxed);
                    let Some(path) = images.get(frame) else { break };
                    // The image itself is not sent: only the sequential run logs to rerun.
                    let (outcome, _) = detect_one(detector, &mut reader, path, limits, None);
                    if sender.send((frame, outcome)).is_err() {
                        break;
                    }
                }
            });
        }
        drop(sender);
        let mut waiting = std::collections::BTreeMap::new();
        let mut due = 0;
        for (frame, outcome) in outcomes {
            waiting.insert(frame, outcome);
            while let Some(outcome) = waiting.remove(&due) {
                if let Err(e) = write(due, outcome) {
                    // Stops the workers after their current image.
                    next.store(images.len(), Ordering::Relaxed);
                    return Err(e);
                }
                due += 1;
            }
        }
        Ok(())
    })
}
