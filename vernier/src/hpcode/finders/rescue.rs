//! Blurred-finder rescue (docs/design.md#hp-finders): finders whose gap no level of the local
//! range opens.
//!
//! The middle levels of the local range ([`super::LEVELS`]) are fractions of a range that a
//! finder's centre and its surround set. Blur of about half a module lifts a grey gap (printed
//! finders, `code31.jpg`) above the lower levels while the corners of the one-module ring sink
//! below the upper ones, so no level opens the gap and closes the ring, although one between
//! the gap's and the ring's own levels still does. The centre stays a compact region at some
//! level. Each such region that no reading made a finder, and that no region like it crowds
//! (as the dots of a dot grid crowd each other), is looked at along rays: where nearly every
//! ray leaves it into a gap and then meets a ring, a window around it is binarised at one
//! global threshold between the most material gap and the least material ring, and read as
//! the other finders are ([`super::finders_at`]).

use super::{
    centroid, compact, finders_at, material_polarity, Finder, MIN_CENTER_AREA, MIN_SPACING,
};
use crate::binarize::{Region, Regions, ThresholdMap};
use crate::grey_image::{GreyImage, Polarity};
use crate::sharpen::{self, Sharpener};
use nalgebra::Vector2;

/// Half-side of the rescue's window, candidate modules: the ring's outer edge at 3.5 modules,
/// with room for a centre read a third too small.
const REACH: f64 = 5.5;
/// Rays of the profile around a candidate centre.
const RAYS: usize = 8;
/// Rays that must show a gap and a ring (one may cross dust, a hair, a scratch).
const MIN_RAYS: usize = 7;
/// Samples per candidate module along a ray …
const STEPS_PER_MODULE: f64 = 4.0;
/// … out to [`REACH`].
const PROFILE_STEPS: usize = (REACH * STEPS_PER_MODULE) as usize;
/// Two regions are alike in size when their sides differ by less than this factor.
const SIZE_ALIKE: f64 = 1.5;
/// A finder found already explains a region of its colour within one of its modules whose
/// module estimate is within this fraction of its own.
const SAME_MODULE: f64 = 0.5;

/// A closed, compact region that no reading made a finder: maybe the centre of a finder whose
/// blurred gap did not open at any of the local levels.
#[derive(Clone, Copy, Debug)]
pub(super) struct Unexplained {
    center: Vector2<f64>,
    /// `√(filled area)`, pixels: about three modules if it is a finder's centre.
    side: f64,
    bright: bool,
}

impl Unexplained {
    /// `r` as a candidate centre, if it is closed, compact and large enough to be one.
    pub(super) fn of(r: &Region) -> Option<Unexplained> {
        (!r.open && r.filled_area >= MIN_CENTER_AREA && compact(r)).then(|| Unexplained {
            center: centroid(r),
            side: r.filled_area.sqrt(),
            bright: r.bright,
        })
    }

    fn module(&self) -> f64 {
        self.side / 3.0
    }

    /// +1 for bright material, −1 for dark: material levels are `sign · intensity`.
    fn sign(&self) -> f32 {
        if self.bright {
            1.0
        } else {
            -1.0
        }
    }

    /// The polarity of the finder it would be the centre of.
    fn polarity(&self) -> Polarity {
        material_polarity(self.bright)
    }
}

/// The unexplained regions worth a rescue: one per place, colour and size (the middle levels
/// see the same centre), none where a finder of that colour and size was found, and none
/// crowded by regions like it, as the dots of a dot grid are (a finder's centre has none
/// nearer than [`MIN_SPACING`] modules, as in [`super::crowded`]).
pub(super) fn candidates(all: Vec<Unexplained>, found: &[Finder]) -> Vec<Unexplained> {
    let index = SpatialIndex::new(&all);
    let alike = |a: &Unexplained, b: &Unexplained| {
        a.bright == b.bright && a.side < SIZE_ALIKE * b.side && b.side < SIZE_ALIKE * a.side
    };
    // The finders by column: one explaining `u` lies within `(1 + SAME_MODULE)` of its modules.
    let mut by_column: Vec<&Finder> = found.iter().collect();
    by_column.sort_by(|a, b| a.center.x.total_cmp(&b.center.x));
    let mut kept: Vec<Unexplained> = Vec::new();
    for (i, u) in all.iter().enumerate() {
        let reach = (1.0 + SAME_MODULE) * u.module();
        let first = by_column.partition_point(|f| f.center.x < u.center.x - reach);
        let explained = by_column[first..]
            .iter()
            .take_while(|f| f.center.x <= u.center.x + reach)
            .any(|f| {
                f.polarity == u.polarity()
                    && (f.module_px / u.module() - 1.0).abs() < SAME_MODULE
                    && (f.center - u.center).norm() < f.module_px
            });
        if explained {
            continue;
        }
        // Alike regions nearer than a module are the same region at another level: the first
        // one stands for them.
        let crowded_or_repeated = index.any_near(
            &all,
            (u.center, u.side),
            MIN_SPACING * u.module(),
            |j, v| j != i && alike(u, v) && ((v.center - u.center).norm() >= u.module() || j < i),
        );
        if !crowded_or_repeated {
            kept.push(*u);
        }
    }
    kept
}

/// The finder whose centre `candidate` may be, read from a window around it binarised at one
/// global threshold, mid-way between the most material gap and the least material ring that
/// its [`ring_profile`] shows. Where the rays show a gap and a ring whose levels blur has
/// merged, so that no threshold lies between them, the profile and the window are read again
/// sharpened at the candidate's module ([`crate::sharpen`]). `thresholds` and `labels` are
/// reused buffers.
pub(super) fn blurred_finder(
    thresholds: &mut ThresholdMap,
    labels: &mut Regions,
    image: &GreyImage,
    candidate: &Unexplained,
    floor: f32,
) -> Option<Finder> {
    let (origin, size) = window_around(image, candidate)?;
    let raw = |x: f64, y: f64| image.bilinear(x, y);
    let (window, levels) = match ring_profile(raw, candidate, floor) {
        RingProfile::Separated(gap, ring) => {
            let window = image.crop(origin.0, origin.1, size.0, size.1).ok()?;
            (window, (gap, ring))
        }
        RingProfile::Merged => {
            let sharpener = Sharpener::around(image, origin, size, candidate.module())?;
            // The sharpening amplifies white noise about `1 + gain` times, the floor with it.
            let floor = floor * (1.0 + sharpen::GAIN);
            let sample = |x: f64, y: f64| sharpener.at(x, y);
            let RingProfile::Separated(gap, ring) = ring_profile(sample, candidate, floor) else {
                return None;
            };
            (sharpener.window()?, (gap, ring))
        }
        RingProfile::Absent => return None,
    };
    read_window(thresholds, labels, &window, origin, candidate, levels)
}

/// A window `((col0, row0), (width, height))`, image pixels.
type WindowRect = ((usize, usize), (usize, usize));

/// The window read around `candidate`: [`REACH`] modules and two pixels each way, clipped to
/// the image.
fn window_around(image: &GreyImage, candidate: &Unexplained) -> Option<WindowRect> {
    let reach = REACH * candidate.module() + 2.0;
    let col0 = (candidate.center.x - reach).floor().max(0.0) as usize;
    let row0 = (candidate.center.y - reach).floor().max(0.0) as usize;
    let col1 = ((candidate.center.x + reach).ceil() as usize).min(image.width());
    let row1 = ((candidate.center.y + reach).ceil() as usize).min(image.height());
    Some((
        (col0, row0),
        (col1.checked_sub(col0)?, row1.checked_sub(row0)?),
    ))
}

/// The finder centred within a module of `candidate` in `window` (whose pixel `(0, 0)` is
/// image pixel `origin`) binarised half-way between the `(gap, ring)` levels; image frame.
fn read_window(
    thresholds: &mut ThresholdMap,
    labels: &mut Regions,
    window: &GreyImage,
    origin: (usize, usize),
    candidate: &Unexplained,
    (gap, ring): (f32, f32),
) -> Option<Finder> {
    thresholds.compute_uniform(window, candidate.sign() * 0.5 * (gap + ring));
    labels.label(window, thresholds, 0.0);
    let regions = &labels.regions;
    let origin = Vector2::new(origin.0 as f64, origin.1 as f64);
    regions
        .iter()
        .filter(|r| r.bright == candidate.bright)
        .filter_map(|r| finders_at(regions, r)[0])
        .map(|f| Finder {
            center: f.center + origin,
            ..f
        })
        .filter(|f| (f.center - candidate.center).norm() < candidate.module())
        .max_by(|a, b| a.score.total_cmp(&b.score))
}

/// What the rays around a candidate centre show ([`ring_profile`]).
#[derive(Clone, Copy, Debug, PartialEq)]
enum RingProfile {
    /// A gap and then a ring on nearly every ray, and one threshold between every gap and
    /// every ring: the most material gap and the least material ring.
    Separated(f32, f32),
    /// A gap and then a ring on nearly every ray, but some ray's gap at least as material as
    /// another's ring (blur of over half a module, a grey gap).
    Merged,
    /// No gap and ring on enough rays (most candidates: clutter), or a ray leaves the image.
    Absent,
}

/// What the rays around a candidate centre show, the image read through `sample` (intensity
/// at a point, `None` outside): the rays that count leave the centre into a gap at least
/// `floor / 2` less material than the centre and then meet a ring at least as much more
/// material than the gap, within [`REACH`]; [`MIN_RAYS`] must, and the most material of
/// their gaps and the least material of their rings are compared.
fn ring_profile(
    sample: impl Fn(f64, f64) -> Option<f32>,
    c: &Unexplained,
    floor: f32,
) -> RingProfile {
    let sign = c.sign();
    let step = c.module() / STEPS_PER_MODULE;
    let Some(centre) = sample(c.center.x, c.center.y).map(|v| sign * v) else {
        return RingProfile::Absent;
    };
    let depth = 0.5 * floor;
    let (mut gap, mut ring, mut missed) = (f32::NEG_INFINITY, f32::INFINITY, 0);
    for k in 0..RAYS {
        let angle = std::f64::consts::TAU * k as f64 / RAYS as f64;
        let (dx, dy) = (angle.cos() * step, angle.sin() * step);
        let mut profile = [0.0f32; PROFILE_STEPS];
        for (j, v) in profile.iter_mut().enumerate() {
            let reach = (j + 1) as f64;
            let Some(level) = sample(c.center.x + dx * reach, c.center.y + dy * reach) else {
                return RingProfile::Absent;
            };
            *v = sign * level;
        }
        match gap_and_ring(&profile, depth) {
            Some((g, r)) if centre - g >= depth => {
                gap = gap.max(g);
                ring = ring.min(r);
            }
            // Most candidates (clutter) fail here on their first rays.
            _ => {
                missed += 1;
                if missed > RAYS - MIN_RAYS {
                    return RingProfile::Absent;
                }
            }
        }
    }
    match gap < ring {
        true => RingProfile::Separated(gap, ring),
        false => RingProfile::Merged,
    }
}

/// The first valley of `profile` (material levels outwards from a centre) and the peak after
/// it, each confirmed by a change of at least `depth` (hysteresis: noise ripples on the
/// centre's plateau are no valley).
fn gap_and_ring(profile: &[f32], depth: f32) -> Option<(f32, f32)> {
    let mut gap = f32::INFINITY;
    let rise = profile.iter().position(|&v| {
        gap = gap.min(v);
        v - gap >= depth
    })?;
    let mut ring = f32::NEG_INFINITY;
    for &v in &profile[rise..] {
        ring = ring.max(v);
        if ring - v >= depth {
            break;
        }
    }
    Some((gap, ring))
}

/// Unexplained regions by size class and cell, for queries of alike regions nearby: regions
/// alike in size ([`SIZE_ALIKE`]) are in the same or adjacent classes, and a class's cells
/// are about as large as the queries around its regions reach, so that a query reads a few
/// cells of three classes and not every small region under a large region's reach.
struct SpatialIndex {
    /// Class of `grids[0]`.
    first_class: i32,
    grids: Vec<Grid>,
}

/// The regions of one size class by cell (cells in rows from the origin, their regions listed
/// one cell after the other).
struct Grid {
    side: f64,
    cols: usize,
    rows: usize,
    /// Regions of cell `c`: `items[start[c]..start[c + 1]]`.
    start: Vec<usize>,
    items: Vec<usize>,
}

impl SpatialIndex {
    fn new(all: &[Unexplained]) -> Self {
        let classes: Vec<i32> = all.iter().map(|u| Self::class(u.side)).collect();
        let (Some(&first_class), Some(&last)) = (classes.iter().min(), classes.iter().max()) else {
            return SpatialIndex {
                first_class: 0,
                grids: Vec::new(),
            };
        };
        let classes = &classes;
        let grids = (first_class..=last)
            .map(|class| {
                let members = || (0..all.len()).filter(move |&i| classes[i] == class);
                let side = Self::cell_side(class);
                let cell = |p: Vector2<f64>| {
                    (
                        (p.x.max(0.0) / side) as usize,
                        (p.y.max(0.0) / side) as usize,
                    )
                };
                let (cols, rows) = members().fold((1, 1), |(c, r), i| {
                    let (x, y) = cell(all[i].center);
                    (c.max(x + 1), r.max(y + 1))
                });
                let index = |i: usize| {
                    let (x, y) = cell(all[i].center);
                    y * cols + x
                };
                let mut start = vec![0usize; cols * rows + 1];
                for i in members() {
                    start[index(i) + 1] += 1;
                }
                for c in 0..cols * rows {
                    start[c + 1] += start[c];
                }
                let mut next = start.clone();
                let mut items = vec![0usize; start[cols * rows]];
                for i in members() {
                    let c = index(i);
                    items[next[c]] = i;
                    next[c] += 1;
                }
                Grid {
                    side,
                    cols,
                    rows,
                    start,
                    items,
                }
            })
            .collect();
        SpatialIndex { first_class, grids }
    }

    /// Size class of a region of side `side`: `⌊log_{SIZE_ALIKE} side⌋`.
    fn class(side: f64) -> i32 {
        (side.ln() / SIZE_ALIKE.ln()).floor() as i32
    }

    /// Cell side of `class`: the reach of a query around its largest region
    /// ([`MIN_SPACING`] modules of a third of its side).
    fn cell_side(class: i32) -> f64 {
        MIN_SPACING / 3.0 * SIZE_ALIKE.powi(class + 1)
    }

    /// Whether `test(j, &all[j])` holds for a region `j` alike in size to a region of side
    /// `side` (within a factor [`SIZE_ALIKE`]) within `radius` of `p`.
    fn any_near(
        &self,
        all: &[Unexplained],
        (p, side): (Vector2<f64>, f64),
        radius: f64,
        test: impl Fn(usize, &Unexplained) -> bool,
    ) -> bool {
        let own = Self::class(side);
        for class in own - 1..=own + 1 {
            let Some(grid) = usize::try_from(class - self.first_class)
                .ok()
                .and_then(|k| self.grids.get(k))
            else {
                continue;
            };
            let cell = |v: f64, n: usize| ((v.max(0.0) / grid.side) as usize).min(n - 1);
            let (x0, x1) = (cell(p.x - radius, grid.cols), cell(p.x + radius, grid.cols));
            let (y0, y1) = (cell(p.y - radius, grid.rows), cell(p.y + radius, grid.rows));
            for y in y0..=y1 {
                let cells = grid.start[y * grid.cols + x0]..grid.start[y * grid.cols + x1 + 1];
                for &j in &grid.items[cells] {
                    if (all[j].center - p).norm() < radius && test(j, &all[j]) {
                        return true;
                    }
                }
            }
        }
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spatial_index_finds_what_a_scan_of_all_regions_finds() {
        // Regions of sides 3.5 to 120 px over 700 × 500 px, dense and sparse, both colours.
        let mut state = 7u32;
        let mut next = || {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) as f64 / (1u32 << 24) as f64
        };
        let all: Vec<Unexplained> = (0..600)
            .map(|_| Unexplained {
                center: Vector2::new(700.0 * next(), 500.0 * next()),
                side: 3.5 * (120.0f64 / 3.5).powf(next().powi(3)),
                bright: next() < 0.5,
            })
            .collect();
        let index = SpatialIndex::new(&all);
        let alike = |a: &Unexplained, b: &Unexplained| {
            a.side < SIZE_ALIKE * b.side && b.side < SIZE_ALIKE * a.side
        };
        let mut hits = 0;
        for (i, u) in all.iter().enumerate() {
            for radius in [2.0 * u.module(), MIN_SPACING * u.module()] {
                let test = |j: usize, v: &Unexplained| j != i && alike(u, v);
                let expected = all
                    .iter()
                    .enumerate()
                    .any(|(j, v)| (v.center - u.center).norm() < radius && test(j, v));
                assert_eq!(
                    index.any_near(&all, (u.center, u.side), radius, test),
                    expected
                );
                hits += usize::from(expected);
            }
        }
        assert!(hits > 100 && hits < 1100, "{hits}");
    }
}
