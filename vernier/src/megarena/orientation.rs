//! Orientation of the thumbnail axes from the 3×3 rule (docs/design.md#megarena-orientation).
//!
//! In the layout, dot rows and columns with index ≡ 1 (mod 3) are the coding lines and dot
//! `(r, c)` with `r ≡ c ≡ 0 (mod 3)` is always missing. Averaging the node levels by residue
//! `(n1 mod 3, n2 mod 3)` gives a 3×3 "global cell" in which, away from the coding residues, three
//! entries are bright and one (the missing dot) dark. Testing the 36 hypotheses (coding residue
//! per axis × position of the missing dot) gives, per thumbnail axis, the coding residue and
//! whether the layout index grows with the phase order (missing residue + 1 = coding residue) or
//! decreases. With both directions known the orientation is resolved over the full turn.
//!
//! Score of a hypothesis: mean level of its three present cells minus the level of its missing
//! cell (the dot contrast; independent of the background level, unlike the original's sum of
//! three minus one).

use super::thumbnail::Thumbnail;
use crate::error::{Error, Result};

/// Smallest accepted score margin between the best and the second-best hypothesis, as a
/// fraction of the best score. The runner-up is normally the hypothesis that swaps a coding
/// residue with a plain one, whose margin is `2/3` of the fraction of zero bits among the
/// visible coding lines (≥ 0.05 for one zero in 13 lines); below it the coding lines cannot be
/// told from the plain lines (e.g. every visible coding bit is 1).
pub const MIN_ORIENTATION_MARGIN: f64 = 0.03;

/// Residue classes of the thumbnail axes (phase orders modulo 3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orientation {
    /// Residue of the coding lines along each thumbnail axis: lines `n_k ≡ coding[k] (mod 3)`.
    pub coding: [usize; 2],
    /// Residue of the line through the missing dot of each 3×3 cell, per axis (layout index
    /// ≡ 0 mod 3).
    pub missing: [usize; 2],
    /// +1 when the layout index grows with the phase order of that axis, −1 when it decreases.
    pub direction: [i64; 2],
    /// Mean node level per residue pair `[n1 mod 3][n2 mod 3]`, grey-level units.
    pub global_cell: [[f64; 3]; 3],
    /// Dot contrast: mean level of the three present cells minus the missing cell, grey-level
    /// units.
    pub dot_contrast: f64,
    /// Score margin between the best and second-best hypotheses, fraction of the best score.
    pub margin: f64,
}

/// Finds the orientation from the global cell of the thumbnail's node levels.
///
/// Errors ([`Error::Decode`]) when no dot contrast is measured or when the hypotheses cannot
/// be separated (margin below [`MIN_ORIENTATION_MARGIN`]).
pub fn find_orientation(thumb: &Thumbnail) -> Result<Orientation> {
    let cell = mean_cell(thumb)?;
    let hypotheses = ranked_hypotheses(&cell);
    let (best, second) = (hypotheses[0], hypotheses[1]);
    let (score, coding, missing) = best;
    if score.is_nan() || score <= 0.0 {
        return Err(Error::Decode(
            "no dot contrast on the lattice: the missing-dot mark of the 3×3 cells is not visible"
                .into(),
        ));
    }
    let margin = (score - second.0) / score;
    if margin < MIN_ORIENTATION_MARGIN {
        return Err(Error::Decode(format!(
            "orientation is ambiguous: the coding lines cannot be told from the plain lines \
             (margin {margin:.3} < {MIN_ORIENTATION_MARGIN})"
        )));
    }
    let direction = [0, 1].map(|k| {
        if (missing[k] + 1) % 3 == coding[k] {
            1
        } else {
            -1
        }
    });
    Ok(Orientation {
        coding,
        missing,
        direction,
        global_cell: cell,
        dot_contrast: score,
        margin,
    })
}

/// Mean level of each residue class `(n1 mod 3, n2 mod 3)` of the thumbnail's nodes: the
/// 3×3 cell averaged over the image.
fn mean_cell(thumb: &Thumbnail) -> Result<[[f64; 3]; 3]> {
    let mut sum = [[0.0f64; 3]; 3];
    let mut count = [[0usize; 3]; 3];
    for n1 in thumb.orders(0) {
        for n2 in thumb.orders(1) {
            if let Some(v) = thumb.level_at(n1, n2) {
                let (r1, r2) = (n1.rem_euclid(3) as usize, n2.rem_euclid(3) as usize);
                sum[r1][r2] += v as f64;
                count[r1][r2] += 1;
            }
        }
    }
    if count.iter().flatten().any(|&c| c == 0) {
        return Err(Error::Decode(
            "not enough periods to decode: the image does not show a full 3×3 cell".into(),
        ));
    }
    let mut cell = [[0.0f64; 3]; 3];
    for r1 in 0..3 {
        for r2 in 0..3 {
            cell[r1][r2] = sum[r1][r2] / count[r1][r2] as f64;
        }
    }
    Ok(cell)
}

/// Every hypothesis (coding residues, missing dot) `(score, coding, missing)`, best first:
/// the score is the mean level of the cell's three present dots minus the missing one's.
fn ranked_hypotheses(cell: &[[f64; 3]; 3]) -> Vec<(f64, [usize; 2], [usize; 2])> {
    // (score, white level, coding, missing) of every hypothesis.
    let mut hypotheses = Vec::with_capacity(36);
    for c1 in 0..3 {
        for c2 in 0..3 {
            // The two non-coding residues in increasing order (r⁻, r⁺).
            let others = |c: usize| {
                let (a, b) = ((c + 1) % 3, (c + 2) % 3);
                [a.min(b), a.max(b)]
            };
            let (o1, o2) = (others(c1), others(c2));
            for quadrant in 0..4 {
                // The original's quadrant numbering: quadrant 0 → (r⁺, r⁺), 1 → (r⁺, r⁻),
                // 2 → (r⁻, r⁺), 3 → (r⁻, r⁻).
                let m1 = if quadrant < 2 { o1[1] } else { o1[0] };
                let m2 = if quadrant % 2 == 0 { o2[1] } else { o2[0] };
                let mut present = 0.0;
                for r1 in o1 {
                    for r2 in o2 {
                        if (r1, r2) != (m1, m2) {
                            present += cell[r1][r2];
                        }
                    }
                }
                let score = present / 3.0 - cell[m1][m2];
                hypotheses.push((score, [c1, c2], [m1, m2]));
            }
        }
    }
    hypotheses.sort_by(|a, b| b.0.total_cmp(&a.0));
    hypotheses
}
