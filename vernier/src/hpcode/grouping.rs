//! Grouping finder squares into HP code markers (docs/design.md#hp-grouping, made robust).
//!
//! The original groups greedily by distance and only uses `3·⌊n/3⌋` finders, so one spurious finder
//! breaks every marker (docs/design.md#defect-hp-grouping). Here every triple of finders of the
//! same polarity is checked against the marker geometry — a right angle at the corner finder, two
//! equal legs, legs `W − 7` modules long, finders of equal size — and the best-fitting triples are
//! kept greedily without sharing a finder. Finders left over are ignored.
//!
//! The marker width `W` is a prior, not a constraint: legs of `W' − 7` modules are accepted for
//! any `W'` within [`WIDTH_SLACK`] cells of the nominal `W` (the original ignores `W`, and the
//! dark-dot example image documented as `W = 33` holds `W' = 39` markers). The fine step then
//! measures `W'` exactly in whole periods.

use super::finders::Finder;
use crate::grey_image::Polarity;
use nalgebra::Vector2;

/// Largest relative difference of the two legs.
const LEG_TOLERANCE: f64 = 0.2;
/// Largest `|cos|` of the corner angle (≈ 90° ± 14°: markers tilted by up to ~30°).
const MAX_CORNER_COS: f64 = 0.25;
/// Largest relative error of a leg length in modules (finder sizes are measured to a few %).
const SCALE_TOLERANCE: f64 = 0.15;
/// Accepted marker widths: nominal `W` ± this many half-period cells.
pub const WIDTH_SLACK: usize = 8;
/// Largest relative deviation of a finder's module from the triple's mean.
const SIZE_TOLERANCE: f64 = 0.25;

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

    /// The triple with `corner` at the right angle and `p`, `q` the two others, assigned so
    /// that `bottom` is 90° clockwise on screen from `right`.
    pub fn with_corner(
        corner: Vector2<f64>,
        p: Vector2<f64>,
        q: Vector2<f64>,
        module_px: f64,
        polarity: Polarity,
        misfit: f64,
    ) -> FinderTriple {
        let (u, v) = (p - corner, q - corner);
        let (right, bottom) = if u.x * v.y - u.y * v.x >= 0.0 {
            (p, q)
        } else {
            (q, p)
        };
        FinderTriple {
            corner,
            right,
            bottom,
            module_px,
            polarity,
            misfit,
        }
    }

    /// Whether `finder` is one of the three (within one module).
    pub fn uses(&self, finder: &Finder) -> bool {
        [self.corner, self.right, self.bottom]
            .iter()
            .any(|p| (p - finder.center).norm() < self.module_px.max(finder.module_px))
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

/// Marker triples among `finders` for markers about `code_size` (W) cells wide, best first,
/// none sharing a finder ([`candidate_triples`], [`disjoint_triples`]). `right`/`bottom` are
/// assigned so that `bottom` is 90° clockwise on screen from `right` (a marker seen from the
/// front); a mirrored marker is recognised later from its ID row.
pub fn group_finders(finders: &[Finder], code_size: usize) -> Vec<FinderTriple> {
    let candidates = candidate_triples(finders, code_size);
    let mut tried = vec![false; candidates.len()];
    disjoint_triples(&candidates, &vec![false; finders.len()], &mut tried)
        .into_iter()
        .map(|k| candidates[k].0)
        .collect()
}

/// Every triple among `finders` whose geometry fits a marker about `code_size` (W) cells wide,
/// with the indices of its finders, best fit first.
pub fn candidate_triples(finders: &[Finder], code_size: usize) -> Vec<(FinderTriple, [usize; 3])> {
    let legs = LegRange::new(code_size);
    let mut triples = Vec::new();
    let n = finders.len();
    let mut near = Vec::new();
    for a in 0..n {
        // Legs are (W − 7) modules.
        let module = finders[a].module_px;
        let max_leg = legs.max * module * (1.0 + SIZE_TOLERANCE);
        let min_leg = legs.min * module * (1.0 - SIZE_TOLERANCE);
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
    triples
}

/// The best-fitting of `candidates` ([`candidate_triples`]) not yet `tried`, none sharing a
/// finder with another or using one `taken`, greedily in their order; each is marked tried.
/// Returns their indices in `candidates`.
pub fn disjoint_triples(
    candidates: &[(FinderTriple, [usize; 3])],
    taken: &[bool],
    tried: &mut [bool],
) -> Vec<usize> {
    let mut used = taken.to_vec();
    let mut kept = Vec::new();
    for (k, (_, ids)) in candidates.iter().enumerate() {
        if tried[k] || ids.iter().any(|&i| used.get(i).copied().unwrap_or(true)) {
            continue;
        }
        for &i in ids {
            used[i] = true;
        }
        tried[k] = true;
        kept.push(k);
    }
    kept
}

/// Marker hypotheses from two finders where the third is missing (covered by dust, broken,
/// outside the finder test): for two finders one leg apart, the third on either side of
/// either; for two finders one diagonal apart, the corner on either side. Only finders not
/// flagged in `used`; at most `limit` hypotheses, best-matched finder sizes first. Each must be
/// confirmed by the marker's grid and ID before it becomes a marker.
pub fn pair_hypotheses(
    finders: &[Finder],
    code_size: usize,
    used: &[bool],
    limit: usize,
) -> Vec<FinderTriple> {
    let legs = LegRange::new(code_size);
    let mut out = Vec::new();
    for a in 0..finders.len() {
        for b in a + 1..finders.len() {
            let (fa, fb) = (&finders[a], &finders[b]);
            if used[a] || used[b] || fa.polarity != fb.polarity {
                continue;
            }
            let module = 0.5 * (fa.module_px + fb.module_px);
            if (fa.module_px - fb.module_px).abs() > SIZE_TOLERANCE * module {
                continue;
            }
            // Best-shaped, equal-sized finders first.
            let misfit = 1.0
                + ((fa.module_px - fb.module_px) / module).powi(2)
                + (2.0 - fa.score - fb.score);
            let u = fb.center - fa.center;
            let perp = Vector2::new(-u.y, u.x);
            let leg = u.norm() / module;
            let mut push = |corner: Vector2<f64>, p: Vector2<f64>, q: Vector2<f64>| {
                out.push(FinderTriple::with_corner(
                    corner,
                    p,
                    q,
                    module,
                    fa.polarity,
                    misfit,
                ));
            };
            if (legs.min..=legs.max).contains(&leg) {
                for s in [1.0, -1.0] {
                    push(fa.center, fb.center, fa.center + perp * s);
                    push(fb.center, fa.center, fb.center + perp * s);
                }
            }
            if (legs.min..=legs.max).contains(&(leg / std::f64::consts::SQRT_2)) {
                let mid = (fa.center + fb.center) / 2.0;
                for s in [0.5, -0.5] {
                    push(mid + perp * s, fa.center, fb.center);
                }
            }
        }
    }
    out.sort_by(|x, y| x.misfit.total_cmp(&y.misfit));
    out.truncate(limit);
    out
}

/// Accepted leg lengths in modules, with tolerance, and the nominal one.
struct LegRange {
    min: f64,
    max: f64,
    nominal: f64,
}

impl LegRange {
    fn new(code_size: usize) -> Self {
        let lo = code_size.saturating_sub(WIDTH_SLACK).max(17) - 7;
        let hi = code_size + WIDTH_SLACK - 7;
        LegRange {
            min: lo as f64 * (1.0 - SCALE_TOLERANCE),
            max: hi as f64 * (1.0 + SCALE_TOLERANCE),
            nominal: code_size.saturating_sub(7).max(1) as f64,
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
    let modules = [a.module_px, b.module_px, c.module_px];
    let module_px = modules.iter().sum::<f64>() / 3.0;
    if modules
        .iter()
        .any(|&m| (m - module_px).abs() > SIZE_TOLERANCE * module_px)
    {
        return None;
    }
    let leg_modules = leg / module_px;
    if !(legs.min..=legs.max).contains(&leg_modules) {
        return None;
    }
    // Ranking prefers the nominal width, mildly.
    let scale_misfit = 0.1 * (leg_modules / legs.nominal).ln();
    Some(FinderTriple::with_corner(
        a.center,
        b.center,
        c.center,
        module_px,
        a.polarity,
        leg_misfit.powi(2) + cos.powi(2) + scale_misfit.powi(2),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finder(x: f64, y: f64, chord: f64) -> Finder {
        Finder {
            center: Vector2::new(x, y),
            module_px: chord / 7.0,
            polarity: Polarity::BrightDots,
            score: 1.0,
            centre_hidden: false,
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
        // Far from the nominal code size (the prior accepts W ± 8) the true markers' legs are
        // too short; geometry alone may still pair distant stray finders, which the grid
        // checks of the fine step reject.
        assert!(group_finders(&finders, 101)
            .iter()
            .all(|t| t.corner != Vector2::new(100.0, 100.0)
                && t.corner != Vector2::new(500.0, 300.0)));
        assert_eq!(group_finders(&finders, 37).len(), 2);
    }

    #[test]
    fn later_rounds_offer_the_triples_whose_finders_are_free() {
        // A marker's three finders (legs 8 % apart) and a fourth finder that makes
        // better-fitting triples with two of them: the first round takes the best alone;
        // once the triples before it gave no marker, the marker's own is offered.
        let finders = vec![
            finder(100.0, 100.0, 28.0),
            finder(200.0, 100.0, 28.0),
            finder(100.0, 208.0, 28.0),
            finder(100.0, 0.0, 28.0),
        ];
        let candidates = candidate_triples(&finders, 33);
        let mut tried = vec![false; candidates.len()];
        let free = vec![false; finders.len()];
        let first = disjoint_triples(&candidates, &free, &mut tried);
        assert_eq!(first.len(), 1);
        assert!(candidates[first[0]].1.contains(&3), "{candidates:?}");
        let own = |k: &usize| candidates[*k].1.iter().all(|&i| i < 3);
        assert!(!first.iter().any(own));
        let later: Vec<usize> = (0..2)
            .flat_map(|_| disjoint_triples(&candidates, &free, &mut tried))
            .collect();
        assert!(later.iter().any(own), "{candidates:?}");
        // Finders taken by a marker found are offered to no later triple.
        let mut tried = vec![false; candidates.len()];
        let taken = vec![true, true, false, false];
        assert!(disjoint_triples(&candidates, &taken, &mut tried).is_empty());
    }
}
