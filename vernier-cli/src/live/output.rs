//! The pose table of `vernier live` on stdout: the rows of `vernier detect --format
//! csv|jsonl|json`, written by the same [`TableWriter`], plus one live-only field appended to
//! each record: `latency_ms`, from the frame's capture (its read returned) to its row being
//! written, ms (queueing in the mailbox, conversion and detection). CSV gets it as a last
//! column and JSON as a last member, so readers of the detect table (`vernier plot`,
//! `vernier stats`, which skip unknown columns) read live tables unchanged. Flushed after
//! every frame.

use std::cell::RefCell;
use std::io::{BufWriter, Stdout, Write};
use std::rc::Rc;

use crate::pose_table::{PoseRow, TableFormat, TableWriter};

/// Name of the live-only field.
pub const LATENCY_FIELD: &str = "latency_ms";

/// A byte buffer shared with the [`TableWriter`], emptied after each record.
#[derive(Clone, Default)]
struct Shared(Rc<RefCell<Vec<u8>>>);

impl Write for Shared {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.0.borrow_mut().extend_from_slice(bytes);
        Ok(bytes.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl Shared {
    fn take(&self) -> Vec<u8> {
        std::mem::take(&mut *self.0.borrow_mut())
    }
}

/// Pose table on stdout with the latency field.
pub struct LiveTable {
    table: TableWriter<Shared>,
    buffer: Shared,
    format: TableFormat,
    out: BufWriter<Stdout>,
}

fn io_error(e: std::io::Error) -> String {
    format!("cannot write the results: {e}")
}

impl LiveTable {
    /// Starts the table (the CSV header, with `latency_ms` last).
    pub fn new(format: TableFormat) -> Result<Self, String> {
        let buffer = Shared::default();
        let table = TableWriter::new(buffer.clone(), format).map_err(io_error)?;
        let mut live = LiveTable {
            table,
            buffer,
            format,
            out: BufWriter::new(std::io::stdout()),
        };
        let header = live.buffer.take();
        if !header.is_empty() {
            let header = append_field(header, format, LATENCY_FIELD, LATENCY_FIELD)?;
            live.out.write_all(&header).map_err(io_error)?;
        }
        Ok(live)
    }

    /// Writes one frame's rows (one record per row, or one object per frame for `json`),
    /// each with `latency_ms`, and flushes.
    pub fn write(&mut self, rows: &[PoseRow], latency_ms: f64) -> Result<(), String> {
        let records: Vec<&[PoseRow]> = match self.format {
            TableFormat::Json => vec![rows],
            TableFormat::Csv | TableFormat::Jsonl => rows.chunks(1).collect(),
        };
        let value = format!("{latency_ms:.3}");
        for record in records {
            self.table.write(record).map_err(io_error)?;
            let line = append_field(self.buffer.take(), self.format, LATENCY_FIELD, &value)?;
            self.out.write_all(&line).map_err(io_error)?;
        }
        self.out.flush().map_err(io_error)
    }

    /// Flushes stdout.
    pub fn finish(mut self) -> Result<(), String> {
        self.out.flush().map_err(io_error)
    }
}

/// Appends a field to one record as [`TableWriter`] writes it: `…\n` in CSV gets
/// `,VALUE` (the header `,NAME`), `{…}\n` in JSON gets `,"NAME":VALUE` (`value` is a JSON
/// number). Errors on a record of another shape (a bug, not an input error).
fn append_field(
    mut record: Vec<u8>,
    format: TableFormat,
    name: &str,
    value: &str,
) -> Result<Vec<u8>, String> {
    let tail: &[u8] = match format {
        TableFormat::Csv => b"\n",
        TableFormat::Json | TableFormat::Jsonl => b"}\n",
    };
    if !record.ends_with(tail) {
        return Err(format!(
            "internal error: unexpected table record `{}`",
            String::from_utf8_lossy(&record)
        ));
    }
    record.truncate(record.len() - tail.len());
    let field = match format {
        TableFormat::Csv => format!(",{value}\n"),
        TableFormat::Json | TableFormat::Jsonl => format!(",\"{name}\":{value}}}\n"),
    };
    record.extend_from_slice(field.as_bytes());
    Ok(record)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn latency_is_the_last_field() {
        let csv = append_field(
            b"a,\"b\nc\"\n".to_vec(),
            TableFormat::Csv,
            "latency_ms",
            "1.5",
        );
        assert_eq!(csv.unwrap(), b"a,\"b\nc\",1.5\n");
        let json = append_field(
            b"{\"x\":1}\n".to_vec(),
            TableFormat::Jsonl,
            "latency_ms",
            "2.5",
        );
        let value: serde_json::Value = serde_json::from_slice(&json.unwrap()).unwrap();
        assert_eq!(value, serde_json::json!({"x": 1, "latency_ms": 2.5}));
        assert!(append_field(b"x".to_vec(), TableFormat::Json, "l", "1").is_err());
    }

    #[test]
    fn live_rows_read_back_as_pose_tables() {
        let row = PoseRow {
            frame: 4,
            source: "camera 0".into(),
            id: Some(2),
            x: Some(1.25),
            y: Some(-3.0),
            time_ms: 7.0,
            ..PoseRow::default()
        };
        for format in [TableFormat::Csv, TableFormat::Jsonl] {
            let buffer = Shared::default();
            let mut table = TableWriter::new(buffer.clone(), format).unwrap();
            let mut text = Vec::new();
            let header = buffer.take();
            if !header.is_empty() {
                text.extend(append_field(header, format, "latency_ms", "latency_ms").unwrap());
            }
            table.write(std::slice::from_ref(&row)).unwrap();
            text.extend(append_field(buffer.take(), format, "latency_ms", "9.000").unwrap());
            let text = String::from_utf8(text).unwrap();
            let rows = crate::pose_table::read_table(&text).unwrap();
            assert_eq!(rows, vec![row.clone()], "{format:?}: {text}");
        }
    }
}
