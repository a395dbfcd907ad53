//! OASIS writer (SEMI P39; docs/design.md#export-gds-oasis): one cell of RECTANGLE records, regular
//! dot arrays as RECTANGLEs with a grid repetition, a TEXT per label line, CRC-32 validation.
//!
//! Units: 1000 database units per µm (1 nm grid), y = −v (OASIS is y up). Dots on layer 1,
//! datatype 1; the label on text layer 2, texttype 0. Not compressed (no CBLOCK): with
//! repetitions a 10⁵-dot Megarena region takes a few kB.

use super::Drawing;

const MAGIC: &[u8] = b"%SEMI-OASIS\r\n";
const START: u8 = 1;
const END: u8 = 2;
const CELL_BY_NAME: u8 = 14;
const TEXT: u8 = 19;
const RECTANGLE: u8 = 20;
/// The END record is always exactly this long (bytes).
const END_RECORD_LENGTH: usize = 256;
/// Validation scheme 1: CRC-32 of the file up to and including the scheme byte.
const VALIDATION_CRC32: u8 = 1;

/// CRC-32 (IEEE 802.3, reflected, as zlib), bitwise: runs once per file.
pub(crate) fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            let mask = (crc & 1).wrapping_neg();
            crc = (crc >> 1) ^ (0xEDB8_8320 & mask);
        }
    }
    !crc
}

/// Byte buffer of OASIS records.
struct Stream(Vec<u8>);

impl Stream {
    fn byte(&mut self, b: u8) {
        self.0.push(b);
    }
    /// Unsigned integer: 7-bit groups, least significant first, high bit = continuation.
    fn uint(&mut self, mut v: u64) {
        loop {
            let low = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                self.0.push(low);
                return;
            }
            self.0.push(low | 0x80);
        }
    }
    /// Signed integer: magnitude shifted left by one, sign in bit 0.
    fn sint(&mut self, v: i64) {
        self.uint((v.unsigned_abs() << 1) | u64::from(v < 0));
    }
    /// String (a-, b- or n-string): length then bytes.
    fn string(&mut self, text: &[u8]) {
        self.uint(text.len() as u64);
        self.0.extend_from_slice(text);
    }
}

/// Writes the repetition of a `cols × rows` grid (counts ≥ 1, not both 1), y up.
fn repetition(s: &mut Stream, cols: u32, rows: u32, pitch_x: i64, pitch_y: i64) {
    let (cols, rows) = (u64::from(cols), u64::from(rows));
    if cols > 1 && rows > 1 {
        s.uint(1);
        s.uint(cols - 2);
        s.uint(rows - 2);
        s.uint(pitch_x.unsigned_abs());
        s.uint(pitch_y.unsigned_abs());
    } else if cols > 1 {
        s.uint(2);
        s.uint(cols - 2);
        s.uint(pitch_x.unsigned_abs());
    } else {
        s.uint(3);
        s.uint(rows - 2);
        s.uint(pitch_y.unsigned_abs());
    }
}

/// The OASIS file of `drawing`.
pub(crate) fn write_oasis(drawing: &Drawing) -> Vec<u8> {
    let mut s = Stream(Vec::with_capacity(4096));
    s.0.extend_from_slice(MAGIC);
    s.byte(START);
    s.string(b"1.0");
    // unit: real of type 0 (positive integer) = database units per µm.
    s.uint(0);
    s.uint(1000);
    // offset-flag 0: the six (flag, offset) table pairs follow here, all absent.
    s.uint(0);
    for _ in 0..12 {
        s.uint(0);
    }

    s.byte(CELL_BY_NAME);
    s.string(drawing.name.as_bytes());
    let (layer, datatype) = drawing.dot_layer;
    for a in drawing.arrays {
        let r = a.first;
        let square = r.width == r.height;
        // Info byte S W H X Y R D L: always explicit layer, datatype, size and position.
        let mut info = 0b0101_1011u8;
        if square {
            info |= 0x80;
        } else {
            info |= 0x20;
        }
        let repeated = a.len() > 1;
        if repeated {
            info |= 0x04;
        }
        s.byte(RECTANGLE);
        s.byte(info);
        s.uint(u64::from(layer.unsigned_abs()));
        s.uint(u64::from(datatype.unsigned_abs()));
        s.uint(r.width.unsigned_abs());
        if !square {
            s.uint(r.height.unsigned_abs());
        }
        // Lower-left corner of the bottom-left element (rows grow downwards in export
        // coordinates, upwards here).
        let bottom_row = i64::from(a.rows - 1) * a.pitch_y;
        s.sint(r.x);
        s.sint(-(r.y + bottom_row + r.height));
        if repeated {
            repetition(&mut s, a.cols, a.rows, a.pitch_x, a.pitch_y);
        }
    }
    let label = &drawing.label;
    for (i, line) in label.lines.iter().enumerate() {
        // Info byte 0 C N X Y R T L: explicit string, position, texttype and layer.
        s.byte(TEXT);
        s.byte(0b0101_1011);
        s.string(line.as_bytes());
        s.uint(u64::from(label.layer.0.unsigned_abs()));
        s.uint(u64::from(label.layer.1.unsigned_abs()));
        s.sint(label.x);
        s.sint(label.y - (i as i64) * label.height * 3 / 2);
    }

    // END: padding b-string sized so that the record is 256 bytes, then the validation.
    s.byte(END);
    let padding = END_RECORD_LENGTH - 1 - 2 - 1 - 4;
    s.string(&vec![0u8; padding]);
    s.byte(VALIDATION_CRC32);
    let crc = crc32(&s.0);
    s.0.extend_from_slice(&crc.to_le_bytes());
    s.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integers_encode_as_in_the_standard() {
        let mut s = Stream(Vec::new());
        s.uint(127);
        s.uint(128);
        s.uint(16384);
        s.sint(-1);
        s.sint(3);
        assert_eq!(s.0, [0x7f, 0x80, 0x01, 0x80, 0x80, 0x01, 0x03, 0x06]);
    }

    #[test]
    fn crc32_matches_zlib() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    }
}
