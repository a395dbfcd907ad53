//! Identity, orientation and period shift of a marker by matching its thumbnail against the
//! bitmaps (docs/design.md#stamp-matching, redesigned).
//!
//! A hypothesis maps thumbnail cells `i` (indices along the measured phases) to bitmap cells `j`
//! (relative to the bitmap's central dot) by `j = j0 + R·i`, `R` one of the 8 dihedral transforms
//! (4 rotations, optionally mirrored) and `j0` an even offset (dots land on dots). Its score is the
//! Pearson correlation between the thumbnail's grey levels and the bitmap's 0/1 cells over every
//! thumbnail cell seen in the image (cells beyond the bitmap count as background, 0). The best
//! hypothesis over all bitmaps gives the marker's identity and where its origin lies in the
//! thumbnail (`i* = −R⁻¹·j0`), from which the pose follows without the original's re-orientation
//! table and its period-shift sign slip (docs/design.md#defect-stamp-shift).

use super::thumbnail::Thumbnail;
use crate::layout::BitmapLayout;
use crate::level_surface::{LevelSample, LevelSurface};

/// One of the 8 dihedral transforms from thumbnail cell axes to bitmap cell axes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Orientation {
    /// Quarter turns `r ∈ 0..4` of the rotation part.
    pub quarter_turns: u8,
    /// Whether a mirror (`i2 → −i2`) is applied before the rotation.
    pub mirrored: bool,
}

impl Orientation {
    /// The 8 transforms, proper rotations first.
    pub(crate) const ALL: [Orientation; 8] = [
        Orientation::new(0, false),
        Orientation::new(1, false),
        Orientation::new(2, false),
        Orientation::new(3, false),
        Orientation::new(0, true),
        Orientation::new(1, true),
        Orientation::new(2, true),
        Orientation::new(3, true),
    ];

    const fn new(quarter_turns: u8, mirrored: bool) -> Self {
        Orientation {
            quarter_turns,
            mirrored,
        }
    }

    /// Integer matrix `R` (row-major) with `j = j0 + R·i`.
    pub(crate) fn matrix(&self) -> [[i64; 2]; 2] {
        let (c, s) = match self.quarter_turns % 4 {
            0 => (1, 0),
            1 => (0, 1),
            2 => (-1, 0),
            _ => (0, -1),
        };
        let m = if self.mirrored { -1 } else { 1 };
        // Rot(r)·diag(1, m).
        [[c, -s * m], [s, c * m]]
    }

    /// `R⁻¹·v`, from bitmap cell axes to thumbnail cell axes (R is orthogonal: the inverse
    /// is the transpose); exact for integer cells.
    pub(crate) fn inverse_apply(&self, v: [f64; 2]) -> [f64; 2] {
        let m = self.matrix().map(|row| row.map(|x| x as f64));
        [
            m[0][0] * v[0] + m[1][0] * v[1],
            m[0][1] * v[0] + m[1][1] * v[1],
        ]
    }
}

/// A bitmap prepared for matching: its set cells relative to the central cell.
#[derive(Clone, Debug)]
pub(crate) struct Template {
    /// `(jx, jy)`: column and row offsets of every set cell from the central cell.
    cells: Vec<[i64; 2]>,
    /// Half extents `((Wb − 1)/2, (Hb − 1)/2)`, cells.
    pub half: [i64; 2],
    bitmap: BitmapLayout,
}

impl Template {
    pub(crate) fn new(bitmap: &BitmapLayout) -> Self {
        let (rows, cols) = (bitmap.cell_rows(), bitmap.cell_cols());
        let half = [(cols as i64 - 1) / 2, (rows as i64 - 1) / 2];
        let mut cells = Vec::new();
        for r in 0..rows {
            for c in 0..cols {
                if bitmap.cell(r, c) {
                    cells.push([c as i64 - half[0], r as i64 - half[1]]);
                }
            }
        }
        Template {
            cells,
            half,
            bitmap: bitmap.clone(),
        }
    }

    /// Whether the cell at offset `j` from the central cell is set (false outside).
    pub(crate) fn is_set(&self, j: [i64; 2]) -> bool {
        let (c, r) = (j[0] + self.half[0], j[1] + self.half[1]);
        c >= 0 && r >= 0 && self.bitmap.cell(r as usize, c as usize)
    }
}

/// The winning hypothesis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Match {
    /// Index of the bitmap.
    pub bitmap: usize,
    pub orientation: Orientation,
    /// Thumbnail cell `(i1, i2)` of the bitmap's central dot (both even).
    pub origin_cell: [i64; 2],
    /// Pearson correlation of the winner, `[−1, 1]`: of its levels flattened for the light
    /// ([`CellReader`]) when it has isolated dots and open gaps, of the raw levels otherwise.
    pub correlation: f64,
    /// Cell vote of the winner against its rivals, `[−1, 1]`: on the thumbnail cells where
    /// the winner and a rival predict different values, `(agreeing − disagreeing)/compared`
    /// cells, each cell counting as much as its neighbourhood reads as the winner predicts
    /// (an occluded cell is no evidence either way), the smallest over the rivals (the best
    /// hypothesis at another placement, and every other bitmap at the winner's placement). 1
    /// without rivals; 0 when a rival predicts the same cells (an ambiguous reading), except a
    /// mirrored view of the winner's own bitmap that a mirror symmetry of it makes identical:
    /// that is the same marker, and the proper reading stands.
    pub vote: f64,
}

/// A hypothesis: bitmap, orientation and thumbnail cell of its central dot.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Hypothesis {
    bitmap: usize,
    orientation: Orientation,
    origin_cell: [i64; 2],
}

/// Which hypotheses to try.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SearchRange {
    /// Thumbnail cells where the bitmap's central dot may lie: `[min, max]` per axis
    /// (inclusive; only even cells are tried).
    pub origin: [[i64; 2]; 2],
    /// Whether mirrored views are possible. Mirrored hypotheses are always tried (so that a
    /// mirrored marker is recognised rather than mis-read), but when they are not possible
    /// they are no rivals in [`Match::vote`].
    pub mirrored_allowed: bool,
    /// Minimum fraction of a bitmap's set cells that must fall on seen thumbnail cells.
    pub min_overlap: f64,
}

/// Best hypothesis over all `templates`, or `None` when the thumbnail has no contrast or no
/// hypothesis overlaps it enough.
///
/// Hypotheses are ranked twice: on the raw levels, and on levels flattened for the light
/// without any hypothesis (on the lattice's dot and gap cells, [`lattice_cells`]). Under an
/// illumination gradient at low contrast, raw levels may correlate better with a wrong reading
/// than with the right one (a mirrored `stamp69x69`, its glyph cells outweighed by the light),
/// while large solid frames and glyphs spoil the hypothesis-free references. Of the two
/// leaders, the one whose own cells correlate better on levels flattened with its own
/// references ([`CellReader`]) wins.
pub(crate) fn best_match(
    thumb: &Thumbnail,
    templates: &[Template],
    range: &SearchRange,
) -> Option<Match> {
    let (dots, gaps) = lattice_cells(thumb);
    let rankings: Vec<Vec<(Hypothesis, f64)>> =
        [Some(raw_levels(thumb)), flatten_levels(thumb, &dots, &gaps)]
            .into_iter()
            .flatten()
            .filter_map(|levels| rank_hypotheses(thumb, templates, range, &levels))
            .collect();
    // Each ranking's leader, its cells read on levels flattened with its own references (an
    // illumination gradient over a stamp of low contrast lowers the correlation of raw
    // levels: 0.43 for stamp G of `stampPatternImage_15um.jpg` at contrast × 0.3 under a gain
    // from 0.3 to 1). Raw first: a tie keeps it, and a leader that raw levels led too is not
    // read again.
    let (chosen, reader, correlation) = rankings
        .iter()
        .enumerate()
        .filter(|(k, ranked)| *k == 0 || ranked[0].0 != rankings[0][0].0)
        .map(|(k, ranked)| {
            let (leader, r) = ranked[0];
            let reader = CellReader::new(thumb, templates, &leader);
            let correlation = reader
                .as_ref()
                .and_then(|c| c.correlation(thumb, |i| predicts_set(templates, &leader, i)))
                .unwrap_or(r);
            (k, reader, correlation)
        })
        .reduce(|best, next| if next.2 > best.2 { next } else { best })?;
    let scored = &rankings[chosen];
    let winner = scored[0].0;
    // Rivals: the best other placement, and the other bitmaps at the winner's placement.
    let runner_up = scored.iter().skip(1).map(|&(h, _)| h).find(|h| {
        let placed_elsewhere =
            h.orientation != winner.orientation || h.origin_cell != winner.origin_cell;
        let possible = range.mirrored_allowed || !h.orientation.mirrored;
        let self_mirror = h.bitmap == winner.bitmap
            && h.orientation.mirrored
            && !winner.orientation.mirrored
            && distinguishing_cells(thumb, templates, &winner, h) == 0;
        placed_elsewhere && possible && !self_mirror
    });
    let mut rivals: Vec<Hypothesis> = runner_up.into_iter().collect();
    rivals.extend(
        (0..templates.len())
            .filter(|&k| k != winner.bitmap)
            .map(|bitmap| Hypothesis { bitmap, ..winner }),
    );
    let vote = cell_vote(thumb, templates, &winner, reader.as_ref(), &rivals);
    log::trace!("match {winner:?} r {correlation:.3} vote {vote:.3}; rivals {rivals:?}");
    Some(Match {
        bitmap: winner.bitmap,
        orientation: winner.orientation,
        origin_cell: winner.origin_cell,
        correlation,
        vote,
    })
}

/// Every hypothesis over `templates` in `range` with its Pearson correlation on `levels`
/// (row-major per thumbnail cell, `None` unseen), best first (a mirrored one ranked
/// [`MIRROR_MARGIN`] lower); `None` when the levels do not vary or no hypothesis overlaps the
/// seen cells enough.
fn rank_hypotheses(
    thumb: &Thumbnail,
    templates: &[Template],
    range: &SearchRange,
    levels: &[Option<f64>],
) -> Option<Vec<(Hypothesis, f64)>> {
    let grid = CentredLevels::new(thumb, templates, levels)?;
    // Every hypothesis tried, with its correlation.
    let mut scored: Vec<(Hypothesis, f64)> = Vec::new();
    let mut offsets: Vec<i64> = Vec::new();
    for (bitmap, template) in templates.iter().enumerate() {
        if template.cells.is_empty() {
            continue;
        }
        for orientation in Orientation::ALL {
            grid.score_origins(
                thumb,
                range,
                (bitmap, template),
                orientation,
                &mut offsets,
                &mut scored,
            );
        }
    }
    // A mirrored reading must beat a proper one clearly: with a bitmap that is its own mirror
    // image both predict the same cells and tie up to rounding.
    let rank = |(h, r): &(Hypothesis, f64)| {
        r - if h.orientation.mirrored {
            MIRROR_MARGIN
        } else {
            0.0
        }
    };
    scored.sort_by(|a, b| rank(b).total_cmp(&rank(a)));
    (!scored.is_empty()).then_some(scored)
}

/// The thumbnail's seen levels, centred on their mean and padded by the largest template
/// radius so that every lookup is in bounds: each entry holds (value − mean, 1) on seen cells
/// and (0, 0) elsewhere.
struct CentredLevels {
    grid: Vec<[f32; 2]>,
    /// Padding, cells.
    pad: i64,
    /// Padded width, cells.
    pw: i64,
    /// Number of seen cells.
    n: usize,
    /// `√(n·var)` of the seen levels.
    norm: f64,
}

impl CentredLevels {
    /// `None` with fewer than 16 seen cells or levels that do not vary.
    fn new(
        thumb: &Thumbnail,
        templates: &[Template],
        levels: &[Option<f64>],
    ) -> Option<CentredLevels> {
        let seen: Vec<f64> = levels.iter().flatten().copied().collect();
        let n = seen.len();
        if n < 16 {
            return None;
        }
        let mean = seen.iter().sum::<f64>() / n as f64;
        let var = seen.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
        // NaN-safe: a NaN variance is rejected too.
        if var.is_nan() || var <= 1e-12 {
            return None;
        }
        let pad = templates.iter().map(|t| t.half[0].max(t.half[1])).max()? + 1;
        let pw = thumb.len[0] as i64 + 2 * pad;
        let ph = thumb.len[1] as i64 + 2 * pad;
        let mut grid = vec![[0.0f32; 2]; (pw * ph) as usize];
        for r in 0..thumb.len[1] {
            for c in 0..thumb.len[0] {
                if let Some(v) = levels[r * thumb.len[0] + c] {
                    let k = (r as i64 + pad) * pw + c as i64 + pad;
                    grid[k as usize] = [(v - mean) as f32, 1.0];
                }
            }
        }
        Some(CentredLevels {
            grid,
            pad,
            pw,
            n,
            norm: (n as f64 * var).sqrt(),
        })
    }

    /// Scores `template` (index `bitmap`) in `orientation` at every origin cell of `range`
    /// where it stays inside the padded grid and overlaps enough seen cells, into `scored`.
    /// `offsets` is scratch.
    fn score_origins(
        &self,
        thumb: &Thumbnail,
        range: &SearchRange,
        (bitmap, template): (usize, &Template),
        orientation: Orientation,
        offsets: &mut Vec<i64>,
        scored: &mut Vec<(Hypothesis, f64)>,
    ) {
        let (pad, pw, n, norm, grid) = (self.pad, self.pw, self.n, self.norm, &self.grid);
        let total = template.cells.len();
        // Padded index of thumbnail cell (i1, i2).
        let index = |i: [i64; 2]| {
            let (c, r) = thumb.index(i);
            (r + pad) * pw + c + pad
        };
        let even_up = |v: i64| v + v.rem_euclid(2);
        // Template cells in thumbnail axes, as padded-index offsets from the origin cell.
        offsets.clear();
        offsets.extend(template.cells.iter().map(|&j| {
            let i = orientation.inverse_apply([j[0] as f64, j[1] as f64]);
            i[1] as i64 * pw + i[0] as i64
        }));
        let reach = template.half[0].max(template.half[1]);
        let mut o2 = even_up(range.origin[1][0]);
        while o2 <= range.origin[1][1] {
            let mut o1 = even_up(range.origin[0][0]);
            while o1 <= range.origin[0][1] {
                let origin = [o1, o2];
                o1 += 2;
                // The whole template must stay inside the padded grid.
                let (c, r) = thumb.index(origin);
                if c + pad < reach
                    || r + pad < reach
                    || c + reach >= thumb.len[0] as i64 + pad
                    || r + reach >= thumb.len[1] as i64 + pad
                {
                    continue;
                }
                let base = index(origin);
                let (mut s1, mut n1) = (0.0f32, 0.0f32);
                for &o in offsets.iter() {
                    let [v, seen] = grid[(base + o) as usize];
                    s1 += v;
                    n1 += seen;
                }
                let n1 = n1 as f64;
                if n1 < range.min_overlap * total as f64 || n1 >= n as f64 {
                    continue;
                }
                // Pearson correlation with the 0/1 template over the seen cells.
                let p = n1 / n as f64;
                let r = s1 as f64 / (norm * (n as f64 * p * (1.0 - p)).sqrt());
                let h = Hypothesis {
                    bitmap,
                    orientation,
                    origin_cell: origin,
                };
                scored.push((h, r));
            }
            o2 += 2;
        }
    }
}

/// Smallest local contrast between the fitted dot and gap levels, in units of the whole
/// thumbnail's: where a fitted surface strays (beyond the field, where no dot is), the
/// flattened levels would blow up.
const MIN_CONTRAST_FRACTION: f64 = 0.25;

/// Cells of a thumbnail as `[c, r, level]`, `(c, r)` the thumbnail index.
type CellSamples = Vec<LevelSample>;

/// The seen cells of `thumb` that show the lattice's own levels under a hypothesis (`set`
/// says which cells it predicts set): the isolated dots (dot cells predicted set, their four
/// side neighbours unset) and the open gaps (gap centres predicted unset, their four side
/// neighbours unset).
fn lattice_references(
    thumb: &Thumbnail,
    set: &impl Fn([i64; 2]) -> bool,
) -> (CellSamples, CellSamples) {
    let sides_unset = |i: [i64; 2]| {
        [[1, 0], [-1, 0], [0, 1], [0, -1]]
            .iter()
            .all(|d| !set([i[0] + d[0], i[1] + d[1]]))
    };
    lattice_samples(
        thumb,
        |i| set(i) && sides_unset(i),
        |i| !set(i) && sides_unset(i),
    )
}

/// The seen cells of `thumb` on the lattice's dot positions and gap centres, whatever the
/// bitmap: mostly dots and open gaps, the rest (missing dots, a frame's or glyph's cells) few
/// enough for [`LevelSurface::fit`] to leave out as outliers.
fn lattice_cells(thumb: &Thumbnail) -> (CellSamples, CellSamples) {
    lattice_samples(thumb, |_| true, |_| true)
}

/// The seen cells of `thumb` at dot positions (both lattice indices even) that `dot` keeps and
/// at gap centres (both odd) that `gap` keeps.
fn lattice_samples(
    thumb: &Thumbnail,
    dot: impl Fn([i64; 2]) -> bool,
    gap: impl Fn([i64; 2]) -> bool,
) -> (CellSamples, CellSamples) {
    let [cols, rows] = thumb.len;
    let (mut dots, mut gaps) = (Vec::new(), Vec::new());
    for r in 0..rows {
        for c in 0..cols {
            let Some(v) = thumb.values[r * cols + c] else {
                continue;
            };
            let i = thumb.cell(c as i64, r as i64);
            match (i[0].rem_euclid(2), i[1].rem_euclid(2)) {
                (0, 0) if dot(i) => dots.push([c as f64, r as f64, v as f64]),
                (1, 1) if gap(i) => gaps.push([c as f64, r as f64, v as f64]),
                _ => {}
            }
        }
    }
    (dots, gaps)
}

/// Each seen cell's level relative to the light where it is, `n = (v − gaps)/(dots − gaps)`:
/// 0 on an open gap, 1 on a dot, from quadratic surfaces fitted to the `dots` and `gaps`
/// samples across the thumbnail ([`CellReader`]); row-major like the thumbnail, `None` where
/// unseen. `None` when either surface cannot be fitted or the two do not differ.
fn flatten_levels(
    thumb: &Thumbnail,
    dots: &[LevelSample],
    gaps: &[LevelSample],
) -> Option<Vec<Option<f64>>> {
    let [cols, rows] = thumb.len;
    // Cell positions scaled from the thumbnail's extent (at least two cells).
    let extent = [cols.max(2) as f64, rows.max(2) as f64];
    let fit = |samples: &[LevelSample]| LevelSurface::fit(samples, [0.0, 0.0], extent);
    let (dot, gap) = (fit(dots)?, fit(gaps)?);
    let whole_contrast = mean_level(dots) - mean_level(gaps);
    if whole_contrast.is_nan() || whole_contrast == 0.0 {
        return None;
    }
    let sign = whole_contrast.signum();
    let min_contrast = MIN_CONTRAST_FRACTION * whole_contrast.abs();
    let levels = (0..rows * cols)
        .map(|k| {
            let v = thumb.values[k]? as f64;
            let (x, y) = ((k % cols) as f64, (k / cols) as f64);
            let (dot, gap) = (dot.at(x, y), gap.at(x, y));
            Some((v - gap) / (sign * ((dot - gap) * sign).max(min_contrast)))
        })
        .collect();
    Some(levels)
}

/// Each cell's level as it is, row-major like the thumbnail, `None` where unseen.
fn raw_levels(thumb: &Thumbnail) -> Vec<Option<f64>> {
    thumb.values.iter().map(|v| v.map(f64::from)).collect()
}

/// Mean level of cell samples `[c, r, level]` (NaN for none).
fn mean_level(samples: &[LevelSample]) -> f64 {
    samples.iter().map(|s| s[2]).sum::<f64>() / samples.len() as f64
}

/// Reads the thumbnail's cells as set or unset under a hypothesis, on levels flattened for the
/// illumination. Two kinds of cell look alike everywhere in the lattice, unlike those of a
/// solid frame or glyph: the *isolated dots* (dot cells that the hypothesis predicts set, their
/// four side neighbours unset) and the *open gaps* (gap-centre cells predicted unset, their
/// four side neighbours unset). A quadratic surface fitted to each across the thumbnail
/// follows the light (a vignette, an illumination gradient) and not the layout, and each
/// cell's level is taken relative to them: `n = (v − gaps)/(dots − gaps)`, 0 on an open gap
/// and 1 on an isolated dot whatever the gain and offset there. The threshold is then one
/// for the whole thumbnail: halfway between the mean flattened levels of the cells predicted
/// set and of those predicted unset.
struct CellReader {
    /// Flattened level per cell, row-major like the thumbnail; `None` where unseen.
    levels: Vec<Option<f64>>,
    /// Columns of the thumbnail.
    cols: usize,
    /// Flattened level halfway between set and unset cells.
    threshold: f64,
    /// Set cells read above the threshold (always so on flattened levels; raw levels of dark
    /// dots read below it).
    bright_set: bool,
    /// Whether the levels are flattened (the hypothesis has isolated dots and open gaps).
    flattened: bool,
}

impl CellReader {
    /// `None` when the hypothesis predicts no seen cell set, or none unset.
    fn new(thumb: &Thumbnail, templates: &[Template], h: &Hypothesis) -> Option<Self> {
        let cols = thumb.len[0];
        let set = |i: [i64; 2]| predicts_set(templates, h, i);
        let (dots, gaps) = lattice_references(thumb, &set);
        // Without isolated dots or open gaps (a bitmap of solid shapes): levels as they are.
        let flattened = flatten_levels(thumb, &dots, &gaps);
        let references = flattened.is_some();
        let levels = flattened.unwrap_or_else(|| raw_levels(thumb));
        let (mut s1, mut n1, mut s0, mut n0) = (0.0, 0usize, 0.0, 0usize);
        for (k, level) in levels.iter().enumerate() {
            if let Some(n) = level {
                if set(thumb.cell((k % cols) as i64, (k / cols) as i64)) {
                    s1 += n;
                    n1 += 1;
                } else {
                    s0 += n;
                    n0 += 1;
                }
            }
        }
        let (m1, m0) = (s1 / n1 as f64, s0 / n0 as f64);
        (n1 > 0 && n0 > 0).then(|| CellReader {
            levels,
            cols,
            threshold: (m1 + m0) / 2.0,
            bright_set: m1 > m0,
            flattened: references,
        })
    }

    /// Pearson correlation of the flattened levels with the cells `set` predicts (1 set, 0
    /// unset), over the seen cells: the thumbnail's correlation with the bitmap once the light
    /// is taken out. `None` on raw levels or when either side does not vary.
    fn correlation(&self, thumb: &Thumbnail, set: impl Fn([i64; 2]) -> bool) -> Option<f64> {
        if !self.flattened {
            return None;
        }
        let (mut n, mut sx, mut sy, mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
        for (k, level) in self.levels.iter().enumerate() {
            let Some(x) = *level else { continue };
            let y = f64::from(u8::from(set(
                thumb.cell((k % self.cols) as i64, (k / self.cols) as i64)
            )));
            n += 1.0;
            (sx, sy) = (sx + x, sy + y);
            (sxx, syy, sxy) = (sxx + x * x, syy + y * y, sxy + x * y);
        }
        let (vx, vy) = (sxx - sx * sx / n, syy - sy * sy / n);
        (vx > 0.0 && vy > 0.0).then(|| (sxy - sx * sy / n) / (vx * vy).sqrt())
    }

    /// Whether the cell at thumbnail index `(c, r)` (inside the thumbnail) reads as set;
    /// `None` where unseen.
    fn reads_set(&self, c: i64, r: i64) -> Option<bool> {
        let n = self.levels[r as usize * self.cols + c as usize]?;
        Some((n > self.threshold) == self.bright_set)
    }
}

/// Correlation margin a mirrored hypothesis needs over a proper one.
const MIRROR_MARGIN: f64 = 1e-6;

/// Seen thumbnail cells.
fn seen_cells(thumb: &Thumbnail) -> impl Iterator<Item = [i64; 2]> + '_ {
    (0..thumb.len[1]).flat_map(move |r| {
        (0..thumb.len[0]).filter_map(move |c| {
            thumb.values[r * thumb.len[0] + c]?;
            Some(thumb.cell(c as i64, r as i64))
        })
    })
}

/// Seen thumbnail cells where hypotheses `a` and `b` predict different values.
fn distinguishing_cells(
    thumb: &Thumbnail,
    templates: &[Template],
    a: &Hypothesis,
    b: &Hypothesis,
) -> usize {
    seen_cells(thumb)
        .filter(|&i| predicts_set(templates, a, i) != predicts_set(templates, b, i))
        .count()
}

/// Whether hypothesis `h` predicts a set cell at thumbnail cell `i`.
fn predicts_set(templates: &[Template], h: &Hypothesis, i: [i64; 2]) -> bool {
    let m = h.orientation.matrix();
    let d = [i[0] - h.origin_cell[0], i[1] - h.origin_cell[1]];
    let j = [
        m[0][0] * d[0] + m[0][1] * d[1],
        m[1][0] * d[0] + m[1][1] * d[1],
    ];
    templates.get(h.bitmap).is_some_and(|t| t.is_set(j))
}

/// Cell-by-cell vote of `winner` against each rival (see [`Match::vote`]).
fn cell_vote(
    thumb: &Thumbnail,
    templates: &[Template],
    winner: &Hypothesis,
    reader: Option<&CellReader>,
    rivals: &[Hypothesis],
) -> f64 {
    let cells: Vec<[i64; 2]> = seen_cells(thumb).collect();
    let Some(reader) = reader else {
        return 0.0;
    };
    // Whether the cell at thumbnail index (col, row) reads as the winner predicts (None:
    // unseen or outside).
    let (cols, rows) = (thumb.len[0] as i64, thumb.len[1] as i64);
    let reads_as_winner = |c: i64, r: i64| {
        if c < 0 || r < 0 || c >= cols || r >= rows {
            return None;
        }
        Some(reader.reads_set(c, r)? == predicts_set(templates, winner, thumb.cell(c, r)))
    };
    // How far a cell's reading is evidence: as much as its 8 neighbours read as the winner
    // predicts (all: 1; half or fewer: 0). A dust speck or a hair over a few cells that tell
    // two bitmaps apart also spoils the cells around them, so it cannot fake a glyph.
    let weight = |i: [i64; 2]| {
        let (c, r) = thumb.index(i);
        let (mut good, mut seen) = (0usize, 0usize);
        for (dc, dr) in [
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ] {
            if let Some(ok) = reads_as_winner(c + dc, r + dr) {
                seen += 1;
                good += usize::from(ok);
            }
        }
        if seen == 0 {
            return 0.0;
        }
        (2.0 * good as f64 / seen as f64 - 1.0).max(0.0)
    };
    let mut vote = 1.0f64;
    for rival in rivals {
        let (mut net, mut compared, mut evidence) = (0.0f64, 0usize, 0.0f64);
        for &i in &cells {
            let set = predicts_set(templates, winner, i);
            if set != predicts_set(templates, rival, i) {
                compared += 1;
                let (c, r) = thumb.index(i);
                let sign = if reader.reads_set(c, r) == Some(set) {
                    1.0
                } else {
                    -1.0
                };
                let w = weight(i);
                net += sign * w;
                evidence += w;
            }
        }
        log::trace!(
            "rival {rival:?}: net {net:.2} of {evidence:.2} weighted cells, {compared} compared"
        );
        let v = if compared == 0 {
            0.0
        } else {
            net / compared as f64
        };
        vote = vote.min(v);
    }
    vote
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn orientation_matrices_form_the_dihedral_group() {
        let mut seen = Vec::new();
        for o in Orientation::ALL {
            let m = o.matrix();
            let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
            assert_eq!(det, if o.mirrored { -1 } else { 1 });
            let j = [m[0][0] * 2 + m[0][1] * 5, m[1][0] * 2 + m[1][1] * 5];
            let back = o.inverse_apply([j[0] as f64, j[1] as f64]);
            assert_eq!(back, [2.0, 5.0]);
            assert!(!seen.contains(&m));
            seen.push(m);
        }
    }

    #[test]
    fn finds_rotation_and_shift_of_an_asymmetric_bitmap() {
        // 9×9 bitmap: dots on even cells plus an L-shaped glyph.
        let mut rows = vec![vec![0u8; 9]; 9];
        for r in (0..9).step_by(2) {
            for c in (0..9).step_by(2) {
                rows[r][c] = 1;
            }
        }
        rows[1][..5].fill(1);
        rows[3][1] = 1;
        let bitmap = BitmapLayout::from_rows(1.0, &rows).unwrap();
        let template = Template::new(&bitmap);
        let truth = Orientation::new(3, false);
        let origin = [2i64, -2];
        // Thumbnail 17×17 cells from −8: cell i sees bitmap cell j = R·(i − origin).
        let (lo, len) = ([-8i64, -8], [17usize, 17]);
        let m = truth.matrix();
        let mut values = Vec::new();
        for i2 in lo[1]..lo[1] + 17 {
            for i1 in lo[0]..lo[0] + 17 {
                let d = [i1 - origin[0], i2 - origin[1]];
                let j = [
                    m[0][0] * d[0] + m[0][1] * d[1],
                    m[1][0] * d[0] + m[1][1] * d[1],
                ];
                let (c, r) = (j[0] + 4, j[1] + 4);
                let on = (0..9).contains(&c)
                    && (0..9).contains(&r)
                    && bitmap.cell(r as usize, c as usize);
                values.push(Some(if on { 0.9 } else { 0.1 }));
            }
        }
        let thumb = Thumbnail { lo, len, values };
        let template_again =
            |rows: &Vec<Vec<u8>>| Template::new(&BitmapLayout::from_rows(1.0, rows).unwrap());
        let range = SearchRange {
            origin: [[-4, 4], [-4, 4]],
            mirrored_allowed: true,
            min_overlap: 0.9,
        };
        let found = best_match(&thumb, &[template], &range).unwrap();
        assert_eq!(found.orientation, truth);
        assert_eq!(found.origin_cell, origin);
        assert!((found.correlation - 1.0).abs() < 1e-5, "{found:?}");
        assert_eq!(found.vote, 1.0, "{found:?}");
        // A second bitmap without the glyph's corner cell: still the first, by a clear vote.
        let mut other_rows = rows.clone();
        other_rows[3][1] = 0;
        other_rows[1][0] = 0;
        let other = Template::new(&BitmapLayout::from_rows(1.0, &other_rows).unwrap());
        let found = best_match(&thumb, &[other, template_again(&rows)], &range).unwrap();
        assert_eq!(found.bitmap, 1);
        assert_eq!(found.vote, 1.0, "{found:?}");
    }

    /// A thumbnail of `rows` seen through the identity hypothesis (thumbnail cell = bitmap
    /// cell), each cell's level `level(set, column)`.
    fn seen(rows: &[Vec<u8>], level: impl Fn(bool, usize) -> f32) -> (Thumbnail, Template) {
        let (h, w) = (rows.len(), rows[0].len());
        let bitmap = BitmapLayout::from_rows(1.0, rows).unwrap();
        let values = (0..h * w)
            .map(|k| Some(level(rows[k / w][k % w] == 1, k % w)))
            .collect();
        let half = [(w as i64 - 1) / 2, (h as i64 - 1) / 2];
        let thumb = Thumbnail {
            lo: [-half[0], -half[1]],
            len: [w, h],
            values,
        };
        (thumb, Template::new(&bitmap))
    }

    /// Whether every cell of `thumb` reads as `rows` has it.
    fn reads_as_drawn(thumb: &Thumbnail, template: Template, rows: &[Vec<u8>]) -> bool {
        let h = Hypothesis {
            bitmap: 0,
            orientation: Orientation::new(0, false),
            origin_cell: [0, 0],
        };
        let reader = CellReader::new(thumb, &[template], &h).unwrap();
        let w = rows[0].len();
        (0..rows.len() * w).all(|k| {
            reader.reads_set((k % w) as i64, (k / w) as i64) == Some(rows[k / w][k % w] == 1)
        })
    }

    #[test]
    fn cells_read_against_the_light_where_they_are() {
        // 41 × 41 cells: dots on even cells, a solid bar (a glyph) across row 5 and down column
        // 33. Dark dots, the light falling from 1 to 0.2 across the columns: on one threshold
        // for the whole thumbnail the dim side's bar reads as gaps.
        let n = 41;
        let mut rows = vec![vec![0u8; n]; n];
        for r in (0..n).step_by(2) {
            for c in (0..n).step_by(2) {
                rows[r][c] = 1;
            }
        }
        rows[5][4..37].fill(1);
        (5..30).for_each(|r| rows[r][33] = 1);
        let light = |c: usize| 1.0 - 0.8 * c as f32 / (n - 1) as f32;
        let (thumb, template) = seen(&rows, |set, c| light(c) * if set { 0.15 } else { 0.9 });
        assert!(reads_as_drawn(&thumb, template, &rows));
        // Without isolated dots (solid 2 × 2 squares on a 4-cell pitch, none cut to one cell
        // at the edges), the raw levels are read, dark ink as set.
        let inked = |v: usize| v % 4 == 1 || v % 4 == 2;
        let solid: Vec<Vec<u8>> = (0..n)
            .map(|r| (0..n).map(|c| u8::from(inked(r) && inked(c))).collect())
            .collect();
        let (thumb, template) = seen(&solid, |set, _| if set { 0.1 } else { 0.8 });
        assert!(reads_as_drawn(&thumb, template, &solid));
    }
}
