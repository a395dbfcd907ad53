//! Candidate stamp frames: convex quadrilaterals outlining bright regions (METHOD.md §5.3.1,
//! redesigned).
//!
//! A stamp's frame is a solid ring of fabricated material, bright after polarity correction,
//! so its **outer border** is a quadrilateral however blurred the image is and whatever touches
//! the frame on the inside (dots merged by blur, glyphs). Steps, on an image decimated by
//! block averaging (noise and cost both drop):
//! 1. adaptive threshold: bright iff `value > local mean + offset`, the mean over a square
//!    window (uneven illumination cancels), the offset a fraction of the robust grey range
//!    (flat noisy areas stay dark);
//! 2. 8-connected components from row runs (union–find);
//! 3. per large component, the convex hull of its run end points (= hull of its outer border);
//! 4. a quadrilateral from the hull: its diameter is one diagonal, the farthest hull points on
//!    either side the two other corners; accepted when every hull vertex lies within a small
//!    tolerance of that quadrilateral's boundary (so the outline really is a quadrilateral),
//!    its sides are long enough and it keeps clear of the image border (a cut frame is not a
//!    quadrilateral).
//!
//! Unlike the original (ArUco's candidate stage), nothing here depends on the marker's
//! orientation, and which candidate is a stamp is decided afterwards by the grid period and
//! the bitmap match, not by contour nesting alone.

use crate::grey_image::GreyImage;
use nalgebra::Vector2;

/// Settings of the frame (quadrilateral) search.
#[derive(Clone, Debug, PartialEq)]
pub struct QuadParams {
    /// Side of the square window of the adaptive threshold's local mean, pixels of the input
    /// image. Default 32: wider than most frames (so their middle stays bright), narrow enough
    /// to follow illumination gradients.
    pub threshold_window: usize,
    /// Threshold offset above the local mean, as a fraction of the image's robust grey range
    /// (1st to 99th percentile). Default 0.04.
    pub threshold_offset: f64,
    /// Shortest accepted quadrilateral side, pixels of the input image. Default 40.
    pub min_side: f64,
    /// Block-averaging factor applied before the search (1 = full resolution). Default 2;
    /// images with a side below 200 pixels are searched at full resolution.
    pub decimation: usize,
    /// Largest distance of the outline from the fitted quadrilateral, as a fraction of the
    /// mean side (plus 1.5 decimated pixels). Default 0.03.
    pub outline_tolerance: f64,
}

impl Default for QuadParams {
    fn default() -> Self {
        QuadParams {
            threshold_window: 32,
            threshold_offset: 0.04,
            min_side: 40.0,
            decimation: 2,
            outline_tolerance: 0.03,
        }
    }
}

/// A convex quadrilateral found in the image, pixel coordinates `(col, row)` of the input
/// image (pixel centres at integers).
#[derive(Clone, Debug, PartialEq)]
pub struct Quad {
    /// Corners, clockwise on screen (y down), starting anywhere.
    pub corners: [Vector2<f64>; 4],
}

impl Quad {
    /// Intersection of the diagonals, pixels (the centre of the outlined square, also under
    /// mild perspective).
    pub fn center(&self) -> Vector2<f64> {
        let [p0, p1, p2, p3] = self.corners;
        let d1 = p2 - p0;
        let d2 = p3 - p1;
        let denom = cross(d1, d2);
        if denom.abs() < 1e-12 {
            return (p0 + p1 + p2 + p3) / 4.0;
        }
        let t = cross(p1 - p0, d2) / denom;
        p0 + d1 * t
    }

    /// Side lengths, pixels, in corner order (`corners[k] → corners[k+1]`).
    pub fn sides(&self) -> [f64; 4] {
        let c = &self.corners;
        [0, 1, 2, 3].map(|k| (c[(k + 1) % 4] - c[k]).norm())
    }

    /// Area, pixels².
    pub fn area(&self) -> f64 {
        polygon_area(&self.corners)
    }

    /// Width of the quadrilateral along the unit direction `dir`, pixels (extent of the
    /// corners' projections).
    pub fn extent_along(&self, dir: Vector2<f64>) -> f64 {
        let proj = self.corners.map(|c| c.dot(&dir));
        let max = proj.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let min = proj.iter().copied().fold(f64::INFINITY, f64::min);
        max - min
    }

    /// Whether the point `p` (pixels) lies inside or on the quadrilateral.
    pub fn contains(&self, p: Vector2<f64>) -> bool {
        (0..4).all(|k| {
            let a = self.corners[k];
            let b = self.corners[(k + 1) % 4];
            cross(b - a, p - a) >= 0.0
        })
    }
}

/// Work buffers of the search, reused between frames.
#[derive(Default)]
pub(crate) struct QuadFinder {
    small: Vec<f32>,
    row_sums: Vec<f32>,
    col_sums: Vec<f32>,
    col_counts: Vec<f32>,
    bright: Vec<u8>,
    runs: Vec<Run>,
    parent: Vec<u32>,
}

#[derive(Clone, Copy, Debug)]
struct Run {
    row: u32,
    start: u32,
    /// Exclusive.
    end: u32,
}

/// Per-component bounding box.
#[derive(Clone, Copy)]
struct Extent {
    min_c: u32,
    max_c: u32,
    min_r: u32,
    max_r: u32,
}

impl QuadFinder {
    /// Quadrilateral outlines of the bright regions of `image`, largest first.
    pub(crate) fn find(&mut self, image: &GreyImage, params: &QuadParams) -> Vec<Quad> {
        let (w, h) = (image.width(), image.height());
        let f = if w.min(h) < 200 {
            1
        } else {
            params.decimation.max(1)
        };
        let (sw, sh) = (w / f, h / f);
        if sw < 8 || sh < 8 {
            return Vec::new();
        }
        self.decimate(image, f, sw, sh);
        let Some(offset) = threshold_offset(&self.small, params.threshold_offset) else {
            return Vec::new();
        };
        let half = (params.threshold_window / f / 2).max(1);
        self.threshold_runs(sw, sh, half, offset);
        let min_side = (params.min_side / f as f64).max(4.0);
        let extents = self.components();
        // Components large enough to be a frame, keyed by root.
        let mut points: Vec<(u32, Vec<Vector2<f64>>)> = extents
            .iter()
            .filter(|(_, e)| {
                ((e.max_c - e.min_c + 1) as f64) >= min_side * 0.7
                    && ((e.max_r - e.min_r + 1) as f64) >= min_side * 0.7
                    && e.min_c >= 2
                    && e.min_r >= 2
                    && (e.max_c as usize) + 2 < sw
                    && (e.max_r as usize) + 2 < sh
            })
            .map(|(root, _)| (*root, Vec::new()))
            .collect();
        if points.is_empty() {
            return Vec::new();
        }
        points.sort_by_key(|(root, _)| *root);
        for i in 0..self.runs.len() {
            let root = find_root(&mut self.parent, i as u32);
            if let Ok(k) = points.binary_search_by_key(&root, |(r, _)| *r) {
                let run = self.runs[i];
                let row = run.row as f64;
                points[k].1.push(Vector2::new(run.start as f64, row));
                points[k].1.push(Vector2::new((run.end - 1) as f64, row));
            }
        }
        let scale = f as f64;
        let mut quads: Vec<Quad> = points
            .into_iter()
            .filter_map(|(_, pts)| {
                let hull = convex_hull(pts);
                fit_quad(&hull, min_side, params.outline_tolerance)
            })
            .map(|q| Quad {
                // Decimated pixel centre i covers input pixels i·f .. i·f + f − 1.
                corners: q.map(|c| c * scale + Vector2::repeat((scale - 1.0) / 2.0)),
            })
            .collect();
        quads.sort_by(|a, b| b.area().total_cmp(&a.area()));
        quads
    }

    /// Block means of `f × f` pixels into `self.small` (`sw × sh`).
    fn decimate(&mut self, image: &GreyImage, f: usize, sw: usize, sh: usize) {
        let w = image.width();
        let px = image.pixels();
        self.small.clear();
        self.small.resize(sw * sh, 0.0);
        let norm = 1.0 / (f * f) as f32;
        for (r, out) in self.small.chunks_exact_mut(sw).enumerate() {
            if f == 2 {
                // The common case, written so that it vectorises.
                let top = &px[2 * r * w..2 * r * w + 2 * sw];
                let bottom = &px[(2 * r + 1) * w..(2 * r + 1) * w + 2 * sw];
                for ((o, t), b) in out
                    .iter_mut()
                    .zip(top.chunks_exact(2))
                    .zip(bottom.chunks_exact(2))
                {
                    *o = (t[0] + t[1] + b[0] + b[1]) * norm;
                }
                continue;
            }
            for dr in 0..f {
                let src = &px[(r * f + dr) * w..(r * f + dr) * w + sw * f];
                for (o, block) in out.iter_mut().zip(src.chunks_exact(f)) {
                    *o += block.iter().sum::<f32>();
                }
            }
            for o in out.iter_mut() {
                *o *= norm;
            }
        }
    }

    /// Adaptive threshold of `self.small` into row runs of bright pixels (`self.runs`).
    fn threshold_runs(&mut self, sw: usize, sh: usize, half: usize, offset: f32) {
        // Box sums: horizontal running sums per row, then vertical running sums of those
        // (f32 is plenty: a few hundred terms of values in [0, 1]).
        self.row_sums.clear();
        self.row_sums.resize(sw * sh, 0.0);
        for (row, out) in self
            .small
            .chunks_exact(sw)
            .zip(self.row_sums.chunks_exact_mut(sw))
        {
            let mut s: f32 = row[..half.min(sw)].iter().sum();
            for c in 0..sw {
                if c + half < sw {
                    s += row[c + half];
                }
                if c > half {
                    s -= row[c - half - 1];
                }
                out[c] = s;
            }
        }
        // Pixels under the window at each column, and the offset scaled by it.
        self.col_counts.clear();
        self.col_counts
            .extend((0..sw).map(|c| ((c + half).min(sw - 1) + 1 - c.saturating_sub(half)) as f32));
        self.col_sums.clear();
        self.col_sums.resize(sw, 0.0);
        for r in 0..half.min(sh) {
            for (acc, v) in self.col_sums.iter_mut().zip(&self.row_sums[r * sw..]) {
                *acc += v;
            }
        }
        self.bright.clear();
        self.bright.resize(sw, 0);
        self.runs.clear();
        for r in 0..sh {
            if r + half < sh {
                let add = &self.row_sums[(r + half) * sw..(r + half + 1) * sw];
                for (acc, v) in self.col_sums.iter_mut().zip(add) {
                    *acc += v;
                }
            }
            if r > half {
                let sub = &self.row_sums[(r - half - 1) * sw..(r - half) * sw];
                for (acc, v) in self.col_sums.iter_mut().zip(sub) {
                    *acc -= v;
                }
            }
            let rows_in = ((r + half).min(sh - 1) + 1 - r.saturating_sub(half)) as f32;
            let row = &self.small[r * sw..(r + 1) * sw];
            // bright ⇔ v > sum/count + offset ⇔ (v − offset)·count > sum.
            for (((b, &v), &sum), &count) in self
                .bright
                .iter_mut()
                .zip(row)
                .zip(&self.col_sums)
                .zip(&self.col_counts)
            {
                *b = u8::from((v - offset) * (count * rows_in) > sum);
            }
            let mut start: Option<usize> = None;
            for (c, &b) in self.bright.iter().enumerate() {
                match (b != 0, start) {
                    (true, None) => start = Some(c),
                    (false, Some(s)) => {
                        self.runs.push(Run {
                            row: r as u32,
                            start: s as u32,
                            end: c as u32,
                        });
                        start = None;
                    }
                    _ => {}
                }
            }
            if let Some(s) = start {
                self.runs.push(Run {
                    row: r as u32,
                    start: s as u32,
                    end: sw as u32,
                });
            }
        }
    }

    /// 8-connected components of the runs; returns the bounding box of each root.
    fn components(&mut self) -> Vec<(u32, Extent)> {
        let n = self.runs.len();
        self.parent.clear();
        self.parent.extend(0..n as u32);
        // Runs are sorted by row then start; walk each row against the previous one.
        let mut cur_start = 0usize; // first run of the current row
        let mut scan = 0usize; // first previous-row run that may still touch the current one
        for i in 0..n {
            let run = self.runs[i];
            if i > 0 && self.runs[i - 1].row != run.row {
                scan = if self.runs[i - 1].row + 1 == run.row {
                    cur_start
                } else {
                    i // the previous row has no runs
                };
                cur_start = i;
            }
            // Previous-row runs ending left of this one cannot touch later runs either.
            while scan < cur_start && self.runs[scan].end < run.start {
                scan += 1;
            }
            let mut j = scan;
            // 8-connectivity: runs touch when their column ranges overlap or meet diagonally.
            while j < cur_start && self.runs[j].start <= run.end {
                union(&mut self.parent, i as u32, j as u32);
                j += 1;
            }
        }
        let mut extents: Vec<Option<Extent>> = vec![None; n];
        for i in 0..n {
            let root = find_root(&mut self.parent, i as u32) as usize;
            let run = self.runs[i];
            let e = extents[root].get_or_insert(Extent {
                min_c: run.start,
                max_c: run.end - 1,
                min_r: run.row,
                max_r: run.row,
            });
            e.min_c = e.min_c.min(run.start);
            e.max_c = e.max_c.max(run.end - 1);
            e.min_r = e.min_r.min(run.row);
            e.max_r = e.max_r.max(run.row);
        }
        extents
            .into_iter()
            .enumerate()
            .filter_map(|(i, e)| e.map(|e| (i as u32, e)))
            .collect()
    }
}

/// Threshold offset from the 1st–99th percentile range of the values; `None` for a flat image.
fn threshold_offset(values: &[f32], fraction: f64) -> Option<f32> {
    // Every 7th value is plenty for two percentiles.
    let sample = || values.iter().step_by(7).copied();
    let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
    let mut count = 0usize;
    for v in sample() {
        lo = lo.min(v);
        hi = hi.max(v);
        count += 1;
    }
    if hi.is_nan() || lo.is_nan() || hi <= lo {
        return None;
    }
    const BINS: usize = 256;
    let mut hist = [0usize; BINS];
    let scale = (BINS - 1) as f32 / (hi - lo);
    for v in sample() {
        hist[(((v - lo) * scale) as usize).min(BINS - 1)] += 1;
    }
    let percentile = |q: f64| {
        let target = (q * count as f64) as usize;
        let mut acc = 0;
        for (i, &n) in hist.iter().enumerate() {
            acc += n;
            if acc > target {
                return lo + i as f32 / scale;
            }
        }
        hi
    };
    let range = percentile(0.99) - percentile(0.01);
    if range > 0.0 {
        Some((fraction as f32) * range)
    } else {
        None
    }
}

fn find_root(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let grand = parent[parent[i as usize] as usize];
        parent[i as usize] = grand;
        i = grand;
    }
    i
}

fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (find_root(parent, a), find_root(parent, b));
    if ra != rb {
        // Smaller index as root keeps roots stable and paths short for raster order.
        let (lo, hi) = if ra < rb { (ra, rb) } else { (rb, ra) };
        parent[hi as usize] = lo;
    }
}

fn cross(a: Vector2<f64>, b: Vector2<f64>) -> f64 {
    a.x * b.y - a.y * b.x
}

/// Signed area (positive when clockwise on screen, y down).
fn polygon_area(poly: &[Vector2<f64>]) -> f64 {
    let n = poly.len();
    (0..n)
        .map(|k| cross(poly[k], poly[(k + 1) % n]))
        .sum::<f64>()
        / 2.0
}

/// Convex hull (Andrew's monotone chain), clockwise on screen (y down), no collinear points.
pub(crate) fn convex_hull(mut pts: Vec<Vector2<f64>>) -> Vec<Vector2<f64>> {
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    pts.dedup();
    if pts.len() < 3 {
        return pts;
    }
    let mut hull: Vec<Vector2<f64>> = Vec::with_capacity(pts.len() + 1);
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Vector2<f64>>> = if pass == 0 {
            Box::new(pts.iter())
        } else {
            Box::new(pts.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2 {
                let (a, b) = (hull[hull.len() - 2], hull[hull.len() - 1]);
                // Keep strictly clockwise turns on screen (positive cross with y down).
                if cross(b - a, p - a) <= 0.0 {
                    hull.pop();
                } else {
                    break;
                }
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// The quadrilateral outlined by a convex hull (clockwise on screen), or `None` when the hull
/// is not close to one with sides ≥ `min_side`.
fn fit_quad(hull: &[Vector2<f64>], min_side: f64, tolerance: f64) -> Option<[Vector2<f64>; 4]> {
    let m = hull.len();
    if m < 4 {
        return None;
    }
    // Diameter: one diagonal.
    let (mut ia, mut ic, mut best) = (0, 0, -1.0);
    for i in 0..m {
        for j in i + 1..m {
            let d = (hull[j] - hull[i]).norm_squared();
            if d > best {
                (ia, ic, best) = (i, j, d);
            }
        }
    }
    let (a, c) = (hull[ia], hull[ic]);
    let axis = c - a;
    // Farthest points on each side of the diagonal.
    let (mut ib, mut id) = (None, None);
    let (mut db, mut dd) = (0.0, 0.0);
    for (k, &p) in hull.iter().enumerate() {
        let s = cross(axis, p - a);
        if s > db {
            (ib, db) = (Some(k), s);
        }
        if s < dd {
            (id, dd) = (Some(k), s);
        }
    }
    let (b, d) = (hull[ib?], hull[id?]);
    // Clockwise on screen (y down): the corner with negative cross(axis, p − a) comes first.
    let quad = [a, d, c, b];
    let sides = [0, 1, 2, 3].map(|k| (quad[(k + 1) % 4] - quad[k]).norm());
    if sides.iter().any(|&s| s < min_side) {
        return None;
    }
    let mean_side = sides.iter().sum::<f64>() / 4.0;
    let tol = 1.5 + tolerance * mean_side;
    let on_outline = |p: Vector2<f64>| {
        (0..4)
            .map(|k| segment_distance(p, quad[k], quad[(k + 1) % 4]))
            .fold(f64::INFINITY, f64::min)
            <= tol
    };
    if !hull.iter().all(|&p| on_outline(p)) {
        return None;
    }
    Some(quad)
}

fn segment_distance(p: Vector2<f64>, a: Vector2<f64>, b: Vector2<f64>) -> f64 {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > 0.0 {
        ((p - a).dot(&ab) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + ab * t - p).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_is_clockwise_without_collinear_points() {
        let pts = vec![
            Vector2::new(0.0, 0.0),
            Vector2::new(1.0, 0.0),
            Vector2::new(2.0, 0.0),
            Vector2::new(2.0, 2.0),
            Vector2::new(0.0, 2.0),
            Vector2::new(1.0, 1.0),
        ];
        let hull = convex_hull(pts);
        assert_eq!(hull.len(), 4);
        assert!(polygon_area(&hull) > 0.0, "{hull:?}");
    }

    #[test]
    fn finds_a_rotated_frame_and_rejects_a_disc() {
        let (w, h) = (300usize, 260usize);
        let mut px = vec![0.1f32; w * h];
        let (cx, cy, angle) = (150.0f64, 130.0f64, 0.3f64);
        let (s, c) = angle.sin_cos();
        for r in 0..h {
            for col in 0..w {
                let (dx, dy) = (col as f64 - cx, r as f64 - cy);
                let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
                let m = u.abs().max(v.abs());
                if (60.0..80.0).contains(&m) {
                    px[r * w + col] = 0.9;
                }
                // A disc elsewhere: bright but not a quadrilateral.
                if (col as f64 - 40.0).hypot(r as f64 - 40.0) < 25.0 {
                    px[r * w + col] = 0.9;
                }
            }
        }
        let image = GreyImage::new(w, h, px).unwrap();
        let quads = QuadFinder::default().find(&image, &QuadParams::default());
        assert_eq!(quads.len(), 1, "{quads:?}");
        let q = &quads[0];
        assert!((q.center() - Vector2::new(cx, cy)).norm() < 1.5, "{q:?}");
        for side in q.sides() {
            assert!((side - 160.0).abs() < 4.0, "{side}");
        }
        assert!(q.contains(Vector2::new(cx, cy)));
        assert!(!q.contains(Vector2::new(5.0, 5.0)));
    }
}
