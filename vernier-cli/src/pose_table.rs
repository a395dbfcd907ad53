//! Pose time series as written by `vernier detect` and `vernier bag` and read by
//! `vernier plot`: one row per frame and marker, as CSV or JSON Lines with the same columns.
//!
//! Columns: `frame` (0-based index in the run), `stamp` (acquisition time, s since the Unix
//! epoch: the ROS header stamp, or the image file's modification time), `source` (image
//! file or bag topic), `id`, pose `x, y, z` (pattern units, µm), `alpha, beta, gamma` (rad),
//! `pixel_size` (pattern units per pixel), `x_px, y_px` (pattern origin in the image, px),
//! `quality`, `duplicate_id`, `decode_confidence` (coarse decoding, 0–1, empty for periodic
//! grids), `time_ms` (processing time of the frame), `error`. A frame
//! without marker or whose detection failed has one row with empty marker columns.

use std::io::Write;

use serde::{Deserialize, Serialize};
use vernier::MarkerPose;

/// One marker in one frame (or one frame without marker).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseRow {
    /// Index of the frame in the run, from 0.
    pub frame: u64,
    /// Acquisition time, seconds since the Unix epoch, when known.
    pub stamp: Option<f64>,
    /// Image file or bag topic.
    pub source: String,
    /// Marker ID (0 for markers without ID); `None` when the frame has no marker.
    pub id: Option<u64>,
    /// Position x of the pattern origin in the camera frame, pattern units.
    pub x: Option<f64>,
    /// Position y, pattern units.
    pub y: Option<f64>,
    /// Position z (0 for planar poses), pattern units.
    pub z: Option<f64>,
    /// In-plane angle, rad.
    pub alpha: Option<f64>,
    /// Out-of-plane angle about y, rad.
    pub beta: Option<f64>,
    /// Out-of-plane angle about x, rad.
    pub gamma: Option<f64>,
    /// Pattern units per pixel.
    pub pixel_size: Option<f64>,
    /// Pattern origin in the image, column, pixels.
    pub x_px: Option<f64>,
    /// Pattern origin in the image, row, pixels.
    pub y_px: Option<f64>,
    /// Detection quality (0–1).
    pub quality: Option<f64>,
    /// True when another marker of the frame has the same ID.
    pub duplicate_id: Option<bool>,
    /// Confidence of the coarse decoding (HP code ID, stamp bitmap, Megarena code), `[0, 1]`;
    /// empty for periodic grids.
    pub decode_confidence: Option<f64>,
    /// Processing time of the frame, ms.
    pub time_ms: f64,
    /// Why the frame failed, if it did.
    pub error: Option<String>,
    /// Strength of the perspective cue that chose the sign of `beta`, `gamma` (0–1), for
    /// poses with out-of-plane angles (`detect --pose-3d`); JSON and JSON Lines only (not a
    /// CSV column), omitted for planar poses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pose_3d_cue_strength: Option<f64>,
    /// The marker's own measured scale, pattern units per pixel (`pixel_size` is the
    /// calibrated one under `--pixel-size`), and its σ; JSON and JSON Lines only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub measured_pixel_size: Option<f64>,
    /// Standard deviation of `measured_pixel_size`, pattern units per pixel.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_size_std: Option<f64>,
    /// Predicted standard deviations of `x`, `y` (pattern units) and `alpha` (rad), from
    /// the image's white noise through the fit (docs/design/phase.md#uncertainty; see
    /// [`predicted_std`]); JSON and JSON Lines only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_std: Option<f64>,
    /// See [`PoseRow::x_std`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_std: Option<f64>,
    /// See [`PoseRow::x_std`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alpha_std: Option<f64>,
    /// Predicted standard deviations of `beta`, `gamma` (rad) and of the marker origin's
    /// depth (the camera-frame translation's z, pattern units; with `--focal-length-px`),
    /// for poses with out-of-plane angles ([`tilt_std`]); JSON and JSON Lines only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub beta_std: Option<f64>,
    /// See [`PoseRow::beta_std`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gamma_std: Option<f64>,
    /// See [`PoseRow::beta_std`].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_std: Option<f64>,
}

/// Column names, in order.
pub const COLUMNS: [&str; 18] = [
    "frame",
    "stamp",
    "source",
    "id",
    "x",
    "y",
    "z",
    "alpha",
    "beta",
    "gamma",
    "pixel_size",
    "x_px",
    "y_px",
    "quality",
    "duplicate_id",
    "decode_confidence",
    "time_ms",
    "error",
];

impl PoseRow {
    /// The rows of one frame: one per marker, or one empty row (with the error, if any).
    /// `period`: the pattern's period (pattern units), for the predicted σ columns.
    pub fn from_result(
        frame: u64,
        stamp: Option<f64>,
        source: &str,
        result: &Result<Vec<MarkerPose>, String>,
        time_ms: f64,
        period: f64,
    ) -> Vec<PoseRow> {
        let base = PoseRow {
            frame,
            stamp,
            source: source.to_string(),
            time_ms,
            ..PoseRow::default()
        };
        match result {
            Ok(markers) if !markers.is_empty() => markers
                .iter()
                .map(|m| {
                    let p = &m.pose;
                    let [x_std, y_std, alpha_std] =
                        predicted_std(m, period).map(|s| Some(s).filter(|s| s.is_finite()));
                    let [beta_std, gamma_std, z_std] = tilt_std(m, period);
                    PoseRow {
                        id: Some(m.id),
                        x: Some(p.x),
                        y: Some(p.y),
                        z: Some(p.z),
                        alpha: Some(p.alpha),
                        beta: Some(p.beta),
                        gamma: Some(p.gamma),
                        pixel_size: Some(p.pixel_size),
                        x_px: Some(m.origin_px.x),
                        y_px: Some(m.origin_px.y),
                        quality: Some(m.quality),
                        duplicate_id: Some(m.duplicate_id),
                        decode_confidence: m.decode_confidence,
                        pose_3d_cue_strength: m.pose_3d_cue_strength,
                        measured_pixel_size: Some(m.measured_pixel_size),
                        pixel_size_std: Some(m.pixel_size_std),
                        x_std,
                        y_std,
                        alpha_std,
                        beta_std,
                        gamma_std,
                        z_std,
                        ..base.clone()
                    }
                })
                .collect(),
            Ok(_) => vec![base],
            Err(e) => vec![PoseRow {
                error: Some(e.clone()),
                ..base
            }],
        }
    }

    /// The CSV fields, in [`COLUMNS`] order.
    fn csv_fields(&self) -> [String; 18] {
        let f = |v: Option<f64>| v.map(|v| v.to_string()).unwrap_or_default();
        [
            self.frame.to_string(),
            f(self.stamp),
            csv_escape(&self.source),
            self.id.map(|v| v.to_string()).unwrap_or_default(),
            f(self.x),
            f(self.y),
            f(self.z),
            f(self.alpha),
            f(self.beta),
            f(self.gamma),
            f(self.pixel_size),
            f(self.x_px),
            f(self.y_px),
            f(self.quality),
            self.duplicate_id.map(|v| v.to_string()).unwrap_or_default(),
            f(self.decode_confidence),
            format!("{:.3}", self.time_ms),
            csv_escape(self.error.as_deref().unwrap_or("")),
        ]
    }
}

/// The σ of a marker's printed `x`, `y` (pattern units) and `alpha` (rad). `x`, `y` are the
/// pattern-frame coordinates `p = Rz(−α)·t` of the camera-frame translation `t` of
/// [`MarkerPose::covariance`], whose block turned back to the pattern axes holds the phase
/// offsets' σ and the measured scale's; an orientation error `δα` also turns `p` by
/// `(y·δα, −x·δα)`, independently (slope noise moves a phase gradient's direction and length
/// apart). A marker 620 µm from the image centre with `σ_α` = 10 µrad and a relative scale σ
/// of 1e-5 gets 6e-3 µm from each, four times its offsets' 1.5e-3 µm (`Image96`–`Image125`).
pub fn predicted_std(m: &MarkerPose, period: f64) -> [f64; 3] {
    let cov = m.covariance(period, m.window_px as f64);
    let alpha = cov[5][5].sqrt();
    let (s, c) = m.pose.alpha.sin_cos();
    // uᵀ·Σ·u for the pattern axis u (camera frame) of the position block Σ.
    let along = |u: [f64; 2]| {
        u[0] * u[0] * cov[0][0] + 2.0 * u[0] * u[1] * cov[0][1] + u[1] * u[1] * cov[1][1]
    };
    let (x, y) = (m.pose.x, m.pose.y);
    [
        (along([c, s]) + (alpha * y).powi(2)).sqrt(),
        (along([-s, c]) + (alpha * x).powi(2)).sqrt(),
        alpha,
    ]
}

/// Predicted standard deviations of `beta`, `gamma` (rad) and of the marker origin's depth
/// (pattern units) from [`MarkerPose::covariance`]'s pitch, roll and translation-z entries:
/// `None` for planar poses and for a depth the model leaves unobserved (no focal length).
pub fn tilt_std(m: &MarkerPose, period: f64) -> [Option<f64>; 3] {
    if m.pose_3d_cue_strength.is_none() {
        return [None; 3];
    }
    let cov = m.covariance(period, m.window_px as f64);
    let observed = |v: f64| (v.is_finite() && v < 1e6).then(|| v.max(0.0).sqrt());
    [
        observed(cov[4][4]),
        observed(cov[3][3]),
        observed(cov[2][2]),
    ]
}

/// Quotes a CSV field when it holds a comma, quote or line break.
fn csv_escape(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// Output format of a pose table.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TableFormat {
    /// One JSON object per image: `image`, `markers` (each with `id`, `x`, `y`, `z`, `alpha`,
    /// `beta`, `gamma`, `pixel_size`, `x_px`, `y_px`, `quality`, `duplicate_id`,
    /// `decode_confidence`, `measured_pixel_size`, `pixel_size_std`, the predicted σ
    /// `x_std`, `y_std`, `alpha_std`, and `pose_3d_cue_strength` with `--pose-3d`), `time_ms`
    /// and, for a failed image, `error`.
    Json,
    /// Comma-separated values with a header line, one row per image and marker.
    Csv,
    /// JSON Lines: one JSON object per image and marker, the CSV's columns and the JSON's
    /// extra fields (`measured_pixel_size`, `pixel_size_std`, `x_std`, `y_std`, `alpha_std`).
    Jsonl,
}

/// Writes rows to a stream (header first for CSV).
pub struct TableWriter<W: Write> {
    out: W,
    format: TableFormat,
}

impl<W: Write> TableWriter<W> {
    /// Starts a table (writes the CSV header).
    pub fn new(mut out: W, format: TableFormat) -> std::io::Result<Self> {
        if format == TableFormat::Csv {
            writeln!(out, "{}", COLUMNS.join(","))?;
        }
        Ok(TableWriter { out, format })
    }

    /// Appends the rows of one frame.
    pub fn write(&mut self, rows: &[PoseRow]) -> std::io::Result<()> {
        if self.format == TableFormat::Json {
            return self.write_image_object(rows);
        }
        for row in rows {
            match self.format {
                TableFormat::Csv => writeln!(self.out, "{}", row.csv_fields().join(","))?,
                TableFormat::Jsonl => {
                    serde_json::to_writer(&mut self.out, row)?;
                    writeln!(self.out)?;
                }
                TableFormat::Json => {}
            }
        }
        Ok(())
    }

    /// One JSON object for the frame whose rows are `rows` (all from the same image).
    fn write_image_object(&mut self, rows: &[PoseRow]) -> std::io::Result<()> {
        let Some(first) = rows.first() else {
            return Ok(());
        };
        let markers: Vec<serde_json::Value> = rows
            .iter()
            .filter(|r| r.id.is_some())
            .map(|r| {
                let mut m = serde_json::json!({
                    "id": r.id, "x": r.x, "y": r.y, "z": r.z,
                    "alpha": r.alpha, "beta": r.beta, "gamma": r.gamma,
                    "pixel_size": r.pixel_size, "x_px": r.x_px, "y_px": r.y_px,
                    "quality": r.quality, "duplicate_id": r.duplicate_id,
                    "decode_confidence": r.decode_confidence,
                });
                // Only poses with out-of-plane angles have a cue strength.
                if let Some(cue) = r.pose_3d_cue_strength {
                    m["pose_3d_cue_strength"] = serde_json::json!(cue);
                }
                if let (Some(s), Some(std)) = (r.measured_pixel_size, r.pixel_size_std) {
                    m["measured_pixel_size"] = serde_json::json!(s);
                    m["pixel_size_std"] = serde_json::json!(std);
                }
                for (key, std) in [
                    ("x_std", r.x_std),
                    ("y_std", r.y_std),
                    ("alpha_std", r.alpha_std),
                    ("beta_std", r.beta_std),
                    ("gamma_std", r.gamma_std),
                    ("z_std", r.z_std),
                ] {
                    if let Some(std) = std {
                        m[key] = serde_json::json!(std);
                    }
                }
                m
            })
            .collect();
        let mut object = serde_json::json!({
            "image": first.source,
            "markers": markers,
            "time_ms": first.time_ms,
        });
        if let Some(error) = &first.error {
            object["error"] = serde_json::Value::String(error.clone());
        }
        serde_json::to_writer(&mut self.out, &object)?;
        writeln!(self.out)
    }

    /// Flushes the stream.
    pub fn finish(mut self) -> std::io::Result<()> {
        self.out.flush()
    }
}

/// Splits one CSV line into fields (double-quoted fields may hold commas and `""`).
fn split_csv_line(line: &str) -> Vec<String> {
    let mut fields = Vec::new();
    let mut field = String::new();
    let mut quoted = false;
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match (c, quoted) {
            ('"', true) if chars.peek() == Some(&'"') => {
                field.push('"');
                chars.next();
            }
            ('"', _) => quoted = !quoted,
            (',', false) => fields.push(std::mem::take(&mut field)),
            _ => field.push(c),
        }
    }
    fields.push(field);
    fields
}

/// Reads the pose table file `path` ([`read_table`]); errors name the file.
pub fn read_table_file(path: &std::path::Path) -> Result<Vec<PoseRow>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    read_table(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Reads a pose table written by [`TableWriter`] (CSV when the first line is the header,
/// else JSON Lines). Unknown CSV columns are ignored; `frame` and `time_ms` may be missing.
pub fn read_table(text: &str) -> Result<Vec<PoseRow>, String> {
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, first)) = lines.next() else {
        return Ok(Vec::new());
    };
    if first.trim_start().starts_with('{') {
        return text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty())
            .map(|(i, l)| serde_json::from_str(l).map_err(|e| format!("line {}: {e}", i + 1)))
            .collect();
    }
    let header = split_csv_line(first);
    let column = |name: &str| header.iter().position(|h| h.trim() == name);
    let index: Vec<Option<usize>> = COLUMNS.iter().map(|c| column(c)).collect();
    if index[4].is_none() || index[5].is_none() {
        return Err(format!(
            "not a pose table: the header `{first}` has no `x` and `y` columns"
        ));
    }
    let mut rows = Vec::new();
    for (i, line) in lines {
        let fields = split_csv_line(line);
        let get = |k: usize| -> &str {
            index[k]
                .and_then(|j| fields.get(j))
                .map_or("", |s| s.as_str())
        };
        let number = |k: usize| -> Result<Option<f64>, String> {
            let s = get(k).trim();
            if s.is_empty() {
                return Ok(None);
            }
            s.parse::<f64>().map(Some).map_err(|_| {
                format!(
                    "line {}: column `{}`: `{s}` is not a number",
                    i + 1,
                    COLUMNS[k]
                )
            })
        };
        let text_field = |k: usize| Some(get(k).to_string()).filter(|s| !s.is_empty());
        rows.push(PoseRow {
            frame: number(0)?.map_or(rows.len() as u64, |v| v as u64),
            stamp: number(1)?,
            source: get(2).to_string(),
            id: number(3)?.map(|v| v as u64),
            x: number(4)?,
            y: number(5)?,
            z: number(6)?,
            alpha: number(7)?,
            beta: number(8)?,
            gamma: number(9)?,
            pixel_size: number(10)?,
            x_px: number(11)?,
            y_px: number(12)?,
            quality: number(13)?,
            duplicate_id: text_field(14).map(|s| s == "true"),
            decode_confidence: number(15)?,
            time_ms: number(16)?.unwrap_or(0.0),
            error: text_field(17),
            ..PoseRow::default()
        });
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Vec<PoseRow> {
        vec![
            PoseRow {
                frame: 0,
                stamp: Some(1.7e9 + 0.25),
                source: "a,b.png".into(),
                id: Some(3),
                x: Some(1.5),
                y: Some(-2.0),
                z: Some(0.0),
                alpha: Some(0.1),
                beta: Some(0.0),
                gamma: Some(0.0),
                pixel_size: Some(0.5),
                x_px: Some(10.25),
                y_px: Some(-3.0),
                quality: Some(0.9),
                duplicate_id: Some(false),
                decode_confidence: Some(0.75),
                time_ms: 12.5,
                error: None,
                ..PoseRow::default()
            },
            PoseRow {
                frame: 1,
                source: "c.png".into(),
                time_ms: 3.0,
                error: Some("no \"pattern\" found".into()),
                ..PoseRow::default()
            },
        ]
    }

    #[test]
    fn csv_and_jsonl_round_trip() {
        for format in [TableFormat::Csv, TableFormat::Jsonl] {
            let mut bytes = Vec::new();
            let mut w = TableWriter::new(&mut bytes, format).unwrap();
            w.write(&sample()).unwrap();
            w.finish().unwrap();
            let text = String::from_utf8(bytes).unwrap();
            assert_eq!(read_table(&text).unwrap(), sample(), "{format:?}:\n{text}");
        }
    }

    #[test]
    fn rows_carry_the_predicted_sigmas_of_the_covariance() {
        let (phase_std, period) = ([2e-3, 1e-3], 10.0);
        let marker = MarkerPose {
            id: 7,
            pose: vernier::Pose::planar(1.0, 2.0, 0.0, 0.5),
            origin_px: Default::default(),
            quality: 0.9,
            phase_std,
            duplicate_id: false,
            decode_confidence: Some(1.0),
            pose_3d_cue_strength: None,
            window_px: 256,
            yaw_std: Some(5e-6),
            measured_pixel_size: 0.5,
            pixel_size_std: 1e-6,
            slope_std: None,
            tilt_covariance: None,
        };
        let rows = PoseRow::from_result(0, None, "a.png", &Ok(vec![marker]), 1.0, period);
        let row = &rows[0];
        // Along the pattern axes σ = P·σ_c/2π; the orientation's σ times the other
        // coordinate (x = 1, y = 2) and the relative scale σ (1e-6 / 0.5) times the same one
        // add in quadrature.
        let tau = std::f64::consts::TAU;
        let along = phase_std.map(|s| period * s / tau);
        let (turn, stretch) = (5e-6, 2e-6);
        let x_std = along[0].hypot(turn * 2.0).hypot(stretch * 1.0);
        let y_std = along[1].hypot(turn * 1.0).hypot(stretch * 2.0);
        assert!((row.x_std.unwrap() - x_std).abs() < 1e-15);
        assert!((row.y_std.unwrap() - y_std).abs() < 1e-15);
        assert_eq!(row.alpha_std, Some(5e-6));
        for format in [TableFormat::Json, TableFormat::Jsonl] {
            let mut bytes = Vec::new();
            let mut w = TableWriter::new(&mut bytes, format).unwrap();
            w.write(&rows).unwrap();
            w.finish().unwrap();
            let text = String::from_utf8(bytes).unwrap();
            for key in ["\"x_std\"", "\"y_std\"", "\"alpha_std\""] {
                assert!(text.contains(key), "{format:?}: {text}");
            }
        }
    }

    #[test]
    fn rejects_other_tables() {
        assert!(read_table("a,b\n1,2\n").is_err());
        assert!(read_table("frame,x,y\n0,abc,1\n")
            .unwrap_err()
            .contains("not a number"));
    }
}
