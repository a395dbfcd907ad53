//! Reading the coding lines and locating them in the sequence (docs/design.md#megarena-decoding,
//! redesigned for robustness and speed).
//!
//! **Reading.** Every visible coding line carries one bit (`s[3j+1] = B[j]`): when the bit is 1
//! all its dots at plain crossings are present, when 0 all are absent. Each such dot votes
//! "present" when its contrast exceeds half of the brighter of its two neighbours on the adjacent
//! plain lines (a local white reference, immune to illumination gradients), else "absent". The
//! line's soft bit is the sum of the votes: its sign is the bit, its magnitude the evidence, so a
//! few dots hidden or added by dust do not flip the bit, and lines cut short by the image border
//! weigh less.
//!
//! **Locating.** Every window of `w` consecutive bits of `B` occurs once (`w` = code depth for
//! generated sequences), so a table of `2^w` entries maps a window value to its position in O(1).
//! All windows of the read bits, and their variants with one or two bits flipped, propose start
//! positions; each proposal is scored over **all** read bits (soft agreement) and the best is
//! kept. It is accepted only when it explains the bits up to `⌊(m − w − 1)/2⌋` errors for `m`
//! bits read and no other proposal scores as well; at least `w + 1` bits (one redundant) are
//! required, i.e. about `3(w + 1)` visible periods, otherwise the image is reported as too small
//! to decode instead of guessing.

use super::orientation::Orientation;
use super::thumbnail::Thumbnail;
use crate::error::{Error, Result};
use crate::megarena_sequence::LineSequence;

/// Longest window the lookup table supports (2^24 entries of 4 bytes).
const MAX_WINDOW: usize = 24;
/// Table entry of a window value that does not occur.
const ABSENT: u32 = u32::MAX;

/// The coding bits `B[j] = s[3j+1]` of a line sequence with an O(1) window → position table.
#[derive(Clone, Debug)]
pub struct WindowIndex {
    bits: Vec<u8>,
    window: usize,
    table: Vec<u32>,
}

impl WindowIndex {
    /// Builds the index of `sequence`. The window length is the code depth, lengthened for
    /// user-supplied sequences until every window is unique.
    ///
    /// Errors when the sequence does not have the Megarena line structure (`s[3k] = s[3k+2] = 1`,
    /// length a multiple of 3) or when no window length up to 24 makes every window unique.
    pub fn new(sequence: &LineSequence) -> Result<Self> {
        let s = sequence.bits();
        if s.len() % 3 != 0 || s.chunks_exact(3).any(|c| c[0] != 1 || c[2] != 1) {
            return Err(Error::pattern(
                "bitSequence",
                "Megarena decoding needs a line sequence of length 3k with s[3j] = s[3j+2] = 1",
            ));
        }
        let bits: Vec<u8> = s.chunks_exact(3).map(|c| c[1]).collect();
        let start = (sequence.code_depth() as usize).max(1);
        for window in start..=MAX_WINDOW.min(bits.len()) {
            if let Some(table) = Self::table(&bits, window) {
                return Ok(WindowIndex {
                    bits,
                    window,
                    table,
                });
            }
        }
        Err(Error::pattern(
            "bitSequence",
            format!("no window of at most {MAX_WINDOW} coding bits is unique in the sequence"),
        ))
    }

    /// The position table for windows of `window` bits, `None` if a window repeats.
    fn table(bits: &[u8], window: usize) -> Option<Vec<u32>> {
        let mut table = vec![ABSENT; 1usize << window];
        for (pos, w) in bits.windows(window).enumerate() {
            let slot = table.get_mut(window_value(w))?;
            if *slot != ABSENT {
                return None;
            }
            *slot = pos as u32;
        }
        Some(table)
    }

    /// Window length `w`, bits.
    pub fn window(&self) -> usize {
        self.window
    }

    /// Number of coding bits `len(B) = L/3`.
    pub fn len(&self) -> usize {
        self.bits.len()
    }

    /// True when the sequence has no coding bit (never for a constructed index).
    pub fn is_empty(&self) -> bool {
        self.bits.is_empty()
    }

    /// Position in `B` of the window with value `value` (first bit most significant).
    pub fn lookup(&self, value: usize) -> Option<usize> {
        self.table
            .get(value)
            .copied()
            .filter(|&p| p != ABSENT)
            .map(|p| p as usize)
    }

    /// Locates soft bits read **in layout order** (`soft[t] > 0`: bit 1, `< 0`: bit 0, `0`: not
    /// read) in `B`. See the module documentation for the rule.
    pub fn locate(&self, soft: &[f64]) -> Result<Located> {
        let w = self.window;
        let read = soft.iter().filter(|v| **v != 0.0).count();
        if read < w + 1 {
            return Err(Error::Decode(format!(
                "not enough periods to decode: {read} coding lines read along one axis, \
                 code depth {w} needs at least {} (about {} visible periods)",
                w + 1,
                3 * (w + 1)
            )));
        }
        let m = soft.len();
        if m > self.bits.len() {
            return Err(Error::Decode(format!(
                "{m} coding lines read, more than the pattern's {}",
                self.bits.len()
            )));
        }
        let hard: Vec<u8> = soft.iter().map(|&v| u8::from(v > 0.0)).collect();
        let last_start = self.bits.len() - m;
        let mut candidates: Vec<usize> = Vec::new();
        let propose = |value: usize, t: usize, out: &mut Vec<usize>| {
            if let Some(p) = self.lookup(value) {
                if let Some(start) = p.checked_sub(t).filter(|&s| s <= last_start) {
                    out.push(start);
                }
            }
        };
        // Windows made only of read bits, as (offset, value).
        let windows: Vec<(usize, usize)> = (0..=m - w)
            .filter(|&t| soft[t..t + w].iter().all(|v| *v != 0.0))
            .map(|t| (t, window_value(&hard[t..t + w])))
            .collect();
        for &(t, value) in &windows {
            propose(value, t, &mut candidates);
        }
        let mut best = self.best_of(&mut candidates, soft, &hard);
        if best.is_none_or(|b| b.mismatches > 0) {
            // Some bit is wrong (or no window is intact): flip one or two bits per window.
            for &(t, value) in &windows {
                for i in 0..w {
                    propose(value ^ (1 << i), t, &mut candidates);
                    for j in i + 1..w {
                        propose(value ^ (1 << i) ^ (1 << j), t, &mut candidates);
                    }
                }
            }
            best = self.best_of(&mut candidates, soft, &hard);
        }
        let Some(best) = best else {
            return Err(Error::Decode(
                "the coding bits match no position of the sequence".into(),
            ));
        };
        let allowed = (read - w - 1) / 2;
        if best.mismatches > allowed {
            return Err(Error::Decode(format!(
                "inconsistent coding bits: the best position disagrees with {} of {read} bits \
                 (at most {allowed} tolerated)",
                best.mismatches
            )));
        }
        if best.ambiguous {
            return Err(Error::Decode(
                "ambiguous coding bits: two positions of the sequence explain them equally".into(),
            ));
        }
        Ok(Located {
            start: best.start,
            read,
            agreeing: read - best.mismatches,
            score_gap: best.gap,
        })
    }

    /// Scores the (deduplicated) candidate starts; the best by soft agreement.
    fn best_of(&self, candidates: &mut Vec<usize>, soft: &[f64], hard: &[u8]) -> Option<Scored> {
        candidates.sort_unstable();
        candidates.dedup();
        let total: f64 = soft.iter().map(|v| v.abs()).sum();
        let scored: Vec<Scored> = candidates
            .iter()
            .filter_map(|&start| {
                let reference = self.bits.get(start..start + soft.len())?;
                let (mut score, mut mismatches) = (0.0, 0usize);
                for ((&v, &h), &r) in soft.iter().zip(hard).zip(reference) {
                    if v == 0.0 {
                        continue;
                    }
                    if h == r {
                        score += v.abs();
                    } else {
                        score -= v.abs();
                        mismatches += 1;
                    }
                }
                Some(Scored {
                    start,
                    score,
                    mismatches,
                    ambiguous: false,
                    gap: 1.0,
                })
            })
            .collect();
        let mut best = *scored.iter().max_by(|a, b| a.score.total_cmp(&b.score))?;
        let second = scored
            .iter()
            .filter(|c| c.start != best.start)
            .map(|c| c.score)
            .fold(f64::NEG_INFINITY, f64::max);
        best.ambiguous = second >= best.score;
        if second.is_finite() && total > 0.0 {
            best.gap = ((best.score - second) / (2.0 * total)).clamp(0.0, 1.0);
        }
        Some(best)
    }
}

/// One candidate start position with its agreement.
#[derive(Clone, Copy, Debug)]
struct Scored {
    start: usize,
    score: f64,
    mismatches: usize,
    ambiguous: bool,
    gap: f64,
}

/// Where a run of read bits lies in `B`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Located {
    /// Index `j` in `B` of the first bit (layout order): its line is layout row/column `3j + 1`.
    pub start: usize,
    /// Number of bits read (lines with at least one voting dot).
    pub read: usize,
    /// Number of read bits equal to the sequence at the decoded position.
    pub agreeing: usize,
    /// Soft-score gap to the second-best position, as a fraction of twice the total evidence,
    /// `[0, 1]` (1: no other candidate).
    pub score_gap: f64,
}

/// Value of a bit window, first bit most significant.
fn window_value(bits: &[u8]) -> usize {
    bits.iter()
        .fold(0usize, |acc, &b| (acc << 1) | (b & 1) as usize)
}

/// Soft bits of the coding lines of one thumbnail axis.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LineBits {
    /// Phase order of the first coding line.
    pub first_line: i64,
    /// Soft bit of each coding line, in increasing phase order (lines `first_line + 3t`):
    /// votes present − votes absent; 0 when no dot of the line could vote.
    pub soft: Vec<f64>,
}

/// Reads the coding lines of thumbnail axis `axis` (0: lines of constant `n1`, 1: constant `n2`).
///
/// `white` is the typical contrast of a present dot: references dimmer than a quarter of it
/// (dust, image border) are not used.
pub fn read_lines(
    thumb: &Thumbnail,
    orientation: &Orientation,
    axis: usize,
    white: f64,
) -> LineBits {
    let (k, o) = if axis == 0 { (0, 1) } else { (1, 0) };
    let get = |line: i64, pos: i64| {
        if k == 0 {
            thumb.get(line, pos)
        } else {
            thumb.get(pos, line)
        }
    };
    let (coding, missing) = (orientation.coding[k] as i64, orientation.missing[k] as i64);
    let (other_coding, other_missing) =
        (orientation.coding[o] as i64, orientation.missing[o] as i64);
    let lines = thumb.orders(k);
    let first_line = lines.start + (coding - lines.start).rem_euclid(3);
    let floor = 0.25 * white;
    let mut soft = Vec::new();
    let mut line = first_line;
    while line < lines.end {
        let mut votes = 0.0;
        for pos in thumb.orders(o) {
            if pos.rem_euclid(3) == other_coding {
                continue; // crossing with a coding line: depends on the other axis' bit
            }
            let Some(v) = get(line, pos) else { continue };
            let mut reference = f32::NEG_INFINITY;
            for neighbour in [line - 1, line + 1] {
                let is_missing_dot =
                    neighbour.rem_euclid(3) == missing && pos.rem_euclid(3) == other_missing;
                if is_missing_dot {
                    continue;
                }
                if let Some(r) = get(neighbour, pos) {
                    reference = reference.max(r);
                }
            }
            if (reference as f64) < floor {
                continue;
            }
            votes += if v > 0.5 * reference { 1.0 } else { -1.0 };
        }
        soft.push(votes);
        line += 3;
    }
    LineBits { first_line, soft }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn table_finds_every_window_of_generated_sequences() {
        for depth in [4, 8, 12] {
            let seq = LineSequence::generated(depth).unwrap();
            let index = WindowIndex::new(&seq).unwrap();
            assert_eq!(index.window(), depth as usize);
            assert_eq!(index.len(), seq.len() / 3);
            let b: Vec<u8> = seq.bits().chunks(3).map(|c| c[1]).collect();
            for (pos, w) in b.windows(depth as usize).enumerate() {
                assert_eq!(index.lookup(window_value(w)), Some(pos));
            }
            assert_eq!(index.lookup(0), None, "the zero window never occurs");
        }
    }

    #[test]
    fn locate_corrects_wrong_bits_and_refuses_short_reads() {
        let seq = LineSequence::generated(10).unwrap();
        let index = WindowIndex::new(&seq).unwrap();
        let b: Vec<u8> = seq.bits().chunks(3).map(|c| c[1]).collect();
        let soft = |start: usize, m: usize| -> Vec<f64> {
            b[start..start + m]
                .iter()
                .map(|&v| if v == 1 { 20.0 } else { -20.0 })
                .collect()
        };
        let clean = index.locate(&soft(700, 20)).unwrap();
        assert_eq!((clean.start, clean.read, clean.agreeing), (700, 20, 20));
        // Two wrong bits, one of them strong: still found, agreement 18/20.
        let mut noisy = soft(123, 20);
        noisy[3] = -noisy[3];
        noisy[15] = -noisy[15] * 0.2;
        let found = index.locate(&noisy).unwrap();
        assert_eq!((found.start, found.agreeing), (123, 18));
        // An unread line is an erasure, not a zero bit.
        let mut erased = soft(40, 16);
        erased[5] = 0.0;
        assert_eq!(index.locate(&erased).unwrap().start, 40);
        // Too few bits: refused.
        let e = index.locate(&soft(40, 10)).unwrap_err().to_string();
        assert!(e.contains("not enough periods to decode"), "{e}");
    }

    #[test]
    fn rejects_sequences_without_line_structure() {
        let bad = LineSequence::from_bits(vec![1, 0, 0, 1, 1, 1]).unwrap();
        assert!(WindowIndex::new(&bad).is_err());
        let ok = LineSequence::from_bits(vec![1, 0, 1, 1, 1, 1, 1, 1, 1]).unwrap();
        let index = WindowIndex::new(&ok).unwrap();
        assert_eq!(index.len(), 3);
    }
}
