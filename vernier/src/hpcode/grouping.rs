//! Grouping finder squares into HP code markers (METHOD.md §5.2.2, made robust).
//!
//! The original groups greedily by distance and only uses `3·⌊n/3⌋` finders, so one spurious
//! finder breaks every marker (§9.7). Here every triple of finders of the same polarity is
//! checked against the marker geometry — a right angle at the corner finder, two equal legs,
//! legs `W − 7` modules long, finders of equal size — and the best-fitting triples are kept
//! greedily without sharing a finder. Finders left over are ignored.
//!
//! The marker width `W` is a prior, not a constraint: legs of `W' − 7` modules are accepted for
//! any `W'` within [`WIDTH_SLACK`] cells of the nominal `W` (the original ignores `W`, and the
//! dark-dot example image documented as `W = 33` holds `W' = 39` markers). The fine step then
//! measures `W'` exactly in whole periods.

use super::finders::Finder;
use crate::grey_image::Polarity;
use nalgebra::Vector2;

/// Largest relative difference of the two legs.
const LEG_TOLERANCE: f64 = 0.1;
/// Largest `|cos|` of the corner angle (≈ 90° ± 8.6°).
const MAX_CORNER_COS: f64 = 0.15;
/// Largest relative error of a leg length in modules (finder sizes are measured to a few %).
const SCALE_TOLERANCE: f64 = 0.1;
/// Accepted marker widths: nominal `W` ± this many half-period cells.
pub const WIDTH_SLACK: usize = 8;
/// Largest relative deviation of a finder's size from the triple's mean.
const SIZE_TOLERANCE: f64 = 0.2;

/// Three finders forming a marker, as assigned from their geometry alone.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FinderTriple {
    /// Finder at the right angle (pattern top-left corner), image pixels `(col, row)`.
    pub corner: Vector2<f64>,
    /// Finder along the pattern +x axis from the corner (top-right).
    pub right: Vector2<f64>,
    /// Finder along the pattern +y axis from the corner (bottom-left).
    pub bottom: Vector2<f64>,
    /// Module (half period) in pixels estimated from the finder sizes and the leg direction.
    pub module_px: f64,
    /// Polarity of the three finders.
    pub polarity: Polarity,
    /// Geometric misfit (0 = perfect), for ranking.
    pub misfit: f64,
}

impl FinderTriple {
    /// Coarse marker centre: midpoint of the right and bottom finders (the centre dot).
    pub fn center(&self) -> Vector2<f64> {
        (self.right + self.bottom) / 2.0
    }

    /// `right` and `bottom` swapped: the reading of a mirrored marker (seen from its back).
    pub fn mirrored(&self) -> FinderTriple {
        FinderTriple {
            right: self.bottom,
            bottom: self.right,
            ..*self
        }
    }
}

/// Marker triples among `finders` for markers about `half_periods` (W) cells wide, best first.
/// `right`/`bottom` are assigned so that `bottom` is 90° clockwise on screen from `right`
/// (a marker seen from the front); a mirrored marker is recognised later from its ID row.
pub fn group_finders(finders: &[Finder], half_periods: usize) -> Vec<FinderTriple> {
    let legs = LegRange::new(half_periods);
    let mut triples = Vec::new();
    let n = finders.len();
    let mut near = Vec::new();
    for a in 0..n {
        // Legs are (W − 7) modules; a chord is 7 to 7·√2 modules.
        let chord = finders[a].chord;
        let max_leg = legs.max * chord / 7.0 * 1.25;
        let min_leg = legs.min * chord / (7.0 * std::f64::consts::SQRT_2) * 0.75;
        near.clear();
        near.extend((0..n).filter(|&b| {
            let d = (finders[b].center - finders[a].center).norm();
            b != a && d >= min_leg && d <= max_leg
        }));
        for (i, &b) in near.iter().enumerate() {
            for &c in &near[i + 1..] {
                if let Some(t) = check_triple(&finders[a], &finders[b], &finders[c], &legs) {
                    triples.push((t, [a, b, c]));
                }
            }
        }
    }
    triples.sort_by(|x, y| x.0.misfit.total_cmp(&y.0.misfit));
    let mut used = vec![false; n];
    let mut kept = Vec::new();
    for (t, ids) in triples {
        if ids.iter().any(|&i| used[i]) {
            continue;
        }
        for i in ids {
            used[i] = true;
        }
        kept.push(t);
    }
    kept
}

/// Accepted leg lengths in modules, with tolerance, and the nominal one.
struct LegRange {
    min: f64,
    max: f64,
    nominal: f64,
}

impl LegRange {
    fn new(half_periods: usize) -> Self {
        let lo = half_periods.saturating_sub(WIDTH_SLACK).max(17) - 7;
        let hi = half_periods + WIDTH_SLACK - 7;
        LegRange {
            min: lo as f64 * (1.0 - SCALE_TOLERANCE),
            max: hi as f64 * (1.0 + SCALE_TOLERANCE),
            nominal: half_periods.saturating_sub(7).max(1) as f64,
        }
    }
}

/// `a` as the corner, `b` and `c` the two others; `None` unless the geometry fits.
fn check_triple(a: &Finder, b: &Finder, c: &Finder, legs: &LegRange) -> Option<FinderTriple> {
    if a.polarity != b.polarity || a.polarity != c.polarity {
        return None;
    }
    let (u, v) = (b.center - a.center, c.center - a.center);
    let (lu, lv) = (u.norm(), v.norm());
    let leg = 0.5 * (lu + lv);
    if leg <= 0.0 {
        return None;
    }
    let leg_misfit = (lu - lv).abs() / leg;
    let cos = u.dot(&v) / (lu * lv);
    if leg_misfit > LEG_TOLERANCE || cos.abs() > MAX_CORNER_COS {
        return None;
    }
    // Scan chords are 7 modules / cos θ, θ = marker rotation folded into [0, π/4].
    let theta = u.y.atan2(u.x).rem_euclid(std::f64::consts::FRAC_PI_2);
    let fold = theta.min(std::f64::consts::FRAC_PI_2 - theta).cos();
    let chords = [a.chord, b.chord, c.chord];
    let mean_chord = chords.iter().sum::<f64>() / 3.0;
    if chords
        .iter()
        .any(|&ch| (ch - mean_chord).abs() > SIZE_TOLERANCE * mean_chord)
    {
        return None;
    }
    let module_px = mean_chord * fold / 7.0;
    let leg_modules = leg / module_px;
    if !(legs.min..=legs.max).contains(&leg_modules) {
        return None;
    }
    // Ranking prefers the nominal width, mildly.
    let scale_misfit = 0.1 * (leg_modules / legs.nominal).ln();
    let (right, bottom) = if u.x * v.y - u.y * v.x >= 0.0 {
        (b.center, c.center)
    } else {
        (c.center, b.center)
    };
    Some(FinderTriple {
        corner: a.center,
        right,
        bottom,
        module_px,
        polarity: a.polarity,
        misfit: leg_misfit.powi(2) + cos.powi(2) + scale_misfit.powi(2),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finder(x: f64, y: f64, chord: f64) -> Finder {
        Finder {
            center: Vector2::new(x, y),
            chord,
            polarity: Polarity::BrightDots,
            row_hits: 5,
            col_hits: 5,
        }
    }

    #[test]
    fn groups_two_markers_and_ignores_a_stray_finder() {
        // W = 33: legs of 26 modules; module 4 px → legs 104 px, chords 28 px.
        let mut finders = vec![
            finder(100.0, 100.0, 28.0),
            finder(204.0, 100.0, 28.0),
            finder(100.0, 204.0, 28.0),
            finder(430.0, 60.0, 28.0),
            // A stray finder near the first marker.
            finder(150.0, 260.0, 28.0),
        ];
        // Second marker rotated by 90° clockwise: right = +y on screen.
        finders.push(finder(500.0, 300.0, 28.0));
        finders.push(finder(500.0, 404.0, 28.0));
        finders.push(finder(396.0, 300.0, 28.0));
        let triples = group_finders(&finders, 33);
        assert_eq!(triples.len(), 2, "{triples:?}");
        let first = triples
            .iter()
            .find(|t| t.corner == Vector2::new(100.0, 100.0))
            .unwrap();
        assert_eq!(first.right, Vector2::new(204.0, 100.0));
        assert_eq!(first.bottom, Vector2::new(100.0, 204.0));
        assert!((first.module_px - 4.0).abs() < 1e-9);
        let second = triples
            .iter()
            .find(|t| t.corner == Vector2::new(500.0, 300.0))
            .unwrap();
        assert_eq!(second.right, Vector2::new(500.0, 404.0));
        // Far from the nominal code size: no marker.
        assert!(group_finders(&finders, 53).is_empty());
        assert_eq!(group_finders(&finders, 37).len(), 2);
    }
}
