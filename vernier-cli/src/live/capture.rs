//! Frame capture for `vernier live`: a thread reads frames with OpenCV's `VideoCapture` into
//! a one-slot mailbox that the detection thread empties. A live source's newer frame replaces
//! a waiting one (counted as dropped); a file waits until the slot is free.

use std::fmt;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use opencv::core::Mat;
use opencv::prelude::*;
use opencv::videoio::{self, VideoCapture};

/// How often waiting threads look at the stop flag (Ctrl-C), ms.
const POLL_MS: u64 = 50;
/// How long the end of a run waits for the capture thread to let go of the device, ms (a
/// camera read can block for seconds; the process exits anyway).
const RELEASE_WAIT_MS: u64 = 2000;

/// Where frames come from.
#[derive(Clone, Debug)]
pub enum Source {
    /// Camera index for OpenCV's default backend.
    Camera(u32),
    /// V4L2 device file.
    Device(PathBuf),
    /// GStreamer pipeline ending in `appsink`.
    Gstreamer(String),
    /// Video file.
    Video(PathBuf),
}

impl fmt::Display for Source {
    /// The `source` column of the pose table.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Source::Camera(index) => write!(f, "camera {index}"),
            Source::Device(path) | Source::Video(path) => write!(f, "{}", path.display()),
            Source::Gstreamer(_) => write!(f, "gstreamer"),
        }
    }
}

impl Source {
    /// Opens the source; the error says which source failed and why.
    fn open(&self) -> Result<VideoCapture, String> {
        let opened = match self {
            Source::Camera(index) => {
                let index = i32::try_from(*index)
                    .map_err(|_| format!("--camera {index} is not a camera index"))?;
                VideoCapture::new(index, videoio::CAP_ANY)
            }
            Source::Device(path) => {
                existing(path, "no such device")?;
                VideoCapture::from_file(path, videoio::CAP_V4L2)
            }
            Source::Gstreamer(pipeline) => {
                VideoCapture::from_file(pipeline, videoio::CAP_GSTREAMER)
            }
            // FFmpeg only: the other backends' attempts print GStreamer's own diagnostics.
            Source::Video(path) => {
                existing(path, "no such file")?;
                VideoCapture::from_file(path, videoio::CAP_FFMPEG)
            }
        };
        let hint = if std::env::var_os("OPENCV_LOG_LEVEL").is_none() {
            " (OPENCV_LOG_LEVEL=WARNING shows OpenCV's reasons)"
        } else {
            ""
        };
        let capture =
            opened.map_err(|e| format!("cannot open {}: {}{hint}", self.describe(), e.message))?;
        if !capture.is_opened().unwrap_or(false) {
            return Err(format!("cannot open {}{hint}", self.describe()));
        }
        Ok(capture)
    }

    /// The source in error messages.
    fn describe(&self) -> String {
        match self {
            Source::Camera(index) => format!("camera {index}"),
            Source::Device(path) => format!("device {}", path.display()),
            Source::Gstreamer(pipeline) => format!("GStreamer pipeline `{pipeline}`"),
            Source::Video(path) => format!("video {}", path.display()),
        }
    }

    /// Live sources never end by themselves: their end is a lost stream.
    fn is_live(&self) -> bool {
        !matches!(self, Source::Video(_))
    }
}

/// Error unless `path` exists (OpenCV's own message for a missing file is vague).
fn existing(path: &std::path::Path, missing: &str) -> Result<(), String> {
    if path.exists() {
        Ok(())
    } else {
        Err(format!("{}: {missing}", path.display()))
    }
}

/// OpenCV logs its warnings (a camera that cannot be opened, backend fallbacks) on stderr;
/// errors are reported by vernier instead, on one line. `OPENCV_LOG_LEVEL` still wins.
pub fn quiet_opencv_logging() {
    if std::env::var_os("OPENCV_LOG_LEVEL").is_none() {
        // Only fails for an unknown level; the logging then stays as it was.
        let _ = opencv::core::set_log_level(opencv::core::LogLevel::LOG_LEVEL_SILENT);
    }
}

/// How the capture thread hands frames over.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Pace {
    /// As fast as the source delivers; a newer frame replaces one still waiting.
    LatestWins,
    /// Wait until the detector took the previous frame (files: every frame analysed).
    EveryFrame,
    /// A file read at its own frame rate, frames replaced like [`Pace::LatestWins`].
    FileRate,
}

/// One captured frame.
pub struct Frame {
    /// Index of the frame in the stream, from 0 (dropped frames included).
    pub index: u64,
    /// The frame as OpenCV delivered it.
    pub mat: Mat,
    /// Capture time, s since the Unix epoch.
    pub stamp: f64,
    /// Capture time, for the latency.
    pub captured: Instant,
}

/// What the detection thread gets next.
pub enum Next {
    /// The latest frame.
    Frame(Frame),
    /// The run is over: `Ok` at the end of a file or on Ctrl-C, `Err` for a lost stream.
    End(Result<(), String>),
}

/// Frame counts of a run.
#[derive(Clone, Copy, Debug, Default)]
pub struct Counts {
    /// Frames read from the source.
    pub captured: u64,
    /// Frames replaced in the mailbox before the detector took them.
    pub dropped: u64,
}

/// The mailbox's content, behind its mutex.
#[derive(Default)]
struct Slot {
    frame: Option<Frame>,
    /// Set by the capture thread when it stops.
    end: Option<Result<(), String>>,
    counts: Counts,
    /// The capture thread has released the source.
    released: bool,
}

/// One-slot mailbox between the capture thread and the detection thread.
#[derive(Default)]
struct Mailbox {
    slot: Mutex<Slot>,
    changed: Condvar,
}

impl Mailbox {
    /// The slot (a panicked peer leaves plain data behind: still usable).
    fn lock(&self) -> MutexGuard<'_, Slot> {
        self.slot.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Waits for a change of the slot, at most [`POLL_MS`].
    fn wait<'a>(&self, guard: MutexGuard<'a, Slot>) -> MutexGuard<'a, Slot> {
        self.changed
            .wait_timeout(guard, Duration::from_millis(POLL_MS))
            .map(|(guard, _)| guard)
            .unwrap_or_else(|e| e.into_inner().0)
    }

    /// Puts a frame in the slot, replacing (dropping) one not yet taken.
    fn put(&self, frame: Frame) {
        let mut slot = self.lock();
        slot.counts.captured += 1;
        if slot.frame.replace(frame).is_some() {
            slot.counts.dropped += 1;
        }
        self.changed.notify_all();
    }

    /// Records the end of the stream.
    fn close(&self, end: Result<(), String>) {
        let mut slot = self.lock();
        slot.end.get_or_insert(end);
        self.changed.notify_all();
    }
}

/// A running capture thread and its mailbox.
pub struct Stream {
    mailbox: Arc<Mailbox>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Stream {
    /// Opens `source` (in the capture thread, which owns it) and starts reading. Fails with
    /// the source's error when it cannot be opened. `raw` asks for the camera's own pixel
    /// format; `stop` ends the run (Ctrl-C).
    pub fn start(
        source: Source,
        pace: Pace,
        raw: bool,
        stop: Arc<AtomicBool>,
    ) -> Result<Stream, String> {
        let mailbox = Arc::new(Mailbox::default());
        let (opened_tx, opened_rx) = std::sync::mpsc::channel();
        let reader = Reader {
            source,
            pace,
            raw,
            mailbox: mailbox.clone(),
            stop: stop.clone(),
        };
        let thread = std::thread::Builder::new()
            .name("vernier-capture".into())
            .spawn(move || reader.run(&opened_tx))
            .map_err(|e| format!("cannot start the capture thread: {e}"))?;
        match opened_rx.recv() {
            Ok(Ok(())) => Ok(Stream {
                mailbox,
                stop,
                thread: Some(thread),
            }),
            Ok(Err(message)) => Err(message),
            Err(_) => Err("the capture thread stopped before opening the source".into()),
        }
    }

    /// The next frame (the latest one for live sources), or the end of the run.
    pub fn next(&self) -> Next {
        let mut slot = self.mailbox.lock();
        loop {
            if let Some(frame) = slot.frame.take() {
                self.mailbox.changed.notify_all();
                return Next::Frame(frame);
            }
            if let Some(end) = slot.end.take() {
                return Next::End(end);
            }
            if self.stop.load(Ordering::SeqCst) {
                return Next::End(Ok(()));
            }
            slot = self.mailbox.wait(slot);
        }
    }

    /// Stops the capture thread (waiting a little for it to release the source) and returns
    /// the run's counts.
    pub fn finish(mut self) -> Counts {
        self.stop.store(true, Ordering::SeqCst);
        let deadline = Instant::now() + Duration::from_millis(RELEASE_WAIT_MS);
        let mut slot = self.mailbox.lock();
        while !slot.released && Instant::now() < deadline {
            slot = self.mailbox.wait(slot);
        }
        let (counts, released) = (slot.counts, slot.released);
        drop(slot);
        if released {
            if let Some(thread) = self.thread.take() {
                // The thread has returned from its work: joining cannot block.
                let _ = thread.join();
            }
        }
        counts
    }
}

/// The capture thread's state.
struct Reader {
    source: Source,
    pace: Pace,
    raw: bool,
    mailbox: Arc<Mailbox>,
    stop: Arc<AtomicBool>,
}

impl Reader {
    /// Opens the source, says so on `opened`, then reads until the end, an error or stop.
    fn run(self, opened: &std::sync::mpsc::Sender<Result<(), String>>) {
        let capture = self.source.open().and_then(|mut capture| {
            self.configure(&mut capture)?;
            Ok(capture)
        });
        let capture = match capture {
            Ok(capture) => {
                let _ = opened.send(Ok(()));
                capture
            }
            Err(message) => {
                let _ = opened.send(Err(message));
                return;
            }
        };
        let end = self.read_all(capture);
        self.mailbox.close(end);
        self.mailbox.lock().released = true;
        self.mailbox.changed.notify_all();
    }

    /// `--raw`: the backend's own pixel format instead of 8-bit BGR.
    fn configure(&self, capture: &mut VideoCapture) -> Result<(), String> {
        if self.raw
            && !capture
                .set(videoio::CAP_PROP_CONVERT_RGB, 0.0)
                .unwrap_or(false)
        {
            return Err(format!(
                "--raw: {} cannot deliver frames in their own pixel format",
                self.source.describe()
            ));
        }
        Ok(())
    }

    /// The frame interval for [`Pace::FileRate`] (the file's frame rate).
    fn interval(&self, capture: &VideoCapture) -> Result<Option<Duration>, String> {
        if self.pace != Pace::FileRate {
            return Ok(None);
        }
        let fps = capture.get(videoio::CAP_PROP_FPS).unwrap_or(0.0);
        if !(fps.is_finite() && fps > 0.0) {
            return Err(format!(
                "--realtime: {} does not give its frame rate",
                self.source.describe()
            ));
        }
        Ok(Some(Duration::from_secs_f64(1.0 / fps)))
    }

    /// Reads frames into the mailbox. `Ok` at the end of a file or on stop; a live source
    /// that stops delivering is an error.
    fn read_all(&self, mut capture: VideoCapture) -> Result<(), String> {
        let interval = self.interval(&capture)?;
        let start = Instant::now();
        let mut index: u64 = 0;
        while !self.stop.load(Ordering::SeqCst) {
            if self.pace == Pace::EveryFrame && !self.wait_for_free_slot() {
                break;
            }
            if let Some(interval) = interval {
                let due = start + interval.mul_f64(index as f64);
                std::thread::sleep(due.saturating_duration_since(Instant::now()));
            }
            let mut mat = Mat::default();
            let read = capture
                .read(&mut mat)
                .map_err(|e| format!("{}: frame {index}: {}", self.source.describe(), e.message))?;
            if !read || mat.empty() {
                return self.ended(index);
            }
            self.check_size(&capture, &mat)?;
            self.mailbox.put(Frame {
                index,
                mat,
                stamp: SystemTime::now()
                    .duration_since(UNIX_EPOCH)
                    .map_or(0.0, |d| d.as_secs_f64()),
                captured: Instant::now(),
            });
            index += 1;
        }
        Ok(())
    }

    /// Waits until the detector took the previous frame; false when stopped meanwhile.
    fn wait_for_free_slot(&self) -> bool {
        let mut slot = self.mailbox.lock();
        while slot.frame.is_some() {
            if self.stop.load(Ordering::SeqCst) {
                return false;
            }
            slot = self.mailbox.wait(slot);
        }
        true
    }

    /// The end of the frames: normal for a file (or on stop), a lost stream for a live source.
    fn ended(&self, frames: u64) -> Result<(), String> {
        if !self.source.is_live() || self.stop.load(Ordering::SeqCst) {
            return Ok(());
        }
        Err(format!(
            "lost the stream of {}: it stopped delivering frames after {frames}",
            self.source.describe()
        ))
    }

    /// With `--raw`, a frame whose size is not the stream's is raw data in a layout vernier
    /// cannot read (compressed, planar YUV).
    fn check_size(&self, capture: &VideoCapture, mat: &Mat) -> Result<(), String> {
        if !self.raw {
            return Ok(());
        }
        let width = capture.get(videoio::CAP_PROP_FRAME_WIDTH).unwrap_or(0.0);
        let height = capture.get(videoio::CAP_PROP_FRAME_HEIGHT).unwrap_or(0.0);
        let expected = (width as i32, height as i32);
        if width > 0.0 && height > 0.0 && (mat.cols(), mat.rows()) != expected {
            return Err(format!(
                "--raw: {} delivers {}x{} buffers for {}x{} frames (compressed or planar \
                 data vernier cannot read; run without --raw)",
                self.source.describe(),
                mat.cols(),
                mat.rows(),
                expected.0,
                expected.1
            ));
        }
        Ok(())
    }
}
