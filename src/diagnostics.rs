//! Counters and timings of the node, reported on `/diagnostics` about once a second over a
//! sliding window (so the level recovers after a burst of bad frames), and the throttle of
//! repeated warnings.

use crate::messages::{
    diagnostic_level, DiagnosticArray, DiagnosticStatus, Header, KeyValue, Time,
};
use std::collections::VecDeque;
use std::time::{Duration, Instant};

/// Length of the sliding window over which rates, times and problem counts are reported.
pub const WINDOW: Duration = Duration::from_secs(10);
/// No image for this long turns the status WARN (ERROR if none ever arrived).
pub const STALE_AFTER: Duration = Duration::from_secs(3);

/// What happened to one frame or message.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Event {
    /// A valid image message arrived.
    Received,
    /// A frame was processed and published: processing time and latency from arrival to
    /// published, milliseconds.
    Processed {
        /// Detection and publishing, ms.
        processing_ms: f64,
        /// From arrival in the receiver to published, ms (includes waiting for the worker).
        latency_ms: f64,
    },
    /// A frame was replaced by a newer one before the worker took it.
    Dropped,
    /// A frame was skipped by `max_rate`.
    RateLimited,
    /// An unusable message (bad encoding, size or length; undecodable CDR or compression).
    Bad,
    /// A processed frame held no marker.
    NotFound,
}

/// Counters since start, and the events of the last [`WINDOW`], from which the status is
/// judged: a burst of bad frames turns it WARN only while it is in the window.
#[derive(Clone, Debug)]
pub struct Stats {
    started: Instant,
    last_received: Option<Instant>,
    /// Events of the window, oldest first.
    events: VecDeque<(Instant, Event)>,
    /// Counts since start, in [`Event`] order.
    totals: [u64; 6],
    /// Last reason a message was rejected.
    pub last_bad_reason: String,
}

impl Stats {
    /// Empty statistics of a node started at `started`.
    pub fn new(started: Instant) -> Stats {
        Stats {
            started,
            last_received: None,
            events: VecDeque::new(),
            totals: [0; 6],
            last_bad_reason: String::new(),
        }
    }

    /// Records `event` at `now`.
    pub fn record(&mut self, now: Instant, event: Event) {
        if event == Event::Received {
            self.last_received = Some(now);
        }
        self.totals[index(&event)] += 1;
        self.events.push_back((now, event));
        self.forget_before(now);
    }

    /// Total count of events like `event` since start.
    pub fn total(&self, event: Event) -> u64 {
        self.totals[index(&event)]
    }

    fn forget_before(&mut self, now: Instant) {
        while let Some((t, _)) = self.events.front() {
            if now.duration_since(*t) <= WINDOW {
                break;
            }
            self.events.pop_front();
        }
    }

    /// The `/diagnostics` message at `now`, stamped `stamp` (the node's clock: `/clock` with
    /// `use_sim_time`), for the node `node_name` subscribed to `topic`.
    pub fn report(
        &mut self,
        now: Instant,
        stamp: Time,
        node_name: &str,
        topic: &str,
    ) -> DiagnosticArray {
        self.forget_before(now);
        let window = self.window_summary();
        let (level, message) = self.status(now, topic, &window);
        DiagnosticArray {
            header: Header {
                stamp,
                frame_id: String::new(),
            },
            status: vec![DiagnosticStatus {
                level,
                name: format!("{node_name}: marker detection"),
                message,
                hardware_id: String::new(),
                values: self.values(now, &window),
            }],
        }
    }

    /// Event counts and sorted timings of the current window.
    fn window_summary(&self) -> WindowSummary {
        let mut summary = WindowSummary {
            count: [0; 6],
            processing_ms: Vec::new(),
            latency_ms: Vec::new(),
        };
        for (_, e) in &self.events {
            summary.count[index(e)] += 1;
            if let Event::Processed {
                processing_ms,
                latency_ms,
            } = e
            {
                summary.processing_ms.push(*processing_ms);
                summary.latency_ms.push(*latency_ms);
            }
        }
        summary.processing_ms.sort_by(f64::total_cmp);
        summary.latency_ms.sort_by(f64::total_cmp);
        summary
    }

    /// The status level ([`diagnostic_level`]) and message at `now`: no image at all (ERROR)
    /// or for [`STALE_AFTER`], then bad messages, then dropped frames (WARN), in that order.
    fn status(&self, now: Instant, topic: &str, window: &WindowSummary) -> (u8, String) {
        let [_, _, dropped, _, bad, _] = window.count;
        match self.last_received {
            None if now.duration_since(self.started) >= STALE_AFTER => (
                diagnostic_level::ERROR,
                format!("no image received on {topic} since start"),
            ),
            Some(last) if now.duration_since(last) >= STALE_AFTER => (
                diagnostic_level::WARN,
                format!(
                    "no image on {topic} for {:.0} s",
                    now.duration_since(last).as_secs_f64()
                ),
            ),
            _ if bad > 0 => (
                diagnostic_level::WARN,
                format!(
                    "{bad} bad messages in the last {} s (last: {})",
                    WINDOW.as_secs(),
                    self.last_bad_reason
                ),
            ),
            _ if dropped > 0 => (
                diagnostic_level::WARN,
                format!(
                    "{dropped} frames dropped while busy in the last {} s",
                    WINDOW.as_secs()
                ),
            ),
            None => (
                diagnostic_level::OK,
                format!("waiting for images on {topic}"),
            ),
            Some(_) => (diagnostic_level::OK, "ok".to_string()),
        }
    }

    /// The key/values of the status at `now`: rates (Hz) and timing percentiles (ms) over the
    /// window, problem counts in the window, and counts since start.
    fn values(&self, now: Instant, window: &WindowSummary) -> Vec<KeyValue> {
        // Seconds the window covers (shorter just after start), never zero.
        let span = now
            .duration_since(self.started)
            .min(WINDOW)
            .as_secs_f64()
            .max(1e-3);
        let [received, processed, dropped, rate_limited, bad, not_found] = window.count;
        let (processing, latency) = (&window.processing_ms, &window.latency_ms);
        let kv = |key: &str, value: String| KeyValue {
            key: key.into(),
            value,
        };
        let total = |e: Event| self.total(e).to_string();
        vec![
            kv("window_s", format!("{span:.1}")),
            kv("rate_hz", format!("{:.2}", processed as f64 / span)),
            kv("input_rate_hz", format!("{:.2}", received as f64 / span)),
            kv("processing_ms_p50", format_ms(percentile(processing, 0.5))),
            kv("processing_ms_p99", format_ms(percentile(processing, 0.99))),
            kv("latency_ms_p50", format_ms(percentile(latency, 0.5))),
            kv("latency_ms_p99", format_ms(percentile(latency, 0.99))),
            kv("window_frames_dropped", dropped.to_string()),
            kv("window_frames_rate_limited", rate_limited.to_string()),
            kv("window_frames_without_marker", not_found.to_string()),
            kv("window_bad_messages", bad.to_string()),
            kv("frames_received", total(Event::Received)),
            kv("frames_processed", total(PROCESSED)),
            kv("frames_dropped", total(Event::Dropped)),
            kv("frames_rate_limited", total(Event::RateLimited)),
            kv("frames_without_marker", total(Event::NotFound)),
            kv("bad_messages", total(Event::Bad)),
        ]
    }
}

/// The events of the window: counts in [`Event`] order, and the processed frames' timings,
/// sorted.
struct WindowSummary {
    count: [u64; 6],
    /// Processing times, ms, ascending.
    processing_ms: Vec<f64>,
    /// Latencies from arrival to published, ms, ascending.
    latency_ms: Vec<f64>,
}

/// Any processed event (for [`Stats::total`]).
pub const PROCESSED: Event = Event::Processed {
    processing_ms: 0.0,
    latency_ms: 0.0,
};

fn index(event: &Event) -> usize {
    match event {
        Event::Received => 0,
        Event::Processed { .. } => 1,
        Event::Dropped => 2,
        Event::RateLimited => 3,
        Event::Bad => 4,
        Event::NotFound => 5,
    }
}

fn format_ms(v: Option<f64>) -> String {
    v.map(|v| format!("{v:.3}")).unwrap_or_else(|| "nan".into())
}

/// Nearest-rank percentile `q ∈ [0, 1]` of sorted values; `None` when empty.
pub fn percentile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    sorted.get(rank.clamp(1, sorted.len()) - 1).copied()
}

/// Lets a warning through at most once per `period`, counting the ones held back.
#[derive(Debug)]
pub struct Throttle {
    period: Duration,
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    /// A throttle passing one warning per `period`.
    pub fn new(period: Duration) -> Self {
        Throttle {
            period,
            last: None,
            suppressed: 0,
        }
    }

    /// `Some(number held back since the last one)` when a warning may be logged at `now`.
    pub fn allow(&mut self, now: Instant) -> Option<u64> {
        match self.last {
            Some(last) if now.duration_since(last) < self.period => {
                self.suppressed += 1;
                None
            }
            _ => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(report: &DiagnosticArray, key: &str) -> String {
        report.status[0]
            .values
            .iter()
            .find(|kv| kv.key == key)
            .map(|kv| kv.value.clone())
            .unwrap_or_default()
    }

    #[test]
    fn percentiles_and_report() {
        assert_eq!(percentile(&[], 0.5), None);
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), Some(50.0));
        assert_eq!(percentile(&v, 0.99), Some(99.0));
        assert_eq!(percentile(&v, 1.0), Some(100.0));
        let t0 = Instant::now();
        let mut stats = Stats::new(t0);
        for ms in [1.0, 2.0, 3.0, 4.0] {
            stats.record(t0, Event::Received);
            stats.record(
                t0,
                Event::Processed {
                    processing_ms: ms,
                    latency_ms: ms + 1.0,
                },
            );
        }
        stats.record(t0, Event::Bad);
        stats.last_bad_reason = "unknown encoding `x`".into();
        let report = stats.report(t0 + Duration::from_secs(2), Time::default(), "/v", "/image");
        assert_eq!(report.status[0].level, diagnostic_level::WARN);
        assert_eq!(value(&report, "rate_hz"), "2.00");
        assert_eq!(value(&report, "processing_ms_p50"), "2.000");
        assert_eq!(value(&report, "processing_ms_p99"), "4.000");
        assert_eq!(value(&report, "latency_ms_p99"), "5.000");
        assert_eq!(value(&report, "bad_messages"), "1");
    }

    #[test]
    fn the_level_recovers_after_a_burst_and_goes_stale_without_images() {
        let t0 = Instant::now();
        let mut stats = Stats::new(t0);
        let at = |s: f64| t0 + Duration::from_secs_f64(s);
        // Nothing yet: OK while starting, ERROR once STALE_AFTER has passed.
        let level = |stats: &mut Stats, s: f64| {
            stats.report(at(s), Time::default(), "/v", "/image").status[0].level
        };
        assert_eq!(level(&mut stats, 1.0), diagnostic_level::OK);
        assert_eq!(level(&mut stats, 3.5), diagnostic_level::ERROR);
        // A burst of bad frames at 4 s among good frames at 10 Hz until 30 s.
        let frames = |stats: &mut Stats, tenths: std::ops::Range<u32>| {
            for i in tenths {
                let t = at(f64::from(i) / 10.0);
                stats.record(t, Event::Received);
                if (40..50).contains(&i) {
                    stats.record(t, Event::Bad);
                }
            }
        };
        frames(&mut stats, 40..100);
        assert_eq!(level(&mut stats, 10.0), diagnostic_level::WARN);
        frames(&mut stats, 100..300);
        assert_eq!(level(&mut stats, 30.0), diagnostic_level::OK);
        let report = stats.report(at(30.0), Time::default(), "/v", "/image");
        assert_eq!(value(&report, "window_bad_messages"), "0");
        assert_eq!(value(&report, "bad_messages"), "10");
        // The camera stops: WARN after STALE_AFTER.
        assert_eq!(level(&mut stats, 31.0), diagnostic_level::OK);
        assert_eq!(level(&mut stats, 33.5), diagnostic_level::WARN);
    }

    #[test]
    fn throttle_counts_suppressed_warnings() {
        let mut t = Throttle::new(Duration::from_secs(5));
        let t0 = Instant::now();
        assert_eq!(t.allow(t0), Some(0));
        assert_eq!(t.allow(t0 + Duration::from_secs(1)), None);
        assert_eq!(t.allow(t0 + Duration::from_secs(2)), None);
        assert_eq!(t.allow(t0 + Duration::from_secs(6)), Some(2));
    }
}
