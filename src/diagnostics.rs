//! Counters and timings of the node, reported on `/diagnostics` about once a second, and
//! the throttle of repeated warnings.

use crate::messages::{
    diagnostic_level, DiagnosticArray, DiagnosticStatus, Header, KeyValue, Time,
};
use std::time::{Duration, Instant};

/// Counters since start, plus the processing times of the current reporting window.
#[derive(Clone, Debug, Default)]
pub struct Stats {
    /// Valid image messages received.
    pub received: u64,
    /// Frames processed (an output was published).
    pub processed: u64,
    /// Frames replaced by a newer one before the worker took them.
    pub dropped: u64,
    /// Frames skipped by the `max_rate` limit.
    pub rate_limited: u64,
    /// Unusable messages (bad encoding, size or length; undecodable CDR).
    pub bad_messages: u64,
    /// Processed frames in which no marker was found.
    pub not_found: u64,
    /// Last reason a message was rejected.
    pub last_bad_reason: String,
    /// Processing times of the current window, milliseconds.
    window_ms: Vec<f64>,
    /// `processed` at the start of the current window.
    window_start_processed: u64,
}

impl Stats {
    /// Records one processed frame that took `elapsed`.
    pub fn record_processing(&mut self, elapsed: Duration) {
        self.processed += 1;
        self.window_ms.push(elapsed.as_secs_f64() * 1e3);
    }

    /// Builds the `/diagnostics` message for the window that lasted `window` and starts a new
    /// window.
    pub fn report(&mut self, node_name: &str, window: Duration) -> DiagnosticArray {
        let frames = self.processed - self.window_start_processed;
        let rate = frames as f64 / window.as_secs_f64().max(1e-9);
        let mut times = std::mem::take(&mut self.window_ms);
        times.sort_by(f64::total_cmp);
        let p50 = percentile(&times, 0.5);
        let p99 = percentile(&times, 0.99);
        self.window_start_processed = self.processed;
        let level = if self.bad_messages > 0 || self.dropped > 0 {
            diagnostic_level::WARN
        } else {
            diagnostic_level::OK
        };
        let message = if self.bad_messages > 0 {
            format!(
                "{} bad messages (last: {})",
                self.bad_messages, self.last_bad_reason
            )
        } else if self.dropped > 0 {
            format!("{} frames dropped while busy", self.dropped)
        } else {
            "ok".to_string()
        };
        let kv = |key: &str, value: String| KeyValue {
            key: key.into(),
            value,
        };
        DiagnosticArray {
            header: Header {
                stamp: Time::now(),
                frame_id: String::new(),
            },
            status: vec![DiagnosticStatus {
                level,
                name: format!("{node_name}: marker detection"),
                message,
                hardware_id: String::new(),
                values: vec![
                    kv("rate_hz", format!("{rate:.2}")),
                    kv("processing_ms_p50", format_ms(p50)),
                    kv("processing_ms_p99", format_ms(p99)),
                    kv("frames_received", self.received.to_string()),
                    kv("frames_processed", self.processed.to_string()),
                    kv("frames_dropped", self.dropped.to_string()),
                    kv("frames_rate_limited", self.rate_limited.to_string()),
                    kv("frames_without_marker", self.not_found.to_string()),
                    kv("bad_messages", self.bad_messages.to_string()),
                ],
            }],
        }
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

    #[test]
    fn percentiles_and_report() {
        assert_eq!(percentile(&[], 0.5), None);
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), Some(50.0));
        assert_eq!(percentile(&v, 0.99), Some(99.0));
        assert_eq!(percentile(&v, 1.0), Some(100.0));
        let mut stats = Stats::default();
        for ms in [1, 2, 3, 4] {
            stats.record_processing(Duration::from_millis(ms));
        }
        stats.bad_messages = 2;
        stats.last_bad_reason = "unknown encoding `x`".into();
        let report = stats.report("/vernier", Duration::from_secs(2));
        let status = &report.status[0];
        assert_eq!(status.level, diagnostic_level::WARN);
        let get = |k: &str| {
            status
                .values
                .iter()
                .find(|kv| kv.key == k)
                .map(|kv| kv.value.clone())
                .unwrap_or_default()
        };
        assert_eq!(get("rate_hz"), "2.00");
        assert_eq!(get("processing_ms_p50"), "2.000");
        assert_eq!(get("processing_ms_p99"), "4.000");
        assert_eq!(get("bad_messages"), "2");
        // The next window starts empty.
        let next = stats.report("/vernier", Duration::from_secs(1));
        assert!(next.status[0]
            .values
            .iter()
            .any(|kv| kv.key == "rate_hz" && kv.value == "0.00"));
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
