//! `vernier live` (cargo feature `opencv`): detects markers in the frames of a camera, V4L2
//! device, GStreamer pipeline or video file as they arrive, with the detector and flags of
//! `vernier detect`.
//!
//! A capture thread reads frames into a one-slot mailbox; the main thread takes the latest
//! frame, converts it to grey, runs the detector and prints its rows (the pose table of
//! vernier-cli/src/pose_table.rs plus `latency_ms`, see [`output`]). When detection is slower
//! than a live source, frames are dropped (the newer frame replaces the waiting one), never
//! queued; a video file waits for the detector instead (every frame is analysed) unless
//! `--realtime`. Ctrl-C (or closing the `--display` window) ends the run cleanly; a summary
//! goes to stderr.

mod capture;
mod convert;
mod display;
mod output;

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use vernier::{Detector, GreyImage, MarkerPose};

use crate::detector_flags::DetectorFlags;
use crate::pose_table::{PoseRow, TableFormat};
use crate::rerun_log::{FrameLog, RerunLog, RerunTarget};
use capture::{Frame, Next, Pace, Source, Stream};

/// Arguments of `vernier live`.
#[derive(clap::Args)]
#[command(group(
    clap::ArgGroup::new("source")
        .required(true)
        .args(["camera", "device", "gstreamer", "video"])
))]
pub struct LiveArgs {
    /// Camera index (0 = first camera), opened by OpenCV's default backend (V4L2 on Linux).
    #[arg(long, value_name = "N")]
    camera: Option<u32>,
    /// V4L2 device file (`/dev/video0`).
    #[arg(long, value_name = "PATH")]
    device: Option<PathBuf>,
    /// GStreamer pipeline ending in `appsink` (`"videotestsrc ! videoconvert ! appsink"`);
    /// needs an OpenCV built with GStreamer (Debian's is).
    #[arg(long, value_name = "PIPELINE")]
    gstreamer: Option<String>,
    /// Video file (any container and codec OpenCV's FFmpeg backend reads). Every frame is
    /// analysed, in order, unless `--realtime`.
    #[arg(long, value_name = "FILE")]
    video: Option<PathBuf>,
    /// With `--video`: read the file at its own frame rate, dropping the frames the detector
    /// cannot keep up with, as a camera would.
    #[arg(long, requires = "video")]
    realtime: bool,
    /// Ask the backend for the camera's own pixel format instead of 8-bit BGR (16-bit mono
    /// V4L2 cameras keep their depth). Frames that are not 8/16-bit mono, BGR or BGRA (raw
    /// YUV, compressed) then end the run with an error.
    #[arg(long)]
    raw: bool,
    /// Marker type, pattern file and detector settings (the flags of `vernier detect`).
    #[command(flatten)]
    detector: DetectorFlags,
    /// Output format: `jsonl` or `csv` (one row per frame and marker, the columns of
    /// `vernier detect --format csv` plus `latency_ms`), or `json` (one object per frame).
    #[arg(long, value_enum, default_value = "jsonl")]
    format: TableFormat,
    /// Show the frames in a window with the markers, their IDs and axes (x red, y green);
    /// `q`, Esc or closing the window ends the run. Needs a graphical session.
    #[arg(long)]
    display: bool,
    /// Also log every analysed frame to rerun (needs the `rerun` cargo feature): `spawn`,
    /// `connect`, a `rerun+http://HOST:PORT/proxy` URL or a `FILE.rrd`, as for `detect`.
    #[arg(long, value_name = "TARGET")]
    rerun: Option<RerunTarget>,
}

impl LiveArgs {
    /// The frame source (clap guarantees exactly one).
    fn source(&self) -> Result<Source, String> {
        match (&self.camera, &self.device, &self.gstreamer, &self.video) {
            (Some(index), ..) => Ok(Source::Camera(*index)),
            (_, Some(path), ..) => Ok(Source::Device(path.clone())),
            (_, _, Some(pipeline), _) => Ok(Source::Gstreamer(pipeline.clone())),
            (.., Some(path)) => Ok(Source::Video(path.clone())),
            _ => Err("give a source: --camera, --device, --gstreamer or --video".into()),
        }
    }

    /// How the capture thread paces itself: files wait for the detector unless `--realtime`.
    fn pace(&self, source: &Source) -> Pace {
        match source {
            Source::Video(_) if self.realtime => Pace::FileRate,
            Source::Video(_) => Pace::EveryFrame,
            _ => Pace::LatestWins,
        }
    }
}

/// Runs `vernier live`: until the video ends, Ctrl-C, or the preview window closes.
pub fn run(args: &LiveArgs) -> Result<ExitCode, String> {
    capture::quiet_opencv_logging();
    let mut detector = args.detector.detector()?;
    let source = args.source()?;
    let mut preview = args.display.then(display::Preview::open).transpose()?;
    let mut rerun = match &args.rerun {
        Some(target) => Some(RerunLog::open(target, args.detector.display_polarity())?),
        None => None,
    };
    let stop = stop_on_ctrl_c()?;
    let stream = Stream::start(source.clone(), args.pace(&source), args.raw, stop.clone())?;
    let mut table = output::LiveTable::new(args.format)?;
    let mut summary = Summary::new();
    let sinks = &mut Sinks {
        table: &mut table,
        preview: preview.as_mut(),
        rerun: rerun.as_mut(),
        period: detector.period(),
    };
    let label = source.to_string();
    let ending = loop {
        match stream.next() {
            Next::Frame(frame) => {
                if summary.layout.is_none() {
                    summary.layout = Some(convert::describe(&frame.mat));
                }
                let analysed = analyse(&mut detector, args.detector.tracking(), &frame)?;
                let keep_going = sinks.publish(&label, &frame, &analysed, &mut summary)?;
                if !keep_going {
                    stop.store(true, Ordering::SeqCst);
                }
            }
            Next::End(ending) => break ending,
        }
    };
    let counts = stream.finish();
    table.finish()?;
    if let Some(rerun) = rerun {
        rerun.finish()?;
    }
    eprintln!("{}", summary.line(&label, &counts));
    ending.map(|()| ExitCode::SUCCESS)
}

/// A frame's grey image and detection result, with the time both took (ms).
struct Analysed {
    image: GreyImage,
    result: Result<Vec<MarkerPose>, String>,
    time_ms: f64,
}

/// Converts and analyses one frame. A frame that cannot be converted (a pixel format the
/// detector cannot read) ends the run: every later frame would fail the same way.
fn analyse(
    detector: &mut Detector,
    tracking: Option<usize>,
    frame: &Frame,
) -> Result<Analysed, String> {
    let start = Instant::now();
    let image = convert::grey_image(&frame.mat)?;
    let result = match tracking {
        Some(every) => detector.detect_next(&image, every),
        None => detector.detect(&image),
    }
    .map_err(|e| e.to_string());
    Ok(Analysed {
        image,
        result,
        time_ms: start.elapsed().as_secs_f64() * 1e3,
    })
}

/// Where each analysed frame goes: the pose table, the preview window and rerun.
struct Sinks<'a> {
    table: &'a mut output::LiveTable,
    preview: Option<&'a mut display::Preview>,
    rerun: Option<&'a mut RerunLog>,
    /// The pattern's period, pattern units (the rows' predicted σ).
    period: f64,
}

impl Sinks<'_> {
    /// Writes the frame's rows (latency measured then), shows and logs it. Returns false
    /// when the user closed the preview.
    fn publish(
        &mut self,
        label: &str,
        frame: &Frame,
        analysed: &Analysed,
        summary: &mut Summary,
    ) -> Result<bool, String> {
        let rows = PoseRow::from_result(
            frame.index,
            Some(frame.stamp),
            label,
            &analysed.result,
            analysed.time_ms,
            self.period,
        );
        let latency_ms = frame.captured.elapsed().as_secs_f64() * 1e3;
        self.table.write(&rows, latency_ms)?;
        summary.add(analysed.result.is_ok(), latency_ms);
        if let Some(log) = self.rerun.as_deref_mut() {
            log.log_frame(&FrameLog {
                frame: frame.index,
                image: &analysed.image,
                result: &analysed.result,
            })?;
        }
        match self.preview.as_deref_mut() {
            Some(preview) => {
                let markers = analysed.result.as_deref().unwrap_or_default();
                preview.show(&frame.mat, markers)
            }
            None => Ok(true),
        }
    }
}

/// Sets up Ctrl-C: the first one asks the run to end (the returned flag), a second one
/// exits at once (status 130) in case a capture call hangs.
fn stop_on_ctrl_c() -> Result<Arc<AtomicBool>, String> {
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            std::process::exit(130);
        }
    })
    .map_err(|e| format!("cannot catch Ctrl-C: {e}"))?;
    Ok(stop)
}

/// Counts for the final stderr line.
struct Summary {
    /// The first frame's size and pixel layout.
    layout: Option<String>,
    start: Instant,
    analysed: u64,
    failed: u64,
    /// Latency of every analysed frame, ms.
    latencies: Vec<f64>,
}

impl Summary {
    fn new() -> Self {
        Summary {
            layout: None,
            start: Instant::now(),
            analysed: 0,
            failed: 0,
            latencies: Vec::new(),
        }
    }

    fn add(&mut self, found: bool, latency_ms: f64) {
        self.analysed += 1;
        self.failed += u64::from(!found);
        self.latencies.push(latency_ms);
    }

    /// `live: SOURCE: WxH 8-bit mono frames, N captured, M analysed, D dropped, F without
    /// pose; latency median A ms, max B ms; R frames/s analysed`.
    fn line(&mut self, label: &str, counts: &capture::Counts) -> String {
        self.latencies.sort_by(f64::total_cmp);
        let latency = match (self.latencies.first(), self.latencies.last()) {
            (Some(_), Some(max)) => format!(
                "latency median {:.1} ms, max {max:.1} ms",
                self.latencies[self.latencies.len() / 2]
            ),
            _ => "no latency (no frame analysed)".into(),
        };
        let seconds = self.start.elapsed().as_secs_f64();
        let rate = if seconds > 0.0 {
            self.analysed as f64 / seconds
        } else {
            0.0
        };
        let layout = self.layout.as_deref().unwrap_or("no");
        format!(
            "live: {label}: {layout} frames, {} captured, {} analysed, {} dropped (detector \
             slower than capture), {} without pose; {latency}; {rate:.1} frames/s analysed",
            counts.captured, self.analysed, counts.dropped, self.failed
        )
    }
}
