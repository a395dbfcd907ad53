//! What an export contains: the exported frame of a layout, its rectangles in export
//! coordinates, and their grouping into regular arrays for the GDSII and OASIS writers.
//!
//! **Export coordinates** are layout coordinates shifted by the margins
//! (`u' = u + left`, `v' = v + top`, docs/design.md#export), y down, pattern units. GDSII and OASIS
//! negate `v'` (y up) and write integers in database units (nm, with the pattern unit taken
//! as µm, docs/design.md#export-gds-oasis).

use std::collections::HashMap;

use crate::error::{Error, Result};
use crate::layout::{Layout, Rect};
use crate::pattern_file::Pattern;

/// Database units per pattern unit in GDSII and OASIS: user unit 1 µm, database unit 1 nm.
pub const DB_PER_UNIT: f64 = 1000.0;

/// Largest coordinate magnitude written, database units: GDSII stores 32-bit integers; the
/// margin keeps array end points (`origin + count · pitch`) representable too.
const MAX_DB_COORD: f64 = (i32::MAX / 2) as f64;

/// Region of a pattern that is exported, and how to reach export coordinates from it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ExportFrame {
    /// Exported region in **layout coordinates** (pattern units): the bounding box, or for
    /// a Megarena the dot cells `[c₀·P, c₁·P) × [r₀·P, r₁·P)` of its region of interest.
    pub frame: Rect,
    /// Canvas in **export coordinates**: the frame grown by the margins (left/top margins
    /// shift the content, so the canvas keeps the frame's top-left corner).
    pub canvas: Rect,
    /// Pattern-frame origin in layout coordinates `(origin_x, origin_y)`.
    pub origin: (f64, f64),
    /// `(left, top)` margins: export = layout + this.
    pub shift: (f64, f64),
}

impl ExportFrame {
    /// The frame of `pattern` (docs/design.md#export; docs/design.md#layout-megarena for the
    /// Megarena region of interest).
    pub fn of(pattern: &Pattern) -> Self {
        let layout = pattern.layout();
        let b = layout.bounds();
        let frame = match pattern {
            Pattern::Megarena(m) => {
                // Dot-aligned cells of the region of interest, with the truncating rule of
                // docs/design.md#layout-megarena (the tolerance absorbs rounding in (L·P)/P).
                let p = m.period();
                let n = m.n_dots();
                let range = |start: f64, length: f64| {
                    let first = ((start / p).trunc().max(0.0) as usize).min(n);
                    let end = (((start + length) / p + 1e-9).trunc().max(0.0) as usize).min(n);
                    (first, end.max(first))
                };
                let roi = m.region_of_interest();
                let (c0, c1) = range(roi.x, roi.width);
                let (r0, r1) = range(roi.y, roi.height);
                Rect::new(
                    c0 as f64 * p,
                    r0 as f64 * p,
                    (c1 - c0) as f64 * p,
                    (r1 - r0) as f64 * p,
                )
            }
            _ => Rect::new(0.0, 0.0, b.width, b.height),
        };
        let m = layout.metadata().margins;
        // Negative margins make no sense for fabrication; treat them as 0.
        let (left, right, top, bottom) = (
            m.left.max(0.0),
            m.right.max(0.0),
            m.top.max(0.0),
            m.bottom.max(0.0),
        );
        ExportFrame {
            frame,
            canvas: Rect::new(
                frame.x,
                frame.y,
                frame.width + left + right,
                frame.height + top + bottom,
            ),
            origin: (-b.x, -b.y),
            shift: (left, top),
        }
    }

    /// Calls `visit` with every rectangle of the frame, in export coordinates.
    pub fn visit_rects(&self, layout: &dyn Layout, visit: &mut dyn FnMut(Rect)) {
        let (ox, oy) = self.origin;
        // A hair larger than the frame: rectangles on its edges belong to it.
        let eps = 1e-9 * (self.frame.width + self.frame.height).max(1.0);
        let region = Rect::new(
            self.frame.x - ox - eps,
            self.frame.y - oy - eps,
            self.frame.width + 2.0 * eps,
            self.frame.height + 2.0 * eps,
        );
        let (dx, dy) = (ox + self.shift.0, oy + self.shift.1);
        layout.visit_rects(&region, &mut |r| visit(r.translated(dx, dy)));
    }
}

/// A rectangle in database units (export coordinates, y down): top-left corner and size.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct DbRect {
    /// Left edge, nm.
    pub x: i64,
    /// Top edge (y down), nm.
    pub y: i64,
    /// Width, nm (> 0).
    pub width: i64,
    /// Height, nm (> 0).
    pub height: i64,
}

/// Converts a rectangle in export coordinates to database units: position and size are
/// rounded separately so that equal dots keep equal sizes (error ≤ 0.5 nm per value).
pub fn to_db(r: &Rect) -> Result<DbRect> {
    let convert = |v: f64, what: &str| -> Result<i64> {
        let db = (v * DB_PER_UNIT).round();
        if db.is_finite() && db.abs() <= MAX_DB_COORD {
            Ok(db as i64)
        } else {
            Err(Error::parameter(
                "export",
                format!(
                    "rectangle {what} {v} µm does not fit in a GDSII/OASIS layout ({} mm at most)",
                    MAX_DB_COORD / 1e6
                ),
            ))
        }
    };
    Ok(DbRect {
        x: convert(r.x, "position")?,
        y: convert(r.y, "position")?,
        width: convert(r.width, "size")?.max(1),
        height: convert(r.height, "size")?.max(1),
    })
}

/// `cols × rows` copies of one rectangle on a regular grid (database units, export
/// coordinates, y down). A single rectangle is a 1 × 1 array.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct DotArray {
    /// Top-left element (its top-left corner and size).
    pub first: DbRect,
    /// Number of columns (≥ 1), along +x.
    pub cols: u32,
    /// Number of rows (≥ 1), along +y (downwards).
    pub rows: u32,
    /// Column pitch, nm (> 0 when `cols > 1`).
    pub pitch_x: i64,
    /// Row pitch, nm (> 0 when `rows > 1`).
    pub pitch_y: i64,
}

impl DotArray {
    /// Number of rectangles in the array.
    pub fn len(&self) -> usize {
        self.cols as usize * self.rows as usize
    }
    /// Always false: arrays hold at least one rectangle.
    pub fn is_empty(&self) -> bool {
        false
    }
    /// Rectangle of column `c`, row `r`.
    pub fn element(&self, c: u32, r: u32) -> DbRect {
        DbRect {
            x: self.first.x + i64::from(c) * self.pitch_x,
            y: self.first.y + i64::from(r) * self.pitch_y,
            ..self.first
        }
    }
}

/// Lattice statistics of the rectangles of one size (first pass).
#[derive(Clone, Copy, Debug)]
struct SizeGroup {
    /// Any member, the reference for the pitch gcd.
    reference: (i64, i64),
    min: (i64, i64),
    max: (i64, i64),
    /// gcd of the offsets to `reference`: the lattice pitch (0 when all offsets are 0).
    gcd: (i64, i64),
    count: usize,
}

/// Occupancy grid of one size group on its lattice (second pass).
struct LatticeGrid {
    size: (i64, i64),
    origin: (i64, i64),
    pitch: (i64, i64),
    n: (usize, usize),
    cells: Vec<bool>,
}

fn gcd(mut a: i64, mut b: i64) -> i64 {
    (a, b) = (a.abs(), b.abs());
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Largest lattice cell count for a group of `count` rectangles: beyond it the rectangles
/// are not on a useful lattice (e.g. a pitch that is not a whole number of nm) and are
/// exported one by one.
fn lattice_cell_limit(count: usize) -> usize {
    count.saturating_mul(16).saturating_add(1 << 16)
}

/// The rectangles of the frame grouped into regular arrays (docs/design.md#export-gds-oasis: arrays
/// instead of one polygon per dot).
///
/// Rectangles of equal size whose positions lie on a common integer lattice (in nm) are
/// placed on an occupancy grid, which is covered exactly by arrays: for a stride `m` of 1–4
/// lattice steps, each of the `m²` interleaved sub-grids is cut into runs along rows, and
/// runs repeated on consecutive rows are merged into 2-D arrays; the stride giving the fewest
/// arrays wins (3 for Megarena, whose 3 × 3 cells omit one dot; 1 or 2 for the others).
/// Other rectangles become 1 × 1 arrays. Duplicate rectangles are written once.
///
/// Cost: two visits of the layout's rectangles plus a few passes over the grid, so a
/// 10⁵-dot Megarena region takes milliseconds.
pub fn dot_arrays(pattern: &Pattern, frame: &ExportFrame) -> Result<Vec<DotArray>> {
    dot_arrays_with_progress(pattern, frame, &mut |_| {})
}

/// [`dot_arrays`], calling `progress` with the number of rectangles visited so far (both
/// passes: up to twice [`super::estimate_rects`]) every [`PROGRESS_STEP`] rectangles.
pub fn dot_arrays_with_progress(
    pattern: &Pattern,
    frame: &ExportFrame,
    progress: &mut dyn FnMut(u64),
) -> Result<Vec<DotArray>> {
    let mut counter = RectCounter {
        visited: 0,
        progress,
    };
    let layout = pattern.layout();
    let groups = size_groups(layout, frame, &mut counter)?;
    let mut grids = lattice_grids(&groups);

    // Pass 2: occupancy grids for lattice groups, plain rectangles for the others.
    let mut singles: Vec<DbRect> = Vec::new();
    frame.visit_rects(layout, &mut |r| {
        counter.tick();
        // Pass 1 converted every rectangle successfully.
        let Ok(d) = to_db(&r) else { return };
        match grids.get_mut(&(d.width, d.height)) {
            Some(grid) => {
                let index = |v: i64, o: i64, p: i64| if p == 0 { 0 } else { (v - o) / p };
                let c = index(d.x, grid.origin.0, grid.pitch.0) as usize;
                let row = index(d.y, grid.origin.1, grid.pitch.1) as usize;
                if let Some(cell) = grid.cells.get_mut(row * grid.n.0 + c) {
                    *cell = true;
                }
            }
            None => singles.push(d),
        }
    });

    let mut arrays: Vec<DotArray> = Vec::new();
    let mut sizes: Vec<_> = grids.keys().copied().collect();
    sizes.sort_unstable();
    for size in sizes {
        if let Some(grid) = grids.get(&size) {
            arrays.extend(cover_grid(grid));
        }
    }
    singles.sort_unstable();
    singles.dedup();
    arrays.extend(singles.into_iter().map(|first| DotArray {
        first,
        cols: 1,
        rows: 1,
        pitch_x: 0,
        pitch_y: 0,
    }));
    Ok(arrays)
}

/// Counts the rectangles visited, reporting every [`PROGRESS_STEP`].
struct RectCounter<'a> {
    visited: u64,
    progress: &'a mut dyn FnMut(u64),
}

impl RectCounter<'_> {
    fn tick(&mut self) {
        self.visited += 1;
        if self.visited % PROGRESS_STEP == 0 {
            (self.progress)(self.visited);
        }
    }
}

/// Pass 1: sizes, bounds and lattice pitch of each size group (database units), or the
/// first rectangle that does not convert.
fn size_groups(
    layout: &dyn Layout,
    frame: &ExportFrame,
    counter: &mut RectCounter,
) -> Result<HashMap<(i64, i64), SizeGroup>> {
    let mut groups: HashMap<(i64, i64), SizeGroup> = HashMap::new();
    let mut error = None;
    frame.visit_rects(layout, &mut |r| {
        counter.tick();
        if error.is_some() {
            return;
        }
        let d = match to_db(&r) {
            Ok(d) => d,
            Err(e) => {
                error = Some(e);
                return;
            }
        };
        let g = groups.entry((d.width, d.height)).or_insert(SizeGroup {
            reference: (d.x, d.y),
            min: (d.x, d.y),
            max: (d.x, d.y),
            gcd: (0, 0),
            count: 0,
        });
        g.min = (g.min.0.min(d.x), g.min.1.min(d.y));
        g.max = (g.max.0.max(d.x), g.max.1.max(d.y));
        g.gcd = (
            gcd(g.gcd.0, d.x - g.reference.0),
            gcd(g.gcd.1, d.y - g.reference.1),
        );
        g.count += 1;
    });
    if let Some(e) = error {
        return Err(e);
    }
    Ok(groups)
}

/// An empty occupancy grid for each size group whose lattice is small enough
/// ([`lattice_cell_limit`]); the other groups are written as plain rectangles.
fn lattice_grids(groups: &HashMap<(i64, i64), SizeGroup>) -> HashMap<(i64, i64), LatticeGrid> {
    let mut grids: HashMap<(i64, i64), LatticeGrid> = HashMap::new();
    for (&size, g) in groups {
        let steps = |lo: i64, hi: i64, pitch: i64| {
            if pitch == 0 {
                Some(1usize)
            } else {
                usize::try_from((hi - lo) / pitch).ok()?.checked_add(1)
            }
        };
        let (Some(nx), Some(ny)) = (
            steps(g.min.0, g.max.0, g.gcd.0),
            steps(g.min.1, g.max.1, g.gcd.1),
        ) else {
            continue;
        };
        match nx.checked_mul(ny) {
            Some(cells) if cells <= lattice_cell_limit(g.count) => {
                grids.insert(
                    size,
                    LatticeGrid {
                        size,
                        origin: g.min,
                        pitch: g.gcd,
                        n: (nx, ny),
                        cells: vec![false; cells],
                    },
                );
            }
            _ => {}
        }
    }
    grids
}

/// Rectangles between two progress reports of [`dot_arrays_with_progress`].
pub const PROGRESS_STEP: u64 = 1 << 16;

/// An array being grown row by row in [`cover_with_stride`]: columns `start..start+len` of
/// the sub-grid, from sub-grid row `top`, `rows` rows so far.
#[derive(Clone, Copy)]
struct OpenRun {
    start: usize,
    len: usize,
    top: usize,
    rows: usize,
}

/// Exact cover of the grid's set cells by arrays, with the best stride.
fn cover_grid(grid: &LatticeGrid) -> Vec<DotArray> {
    let mut best: Option<Vec<DotArray>> = None;
    for stride in 1..=4usize {
        if stride > 1 && stride > grid.n.0.max(grid.n.1) {
            break;
        }
        let arrays = cover_with_stride(grid, stride);
        if best.as_ref().is_none_or(|b| arrays.len() < b.len()) {
            best = Some(arrays);
        }
    }
    best.unwrap_or_default()
}

/// Covers the grid with arrays whose pitch is `stride` lattice steps: one run-merging pass
/// per interleaved sub-grid.
fn cover_with_stride(grid: &LatticeGrid, stride: usize) -> Vec<DotArray> {
    let (nx, ny) = grid.n;
    let mut out = Vec::new();
    for row_phase in 0..stride.min(ny) {
        for col_phase in 0..stride.min(nx) {
            let sub_cols = (nx - col_phase).div_ceil(stride);
            let sub_rows = (ny - row_phase).div_ceil(stride);
            let to_array = |run: &OpenRun| {
                let (c, r) = (col_phase + run.start * stride, row_phase + run.top * stride);
                let pitch = (grid.pitch.0 * stride as i64, grid.pitch.1 * stride as i64);
                DotArray {
                    first: DbRect {
                        x: grid.origin.0 + c as i64 * grid.pitch.0,
                        y: grid.origin.1 + r as i64 * grid.pitch.1,
                        width: grid.size.0,
                        height: grid.size.1,
                    },
                    // Counts are bounded by the lattice cell limit (≪ 2³²).
                    cols: run.len as u32,
                    rows: run.rows as u32,
                    pitch_x: if run.len > 1 { pitch.0 } else { 0 },
                    pitch_y: if run.rows > 1 { pitch.1 } else { 0 },
                }
            };
            let mut open: Vec<OpenRun> = Vec::new();
            let mut next: Vec<OpenRun> = Vec::new();
            for sr in 0..sub_rows {
                let row = row_phase + sr * stride;
                let line = &grid.cells[row * nx..(row + 1) * nx];
                let mut previous = open.iter().peekable();
                let mut sc = 0;
                while sc < sub_cols {
                    if !line[col_phase + sc * stride] {
                        sc += 1;
                        continue;
                    }
                    let start = sc;
                    while sc < sub_cols && line[col_phase + sc * stride] {
                        sc += 1;
                    }
                    let len = sc - start;
                    // Close the open runs left of this one; extend an identical one.
                    let mut extended = None;
                    while let Some(p) = previous.peek() {
                        if p.start > start {
                            break;
                        }
                        let p = **p;
                        previous.next();
                        if p.start == start && p.len == len {
                            extended = Some(p);
                        } else {
                            out.push(to_array(&p));
                        }
                    }
                    next.push(match extended {
                        Some(p) => OpenRun {
                            rows: p.rows + 1,
                            ..p
                        },
                        None => OpenRun {
                            start,
                            len,
                            top: sr,
                            rows: 1,
                        },
                    });
                }
                out.extend(previous.map(to_array));
                std::mem::swap(&mut open, &mut next);
                next.clear();
            }
            out.extend(open.iter().map(to_array));
        }
    }
    out.sort_unstable();
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{CustomDot, CustomLayout, MegarenaLayout, PeriodicLayout};

    fn expand(arrays: &[DotArray]) -> Vec<DbRect> {
        let mut all: Vec<DbRect> = arrays
            .iter()
            .flat_map(|a| (0..a.rows).flat_map(move |r| (0..a.cols).map(move |c| a.element(c, r))))
            .collect();
        all.sort_unstable();
        all
    }

    fn direct(pattern: &Pattern) -> Vec<DbRect> {
        let frame = ExportFrame::of(pattern);
        let mut all = Vec::new();
        frame.visit_rects(pattern.layout(), &mut |r| all.push(to_db(&r).unwrap()));
        all.sort_unstable();
        all
    }

    #[test]
    fn periodic_grid_is_two_arrays() {
        let p = Pattern::from(PeriodicLayout::new(10.0, 5, 7).unwrap());
        let arrays = dot_arrays(&p, &ExportFrame::of(&p)).unwrap();
        assert_eq!(expand(&arrays), direct(&p));
        assert_eq!(arrays.len(), 2, "{arrays:?}");
    }

    #[test]
    fn megarena_uses_few_arrays() {
        let m = MegarenaLayout::new(14.0, 8)
            .unwrap()
            .with_region_of_interest(Rect::new(0.0, 0.0, 3000.0, 2000.0))
            .unwrap();
        let p = Pattern::from(m);
        let arrays = dot_arrays(&p, &ExportFrame::of(&p)).unwrap();
        let rects = direct(&p);
        assert_eq!(expand(&arrays), rects);
        assert!(
            arrays.len() * 20 < rects.len(),
            "{} arrays for {} dots",
            arrays.len(),
            rects.len()
        );
    }

    #[test]
    fn irregular_rectangles_stay_single() {
        let dots = vec![
            CustomDot::new(0.0, 0.0, 1.0, 1.0, 1.0),
            CustomDot::new(3.3333, 0.5, 1.0, 1.0, 1.0),
            CustomDot::new(7.1, 2.0, 2.0, 1.0, 1.0),
        ];
        let p = Pattern::from(CustomLayout::new(dots).unwrap());
        let arrays = dot_arrays(&p, &ExportFrame::of(&p)).unwrap();
        assert_eq!(expand(&arrays), direct(&p));
        assert_eq!(arrays.len(), 3);
    }

    #[test]
    fn huge_coordinates_are_an_error() {
        let dots = vec![CustomDot::new(1e9, 0.0, 1.0, 1.0, 1.0)];
        let p = Pattern::from(CustomLayout::new(dots).unwrap());
        let e = dot_arrays(&p, &ExportFrame::of(&p))
            .unwrap_err()
            .to_string();
        assert!(e.contains("does not fit"), "{e}");
    }
}
