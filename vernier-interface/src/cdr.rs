//! OMG CDR (XCDR1) encoding of the messages, as DDS puts them on the wire and rosbag2 stores
//! them in MCAP: a 4-byte encapsulation header, then the serde fields in declaration order.

use byteorder::{BigEndian, LittleEndian};
use serde::{Deserialize, Serialize};

/// CDR encapsulation header of little-endian plain CDR payloads.
const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Decodes a CDR payload with its 4-byte encapsulation header (either byte order).
pub fn from_cdr<'de, T: Deserialize<'de>>(payload: &'de [u8]) -> Result<T, String> {
    let (head, body) = payload
        .split_at_checked(4)
        .ok_or("CDR payload shorter than its header")?;
    let decoded = match head[..2] {
        [0x00, 0x01] | [0x00, 0x03] => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        [0x00, 0x00] | [0x00, 0x02] => cdr_encoding::from_bytes::<T, BigEndian>(body),
        _ => return Err(format!("unsupported CDR encapsulation {head:02x?}")),
    };
    decoded
        .map(|(value, _)| value)
        .map_err(|e| format!("bad CDR message: {e}"))
}

/// Encodes a message as little-endian CDR with its encapsulation header.
pub fn to_cdr<T: Serialize>(value: &T) -> Result<Vec<u8>, String> {
    let body = body_to_cdr(value)?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&CDR_LE_HEADER);
    out.extend_from_slice(&body);
    Ok(out)
}

/// The little-endian CDR body of a message, without encapsulation header (what the byte
/// layout tests compare).
pub fn body_to_cdr<T: Serialize>(value: &T) -> Result<Vec<u8>, String> {
    cdr_encoding::to_vec::<T, LittleEndian>(value)
        .map_err(|e| format!("cannot encode a message: {e}"))
}

/// Decodes a little-endian CDR body without encapsulation header.
pub fn body_from_cdr<'de, T: Deserialize<'de>>(body: &'de [u8]) -> Result<T, String> {
    cdr_encoding::from_bytes::<T, LittleEndian>(body)
        .map(|(value, _)| value)
        .map_err(|e| format!("bad CDR message: {e}"))
}

/// Big-endian CDR with its header (the tests check both byte orders).
#[cfg(test)]
pub(crate) fn to_cdr_big_endian<T: Serialize>(value: &T) -> Vec<u8> {
    let mut out = vec![0x00, 0x00, 0x00, 0x00];
    out.extend(cdr_encoding::to_vec::<T, BigEndian>(value).unwrap_or_default());
    out
}
