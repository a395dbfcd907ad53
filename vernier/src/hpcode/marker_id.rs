//! Reading the marker ID from the measured dot grid (docs/design.md#layout-hpcode,
//! docs/design.md#hp-id, redone).
//!
//! The original samples a Bresenham line between two finders and binarises it with Otsu, which
//! throws on short lines (docs/design.md#defect-hp-grouping, Image134). Here the fine phase planes
//! give the exact image position of every dot, so each ID dot is sampled where it must be and
//! compared with a threshold halfway between the dots of the next row (always present) and the
//! empty cells in between (always background). The left dot column, which carries no ID, is read
//! the same way: in a marker seen from the front it is complete; a mirrored marker (seen from its
//! back, e.g. a flipped image) shows its ID there instead.

use crate::grey_image::{GreyImage, Polarity};
use crate::level_surface::{LevelSample, LevelSurface};
use crate::order_stats::robust_sigma;
use crate::sharpen::Sharpener;
use nalgebra::Vector2;
use std::f64::consts::PI;

/// Dot grid of one marker in the image: where dot `(row r, col c)` of the `n × n` marker is.
#[derive(Clone, Copy, Debug)]
pub(crate) struct DotGrid {
    /// Image position `(col, row)` of the centre dot, pixels.
    pub center: Vector2<f64>,
    /// Image displacement of one period along the pattern x axis, pixels.
    pub step_x: Vector2<f64>,
    /// Image displacement of one period along the pattern y axis, pixels.
    pub step_y: Vector2<f64>,
    /// Dots per side `n` (odd).
    pub size: usize,
    /// Perspective `p` of a tilted marker, per period: the dot `u = (c − h, r − h)` periods
    /// from the centre is at `center + (step_x·u₁ + step_y·u₂)/(1 + p·u)` (the general
    /// homography with this centre and these steps there); zero for an untilted marker.
    pub perspective: Vector2<f64>,
    /// True when the grid was fitted to the marker's own dots
    /// ([`super::dot_homography::fit_dot_homography`]): the ID is then read where it puts the
    /// dots, with no local search for them ([`reference_shifts`]).
    pub fitted_to_dots: bool,
}

impl DotGrid {
    /// The grid of an untilted marker: `n` dots per side, the centre dot at `center`, steps of
    /// one period along the pattern axes (image pixels).
    pub fn new(center: Vector2<f64>, step_x: Vector2<f64>, step_y: Vector2<f64>, n: usize) -> Self {
        DotGrid {
            center,
            step_x,
            step_y,
            size: n,
            perspective: Vector2::zeros(),
            fitted_to_dots: false,
        }
    }

    /// Image position of the point at dot coordinates `(r, c)` (fractional allowed).
    pub(crate) fn at(&self, r: f64, c: f64) -> Vector2<f64> {
        let h = self.half_width();
        self.at_marker(Vector2::new(c - h, r - h))
    }

    /// Image position of the point at marker coordinates `u = (c − h, r − h)` (periods from
    /// the centre dot along the pattern axes); [`DotGrid::marker_coordinates`] is its inverse.
    pub(crate) fn at_marker(&self, u: Vector2<f64>) -> Vector2<f64> {
        let depth = 1.0 + self.perspective.dot(&u);
        self.center + (self.step_x * u.x + self.step_y * u.y) / depth
    }

    /// Half the field's width `h = (n − 1)/2`, periods: the centre dot's index on both axes.
    pub(crate) fn half_width(&self) -> f64 {
        (self.size - 1) as f64 / 2.0
    }

    /// The steps at the centre as the columns of a matrix, image pixels per period.
    pub(crate) fn steps(&self) -> nalgebra::Matrix2<f64> {
        nalgebra::Matrix2::from_columns(&[self.step_x, self.step_y])
    }

    /// The same homography with its dots renumbered so that the dot at marker coordinates
    /// `shift` (whole periods from the centre dot) becomes the centre dot.
    pub(crate) fn renumbered(&self, shift: Vector2<f64>) -> DotGrid {
        // x = (A·u + t)/(1 + p·u) with A = S + t·pᵀ; for u = u' + k, divide through by
        // d = 1 + p·k: t' = x(k), A' = A/d, p' = p/d.
        let a = self.steps() + self.center * self.perspective.transpose();
        let depth = 1.0 + self.perspective.dot(&shift);
        let center = (a * shift + self.center) / depth;
        let perspective = self.perspective / depth;
        let steps = a / depth - center * perspective.transpose();
        DotGrid {
            center,
            step_x: steps.column(0).into(),
            step_y: steps.column(1).into(),
            size: self.size,
            perspective,
            fitted_to_dots: self.fitted_to_dots,
        }
    }

    /// The inverse of [`DotGrid::at`]: the marker coordinates `u = (c − h, r − h)` (periods
    /// from the centre dot) of image point `p`; `None` where the homography is singular.
    pub(crate) fn marker_coordinates(&self, p: Vector2<f64>) -> Option<Vector2<f64>> {
        // d·(1 + p·u) = S·u for d = p − centre, so (S − d·pᵀ)·u = d.
        let d = p - self.center;
        Some((self.steps() - d * self.perspective.transpose()).try_inverse()? * d)
    }
}

/// The dots of one marker edge (the ID row or the left column) classified as present/absent.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct EdgeBits {
    /// Bit `k` = dot absent, `k = 0` next to the far finder.
    pub bits: Vec<bool>,
    /// Smallest margin of the edge's dots (1 = perfectly clean, 0 = undecidable): the
    /// [`bit_margin`] of its level, and on an ID edge no more than how clearly no occluder made
    /// the reading ([`EdgeSamples::occlusion_margins`]).
    pub margin: f64,
    /// Smallest signed distance of a dot's level above the threshold, half contrasts: > 0
    /// when every dot of the edge is present, the more so the larger.
    pub completeness: f64,
    /// The same for all dots but the worst one (what the edge shows if that dot is spoiled).
    pub completeness_but_one: f64,
}

impl EdgeBits {
    /// Dots of the edge read as absent.
    fn missing(&self) -> usize {
        self.bits.iter().filter(|&&b| b).count()
    }
}

impl EdgeBits {
    /// The bits as an integer (bit k = 1 when the dot is absent).
    pub fn value(&self) -> u64 {
        self.bits
            .iter()
            .enumerate()
            .filter(|(_, &b)| b)
            .map(|(k, _)| 1u64 << k)
            .sum()
    }
}

/// Missing dots of the ID edge from which one spoiled dot of the complete edge is tolerated.
const MIN_MISSING_TO_TOLERATE_ONE: usize = 3;

/// Result of reading a marker's ID.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct IdReading {
    /// Decoded ID.
    pub id: u64,
    /// True when the ID was found in the left column: the marker is mirrored.
    pub mirrored: bool,
    /// Confidence in `[0, 1]`: the smaller of the ID edge's smallest bit margin and of how
    /// clearly the other edge is complete (0 when it misses a dot: inconsistent marker).
    pub confidence: f64,
    /// The two parts of the confidence: ID-edge margin, completeness of the other edge.
    pub parts: (f64, f64),
}

/// Reads the ID of the marker whose dots are at `grid`, or `None` when a needed sample lies
/// outside the image or the dots do not stand out of the background.
pub(crate) fn read_id(image: &GreyImage, polarity: Polarity, grid: &DotGrid) -> Option<IdReading> {
    let n = grid.size;
    if n < 9 {
        return None;
    }
    // Top row: ID dots (0, n−5−k); present references (1, c); background between them.
    let top = EdgeSamples::take(image, polarity, grid, Edge::Top)?;
    let left = EdgeSamples::take(image, polarity, grid, Edge::Left)?;
    let (top_signed, left_signed) = (top.signed(), left.signed());
    // Which edge holds the ID needs the dots' levels only; occluders are judged on that edge
    // alone (the complete edge's margin is never used), the costliest part of a reading.
    let (top_bits, left_bits) = (top.bits(&top_signed, false), left.bits(&left_signed, false));
    // Seen from the front the left column is complete and the top row holds the ID; mirrored,
    // the other way round: the edge missing fewer dots is the complete one. On a tie (ID 0,
    // or a spoiled dot), front unless the left column misses a dot and the top row is the
    // more clearly complete edge (a marker with ID 0 reads the same both ways).
    let mirrored = match left_bits.missing().cmp(&top_bits.missing()) {
        std::cmp::Ordering::Less => false,
        std::cmp::Ordering::Greater => true,
        std::cmp::Ordering::Equal => {
            left_bits.completeness < 0.0 && top_bits.completeness > left_bits.completeness
        }
    };
    let (id_edge, complete_edge) = if mirrored {
        (left.bits(&left_signed, true), &top_bits)
    } else {
        (top.bits(&top_signed, true), &left_bits)
    };
    // One dot of the complete edge spoiled by dust or hair is tolerated when the ID edge
    // misses enough dots that the two edges cannot be told apart wrongly (1 against ≥ 3);
    // otherwise a spoiled dot leaves the handedness in doubt and costs all confidence.
    let completeness = if id_edge.missing() >= MIN_MISSING_TO_TOLERATE_ONE {
        complete_edge.completeness_but_one
    } else {
        complete_edge.completeness
    };
    let confidence = id_edge.margin.min(completeness.clamp(0.0, 1.0));
    Some(IdReading {
        id: id_edge.value(),
        mirrored,
        confidence,
        parts: (id_edge.margin, completeness),
    })
}

/// A line of `n − 8` dot positions along one side of the marker, between the finders (or the
/// finder and the dot corner): an edge row or column of the dot field, or the line one period
/// beyond it, outside the marker.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Edge {
    /// The top row (the ID, seen from the front).
    Top,
    /// The left column (the ID, mirrored).
    Left,
    /// The bottom row (always complete).
    Bottom,
    /// The right column (always complete).
    Right,
    /// The line one period beyond an edge (never a dot).
    Beyond(Side),
}

/// A complete side of the marker's dot field ([`Edge::Bottom`], [`Edge::Right`]).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Side {
    Bottom,
    Right,
}

impl Edge {
    /// Image position of the point `r` rows inside this edge's line (`r = 0` the line itself,
    /// `r = 1` the reference dots next to it, always present), at `c` along it.
    fn point(self, grid: &DotGrid, r: f64, c: f64) -> Vector2<f64> {
        let last = (grid.size - 1) as f64;
        match self {
            Edge::Top => grid.at(r, c),
            Edge::Left => grid.at(c, r),
            Edge::Bottom => grid.at(last - r, c),
            Edge::Right => grid.at(c, last - r),
            Edge::Beyond(Side::Bottom) => grid.at(last + 1.0 - r, c),
            Edge::Beyond(Side::Right) => grid.at(c, last + 1.0 - r),
        }
    }
}

/// Reads the `n − 8` dot positions of `edge`, present or missing against the reference dots
/// one row inside it. With `judge_occluders` (an edge that may carry the ID), each dot's margin
/// also says how clearly no occluder made its reading ([`EdgeSamples::occlusion_margins`]).
fn read_edge(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
    edge: Edge,
    judge_occluders: bool,
) -> Option<EdgeBits> {
    let samples = EdgeSamples::take(image, polarity, grid, edge)?;
    Some(samples.bits(&samples.signed(), judge_occluders))
}

/// The levels [`read_edge`] samples along one edge, dot column `4 + i` at index `i`
/// ([`dot_level`], material units).
struct EdgeSamples<'a> {
    image: &'a GreyImage,
    polarity: Polarity,
    grid: &'a DotGrid,
    edge: Edge,
    /// Local grid shift `(rows, columns)` of each column's reference dot, periods.
    shifts: Vec<(f64, f64)>,
    /// The edge's dots.
    levels: Vec<f64>,
    /// Their reference dots, one row inside (always present).
    present: Vec<f64>,
    /// The two gaps beside each reference dot, towards the edge (always empty).
    background: Vec<f64>,
    /// Medians of `present` and `background`.
    hi: f64,
    lo: f64,
}

impl<'a> EdgeSamples<'a> {
    /// Each dot's level against its own neighbourhood (the three reference dots below it and
    /// the four gaps beside those), so that uneven illumination along the edge does not eat
    /// the margin: half contrasts, ≥ 0 for a present dot.
    fn signed(&self) -> Vec<f64> {
        (0..self.levels.len())
            .map(|i| self.signed_within(i, 1, self.levels[i]))
            .collect()
    }

    /// The edge's bits from its dots' `signed` levels; with `judge_occluders` (the edge that
    /// carries the ID), each dot's margin also says how clearly no occluder made its reading
    /// ([`EdgeSamples::occlusion_margins`]).
    fn bits(&self, signed: &[f64], judge_occluders: bool) -> EdgeBits {
        let (occlusion, empty) = match judge_occluders {
            true => (self.occlusion_margins(signed), self.empty_level()),
            false => (vec![1.0; signed.len()], -1.0),
        };
        log::trace!(
            "edge {:?} dot margins {signed:.2?}, occlusion margins {occlusion:.2?}, empty {empty:.2}",
            self.edge
        );
        // levels[i] is dot column 4 + i; bit k is dot column n − 5 − k.
        let bits: Vec<bool> = signed.iter().rev().map(|&s| s < 0.0).collect();
        let margin = signed
            .iter()
            .zip(&occlusion)
            .map(|(&s, &o)| bit_margin(s, empty).min(o.clamp(0.0, 1.0)))
            .fold(1.0f64, f64::min);
        let mut sorted = signed.to_vec();
        sorted.sort_by(f64::total_cmp);
        EdgeBits {
            bits,
            margin,
            completeness: sorted.first().copied().unwrap_or(f64::INFINITY),
            completeness_but_one: sorted.get(1).copied().unwrap_or(f64::INFINITY),
        }
    }

    /// Samples `edge` of `grid`; `None` when a sample lies outside the image or the reference
    /// dots do not stand out of the gaps.
    fn take(
        image: &'a GreyImage,
        polarity: Polarity,
        grid: &'a DotGrid,
        edge: Edge,
    ) -> Option<Self> {
        let point = |r: f64, c: f64| edge.point(grid, r, c);
        let sample = |p: Vector2<f64>| dot_level(image, polarity, p, grid);
        let shifts = match grid.fitted_to_dots {
            true => vec![(0.0, 0.0); grid.size - 8],
            false => reference_shifts(grid.size, &point, &sample)?,
        };
        let mut samples = EdgeSamples {
            image,
            polarity,
            grid,
            edge,
            shifts,
            levels: Vec::new(),
            present: Vec::new(),
            background: Vec::new(),
            hi: f64::NAN,
            lo: f64::NAN,
        };
        for i in 0..samples.shifts.len() {
            let level = |r: f64, c: f64| sample(samples.at(i, r, c));
            let (dot, reference) = (level(0.0, 0.0)?, level(1.0, 0.0)?);
            let gaps = [level(0.5, -0.5)?, level(0.5, 0.5)?];
            samples.levels.push(dot);
            samples.present.push(reference);
            samples.background.extend(gaps);
        }
        samples.hi = median_or_nan(&mut samples.present.clone());
        samples.lo = median_or_nan(&mut samples.background.clone());
        (samples.half() > 0.0).then_some(samples)
    }

    /// Half the edge's contrast (NaN without samples).
    fn half(&self) -> f64 {
        0.5 * (self.hi - self.lo)
    }

    /// Image position of the point `r` rows inside the edge and `c` along it from dot column
    /// `4 + i`, moved by that column's reference shift.
    fn at(&self, i: usize, r: f64, c: f64) -> Vector2<f64> {
        let (dr, dc) = self.shifts[i];
        self.edge.point(self.grid, r + dr, 4.0 + i as f64 + c + dc)
    }

    /// The columns within `reach` of column `i`.
    fn within(&self, i: usize, reach: usize) -> std::ops::Range<usize> {
        i.saturating_sub(reach)..(i + reach + 1).min(self.levels.len())
    }

    /// `level` in half contrasts from the threshold of the references and gaps within `reach`
    /// columns of column `i` (the local contrast never taken below half the edge's).
    fn signed_within(&self, i: usize, reach: usize, level: f64) -> f64 {
        let dots = self.within(i, reach);
        let hi = median_or_nan(&mut self.present[dots.clone()].to_vec());
        let lo = median_or_nan(&mut self.background[2 * dots.start..2 * dots.end].to_vec());
        let half = (0.5 * (hi - lo)).max(0.5 * self.half());
        (level - 0.5 * (hi + lo)) / half
    }

    /// Signed level ([`EdgeSamples::signed_within`]) where no dot is drawn: the median over
    /// the edge's columns of the position one period outside the edge, never above −1 (the
    /// gaps'). Blur lifts the gaps, between four dots' corners, far more than an empty dot
    /// position, whose nearest dots are a period away: a blurred missing dot reads well below
    /// −1 (−1.8 to −2.3 beside the dots of `HPCodeImage_20um.png` blurred by 2 px, −1.0 to −1.1
    /// on sharp images). −1 where no such position lies inside the image.
    fn empty_level(&self) -> f64 {
        let mut outside: Vec<f64> = (0..self.levels.len())
            .filter_map(|i| {
                let level = dot_level(self.image, self.polarity, self.at(i, -1.0, 0.0), self.grid)?;
                Some(self.signed_within(i, 1, level))
            })
            .collect();
        match outside.is_empty() {
            true => -1.0,
            false => median_or_nan(&mut outside).min(-1.0),
        }
    }

    /// Per dot (read as `signed`), how clearly no occluder made its reading
    /// (docs/design.md#hp-id-occluders): a present dot needs surroundings like a drawn dot's
    /// (no fibre running through it, [`ridge_level`]; no blob filling the bridges to its
    /// reference dot and its neighbours), a missing one intact dots around it
    /// ([`EdgeSamples::hiding_margins`]).
    fn occlusion_margins(&self, signed: &[f64]) -> Vec<f64> {
        let (image, polarity) = (self.image, self.polarity);
        // A difference of levels: half contrasts without the threshold's offset.
        let ridge = |i: usize, r: f64| {
            ridge_level(|(dr, dc)| material(image, polarity, self.at(i, r + dr, dc)))
                .map(|level| level / self.half())
        };
        // The least material of the bridges from a dot inwards and along its line: a blob
        // that fills an empty position fills them all, a speck or an impulse one of them. The
        // reference dots' (towards the next row, and along theirs) lie between present dots,
        // so blur lifts them at least as much as an ID dot's. In half contrasts from the
        // edge's threshold, since an occluder spoils the local levels.
        let bridge = |i: usize, r: f64| {
            let level = |(dr, dc)| {
                patch_level(
                    image,
                    polarity,
                    self.at(i, r + dr, dc),
                    self.grid,
                    BRIDGE_RANK,
                )
            };
            let bridges = [(0.5, 0.0), (0.0, -0.5), (0.0, 0.5)].map(level);
            let least = bridges
                .into_iter()
                .try_fold(f64::INFINITY, |least, b| Some(least.min(b?)));
            least.map(|l| (l - 0.5 * (self.hi + self.lo)) / self.half())
        };
        let hiding = self.hiding_margins(signed);
        let ridges = excess(signed, |i| ridge(i, 0.0), |i| ridge(i, 1.0));
        let bridges = excess(signed, |i| bridge(i, 0.0), |i| bridge(i, 1.0));
        log::trace!(
            "edge {:?} ridge excess {ridges:.2?}, bridge excess {bridges:.2?}",
            self.edge
        );
        (0..signed.len())
            .map(|i| match signed[i] >= 0.0 {
                true => 1.0 - 2.0 * ridges[i].max(bridges[i]),
                false => hiding[i],
            })
            .collect()
    }

    /// Per dot read missing (∞ for the others), how clearly no occluder hid it: what hides a
    /// dot whole at the background's level reaches into the dots around it, so the reference
    /// dots beside it must be intact, and the dots beside it on the edge, where present, too.
    ///
    /// * A reference dot wholly hidden: its level against the seven references around it
    ///   (a median that an occluder hiding three of them does not move, and that follows the
    ///   illumination), raised by three robust standard deviations of the references' own
    ///   levels (noise).
    /// * A dot hidden in part, on its side facing the missing reading ([`facing_level`]):
    ///   `1 − 2·shortfall`, the shortfall of that side's level from the median of the same
    ///   measure on the seven references around it (their side facing the edge), less three
    ///   robust standard deviations of theirs.
    ///
    /// [`facing_level`]: EdgeSamples::facing_level
    fn hiding_margins(&self, signed: &[f64]) -> Vec<f64> {
        let n = signed.len();
        if signed.iter().all(|&s| s >= 0.0) {
            return vec![f64::INFINITY; n];
        }
        let references: Vec<f64> = (0..n)
            .map(|j| self.signed_within(j, 3, self.present[j]))
            .collect();
        let (_, allowance) = median_and_allowance(&references);
        // Towards the edge: one row outwards.
        let facing: Vec<f64> = (0..n)
            .map(|j| self.signed_within(j, 3, self.facing_level(j, 1.0, (-1.0, 0.0))))
            .collect();
        let finite = |values: &[f64]| -> Vec<f64> {
            values.iter().copied().filter(|v| v.is_finite()).collect()
        };
        let (_, facing_allowance) = median_and_allowance(&finite(&facing));
        // Per column, the lowest level an intact side may have there: the median of the seven
        // references' around it, less their allowance.
        let floor: Vec<f64> = (0..n)
            .map(|j| median_or_nan(&mut finite(&facing[self.within(j, 3)])) - facing_allowance)
            .collect();
        // `1 − 2·shortfall` of a side's level beside column j (1 where not judged: NaN).
        let intact_side = |j: usize, level: f64| {
            let shortfall = floor[j] - level;
            match shortfall.is_nan() {
                true => 1.0,
                false => 1.0 - 2.0 * shortfall.max(0.0),
            }
        };
        (0..n)
            .map(|i| match signed[i] >= 0.0 {
                true => f64::INFINITY,
                false => self
                    .within(i, 1)
                    .map(|j| {
                        let reference = (references[j] + allowance).min(intact_side(j, facing[j]));
                        if j == i || signed[j] < 0.0 {
                            return reference;
                        }
                        // The dot beside it on the edge, its side towards column i.
                        let towards = if i > j { 1.0 } else { -1.0 };
                        let side = self.facing_level(j, 0.0, (0.0, towards));
                        reference.min(intact_side(j, self.signed_within(j, 3, side)))
                    })
                    .fold(f64::INFINITY, f64::min),
            })
            .collect()
    }

    /// Material of the side facing `towards` (a unit step along a grid axis, rows and
    /// columns) of the dot `r` rows inside the edge at column `j`: the median of three samples
    /// [`FACING_DEPTH`] from its centre towards that side, spread ±[`FACING_DEPTH`] across.
    /// The centre is taken where that level is highest within ±[`FACING_SEARCH`] of the
    /// grid's position (under perspective a dot lies off the linear grid), which a dot hidden
    /// on that side up to its centre cannot escape. NaN where a sample leaves the image.
    fn facing_level(&self, j: usize, r: f64, towards: (f64, f64)) -> f64 {
        const STEPS: i32 = 2;
        let step = FACING_SEARCH / STEPS as f64;
        let (a, b) = towards;
        let mut best = f64::NAN;
        for di in -STEPS..=STEPS {
            for dj in -STEPS..=STEPS {
                let row = r + di as f64 * step + FACING_DEPTH * a;
                let column = dj as f64 * step + FACING_DEPTH * b;
                let mut three = [0.0; 3];
                for (sample, s) in three.iter_mut().zip([-FACING_DEPTH, 0.0, FACING_DEPTH]) {
                    let p = self.at(j, row + s * b, column - s * a);
                    match material(self.image, self.polarity, p) {
                        Some(v) => *sample = v,
                        None => return f64::NAN,
                    }
                }
                three.sort_by(f64::total_cmp);
                best = best.max(three[1]);
            }
        }
        best
    }
}

/// Fraction of a complete edge's dots read missing from which the grid is taken to be off the
/// marker there ([`field_ends_at_its_edges`]): a grid a period or more off reads every dot of
/// the line missing, dust or a hair over the edge some of them (stress scene 52194: 5 of 9).
const MAX_MISSING_ON_EDGE: f64 = 2.0 / 3.0;
/// Fraction of the positions one period beyond an edge read present from which the grid is
/// taken to be off the marker: there is no dot there, and occluders hide material rather than
/// show it, so only clutter lying on the lattice's positions could pass for half of them.
const MAX_PRESENT_BEYOND_EDGE: f64 = 0.5;

/// Whether the dot field ends where `grid` says: its bottom row and right column (complete in
/// every marker, whichever side it is seen from) read present and the lines one period beyond
/// them read empty, up to what occluders and clutter can do ([`MAX_MISSING_ON_EDGE`],
/// [`MAX_PRESENT_BEYOND_EDGE`]). A grid a whole period off the marker, or drifting off it
/// towards a far edge (finders that fit a tilted view while the planes' steps do not hold to
/// the marker's far corner, as under strong perspective), passes every check inside the field,
/// which looks alike shifted by a period, and reads another row as the ID; here one of the
/// four lines reads wrong. Lines whose samples leave the image, or that show no contrast, are
/// not judged.
pub(crate) fn field_ends_at_its_edges(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
) -> bool {
    if grid.size < 9 {
        return false;
    }
    let fraction = |edge: Edge, missing: bool| {
        read_edge(image, polarity, grid, edge, false).map(|bits| {
            let count = bits.bits.iter().filter(|&&b| b == missing).count();
            count as f64 / bits.bits.len().max(1) as f64
        })
    };
    [(Edge::Bottom, Side::Bottom), (Edge::Right, Side::Right)]
        .into_iter()
        .all(|(inside, side)| {
            fraction(inside, true).is_none_or(|f| f < MAX_MISSING_ON_EDGE)
                && fraction(Edge::Beyond(side), false).is_none_or(|f| f <= MAX_PRESENT_BEYOND_EDGE)
        })
}

/// How clearly a dot of signed level `s` (half contrasts from the threshold: +1 a present
/// dot's level, −1 the background's between four dots) reads as what it reads, in `[0, 1]`;
/// `empty` (≤ −1) is the level of a position where no dot is drawn
/// ([`EdgeSamples::empty_level`]). Occluders that hide material (a dark hair or dust over a
/// bright dot, bright residue over a dark one; the usual kind) put a present dot anywhere
/// between the two levels, never a missing one above the background, so the two readings do
/// not weigh the same:
///
/// * present (`s ≥ 0`): `s`, its distance above the threshold — a missing dot does not get
///   there;
/// * missing (`s < 0`): `2s/empty − 1`, its distance below the middle of the lower band (`s =
///   empty/2`) in units of that half band (`−2s − 1` on sharp images, where `empty` is −1). A
///   dot halfway down to the empty level may be a present dot under a hair (`code22.tif`; blurred
///   by 2 px, its hair hides the dot to −0.84 while an empty position reads −1.8) or at a cut
///   edge (`code21.jpg`); read as missing, it would give another marker's ID.
fn bit_margin(s: f64, empty: f64) -> f64 {
    let margin = if s >= 0.0 {
        s
    } else {
        2.0 * s / empty.min(-1.0) - 1.0
    };
    margin.clamp(0.0, 1.0)
}

/// Largest local shift searched for a reference dot, periods along each axis.
const MAX_REFERENCE_SHIFT: f64 = 0.3;

/// Local grid shifts `(rows, columns)`, in periods, of the edge's ID columns `4..=n − 5`: where
/// the reference dots of row 1 (always present) are brightest within ±[`MAX_REFERENCE_SHIFT`],
/// the median over each column and its two neighbours. The grid is the window's planes,
/// linear, so under perspective the marker's edges lie up to ~0.3 period off it; the ID dot one
/// period away is displaced alike, so it is sampled with its reference dot's shift (searching
/// the ID positions themselves would climb a missing dot's neighbours).
fn reference_shifts(
    n: usize,
    point: &dyn Fn(f64, f64) -> Vector2<f64>,
    sample: &dyn Fn(Vector2<f64>) -> Option<f64>,
) -> Option<Vec<(f64, f64)>> {
    const STEPS: i32 = 2;
    let step = MAX_REFERENCE_SHIFT / STEPS as f64;
    let mut best = Vec::with_capacity(n);
    for c in 4..=n - 5 {
        let mut top: (f64, (f64, f64)) = (f64::NEG_INFINITY, (0.0, 0.0));
        for i in -STEPS..=STEPS {
            for j in -STEPS..=STEPS {
                let (dr, dc) = (i as f64 * step, j as f64 * step);
                let v = sample(point(1.0 + dr, c as f64 + dc))?;
                // Ties (a flat-topped dot) keep the smaller shift.
                let closer = dr.abs() + dc.abs() < top.1 .0.abs() + top.1 .1.abs();
                if v > top.0 || (v == top.0 && closer) {
                    top = (v, (dr, dc));
                }
            }
        }
        best.push(top.1);
    }
    let median3 = |k: usize, f: fn(&(f64, f64)) -> f64| {
        let near = k.saturating_sub(1)..(k + 2).min(best.len());
        median_or_nan(&mut best[near].iter().map(f).collect::<Vec<_>>())
    };
    Some(
        (0..best.len())
            .map(|k| (median3(k, |s| s.0), median3(k, |s| s.1)))
            .collect(),
    )
}

/// Whether dot `(r, c)` of an `n`-dot grid lies in a finder's 4 × 4 dots: the top-left,
/// top-right and bottom-left corners (rows and columns 0–3 from those sides).
pub(crate) fn in_finder_corner(n: usize, r: usize, c: usize) -> bool {
    let (near_r, near_c) = (r < 4, c < 4);
    let (far_r, far_c) = (r + 4 >= n, c + 4 >= n);
    (near_r && (near_c || far_c)) || (far_r && near_c)
}

/// The light over a marker's dot field (docs/design.md#level-surfaces): smooth surfaces of the
/// material level ([`dot_level`]) of its dots, of the bridges between two neighbouring dots
/// and of the gaps between four, each fitted across the grid to every such place outside the
/// finders and the two ID edges (dots that are always drawn). Positions are grid columns and
/// rows. Each reading is then judged against the light where it is: a steep illumination
/// gradient or vignette over a marker of low contrast moves the level by more than the dots'
/// contrast between one corner and the other, so one threshold for the marker (or one taken a
/// few dots away) reads a whole corner as ink or as none.
pub(crate) struct FieldLight {
    /// The dots' levels, `[column, row, level]`.
    dots: Vec<LevelSample>,
    /// The gaps' levels, likewise.
    gaps: Vec<LevelSample>,
    dot: LevelSurface,
    bridge: LevelSurface,
    gap: LevelSurface,
}

impl FieldLight {
    /// Samples and fits the light of `grid`'s field; `None` when a sample falls outside the
    /// image or the grid is too small to have a field (`n < 9`).
    pub(crate) fn measure(image: &GreyImage, polarity: Polarity, grid: &DotGrid) -> Option<Self> {
        let n = grid.size;
        if n < 9 {
            return None;
        }
        // Dot (r, c) is always drawn: inside the grid, off the ID edges (row and column 0),
        // outside the finders.
        let drawn = |r: usize, c: usize| {
            (1..n).contains(&r) && (1..n).contains(&c) && !in_finder_corner(n, r, c)
        };
        let level = |r: f64, c: f64| -> Option<LevelSample> {
            Some([c, r, dot_level(image, polarity, grid.at(r, c), grid)?])
        };
        let (mut dots, mut bridges, mut gaps) = (Vec::new(), Vec::new(), Vec::new());
        for r in 1..n {
            for c in 1..n {
                if !drawn(r, c) {
                    continue;
                }
                let (rf, cf) = (r as f64, c as f64);
                dots.push(level(rf, cf)?);
                if drawn(r, c + 1) {
                    bridges.push(level(rf, cf + 0.5)?);
                }
                if drawn(r + 1, c) {
                    bridges.push(level(rf + 0.5, cf)?);
                }
                if drawn(r + 1, c + 1) && drawn(r, c + 1) && drawn(r + 1, c) {
                    gaps.push(level(rf + 0.5, cf + 0.5)?);
                }
            }
        }
        let last = (n - 1) as f64;
        let fit = |samples: &[LevelSample]| LevelSurface::fit(samples, [0.0; 2], [last; 2]);
        Some(FieldLight {
            dot: fit(&dots)?,
            bridge: fit(&bridges)?,
            gap: fit(&gaps)?,
            dots,
            gaps,
        })
    }

    /// How far blur has lifted the bridges between two dots towards the dots, at the
    /// field's centre: `(bridge − gap)/(dot − gap)`, each level as [`dot_level`] reads it
    /// (docs/design.md#hp-blurred-finders). On a numeric model of dots half a period wide
    /// (square or round alike within 0.01), blurred by σ periods: 0 sharp, 0.16 at σ 0.1,
    /// 0.29 at 0.2, 0.34 at 0.25, 0.38 at 0.3 and 0.43 at 0.4. `None` when the dots do not
    /// stand out of the gaps there.
    pub(crate) fn bridge_rise(&self, grid: &DotGrid) -> Option<f64> {
        let h = grid.half_width();
        let (dot, bridge, gap) = (self.dot.at(h, h), self.bridge.at(h, h), self.gap.at(h, h));
        (dot > gap).then(|| (bridge - gap) / (dot - gap))
    }

    /// Material level halfway between the dots' and the gaps' at grid row `r`, column `c`.
    fn dot_or_gap(&self, r: f64, c: f64) -> f64 {
        0.5 * (self.dot.at(c, r) + self.gap.at(c, r))
    }

    /// Material level halfway between the dots' and the bridges' at grid row `r`, column `c`
    /// (blur lifts the bridges towards the dots, while a finder's solid ring stays at least as
    /// bright as a dot).
    fn dot_or_bridge(&self, r: f64, c: f64) -> f64 {
        0.5 * (self.dot.at(c, r) + self.bridge.at(c, r))
    }
}

/// Fraction of the marker's grid that looks as it should, `[0, 1]`: every dot outside the
/// finders and the two ID edges present, every gap between four such dots empty, each against
/// the light where it is ([`FieldLight`]). 0 when the dots are not brighter than the gaps. The
/// check that a finder triple encloses a real dot grid (clutter that happens to look like
/// three finders does not: a smooth surface cannot follow it), tolerant of dust and hair over a
/// part of the marker.
pub(crate) fn grid_support(light: &FieldLight) -> f64 {
    let (mut dots, mut gaps) = (
        light.dots.iter().map(|s| s[2]).collect::<Vec<_>>(),
        light.gaps.iter().map(|s| s[2]).collect::<Vec<_>>(),
    );
    let (hi, lo) = (median_or_nan(&mut dots), median_or_nan(&mut gaps));
    if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
        return 0.0;
    }
    let threshold = |s: &LevelSample| light.dot_or_gap(s[1], s[0]);
    let good = light.dots.iter().filter(|s| s[2] > threshold(s)).count()
        + light.gaps.iter().filter(|s| s[2] < threshold(s)).count();
    good as f64 / (light.dots.len() + light.gaps.len()) as f64
}

/// The image a marker's levels are read on: the image itself, or a sharpened crop of it
/// around the marker (docs/design.md#hp-blurred-finders) whose pixel `(0, 0)` is image pixel
/// `origin`.
pub(crate) struct ReadingView<'a> {
    /// The image or the sharpened part.
    pub image: std::borrow::Cow<'a, GreyImage>,
    /// Image pixel `(col, row)` of the view's `(0, 0)`.
    pub origin: Vector2<f64>,
}

impl<'a> ReadingView<'a> {
    /// The image as it is.
    pub(crate) fn raw(image: &'a GreyImage) -> Self {
        ReadingView {
            image: std::borrow::Cow::Borrowed(image),
            origin: Vector2::zeros(),
        }
    }

    /// The part of `image` around the marker whose dots are at `dots` (its field and
    /// [`SHARPENED_MARGIN`] periods beyond, clipped to the image), sharpened at the scale of a
    /// finder's centre ([`crate::sharpen`]), when blur has lifted the bridges between its
    /// dots as a blur of a quarter period or more does ([`BLURRED_BRIDGE_RISE`]); `None`
    /// otherwise or when that part is empty.
    pub(crate) fn sharpened_if_blurred(
        image: &GreyImage,
        polarity: Polarity,
        dots: &DotGrid,
    ) -> Option<ReadingView<'static>> {
        let rise = FieldLight::measure(image, polarity, dots)?.bridge_rise(dots)?;
        if !BLURRED_BRIDGE_RISE.contains(&rise) {
            return None;
        }
        let h = dots.half_width() + SHARPENED_MARGIN;
        let corners =
            [(-h, -h), (h, -h), (-h, h), (h, h)].map(|(x, y)| dots.at_marker(Vector2::new(x, y)));
        let (lo, hi) = corners.iter().fold(
            (
                Vector2::repeat(f64::INFINITY),
                Vector2::repeat(f64::NEG_INFINITY),
            ),
            |(lo, hi), p| (lo.inf(p), hi.sup(p)),
        );
        let col0 = lo.x.floor().clamp(0.0, image.width() as f64) as usize;
        let row0 = lo.y.floor().clamp(0.0, image.height() as f64) as usize;
        let col1 = (hi.x.ceil().max(0.0) as usize)
            .saturating_add(1)
            .min(image.width());
        let row1 = (hi.y.ceil().max(0.0) as usize)
            .saturating_add(1)
            .min(image.height());
        let (width, height) = (col1.checked_sub(col0)?, row1.checked_sub(row0)?);
        if width == 0 || height == 0 {
            return None;
        }
        // A module is half a period.
        let module = 0.25 * (dots.step_x.norm() + dots.step_y.norm());
        let sharp = Sharpener::around(image, (col0, row0), (width, height), module)?.window()?;
        Some(ReadingView {
            image: std::borrow::Cow::Owned(sharp),
            origin: Vector2::new(col0 as f64, row0 as f64),
        })
    }

    /// `dots` in this view's pixels.
    pub(crate) fn local(&self, dots: &DotGrid) -> DotGrid {
        DotGrid {
            center: dots.center - self.origin,
            ..*dots
        }
    }
}

/// Bridge rises ([`FieldLight::bridge_rise`]) of a marker read again sharpened
/// when its reading fails: from that of dots half a period wide under a blur of a quarter
/// period (0.34), the most that the stress suite's blur row draws and the raw readings are
/// measured to take (100 % found), up to half the contrast, above what any blur gives dots
/// of that width (0.43 at 0.4 period, where the grid's fundamental keeps 4 %): a grid
/// half a period off its dots reads its bridges as bright as or brighter than its "dots".
const BLURRED_BRIDGE_RISE: std::ops::Range<f64> = 0.34..0.5;

/// Periods of image beyond a marker's dot field that its sharpened view holds: the finders'
/// outer edges (half a period out), the line one period beyond the field that
/// [`field_ends_at_its_edges`] reads and the samples around it (up to about 1.6
/// periods out).
const SHARPENED_MARGIN: f64 = 3.0;

/// Cheap test, before any phase analysis, that a dot grid surrounds `center`: on the 7×7 lattice of
/// period steps `step_x`, `step_y` (from the finders' size and directions), the fraction of lattice
/// points brighter (in material) than the mean of the four cells between them and their neighbours.
/// The finders locate the centre to a fraction of a period: a dot or the gap between four dots,
/// depending on `W`, on an untilted marker ([`UNTILTED_SHIFTS`], both tried); up to ~0.3 period
/// off either on a steeply tilted one (the midpoint of two finders is not the image of the marker's
/// centre under perspective). When neither reaches `enough`, the lattice is also tried at the
/// quarter-period phase whose central points are the most material. About ½ on texture that is
/// not a grid, near 1 on a marker's dot field.
pub(crate) fn grid_precheck(
    image: &GreyImage,
    polarity: Polarity,
    center: Vector2<f64>,
    step_x: Vector2<f64>,
    step_y: Vector2<f64>,
    enough: f64,
) -> f64 {
    let grid = DotGrid::new(center, step_x, step_y, 7);
    let score = |(shift_r, shift_c): (f64, f64)| -> Option<f64> {
        let mut above = 0usize;
        for r in 0..7 {
            for c in 0..7 {
                let (r, c) = (r as f64 + shift_r, c as f64 + shift_c);
                let dot = dot_level(image, polarity, grid.at(r, c), &grid)?;
                let mut gaps = 0.0;
                for (dr, dc) in [(-0.5, -0.5), (-0.5, 0.5), (0.5, -0.5), (0.5, 0.5)] {
                    gaps += dot_level(image, polarity, grid.at(r + dr, c + dc), &grid)?;
                }
                above += (dot > gaps / 4.0) as usize;
            }
        }
        Some(above as f64 / 49.0)
    };
    let untilted = UNTILTED_SHIFTS
        .iter()
        .filter_map(|&shift| score(shift))
        .fold(0.0, f64::max);
    if untilted >= enough {
        return untilted;
    }
    // The lattice phase where the 3 × 3 central lattice points are the most material, to a
    // quarter period: one more phase tried, not fourteen (the best of many phases of texture
    // that is not a grid would pass more often).
    let material = |(shift_r, shift_c): (f64, f64)| -> Option<f64> {
        let mut sum = 0.0;
        for r in 2..5 {
            for c in 2..5 {
                let at = grid.at(r as f64 + shift_r, c as f64 + shift_c);
                sum += dot_level(image, polarity, at, &grid)?;
            }
        }
        Some(sum)
    };
    let densest = (0..16)
        .map(|k| ((k / 4) as f64 / 4.0, (k % 4) as f64 / 4.0))
        .filter_map(|shift| material(shift).map(|m| (m, shift)))
        .max_by(|a, b| a.0.total_cmp(&b.0));
    let shifted = densest.and_then(|(_, shift)| score(shift));
    log::trace!("grid pre-check: {untilted:.2} untilted, {shifted:.2?} at {densest:.2?}");
    shifted.map_or(untilted, |s| untilted.max(s))
}

/// The lattice phases of an untilted marker's centre, periods along its rows and columns: a
/// dot, or the gap between four dots.
const UNTILTED_SHIFTS: [(f64, f64); 2] = [(0.0, 0.0), (0.5, 0.5)];

/// Whether the four corners of the marker show what they must: a finder square at the three
/// finder corners and plain dots at the fourth. A finder differs from a block of dots by its
/// *bridges*: the cells between two neighbouring dot positions are material in its ring and
/// centre (13 of 24, more when blurred), empty in a dot grid. So a reading turned by a quarter
/// turn (three finders seen as a different corner triple, e.g. from a two-finder hypothesis)
/// is caught: it expects dots where a finder is. Lenient on the finders (dust may hide one:
/// the middle one of the three is compared), strict on the dot corner.
///
/// Dust or hair at the level of the material fills the bridges of a dot corner too, but also
/// the *diagonal* cells between four dots, which are empty in a sharp finder (but its very
/// centre, 1 of 9). So the corners also pass when the bridge fraction minus the diagonal
/// fraction (~0.43 for a sharp finder, ~0 for dots, occluded or not) tells them apart. Blur
/// fills a finder's diagonals as well, so that second test only helps sharp markers, and it
/// needs all three finder corners to show a finder (the dot corner being unknown). Whatever
/// the test, no finder corner may look like plain dots (most dots present, almost no bridges):
/// an occluded finder shows all ink or none, plain dots are the other corner of a reading
/// turned by a quarter turn.
pub(crate) fn corners_consistent(
    image: &GreyImage,
    polarity: Polarity,
    grid: &DotGrid,
    light: &FieldLight,
) -> bool {
    let n = grid.size;
    if n < 9 {
        return false;
    }
    // Ink fractions of the bridges, the diagonals and the dots of the 4×4 dots from (r0, c0),
    // each against the light where it is ([`FieldLight`]): vignetting or an illumination
    // gradient may move the level by more than the dot contrast across the marker, and the
    // surfaces leave dust over a few dots out.
    let corner = |(r0, c0): (usize, usize)| -> Option<(f64, f64, f64)> {
        let ink = |r: f64, c: f64| -> Option<f64> {
            let level = dot_level(image, polarity, grid.at(r, c), grid)?;
            Some(f64::from(u8::from(level > light.dot_or_bridge(r, c))))
        };
        let (mut bridges, mut diagonals, mut dots) = (0.0, 0.0, 0.0);
        for r in r0..r0 + 4 {
            for c in c0..c0 + 4 {
                let (rf, cf) = (r as f64, c as f64);
                dots += ink(rf, cf)?;
                if c + 1 < c0 + 4 {
                    bridges += ink(rf, cf + 0.5)?;
                }
                if r + 1 < r0 + 4 {
                    bridges += ink(rf + 0.5, cf)?;
                }
                if c + 1 < c0 + 4 && r + 1 < r0 + 4 {
                    diagonals += ink(rf + 0.5, cf + 0.5)?;
                }
            }
        }
        Some((bridges / 24.0, diagonals / 9.0, dots / 16.0))
    };
    let far = n - 4;
    let Some(finders) = [(0, 0), (0, far), (far, 0)]
        .map(corner)
        .into_iter()
        .collect::<Option<Vec<_>>>()
    else {
        return false;
    };
    let Some(dots) = corner((far, far)) else {
        return false;
    };
    log::trace!("corners (bridges, diagonals, dots): finders {finders:?}, dot corner {dots:.3?}");
    if finders.iter().any(|c| c.2 >= 0.5 && c.0 < 0.2) {
        return false;
    }
    // The dot corner is compared with the middle finder corner; `rank` 1 lets one finder be
    // hidden, 0 needs all three to show.
    let separated =
        |measure: fn(&(f64, f64, f64)) -> f64, rank: usize, min_finder: f64, max_dots: f64| {
            let mut seen: Vec<f64> = finders.iter().map(measure).collect();
            seen.sort_by(f64::total_cmp);
            seen[rank] >= min_finder && measure(&dots) < (0.5 * seen[1]).min(max_dots)
        };
    // A dot corner that does not show most of its dots is hidden (dust brighter than the dots
    // over it) and tells nothing: every finder corner must then show a finder's bridges
    // plainly, or a reading reflected across the marker's diagonal, with a finder spoiled by
    // that dust taken for the dot corner, could pass (stress scene 62907: a blob darker than
    // the dots beside the real dot corner gave it 0.42 of bridges).
    if dots.2 < 0.5 {
        return separated(|c| c.0, 0, HIDDEN_DOT_CORNER_MIN_BRIDGES, 0.4);
    }
    // An occluded dot corner is one unknown corner already: the dust test then needs all
    // three finders to show themselves, or a quarter turn with a hidden finder could pass.
    separated(|c| c.0, 1, 0.3, 0.4) || separated(|c| c.0 - c.1, 0, 0.2, 0.25)
}

/// Smallest bridge fraction of every finder corner when the dot corner is hidden
/// ([`corners_consistent`]): a sharp finder shows 13 of 24 bridges (0.54), blur more; a dot
/// corner that dust partly fills, less.
const HIDDEN_DOT_CORNER_MIN_BRIDGES: f64 = 0.5;

/// Rank (ascending, of 9) of the sample taken as a dot's level: the third highest. Occluders
/// that hide material (a dark hair over a bright dot, bright dust over a dark one) lower some
/// samples and are ignored up to six samples; occluders that mimic material (a dark hair over
/// an empty cell of dark-dot markers) need to cover three samples to matter.
const OCCLUSION_RANK: usize = 6;

/// Directions of the lines [`ridge_level`] samples through a dot position, over a half turn
/// (every 15°).
const RIDGE_DIRECTIONS: usize = 12;
/// Distances of those lines from the position, periods: a line within ~0.2 period of it can
/// fill a third of [`dot_level`]'s samples.
const RIDGE_OFFSETS: [f64; 5] = [-0.24, -0.12, 0.0, 0.12, 0.24];
/// Distances along each line, on both sides, periods: beyond a drawn dot's half-width (¼
/// period, ~0.35 at its corners), short of the neighbouring dots' edges (¾ period along the
/// axes).
const RIDGE_REACH: [f64; 3] = [0.36, 0.44, 0.52];
/// Distance across the line at which its sides are sampled, periods: beyond the half-width of
/// a fibre half a period wide, with the lines' spacing to spare.
const RIDGE_SIDE: f64 = 0.4;

/// How far the most material line across the surroundings of a dot position stands out of its
/// two sides, over lines in [`RIDGE_DIRECTIONS`] at [`RIDGE_OFFSETS`]: a line's level is the
/// smaller over its two halves (beyond the position on either side) of the half's median
/// material at [`RIDGE_REACH`] (an impulse, such as a hot pixel, is ignored) less the larger
/// of the same medians [`RIDGE_SIDE`] to either side of it.
/// `material_at(dr, dc)` is the material at `(dr, dc)` periods from the position along the
/// grid's rows and columns. Around a drawn dot every such line leaves the dot into background
/// as its sides do, up to blur of the neighbouring dots; a fibre that fills an empty position
/// runs on beyond it, on both sides, as a ridge. Surroundings that are uniformly lighter or
/// darker (the substrate beyond the marker's edge often differs from the gaps between its
/// dots) make no ridge. Lines that leave the image are left out; `None` when all do.
fn ridge_level(material_at: impl Fn((f64, f64)) -> Option<f64>) -> Option<f64> {
    let mut most: Option<f64> = None;
    for k in 0..RIDGE_DIRECTIONS {
        let (sin, cos) = (PI * k as f64 / RIDGE_DIRECTIONS as f64).sin_cos();
        // Along the line (rows, columns): `(sin, cos)`; across it: `(cos, −sin)`.
        let at =
            |t: f64, across: f64| material_at((across * cos + t * sin, t * cos - across * sin));
        for offset in RIDGE_OFFSETS {
            // Each half of the line: its median material less its more material side's.
            let half = |way: f64| -> Option<f64> {
                let median_along = |across: f64| -> Option<f64> {
                    let mut levels = [0.0; RIDGE_REACH.len()];
                    for (level, t) in levels.iter_mut().zip(RIDGE_REACH) {
                        *level = at(way * t, across)?;
                    }
                    Some(median_or_nan(&mut levels))
                };
                let sides =
                    median_along(offset - RIDGE_SIDE)?.max(median_along(offset + RIDGE_SIDE)?);
                Some(median_along(offset)? - sides)
            };
            // A line darker than a side is no ridge, whatever the sides hold (a line that
            // leaves a reference dot's surroundings between dots and an ID dot's outside
            // the marker sees different sides).
            if let Some(line) = half(1.0).zip(half(-1.0)).map(|(a, b)| a.min(b).max(0.0)) {
                most = Some(most.map_or(line, |m| m.max(line)));
            }
        }
    }
    most
}

/// How much more each present dot's surroundings show of a measure (a ridge, a filled
/// bridge) than the reference dots' do, half contrasts: the dot's value less the references'
/// median and [`NOISE_ALLOWANCE`] robust standard deviations of theirs; `−∞` for dots read
/// missing or not judged. `own(i)` is the measure around dot `i` of the edge, `reference(i)`
/// around its reference dot (in half contrasts, `None` where it cannot be judged). The
/// reference dots have at least the ID dots' neighbours, so blur lifts their surroundings as
/// much; an occluder over one ID position lifts that position's alone (or a reference's,
/// which the median ignores).
fn excess(
    signed: &[f64],
    own: impl Fn(usize) -> Option<f64>,
    reference: impl Fn(usize) -> Option<f64>,
) -> Vec<f64> {
    let references: Vec<f64> = (0..signed.len()).filter_map(reference).collect();
    let (median, allowance) = median_and_allowance(&references);
    (0..signed.len())
        .map(|i| {
            // Only present dots are judged, and NaN (no reference judged) judges none.
            let judged = signed[i] >= 0.0 && !median.is_nan();
            match judged.then(|| own(i)).flatten() {
                Some(level) => level - median - allowance,
                None => f64::NEG_INFINITY,
            }
        })
        .collect()
}

/// The median of the reference dots' `values` (NaN for none) and the allowance above it,
/// [`NOISE_ALLOWANCE`] robust standard deviations of theirs.
fn median_and_allowance(values: &[f64]) -> (f64, f64) {
    let median = median_or_nan(&mut values.to_vec());
    let mut deviations: Vec<f64> = values.iter().map(|v| (v - median).abs()).collect();
    (median, NOISE_ALLOWANCE * robust_sigma(&mut deviations))
}

/// Robust standard deviations of the reference dots' own measures by which an ID dot's must
/// exceed their median before it counts ([`excess`]): noise, JPEG blocks and impulses make
/// ridges of their own, as much around a reference dot as around an ID dot.
const NOISE_ALLOWANCE: f64 = 3.0;
/// Distance from a dot's centre of the samples of its side ([`EdgeSamples::facing_level`]),
/// periods: well inside the smallest drawn dots (some real markers' are under half a period
/// wide), so that the side's level falls only where an occluder reaches that far towards the
/// dot's centre.
const FACING_DEPTH: f64 = 0.08;
/// How far [`EdgeSamples::facing_level`] looks for a dot's centre around its grid position,
/// periods.
const FACING_SEARCH: f64 = 0.1;
/// Rank (ascending, of 9) of the sample taken as a bridge's level: the median, which an
/// impulse does not move.
const BRIDGE_RANK: usize = 4;

/// Material level of `image` at point `p` (1 = a dot's level for bright dots, and the
/// background's for dark dots, inverted), bilinear; `None` outside the image.
fn material(image: &GreyImage, polarity: Polarity, p: Vector2<f64>) -> Option<f64> {
    let v = f64::from(image.bilinear(p.x, p.y)?);
    Some(match polarity {
        Polarity::BrightDots => v,
        Polarity::DarkDots => 1.0 - v,
    })
}

/// Material level (1 = dot) around image point `p`: an upper order statistic
/// ([`OCCLUSION_RANK`]) of nine bilinear samples on a 3×3 grid ±0.15 period along the grid
/// axes, so that a hair or scratch over part of a dot does not change it. `None` outside the
/// image.
fn dot_level(
    image: &GreyImage,
    polarity: Polarity,
    p: Vector2<f64>,
    grid: &DotGrid,
) -> Option<f64> {
    patch_level(image, polarity, p, grid, OCCLUSION_RANK)
}

/// The material sample of `rank` (ascending) among nine bilinear samples on a 3×3 grid ±0.15
/// period along the grid axes around image point `p`; `None` outside the image.
fn patch_level(
    image: &GreyImage,
    polarity: Polarity,
    p: Vector2<f64>,
    grid: &DotGrid,
    rank: usize,
) -> Option<f64> {
    let (dx, dy) = (grid.step_x * 0.15, grid.step_y * 0.15);
    let mut samples = [0.0f64; 9];
    for (k, s) in samples.iter_mut().enumerate() {
        *s = material(
            image,
            polarity,
            p + dx * (k % 3) as f64 - dx + dy * (k / 3) as f64 - dy,
        )?;
    }
    samples.sort_by(f64::total_cmp);
    samples.get(rank).copied()
}

/// The median, NaN for no values (then every comparison with it fails).
fn median_or_nan(values: &mut [f64]) -> f64 {
    crate::order_stats::median(values).unwrap_or(f64::NAN)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::HpCodeLayout;
    use crate::pose::Pose;
    use crate::render::{render, RenderOptions};

    fn grid_for(pose: &Pose, period: f64, size: usize, image: &GreyImage) -> DotGrid {
        let (cx, cy) = image.center();
        let center = Vector2::new(cx as f64, cy as f64) + pose.origin_in_image();
        let (s, c) = pose.alpha.sin_cos();
        let k = period / pose.pixel_size;
        DotGrid::new(
            center,
            Vector2::new(c, s) * k,
            Vector2::new(-s, c) * k,
            size,
        )
    }

    #[test]
    fn reads_ids_of_both_polarities() {
        for id in [0u64, 1, 0b1_0110_0101, 511] {
            let layout = HpCodeLayout::from_code_size(10.0, 33)
                .unwrap()
                .with_id(id)
                .unwrap();
            let pose = Pose::planar(3.0, -2.0, 0.4, 1.0);
            let image = render(&layout, &pose, &RenderOptions::new(260, 240)).unwrap();
            let grid = grid_for(&pose, 10.0, 17, &image);
            let r = read_id(&image, Polarity::BrightDots, &grid).unwrap();
            assert_eq!((r.id, r.mirrored), (id, false));
            assert!(r.confidence > 0.5, "{r:?}");
            let r = read_id(&image.inverted(), Polarity::DarkDots, &grid).unwrap();
            assert_eq!(r.id, id);
        }
    }

    /// `image` with the dot of `grid` at `(r, c)` dimmed towards the background by `hidden`
    /// (0: untouched, 1: gone), as a hair or a dust grain over it would.
    fn dim_dot(image: &GreyImage, grid: &DotGrid, (r, c): (f64, f64), hidden: f32) -> GreyImage {
        let (w, h) = (image.width(), image.height());
        let background = image.bilinear(grid.at(r + 0.5, c + 0.5).x, grid.at(r + 0.5, c + 0.5).y);
        let background = background.unwrap();
        let center = grid.at(r, c);
        let radius = 0.45 * grid.step_x.norm();
        let mut pixels = image.pixels().to_vec();
        for (i, v) in pixels.iter_mut().enumerate() {
            let p = Vector2::new((i % w) as f64, (i / w) as f64);
            if (p - center).norm() < radius {
                *v += hidden * (background - *v);
            }
        }
        GreyImage::new(w, h, pixels).unwrap()
    }

    #[test]
    fn a_grid_a_period_off_the_marker_is_caught_at_its_far_edges() {
        // Inside the field a grid shifted by a whole period looks right (dots where dots
        // are); the bottom row, the right column and the lines beyond them do not.
        let layout = HpCodeLayout::from_code_size(10.0, 33)
            .unwrap()
            .with_id(0b1_0110_0101)
            .unwrap();
        let pose = Pose::planar(-4.0, 3.0, 0.3, 1.0);
        let image = render(&layout, &pose, &RenderOptions::new(300, 280)).unwrap();
        let grid = grid_for(&pose, 10.0, 17, &image);
        assert!(field_ends_at_its_edges(&image, Polarity::BrightDots, &grid));
        for (dx, dy) in [(1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)] {
            let shifted = DotGrid {
                center: grid.center + grid.step_x * dx + grid.step_y * dy,
                ..grid
            };
            assert!(
                !field_ends_at_its_edges(&image, Polarity::BrightDots, &shifted),
                "shifted by ({dx}, {dy}) periods"
            );
        }
        // A hair over half of the right column is not a shifted grid.
        let mut hidden = image.clone();
        for r in 4..9 {
            hidden = dim_dot(&hidden, &grid, (r as f64, 16.0), 0.9);
        }
        assert!(field_ends_at_its_edges(
            &hidden,
            Polarity::BrightDots,
            &grid
        ));
    }

    #[test]
    fn a_present_dot_half_hidden_never_reads_as_missing() {
        // ID 0: every dot present. One dot of the left column (the complete edge) and one of
        // the ID row dimmed by a hair: at 30 % of the contrast left (below the threshold) the
        // marker would read mirrored with another ID or with a bit set; it must be refused
        // instead. At 70 % left (above the threshold) the dot still reads present.
        let layout = HpCodeLayout::from_code_size(10.0, 33).unwrap();
        let pose = Pose::planar(1.0, 2.0, -0.3, 1.0);
        let image = render(&layout, &pose, &RenderOptions::new(260, 240)).unwrap();
        let grid = grid_for(&pose, 10.0, 17, &image);
        for dot in [(8.0, 0.0), (0.0, 7.0)] {
            let hidden = dim_dot(&image, &grid, dot, 0.7);
            let r = read_id(&hidden, Polarity::BrightDots, &grid).unwrap();
            assert!(r.confidence < 0.2, "dot {dot:?} 70 % hidden: {r:?}");
            let dimmed = dim_dot(&image, &grid, dot, 0.3);
            let r = read_id(&dimmed, Polarity::BrightDots, &grid).unwrap();
            assert_eq!((r.id, r.mirrored), (0, false), "dot {dot:?} 30 % hidden");
            assert!(r.confidence >= 0.2, "dot {dot:?} 30 % hidden: {r:?}");
        }
    }

    /// `image` with a straight fibre `width` periods wide through `grid`'s point `(r, c)` at
    /// `angle` to the rows, blended `strength` of the way towards `level` (antialiased over
    /// one pixel), as a hair or a textile fibre over the marker would be.
    fn fibre(
        image: &GreyImage,
        grid: &DotGrid,
        (r, c): (f64, f64),
        (angle, width): (f64, f64),
        level: f32,
        strength: f32,
    ) -> GreyImage {
        let through = grid.at(r, c);
        let along = (grid.step_x * angle.cos() + grid.step_y * angle.sin()).normalize();
        let half_width = 0.5 * width * grid.step_x.norm();
        occluded(image, (level, strength), |p| {
            let d = p - through;
            half_width - (d.x * along.y - d.y * along.x).abs()
        })
    }

    /// `image` blended `strength` of the way towards `level` wherever `inside(pixel)` (pixels
    /// inside the occluder's edge; negative outside) is over −½, antialiased over one pixel.
    fn occluded(
        image: &GreyImage,
        (level, strength): (f32, f32),
        inside: impl Fn(Vector2<f64>) -> f64,
    ) -> GreyImage {
        let (w, h) = (image.width(), image.height());
        let mut pixels = image.pixels().to_vec();
        for (i, v) in pixels.iter_mut().enumerate() {
            let p = Vector2::new((i % w) as f64, (i / w) as f64);
            let cover = (inside(p) + 0.5).clamp(0.0, 1.0) as f32;
            *v += strength * cover * (level - *v);
        }
        GreyImage::new(w, h, pixels).unwrap()
    }

    /// The occluder tests' marker (W 33, 10-µm period, ID [`OCCLUDED_ID`]) and its pose.
    fn occluded_marker() -> (HpCodeLayout, Pose) {
        let layout = HpCodeLayout::from_code_size(10.0, 33)
            .unwrap()
            .with_id(OCCLUDED_ID)
            .unwrap();
        (layout, Pose::planar(2.0, -1.0, 0.2, 0.8))
    }

    const OCCLUDED_ID: u64 = 0b1_0110_0101;

    #[test]
    fn a_fibre_over_an_empty_id_cell_never_reads_as_a_dot() {
        // A fibre as dark as the dots of a dark-dot marker, across an empty ID cell, fills
        // enough of the cell to read as a dot there: another marker's ID. A dot is a blob
        // whose surroundings are background; a fibre runs on beyond the cell on both sides.
        // Sharp and noise-free, then blurred (0.12 period) with 3 % noise at 60 % contrast.
        let (id, (layout, pose)) = (OCCLUDED_ID, occluded_marker());
        let blurred = RenderOptions {
            blur_sigma: 1.5,
            noise_std: 0.03,
            background: 0.9,
            foreground: 0.3,
            seed: 5,
            ..RenderOptions::new(300, 280)
        };
        let mut wrong = Vec::new();
        for options in [RenderOptions::new(300, 280), blurred] {
            let image = render(&layout, &pose, &options).unwrap();
            let image = match options.foreground > options.background {
                true => image.inverted(),
                false => image,
            };
            let grid = grid_for(&pose, 10.0, 17, &image);
            let clean = read_id(&image, Polarity::DarkDots, &grid).unwrap();
            assert_eq!(clean.id, id);
            assert!(clean.confidence >= 0.4, "{clean:?}");
            let dot = options.foreground.min(options.background);
            for column in [4.0, 6.0, 7.0, 10.0, 12.0] {
                for degrees in [0.0, 30.0, 60.0, 90.0, 135.0] {
                    for (width, offset) in [(0.1, 0.0), (0.25, 0.0), (0.25, 0.12), (0.5, 0.12)] {
                        for strength in [0.6, 0.9] {
                            let angle = f64::to_radians(degrees);
                            let at = (offset * angle.cos(), column - offset * angle.sin());
                            let across = (angle, width);
                            let spoiled = fibre(&image, &grid, at, across, dot, strength);
                            let r = read_id(&spoiled, Polarity::DarkDots, &grid).unwrap();
                            if r.id != id && r.confidence >= 0.2 {
                                wrong.push((column, degrees, width, strength, r.id, r.confidence));
                            }
                        }
                    }
                }
            }
        }
        assert!(wrong.is_empty(), "{} wrong: {wrong:.2?}", wrong.len());
    }

    /// `image` with a round blob of `radius` periods around the point `(r, c)` of `grid`,
    /// blended `strength` of the way towards `level`.
    fn blob(
        image: &GreyImage,
        grid: &DotGrid,
        (r, c): (f64, f64),
        radius: f64,
        (level, strength): (f32, f32),
    ) -> GreyImage {
        let (center, radius) = (grid.at(r, c), radius * grid.step_x.norm());
        occluded(image, (level, strength), |p| radius - (p - center).norm())
    }

    #[test]
    fn a_blob_hiding_an_id_dot_and_its_neighbours_in_part_is_refused() {
        // A blob at the background's level 0.8–1.05 period in radius hides a present ID dot
        // whole and reaches into the dots around it, whose upper level ignores it: the ID
        // dot reads missing, another marker's ID. Its neighbours' centres show the blob.
        let (id, (layout, pose)) = (OCCLUDED_ID, occluded_marker());
        let options = RenderOptions {
            blur_sigma: 1.2,
            noise_std: 0.01,
            seed: 3,
            ..RenderOptions::new(300, 280)
        };
        let image = render(&layout, &pose, &options).unwrap();
        let grid = grid_for(&pose, 10.0, 17, &image);
        let background = options.background;
        let mut wrong = Vec::new();
        // Blobs that reach the centre of the reference dot or of the ID dots beside it (a
        // smaller one leaves the image of another marker: no reader can tell them apart).
        for column in 4..=12 {
            for (across, radius) in [(0.3, 0.8), (0.3, 0.9), (0.15, 0.95), (0.0, 1.05)] {
                let at = (across, column as f64);
                let spoiled = blob(&image, &grid, at, radius, (background, 0.95));
                let r = read_id(&spoiled, Polarity::BrightDots, &grid).unwrap();
                if r.id != id && r.confidence >= 0.2 {
                    wrong.push((column, across, radius, r.id, r.confidence));
                }
            }
        }
        assert!(wrong.is_empty(), "{} wrong: {wrong:.2?}", wrong.len());
    }
}
