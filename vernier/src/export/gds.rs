//! GDSII stream writer (docs/design.md#export-gds-oasis): regular dot arrays become AREFs of a
//! one-rectangle cell, isolated rectangles plain BOUNDARY elements.
//!
//! Units: user unit 1 µm, database unit 1 nm; y = −v (GDS is y up). Dots on layer 1,
//! datatype 1; the descriptive label on layer 2, texttype 0 (TEXT elements).

use super::geometry::DotArray;
use super::Drawing;
use crate::error::{Error, Result};

// Record types (high byte) and data types (low byte) of the records written.
const HEADER: u16 = 0x0002;
const BGNLIB: u16 = 0x0102;
const LIBNAME: u16 = 0x0206;
const UNITS: u16 = 0x0305;
const ENDLIB: u16 = 0x0400;
const BGNSTR: u16 = 0x0502;
const STRNAME: u16 = 0x0606;
const ENDSTR: u16 = 0x0700;
const BOUNDARY: u16 = 0x0800;
const AREF: u16 = 0x0B00;
const TEXT: u16 = 0x0C00;
const LAYER: u16 = 0x0D02;
const DATATYPE: u16 = 0x0E02;
const XY: u16 = 0x1003;
const ENDEL: u16 = 0x1100;
const SNAME: u16 = 0x1206;
const COLROW: u16 = 0x1302;
const TEXTTYPE: u16 = 0x1602;
const STRING: u16 = 0x1906;
const STRANS: u16 = 0x1A01;
const MAG: u16 = 0x1B05;

/// Largest column or row count of one AREF (signed 16-bit field).
const MAX_AREF_COUNT: u32 = 32767;
/// Longest STRING record payload accepted by common readers.
const MAX_STRING: usize = 512;

/// An 8-byte GDSII real: sign bit, excess-64 base-16 exponent, 56-bit mantissa.
pub(crate) fn gds_real8(value: f64) -> [u8; 8] {
    if value == 0.0 || !value.is_finite() {
        return [0; 8];
    }
    let mut mantissa = value.abs();
    let mut exponent: i32 = 64;
    // Normalise to [1/16, 1); divisions by 16 are exact in binary floating point.
    while mantissa >= 1.0 {
        mantissa /= 16.0;
        exponent += 1;
    }
    while mantissa < 1.0 / 16.0 {
        mantissa *= 16.0;
        exponent -= 1;
    }
    let mut bits = (mantissa * (1u64 << 56) as f64).round() as u64;
    if bits >= 1 << 56 {
        bits >>= 4;
        exponent += 1;
    }
    let mut out = bits.to_be_bytes();
    out[0] = (u8::from(value < 0.0) << 7) | (exponent.clamp(0, 127) as u8);
    out
}

/// Byte buffer of GDSII records.
struct Stream(Vec<u8>);

impl Stream {
    fn record(&mut self, kind: u16, payload: &[u8]) -> Result<()> {
        let length = u16::try_from(payload.len() + 4).map_err(|_| {
            Error::parameter(
                "export",
                format!("GDSII record of {} bytes is too long", payload.len()),
            )
        })?;
        self.0.extend_from_slice(&length.to_be_bytes());
        self.0.extend_from_slice(&kind.to_be_bytes());
        self.0.extend_from_slice(payload);
        Ok(())
    }
    fn i16s(&mut self, kind: u16, values: &[i16]) -> Result<()> {
        let payload: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
        self.record(kind, &payload)
    }
    /// Points in database units; every coordinate was range-checked by the geometry step.
    fn xy(&mut self, points: &[(i64, i64)]) -> Result<()> {
        let mut payload = Vec::with_capacity(points.len() * 8);
        for &(x, y) in points {
            for v in [x, y] {
                let v = i32::try_from(v).map_err(|_| {
                    Error::parameter("export", format!("coordinate {v} nm overflows GDSII"))
                })?;
                payload.extend_from_slice(&v.to_be_bytes());
            }
        }
        self.record(XY, &payload)
    }
    /// ASCII string padded with NUL to an even length.
    fn string(&mut self, kind: u16, text: &str) -> Result<()> {
        let mut payload: Vec<u8> = text.bytes().take(MAX_STRING).collect();
        if payload.len() % 2 == 1 {
            payload.push(0);
        }
        self.record(kind, &payload)
    }
    fn real8(&mut self, kind: u16, values: &[f64]) -> Result<()> {
        let payload: Vec<u8> = values.iter().flat_map(|&v| gds_real8(v)).collect();
        self.record(kind, &payload)
    }
    /// Closed rectangle outline (y up), counter-clockwise.
    fn boundary(
        &mut self,
        layer: i16,
        datatype: i16,
        x0: i64,
        y0: i64,
        x1: i64,
        y1: i64,
    ) -> Result<()> {
        self.record(BOUNDARY, &[])?;
        self.i16s(LAYER, &[layer])?;
        self.i16s(DATATYPE, &[datatype])?;
        self.xy(&[(x0, y0), (x1, y0), (x1, y1), (x0, y1), (x0, y0)])?;
        self.record(ENDEL, &[])
    }
}

/// Name of the one-rectangle cell referenced by the arrays of `w × h` nm dots.
fn dot_cell_name(w: i64, h: i64) -> String {
    format!("DOT_{w}x{h}")
}

/// The GDSII file of `drawing`.
///
/// Structure: one cell `DOT_<w>x<h>` per dot size, holding that rectangle with its top-left
/// corner at the cell origin; the top cell (named after the class) holds an AREF per regular
/// array (split at 32 767 columns/rows), a BOUNDARY per isolated rectangle, and the label.
pub(crate) fn write_gds(drawing: &Drawing) -> Result<Vec<u8>> {
    let mut s = Stream(Vec::new());
    s.i16s(HEADER, &[600])?;
    let stamp = drawing.timestamp;
    let dates: Vec<i16> = stamp.iter().chain(stamp.iter()).copied().collect();
    s.i16s(BGNLIB, &dates)?;
    s.string(LIBNAME, drawing.name)?;
    // Database unit in user units (1 nm / 1 µm), then in metres.
    s.real8(UNITS, &[1e-3, 1e-9])?;

    let (layer, datatype) = drawing.dot_layer;
    let mut sizes: Vec<(i64, i64)> = drawing
        .arrays
        .iter()
        .filter(|a| a.len() > 1)
        .map(|a| (a.first.width, a.first.height))
        .collect();
    sizes.sort_unstable();
    sizes.dedup();
    for &(w, h) in &sizes {
        s.i16s(BGNSTR, &dates)?;
        s.string(STRNAME, &dot_cell_name(w, h))?;
        s.boundary(layer, datatype, 0, -h, w, 0)?;
        s.record(ENDSTR, &[])?;
    }

    s.i16s(BGNSTR, &dates)?;
    s.string(STRNAME, drawing.name)?;
    for a in drawing.arrays {
        write_array(&mut s, a, layer, datatype)?;
    }
    let label = &drawing.label;
    for (i, line) in label.lines.iter().enumerate() {
        s.record(TEXT, &[])?;
        s.i16s(LAYER, &[label.layer.0])?;
        s.i16s(TEXTTYPE, &[label.layer.1])?;
        s.i16s(STRANS, &[0])?;
        // Magnification = text height in user units (µm).
        s.real8(MAG, &[label.height as f64 / 1000.0])?;
        let y = label.y - (i as i64) * label.height * 3 / 2;
        s.xy(&[(label.x, y)])?;
        s.string(STRING, line)?;
        s.record(ENDEL, &[])?;
    }
    s.record(ENDSTR, &[])?;
    s.record(ENDLIB, &[])?;
    Ok(s.0)
}

/// One array: BOUNDARY when it holds one rectangle, else AREFs of its dot cell.
fn write_array(s: &mut Stream, a: &DotArray, layer: i16, datatype: i16) -> Result<()> {
    let r = a.first;
    if a.len() == 1 {
        return s.boundary(layer, datatype, r.x, -(r.y + r.height), r.x + r.width, -r.y);
    }
    let name = dot_cell_name(r.width, r.height);
    // A zero pitch only occurs with a count of 1; any non-zero vector then works.
    let px = if a.cols > 1 { a.pitch_x } else { r.width };
    let py = if a.rows > 1 { a.pitch_y } else { r.height };
    let mut row = 0;
    while row < a.rows {
        let rows = (a.rows - row).min(MAX_AREF_COUNT);
        let mut col = 0;
        while col < a.cols {
            let cols = (a.cols - col).min(MAX_AREF_COUNT);
            let x = r.x + i64::from(col) * px;
            let y = -(r.y + i64::from(row) * py);
            s.record(AREF, &[])?;
            s.string(SNAME, &name)?;
            // Counts are ≤ 32767 here.
            s.i16s(COLROW, &[cols as i16, rows as i16])?;
            s.xy(&[
                (x, y),
                (x + i64::from(cols) * px, y),
                (x, y - i64::from(rows) * py),
            ])?;
            s.record(ENDEL, &[])?;
            col += cols;
        }
        row += rows;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Inverse of [`gds_real8`].
    fn gds_real8_value(bytes: [u8; 8]) -> f64 {
        let sign = if bytes[0] & 0x80 != 0 { -1.0 } else { 1.0 };
        let exponent = i32::from(bytes[0] & 0x7f) - 64;
        let mut m = bytes;
        m[0] = 0;
        let mantissa = u64::from_be_bytes(m) as f64 / (1u64 << 56) as f64;
        sign * mantissa * 16f64.powi(exponent)
    }

    #[test]
    fn real8_round_trips() {
        for v in [1e-3, 1e-9, 1.0, 0.5, 16.0, 1234.5678, -3.25, 8.0 * 7.0] {
            let back = gds_real8_value(gds_real8(v));
            assert!((back - v).abs() <= v.abs() * 1e-15, "{v} -> {back}");
        }
        // The canonical encoding of 1e-3 (user units of a 1 nm / 1 µm library).
        assert_eq!(
            gds_real8(1e-3),
            [0x3e, 0x41, 0x89, 0x37, 0x4b, 0xc6, 0xa7, 0xf0]
        );
        assert_eq!(gds_real8(0.0), [0; 8]);
    }
}
