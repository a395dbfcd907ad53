//! Candidate stamp frames: convex quadrilaterals outlining regions of one colour
//! (docs/design.md#stamp-frames, redesigned).
//!
//! A stamp's frame is a solid ring of fabricated material, brighter or darker than what
//! surrounds it, so its **outer border** is a quadrilateral however blurred the image is and
//! whatever touches the frame on the inside (dots merged by blur, glyphs). Steps, on an image
//! decimated by block averaging (noise and cost both drop):
//! 1. adaptive threshold: bright iff `value > local mean + offset`, dark iff `value < local
//!    mean − offset`, the mean over a square window (uneven illumination cancels), the offset
//!    three times the image's noise (not its grey range), so any contrast well above the noise
//!    works and flat noisy areas belong to neither colour; both polarities from one pass;
//! 2. per mask, the plain mask and **morphological levels**: a closing by an octagon of radius
//!    1, 3, 7… decimated pixels then an opening by one twice as wide (bit-parallel), so that at
//!    some level a frame cut by a hair is whole again and a thin line or a speck (a hair, a
//!    scratch, dust) joining the frame to its surroundings is gone, while the frame, filled by
//!    the closing, keeps its outline;
//! 3. 8-connected components from row runs (union–find), per large component the convex hull
//!    of its run end points (= hull of its outer border);
//! 4. a quadrilateral from the hull: the largest one with its corners on hull vertices,
//!    accepted when most of the outline follows it (so it really is a quadrilateral, whatever
//!    small thing sticks to it), its sides are long enough and it keeps clear of the image
//!    border (a cut frame is not a quadrilateral); the same frame found at several levels is
//!    kept once;
//! 5. each side refined on the full-resolution image: the outer edge of the frame located
//!    along profiles across the side (steepest step of the frame's polarity) and a line fitted
//!    to them robustly, so profiles crossing a hair or a dust speck do not pull it.
//!
//! Unlike the original (ArUco's candidate stage), nothing here depends on the marker's
//! orientation, and which candidate is a stamp is decided afterwards by the grid period and
//! the bitmap match, not by contour nesting alone.

use crate::grey_image::{GreyImage, Polarity};
use crate::order_stats::{median, robust_sigma, TUKEY_BIWEIGHT};
use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};

/// Settings of the frame (quadrilateral) search.
#[derive(Clone, Debug, PartialEq)]
pub struct QuadParams {
    /// Side of the square window of the adaptive threshold's local mean, pixels of the input
    /// image. Default 32: wider than most frames (so their middle stays bright), narrow enough
    /// to follow illumination gradients (thicker frames come whole at a morphological level).
    pub threshold_window: usize,
    /// Shortest accepted quadrilateral side, pixels of the input image. Default 40.
    pub min_side: f64,
    /// Block-averaging factor applied before the search (1 = full resolution). Default 2;
    /// images with a side below 200 pixels are searched at full resolution.
    pub decimation: usize,
    /// Largest distance of the outline from the fitted quadrilateral (for three quarters of
    /// its length), as a fraction of the mean side (plus 1.5 decimated pixels). Default 0.03.
    pub outline_tolerance: f64,
    /// Morphological levels searched besides the plain masks, `0..=5`: level `k` closes the
    /// masks by an octagon of radius `r = 2^k − 1` decimated pixels, then opens them by one of
    /// radius `2r + 1`. Default 3 (closings up to 7, i.e. 14 input pixels at the default
    /// decimation: hairs and specks up to a period or two wide on grids of up to ~30 pixels
    /// per period).
    pub levels: usize,
}

impl Default for QuadParams {
    fn default() -> Self {
        QuadParams {
            threshold_window: 32,
            min_side: 40.0,
            decimation: 2,
            outline_tolerance: 0.03,
            levels: 3,
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

    /// Mean side length, pixels.
    pub fn mean_side(&self) -> f64 {
        self.sides().iter().sum::<f64>() / 4.0
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

    /// Largest distance from a corner of `other` to the nearest corner of this quadrilateral,
    /// pixels (0 for the same outline, whatever corner each starts from).
    pub fn corner_distance(&self, other: &Quad) -> f64 {
        other
            .corners
            .iter()
            .map(|p| {
                self.corners
                    .iter()
                    .map(|c| (c - p).norm())
                    .fold(f64::INFINITY, f64::min)
            })
            .fold(0.0, f64::max)
    }

    /// The homography of image points that takes the affine view of this outline at its
    /// centre (the one a pair of phase planes measured there gives) to the projective one:
    /// `H·A⁻¹`, `H` mapping the unit square onto the outline and `A` its affine approximation
    /// at the square's centre. The identity for a parallelogram; `None` for a degenerate
    /// outline.
    pub fn perspective_warp(&self) -> Option<Matrix3<f64>> {
        let h = square_to_quad(&self.corners)?;
        let apply = |u: f64, v: f64| {
            let q = h * Vector3::new(u, v, 1.0);
            Vector2::new(q.x / q.z, q.y / q.z)
        };
        // Value and Jacobian of H at the square's centre (central differences: H is smooth).
        let e = 1e-4;
        let m = apply(0.5, 0.5);
        let du = (apply(0.5 + e, 0.5) - apply(0.5 - e, 0.5)) / (2.0 * e);
        let dv = (apply(0.5, 0.5 + e) - apply(0.5, 0.5 - e)) / (2.0 * e);
        // A⁻¹(x) = (0.5, 0.5) + J⁻¹·(x − m), as a 3×3 matrix.
        let j_inv = Matrix2::new(du.x, dv.x, du.y, dv.y).try_inverse()?;
        let t = Vector2::new(0.5, 0.5) - j_inv * m;
        Some(h * affine_matrix(&j_inv, t))
    }

    /// The sides re-fitted to the outer edge of a frame of `polarity` (bright: brighter than
    /// what is outside) on `image`, within `search` pixels of the current lines, or else (an
    /// outline bent by something stuck to the frame) within `2·search` and then `search` of
    /// those; `None` when a side has no clear edge along most of its length.
    ///
    /// Along profiles across each side (its middle 70 %, clear of rounded corners), the edge
    /// is the steepest step from frame to outside (sub-pixel, parabola); the side's line is a
    /// Tukey-weighted fit to those positions, so profiles spoilt by a hair or a speck are
    /// outliers, and the corners are the intersections of consecutive lines.
    pub fn refined(&self, image: &GreyImage, polarity: Polarity, search: f64) -> Option<Quad> {
        let fine = match self.refit(image, polarity, search) {
            Some(q) => q,
            None => {
                let wide = self.refit(image, polarity, 2.0 * search)?;
                wide.refit(image, polarity, search).unwrap_or(wide)
            }
        };
        // A refinement that moved a corner beyond the bands followed something else.
        (fine.corner_distance(self) <= 6.0 * search + 2.0).then_some(fine)
    }

    /// How far perspective bends this outline: the largest distance from a corner to where
    /// the affine view at its centre ([`Quad::perspective_warp`]) puts it, pixels; `None` for
    /// a degenerate outline.
    pub fn perspective_bend(&self) -> Option<f64> {
        let unwarp = self.perspective_warp()?.try_inverse()?;
        self.corners
            .iter()
            .map(|c| {
                let q = unwarp * Vector3::new(c.x, c.y, 1.0);
                (q.z.abs() > 1e-12).then(|| (Vector2::new(q.x / q.z, q.y / q.z) - c).norm())
            })
            .try_fold(0.0f64, |most, d| Some(most.max(d?)))
    }

    /// Whether `image` shows a frame of `polarity` (bright: brighter than what is outside)
    /// all along this outline. Per side, the median over its profiles of the steepest
    /// frame-to-outside step within a quarter of a grid period (`period_px`, pixels) of the
    /// side: on every side it must be at least twice the same median a period further out
    /// (where only background lies) and at least half the median of the four sides. An
    /// outline a grid period off the frame (a pose matched at the wrong shift) leaves at least
    /// two sides in the background or inside the solid frame, with no step, while the others
    /// lie on the frame's edges; an occluder across part of a side (a hair, a dust speck)
    /// spoils a minority of its profiles, which the medians ignore.
    pub(crate) fn edges_confirmed(
        &self,
        image: &GreyImage,
        polarity: Polarity,
        period_px: f64,
    ) -> bool {
        let center = self.center();
        let band = 0.25 * period_px;
        let sign = polarity.sign();
        // Per side: the medians on the side and a period out.
        let mut sides = [[0.0f64; 2]; 4];
        let mut values = Vec::new();
        for (k, medians) in sides.iter_mut().enumerate() {
            let Some(side) = SideProfiles::new(self.corners[k], self.corners[(k + 1) % 4], center)
            else {
                return false;
            };
            let mut heights: [Vec<f64>; 2] = Default::default();
            for j in 0..side.count() {
                let base = side.profile(j).0;
                // Profiles that leave the image are not judged (a profile that never steps
                // down counts as a zero step).
                let far = base + side.normal * (period_px + band + 2.0);
                if image.bilinear(far.x, far.y).is_none() {
                    continue;
                }
                for (h, shift) in heights.iter_mut().zip([0.0, period_px]) {
                    let step =
                        steepest_step(image, (base, side.normal), sign, (shift, band), &mut values);
                    h.push(step.map_or(0.0, |(_, height)| height as f64));
                }
            }
            if 2 * heights[0].len() < side.count() {
                return false;
            }
            *medians = heights.map(|mut h| median(&mut h).unwrap_or(0.0));
        }
        let mut on_sides: Vec<f64> = sides.iter().map(|m| m[0]).collect();
        let typical = median(&mut on_sides).unwrap_or(0.0);
        sides
            .iter()
            .all(|&[at, out]| at > 0.0 && at >= 2.0 * out && 2.0 * at >= typical)
    }

    /// One pass of [`Quad::refined`] with a band of ±`search` pixels.
    fn refit(&self, image: &GreyImage, polarity: Polarity, search: f64) -> Option<Quad> {
        let center = self.center();
        let sign = polarity.sign();
        let mut lines = [(Vector2::zeros(), Vector2::zeros()); 4];
        for (k, line) in lines.iter_mut().enumerate() {
            let a = self.corners[k];
            let b = self.corners[(k + 1) % 4];
            *line = refine_side(image, a, b, center, sign, search)?;
        }
        corners_of(&lines).map(|corners| Quad { corners })
    }
}

/// The affine map `x ↦ linear·x + shift` as a 3×3 matrix of homogeneous coordinates.
pub(crate) fn affine_matrix(linear: &Matrix2<f64>, shift: Vector2<f64>) -> Matrix3<f64> {
    let mut m = Matrix3::identity();
    m.fixed_view_mut::<2, 2>(0, 0).copy_from(linear);
    m.fixed_view_mut::<2, 1>(0, 2).copy_from(&shift);
    m
}

/// The homography taking the unit square's corners `(0,0), (1,0), (1,1), (0,1)` to `corners`
/// (Heckbert's square-to-quad mapping); `None` when three corners are collinear.
pub(crate) fn square_to_quad(corners: &[Vector2<f64>; 4]) -> Option<Matrix3<f64>> {
    let [p0, p1, p2, p3] = *corners;
    let s = p0 - p1 + p2 - p3;
    let (d1, d2) = (p1 - p2, p3 - p2);
    let det = cross(d1, d2);
    if det.abs() < 1e-12 {
        return None;
    }
    let g = cross(s, d2) / det;
    let h = cross(d1, s) / det;
    Some(Matrix3::new(
        p1.x - p0.x + g * p1.x,
        p3.x - p0.x + h * p3.x,
        p0.x,
        p1.y - p0.y + g * p1.y,
        p3.y - p0.y + h * p3.y,
        p0.y,
        g,
        h,
        1.0,
    ))
}

/// One side re-fitted to the frame's outer edge (see [`Quad::refined`]): a point on the new
/// line and its unit direction; `None` without enough consistent edge points.
fn refine_side(
    image: &GreyImage,
    a: Vector2<f64>,
    b: Vector2<f64>,
    center: Vector2<f64>,
    sign: f32,
    search: f64,
) -> Option<(Vector2<f64>, Vector2<f64>)> {
    let side = SideProfiles::new(a, b, center)?;
    let count = side.count();
    let mut values = Vec::new();
    // (position along the side from its middle, edge offset along n), pixels.
    let points: Vec<(f64, f64)> = (0..count)
        .filter_map(|j| {
            let (base, along) = side.profile(j);
            steepest_step(image, (base, side.normal), sign, (0.0, search), &mut values)
                .map(|(offset, _)| (along, offset))
        })
        .collect();
    let (offset, slope) = robust_line(&points, count)?;
    let dir = (side.direction + side.normal * slope).normalize();
    Some(((a + b) / 2.0 + side.normal * offset, dir))
}

/// Profiles across one side of an outline, over the middle 70 % of its length (clear of
/// rounded corners), one every ~8 pixels (8 to 32 of them).
struct SideProfiles {
    a: Vector2<f64>,
    b: Vector2<f64>,
    /// Unit direction from `a` to `b`.
    direction: Vector2<f64>,
    /// Unit normal pointing away from the outline's centre (outwards).
    normal: Vector2<f64>,
}

impl SideProfiles {
    /// The side from `a` to `b` of an outline centred on `center`; `None` when shorter than
    /// 4 pixels.
    fn new(a: Vector2<f64>, b: Vector2<f64>, center: Vector2<f64>) -> Option<Self> {
        let len = (b - a).norm();
        if len < 4.0 {
            return None;
        }
        let direction = (b - a) / len;
        let mut normal = Vector2::new(direction.y, -direction.x);
        if normal.dot(&((a + b) / 2.0 - center)) < 0.0 {
            normal = -normal;
        }
        Some(SideProfiles {
            a,
            b,
            direction,
            normal,
        })
    }

    /// Number of profiles.
    fn count(&self) -> usize {
        (((self.b - self.a).norm() / 8.0).round() as usize).clamp(8, 32)
    }

    /// Profile `j`'s point on the side and its position along the side from the middle,
    /// pixels.
    fn profile(&self, j: usize) -> (Vector2<f64>, f64) {
        let t = 0.15 + 0.7 * (j as f64 + 0.5) / self.count() as f64;
        (
            self.a + (self.b - self.a) * t,
            (t - 0.5) * (self.b - self.a).norm(),
        )
    }
}

/// The steepest step from frame (inside, `−n`) to outside (`+n`) along the profile through
/// `base` in direction `n`, within `search` pixels of `shift` pixels outwards: its sub-pixel
/// offset along `n` (parabola) and its height, `sign × (value 1 px inside − value 1 px
/// outside)`; `None` where the profile leaves the image or never steps down. `values` is
/// scratch space (its contents are replaced).
fn steepest_step(
    image: &GreyImage,
    (base, n): (Vector2<f64>, Vector2<f64>),
    sign: f32,
    (shift, search): (f64, f64),
    values: &mut Vec<f32>,
) -> Option<(f64, f32)> {
    // Profiles sampled every half pixel (every pixel for wide bands: 12 samples each way are
    // plenty) over the band, plus the reach of the step measure (±1 px, `reach` samples) and
    // one sample (sub-pixel peak).
    let step_px = (search / 12.0).clamp(0.5, 1.0);
    let reach = (1.0 / step_px).round().max(1.0) as i64;
    let inner = (search / step_px).ceil() as i64;
    let half = inner + reach + 1;
    values.clear();
    for m in -half..=half {
        let at = base + n * (shift + m as f64 * step_px);
        values.push(sign * image.bilinear(at.x, at.y)?);
    }
    // Frame inside (−n), outside (+n): the step is value(d − 1 px) − value(d + 1 px).
    let step = |m: i64| {
        let i = (m + half) as usize;
        values[i - reach as usize] - values[i + reach as usize]
    };
    let (mut best, mut at) = (0.0f32, None);
    for m in -inner..=inner {
        let s = step(m);
        if s > best {
            (best, at) = (s, Some(m));
        }
    }
    let m = at?;
    let (l, c, r) = (step(m - 1) as f64, best as f64, step(m + 1) as f64);
    let curvature = l - 2.0 * c + r;
    let delta = if curvature < 0.0 {
        (0.5 * (l - r) / curvature).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    Some((shift + (m as f64 + delta) * step_px, best))
}

/// Tukey-weighted straight-line fit `e = offset + slope·s` to `(s, e)` points, started from
/// the median offset; `None` when fewer than half of `expected` points are inliers.
fn robust_line(points: &[(f64, f64)], expected: usize) -> Option<(f64, f64)> {
    if points.len() < 6 || 2 * points.len() < expected {
        return None;
    }
    let mut offsets: Vec<f64> = points.iter().map(|p| p.1).collect();
    let (mut offset, mut slope) = (median(&mut offsets).unwrap_or(0.0), 0.0);
    let mut residuals = Vec::with_capacity(points.len());
    let mut scale = 0.0;
    for _ in 0..5 {
        residuals.clear();
        residuals.extend(points.iter().map(|&(s, e)| (e - offset - slope * s).abs()));
        let mut r = residuals.clone();
        // Robust spread, floored at a quarter pixel (sharp synthetic edges give ~0).
        scale = robust_sigma(&mut r).max(0.25);
        let c = TUKEY_BIWEIGHT * scale;
        let (mut sw, mut ss, mut se, mut sss, mut sse) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for (&(s, e), &res) in points.iter().zip(&residuals) {
            let w = if res < c {
                (1.0 - (res / c).powi(2)).powi(2)
            } else {
                0.0
            };
            sw += w;
            ss += w * s;
            se += w * e;
            sss += w * s * s;
            sse += w * s * e;
        }
        let det = sw * sss - ss * ss;
        if sw <= 0.0 || det.abs() < 1e-12 {
            return None;
        }
        slope = (sw * sse - ss * se) / det;
        offset = (se - slope * ss) / sw;
    }
    let inliers = points
        .iter()
        .filter(|&&(s, e)| (e - offset - slope * s).abs() <= 3.0 * scale)
        .count();
    (2 * inliers >= expected && slope.is_finite() && offset.is_finite()).then_some((offset, slope))
}

/// A frame candidate: its outline (refined) and the polarity of the region it outlines.
#[derive(Clone, Debug)]
pub(crate) struct Candidate {
    pub quad: Quad,
    /// `BrightDots`: the frame is brighter than its surroundings.
    pub polarity: Polarity,
}

/// A binary image, one bit per pixel (bit `c % 64` of word `c / 64` is column `c`), rows
/// padded to whole 64-bit words with zeros.
#[derive(Clone, Default)]
struct BitMask {
    width: usize,
    height: usize,
    stride: usize,
    words: Vec<u64>,
}

impl BitMask {
    fn reset(&mut self, width: usize, height: usize) {
        self.width = width;
        self.height = height;
        self.stride = width.div_ceil(64);
        self.words.clear();
        self.words.resize(self.stride * height, 0);
    }

    /// Valid bits of each row's last word.
    fn tail(&self) -> u64 {
        match self.width % 64 {
            0 => u64::MAX,
            r => (1u64 << r) - 1,
        }
    }

    fn invert(&mut self) {
        if self.stride == 0 {
            return;
        }
        let tail = self.tail();
        for row in self.words.chunks_exact_mut(self.stride) {
            for w in row.iter_mut() {
                *w = !*w;
            }
            if let Some(last) = row.last_mut() {
                *last &= tail;
            }
        }
    }

    /// One dilation step: by the 3×3 square (`square`), else by the 4-neighbour cross. One
    /// pass, row by row, with three rows of scratch in `tmp`.
    fn grow(&mut self, square: bool, tmp: &mut Vec<u64>) {
        let (stride, tail, h) = (self.stride, self.tail(), self.height);
        if stride == 0 || h == 0 {
            return;
        }
        tmp.clear();
        tmp.resize(3 * stride, 0);
        // Scratch rows: `prev` (the row above, grown for a square, as it was for a cross),
        // `cur` and `next`, rotated by index.
        let (mut prev, mut cur, mut next) = (0usize, 1usize, 2usize);
        if square {
            grow_row(&self.words[..stride], &mut tmp[stride..2 * stride], tail);
        }
        for r in 0..h {
            let row = r * stride..(r + 1) * stride;
            if square {
                // Row r becomes the OR of the grown rows r − 1, r, r + 1.
                if r + 1 < h {
                    let (rows, scratch) =
                        (&self.words, &mut tmp[next * stride..(next + 1) * stride]);
                    grow_row(&rows[row.end..row.end + stride], scratch, tail);
                } else {
                    tmp[next * stride..(next + 1) * stride].fill(0);
                }
                for (i, w) in self.words[row].iter_mut().enumerate() {
                    *w = tmp[prev * stride + i] | tmp[cur * stride + i] | tmp[next * stride + i];
                }
                (prev, cur, next) = (cur, next, prev);
            } else {
                // Row r grown sideways, OR the rows r − 1 and r + 1 as they were.
                let (head, rest) = self.words.split_at_mut(row.end);
                let original = &mut tmp[cur * stride..(cur + 1) * stride];
                original.copy_from_slice(&head[row.clone()]);
                grow_row(original, &mut head[row.clone()], tail);
                let below = if r + 1 < h {
                    Some(&rest[..stride])
                } else {
                    None
                };
                for (i, w) in head[row].iter_mut().enumerate() {
                    *w |= tmp[prev * stride + i] | below.map_or(0, |b| b[i]);
                }
                (prev, cur) = (cur, prev);
            }
        }
    }

    /// Dilation by the octagon of radius `radius` (alternate 3×3 squares and crosses: a disc
    /// to within 8 %, so a turned frame keeps straight sides and sharp corners); pixels
    /// outside the image are unset.
    fn dilate(&mut self, radius: usize, tmp: &mut Vec<u64>) {
        for step in 0..radius {
            self.grow(step % 2 == 0, tmp);
        }
    }

    /// Erosion by the octagon of radius `radius`; pixels outside the image count as set (the
    /// image border erodes nothing).
    fn erode(&mut self, radius: usize, tmp: &mut Vec<u64>) {
        self.invert();
        self.dilate(radius, tmp);
        self.invert();
    }

    /// The runs of set pixels into `runs`, row by row (sorted by row, then start).
    fn runs(&self, runs: &mut Vec<Run>) {
        runs.clear();
        if self.stride == 0 {
            return;
        }
        for (r, row) in self.words.chunks_exact(self.stride).enumerate() {
            let mut start: Option<usize> = None;
            for (i, &word) in row.iter().enumerate() {
                let base = i * 64;
                let mut b = 0u32;
                while b < 64 {
                    let rest = word >> b;
                    match start {
                        None => {
                            if rest == 0 {
                                break;
                            }
                            b += rest.trailing_zeros();
                            start = Some(base + b as usize);
                        }
                        Some(s) => {
                            // Ones from bit b (the shift fills with zeros: bounded by 64 − b).
                            let ones = (!rest).trailing_zeros();
                            if b + ones >= 64 {
                                break;
                            }
                            b += ones;
                            runs.push(Run {
                                row: r as u32,
                                start: s as u32,
                                end: (base + b as usize) as u32,
                            });
                            start = None;
                        }
                    }
                }
            }
            if let Some(s) = start {
                runs.push(Run {
                    row: r as u32,
                    start: s as u32,
                    end: self.width as u32,
                });
            }
        }
    }
}

/// Work buffers of the search, reused between frames.
#[derive(Default)]
pub(crate) struct QuadFinder {
    small: Option<GreyImage>,
    row_sums: Vec<f32>,
    col_sums: Vec<f32>,
    col_counts: Vec<f32>,
    prefix: Vec<f32>,
    means: Vec<f32>,
    above: Vec<u8>,
    below: Vec<u8>,
    masks: [BitMask; 2],
    level: BitMask,
    tmp: Vec<u64>,
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

/// Smallest quadrilateral side per unit of closing radius at a morphological level: a closing
/// that large bridges anything a stamp of that size can have stuck to it or cut through its
/// frame (a hair, a dust speck a few periods wide: a stamp is ~35 periods across), and a
/// larger one only merges it with its neighbours.
const SIDE_PER_RADIUS: f64 = 8.0;

impl QuadFinder {
    /// Quadrilateral outlines of the regions of either colour of `image` (bright for
    /// `BrightDots`, dark for `DarkDots`, or both for `None`) that are `plausible`, refined
    /// ([`Quad::refined`], with an edge search of half the thinnest frame: `frame_fractions`
    /// are the bitmaps' frame thicknesses over their sides), in the order to try them (see
    /// `order_candidates`).
    pub(crate) fn find(
        &mut self,
        image: &GreyImage,
        params: &QuadParams,
        polarity: Option<Polarity>,
        frame_fractions: &[f64],
        plausible: &dyn Fn(&Quad) -> bool,
    ) -> Vec<Candidate> {
        let frame_fraction = frame_fractions
            .iter()
            .copied()
            .fold(f64::INFINITY, f64::min);
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
        let Some(small) = &self.small else {
            return Vec::new();
        };
        // The offset: three noise deviations (a flat area is speckled by one pixel in a
        // thousand), at least a quarter of an 8-bit grey level (exactly flat areas).
        let offset = (NOISE_OFFSET * noise_sigma(small)).max(MIN_OFFSET);
        let half = (params.threshold_window / f / 2).max(1);
        self.threshold_masks(sw, sh, half, offset);
        let min_side = (params.min_side / f as f64).max(4.0);
        let scale = f as f64;
        let mut found: Vec<(Quad, Polarity)> = Vec::new();
        let polarities = [Polarity::BrightDots, Polarity::DarkDots];
        for (m, &pol) in polarities.iter().enumerate() {
            if polarity.is_some_and(|p| p != pol) {
                continue;
            }
            for level in 0..=params.levels.min(5) {
                let outlines =
                    self.level_outlines(m, level, (sw, sh), min_side, params.outline_tolerance);
                for q in outlines {
                    let quad = Quad {
                        // Decimated pixel centre i covers input pixels i·f .. i·f + f − 1.
                        corners: q.map(|c| c * scale + Vector2::repeat((scale - 1.0) / 2.0)),
                    };
                    log::trace!(
                        "level {level} {pol:?}: quad centre {:.1?} sides {:.1?}",
                        quad.center(),
                        quad.sides()
                    );
                    // The same outline at a finer level was found already (refining it again
                    // would give the same frame).
                    let tol = 0.02 * quad.mean_side() + 2.0 * scale;
                    let known = found
                        .iter()
                        .any(|(k, p)| *p == pol && k.corner_distance(&quad) <= tol);
                    if !known && plausible(&quad) {
                        found.push((quad, pol));
                    }
                }
            }
        }
        let mut candidates = refined_candidates(image, found, frame_fraction, scale);
        order_candidates(&mut candidates, frame_fractions);
        candidates
    }

    /// Outlines (decimated pixels) in mask `m` (0 bright, 1 dark) of the `sw × sh` decimated
    /// image at morphological `level` (closing then opening of radius `2^level − 1`), of
    /// sides ≥ `min_side` and what that radius can bridge.
    fn level_outlines(
        &mut self,
        m: usize,
        level: usize,
        (sw, sh): (usize, usize),
        min_side: f64,
        tolerance: f64,
    ) -> Vec<[Vector2<f64>; 4]> {
        let mut mask = std::mem::take(&mut self.level);
        mask.clone_from(&self.masks[m]);
        let radius = (1usize << level) - 1;
        if radius > 0 {
            // Closing (bridges dark cuts, fills the stamp), then a twice wider opening
            // (drops bright lines and specks, even those the closing merged with a
            // dark line between them: the two halo bands along a hair).
            mask.dilate(radius, &mut self.tmp);
            mask.erode(radius, &mut self.tmp);
            mask.erode(2 * radius + 1, &mut self.tmp);
            mask.dilate(2 * radius + 1, &mut self.tmp);
        }
        let level_min = min_side.max(SIDE_PER_RADIUS * radius as f64);
        mask.runs(&mut self.runs);
        self.level = mask;
        // An opening by radius ρ rounds the corners: the outline leaves them by ~0.4 ρ.
        let slack = if radius > 0 {
            0.45 * (2 * radius + 1) as f64
        } else {
            0.0
        };
        self.outlines(sw, sh, level_min, tolerance, slack)
    }

    /// Block means of `f × f` pixels into `self.small` (`sw × sh`).
    fn decimate(&mut self, image: &GreyImage, f: usize, sw: usize, sh: usize) {
        let w = image.width();
        let px = image.pixels();
        let reuse = self
            .small
            .as_ref()
            .is_some_and(|s| s.width() == sw && s.height() == sh);
        if !reuse {
            self.small = GreyImage::new(sw, sh, vec![0.0; sw * sh]).ok();
        }
        let Some(small) = self.small.as_mut() else {
            return;
        };
        let norm = 1.0 / (f * f) as f32;
        for (r, out) in small.pixels_mut().chunks_exact_mut(sw).enumerate() {
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
            out.fill(0.0);
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

    /// The bright (above the local mean by more than `offset`) and dark (below it by more
    /// than `offset`) masks of the decimated image, the mean over a `(2·half + 1)²` window.
    fn threshold_masks(&mut self, sw: usize, sh: usize, half: usize, offset: f32) {
        let clip = self.small.as_ref().and_then(|s| robust_range(s.pixels()));
        let [bright, dark] = &mut self.masks;
        bright.reset(sw, sh);
        dark.reset(sw, sh);
        let Some(small) = &self.small else {
            return;
        };
        let small = small.pixels();
        // Box sums: horizontal running sums per row, then vertical running sums of those
        // (f32 is plenty: a few hundred terms of values in [0, 1]).
        row_box_sums(
            small,
            (sw, sh),
            half,
            clip,
            &mut self.prefix,
            &mut self.row_sums,
        );
        // Inverse of the pixels under the window at each column (times its rows, per row).
        self.col_counts.clear();
        self.col_counts.extend(
            (0..sw).map(|c| 1.0 / ((c + half).min(sw - 1) + 1 - c.saturating_sub(half)) as f32),
        );
        self.col_sums.clear();
        self.col_sums.resize(sw, 0.0);
        for r in 0..half.min(sh) {
            for (acc, v) in self.col_sums.iter_mut().zip(&self.row_sums[r * sw..]) {
                *acc += v;
            }
        }
        self.means.clear();
        self.means.resize(sw, 0.0);
        self.above.clear();
        self.above.resize(sw, 0);
        self.below.clear();
        self.below.resize(sw, 0);
        let stride = bright.stride;
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
            let inv_rows = 1.0 / ((r + half).min(sh - 1) + 1 - r.saturating_sub(half)) as f32;
            for ((m, &sum), &inv) in self
                .means
                .iter_mut()
                .zip(&self.col_sums)
                .zip(&self.col_counts)
            {
                *m = sum * inv * inv_rows;
            }
            threshold_row(
                &small[r * sw..(r + 1) * sw],
                &self.means,
                offset,
                (&mut self.above, &mut self.below),
                &mut bright.words[r * stride..(r + 1) * stride],
                &mut dark.words[r * stride..(r + 1) * stride],
            );
        }
    }

    /// Quadrilateral outlines (decimated pixels) of the large components of `self.runs`.
    fn outlines(
        &mut self,
        sw: usize,
        sh: usize,
        min_side: f64,
        tolerance: f64,
        slack: f64,
    ) -> Vec<[Vector2<f64>; 4]> {
        let extents = self.components();
        // Components large enough to be a frame, clear of the border, keyed by root.
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
        // Only the leftmost and rightmost pixel of each row of a component can be on its hull;
        // rows come in order, so each component's points stay sorted by (row, column).
        for i in 0..self.runs.len() {
            let root = find_root(&mut self.parent, i as u32);
            if let Ok(k) = points.binary_search_by_key(&root, |(r, _)| *r) {
                let run = self.runs[i];
                let (row, first, last) = (run.row as f64, run.start as f64, (run.end - 1) as f64);
                let pts = &mut points[k].1;
                match pts.len() {
                    n if n >= 2 && pts[n - 1].y == row => {
                        pts[n - 2].x = pts[n - 2].x.min(first);
                        pts[n - 1].x = pts[n - 1].x.max(last);
                    }
                    _ => {
                        pts.push(Vector2::new(first, row));
                        pts.push(Vector2::new(last, row));
                    }
                }
            }
        }
        points
            .into_iter()
            .filter_map(|(_, pts)| fit_quad(&convex_hull(pts), min_side, tolerance, slack))
            .collect()
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

/// The coarse outlines `found` refined on `image` (an edge search of half the thinnest
/// frame, `frame_fraction` of the side), outlines refining to the same frame kept once.
fn refined_candidates(
    image: &GreyImage,
    found: Vec<(Quad, Polarity)>,
    frame_fraction: f64,
    scale: f64,
) -> Vec<Candidate> {
    let mut candidates: Vec<Candidate> = Vec::with_capacity(found.len());
    for (coarse, polarity) in found {
        // The decimated outline is good to a decimated pixel or so.
        let search = (frame_fraction * coarse.mean_side() / 2.0).max(1.5 * scale);
        let quad = coarse.refined(image, polarity, search).unwrap_or(coarse);
        // Outlines of one frame found at several levels, distorted differently, refine to
        // the same one; distinct ones (a frame and a bent outline of it) are all kept.
        let tol = 1.0 + 0.005 * quad.mean_side();
        if !candidates
            .iter()
            .any(|c| c.polarity == polarity && c.quad.corner_distance(&quad) <= tol)
        {
            candidates.push(Candidate { quad, polarity });
        }
    }
    candidates
}

/// Horizontal box sums of each row of the `sw × sh` image `small` over `[c − half, c + half]`
/// (clipped at the ends), of values clipped to `clip`, into `row_sums`.
fn row_box_sums(
    small: &[f32],
    (sw, sh): (usize, usize),
    half: usize,
    clip: Option<(f32, f32)>,
    prefix: &mut Vec<f32>,
    row_sums: &mut Vec<f32>,
) {
    row_sums.clear();
    row_sums.resize(sw * sh, 0.0);
    prefix.clear();
    prefix.resize(sw + 1, 0.0);
    for (row, out) in small.chunks_exact(sw).zip(row_sums.chunks_exact_mut(sw)) {
        // Window sums from prefix sums (values in [0, 1]: f32 keeps ~1e-4 over a row).
        // The mean of values clipped to the robust range: a thin thing far darker or
        // brighter than the rest (a hair, a speck) does not pull it, which would draw a
        // halo of the other colour around it, joined to the frames it crosses.
        let (lo, hi) = clip.unwrap_or((f32::NEG_INFINITY, f32::INFINITY));
        let mut acc = 0.0f32;
        for (p, &v) in prefix[1..].iter_mut().zip(row) {
            acc += v.clamp(lo, hi);
            *p = acc;
        }
        // Sum over [c − half, c + half] ∩ [0, sw): clipped at the ends, plain in between
        // (that loop vectorises).
        let p = &*prefix;
        let first = half.min(sw);
        let last = sw.saturating_sub(half + 1).max(first);
        for (c, o) in out[..first].iter_mut().enumerate() {
            *o = p[(c + half + 1).min(sw)];
        }
        if first < last {
            for (o, (hi, lo)) in out[first..last]
                .iter_mut()
                .zip(p[first + half + 1..].iter().zip(&p[first - half..]))
            {
                *o = hi - lo;
            }
        }
        for (c, o) in out.iter_mut().enumerate().skip(last) {
            *o = p[(c + half + 1).min(sw)] - p[c.saturating_sub(half)];
        }
    }
}

/// Sorts candidates largest first (outermost outlines first: what lies inside an accepted
/// frame is part of it), those that look like a frame before the others: a frame's inner
/// outline shows in the other colour, `1 − 2·fraction` of its size and around the same
/// centre, for one of the bitmaps' frame `fractions` (thickness over side). An outline of
/// the background around a frame (a moat, the threshold's halo) then comes after the frame,
/// and is skipped once the frame is accepted.
fn order_candidates(candidates: &mut Vec<Candidate>, fractions: &[f64]) {
    let framed: Vec<bool> = candidates
        .iter()
        .map(|c| {
            let side = c.quad.mean_side();
            candidates.iter().any(|o| {
                let ratio = o.quad.mean_side() / side;
                o.polarity != c.polarity
                    && (o.quad.center() - c.quad.center()).norm() < 0.05 * side
                    && fractions
                        .iter()
                        .any(|f| (ratio / (1.0 - 2.0 * f) - 1.0).abs() < 0.02)
            })
        })
        .collect();
    let mut order: Vec<usize> = (0..candidates.len()).collect();
    let area = |i: usize| candidates[i].quad.area();
    order.sort_by(|&a, &b| framed[b].cmp(&framed[a]).then(area(b).total_cmp(&area(a))));
    let sorted: Vec<Candidate> = order.iter().map(|&i| candidates[i].clone()).collect();
    *candidates = sorted;
}

/// The 1st and 99th percentiles of `values` (to within 1/256 of their range); `None` for a
/// flat image.
fn robust_range(values: &[f32]) -> Option<(f32, f32)> {
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
    let percentile = |q: f64, upper: bool| {
        let target = (q * count as f64) as usize;
        let mut acc = 0;
        for (i, &n) in hist.iter().enumerate() {
            acc += n;
            if acc > target {
                // The bin's upper edge for the high percentile: nothing inside it is clipped.
                return lo + (i + usize::from(upper)) as f32 / scale;
            }
        }
        hi
    };
    Some((percentile(0.01, false), percentile(0.99, true)))
}

/// Threshold offset, in noise standard deviations.
const NOISE_OFFSET: f32 = 3.0;
/// Smallest threshold offset, intensity units (`[0, 1]` images).
const MIN_OFFSET: f32 = 1e-3;

/// Noise standard deviation of `image`: the 10th percentile of the standard deviations of its
/// 4×4 blocks (the quietest tenth sees only noise in any real image: background, the inside
/// of a frame); 0 for an image smaller than 4×4.
fn noise_sigma(image: &GreyImage) -> f32 {
    const B: usize = 4;
    let (w, h) = (image.width(), image.height());
    let px = image.pixels();
    let mut spreads = Vec::with_capacity((w / B) * (h / B));
    let mut sums = vec![(0.0f32, 0.0f32); w / B];
    for by in 0..h / B {
        sums.fill((0.0, 0.0));
        for row in px[by * B * w..(by + 1) * B * w].chunks_exact(w) {
            for (acc, block) in sums.iter_mut().zip(row.chunks_exact(B)) {
                for &v in block {
                    acc.0 += v;
                    acc.1 += v * v;
                }
            }
        }
        let n = (B * B) as f32;
        spreads.extend(sums.iter().map(|&(s, s2)| {
            let mean = s / n;
            (s2 / n - mean * mean).max(0.0)
        }));
    }
    if spreads.is_empty() {
        return 0.0;
    }
    let k = spreads.len() / 10;
    let (_, variance, _) = spreads.select_nth_unstable_by(k, f32::total_cmp);
    variance.sqrt()
}

/// `dst` = the row `src` OR-ed with itself shifted by one pixel left and right.
fn grow_row(src: &[u64], dst: &mut [u64], tail: u64) {
    let n = src.len();
    let mut prev = 0u64;
    for i in 0..n {
        let cur = src[i];
        let next = if i + 1 < n { src[i + 1] } else { 0 };
        dst[i] = cur | (cur << 1) | (prev >> 63) | (cur >> 1) | (next << 63);
        prev = cur;
    }
    if let Some(last) = dst.last_mut() {
        *last &= tail;
    }
}

/// One row of the threshold masks: sets bit `c % 64` of word `c / 64` of `bright_row` where
/// pixel `c` of `row` is above its local mean (`means`) by more than `offset`, and of
/// `dark_row` where it is below it by more than `offset`; `above` and `below` are scratch
/// rows of the row's length.
fn threshold_row(
    row: &[f32],
    means: &[f32],
    offset: f32,
    (above, below): (&mut [u8], &mut [u8]),
    bright_row: &mut [u64],
    dark_row: &mut [u64],
) {
    // One byte (0 or 1) per pixel, then 8 bytes to 8 bits at a time.
    for ((a, b), (&v, &m)) in above
        .iter_mut()
        .zip(below.iter_mut())
        .zip(row.iter().zip(means))
    {
        *a = u8::from(v > m + offset);
        *b = u8::from(v < m - offset);
    }
    for (k, (a, b)) in above.chunks(64).zip(below.chunks(64)).enumerate() {
        bright_row[k] = pack_bits(a);
        dark_row[k] = pack_bits(b);
    }
}

/// Up to 64 bytes, each 0 or 1, as the bits of a word (byte `i` → bit `i`).
fn pack_bits(bytes: &[u8]) -> u64 {
    let mut word = 0u64;
    for (k, group) in bytes.chunks(8).enumerate() {
        let mut b = [0u8; 8];
        b[..group.len()].copy_from_slice(group);
        // Byte i times 2^(7 − i) lands on bit 56 + i, without carries (distinct positions).
        let packed = u64::from_le_bytes(b).wrapping_mul(0x0102_0408_1020_4080) >> 56;
        word |= packed << (8 * k);
    }
    word
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

/// Convex hull (Andrew's monotone chain along rows), clockwise on screen (y down), no
/// collinear points.
pub(crate) fn convex_hull(mut pts: Vec<Vector2<f64>>) -> Vec<Vector2<f64>> {
    // Row-major order: points gathered row by row are sorted already (a linear pass).
    pts.sort_by(|a, b| a.y.total_cmp(&b.y).then(a.x.total_cmp(&b.x)));
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

/// The quadrilateral outlined by a convex hull (clockwise on screen): the largest one with
/// its corners on hull vertices, accepted when at least 3/4 of the hull's outline lies within
/// `1.5 + slack + tolerance × mean side` of its boundary and every side is ≥ `min_side`.
///
/// Something stuck to the frame (a dust speck) only adds a bump to the hull, which the
/// largest inscribed quadrilateral leaves out (a corner moved to the bump's tip would give up
/// far more area than it gains) and which is a small part of the outline; a disc or a blob has
/// much of its outline away from any inscribed quadrilateral.
fn fit_quad(
    hull: &[Vector2<f64>],
    min_side: f64,
    tolerance: f64,
    slack: f64,
) -> Option<[Vector2<f64>; 4]> {
    let m = hull.len();
    if m < 4 {
        return None;
    }
    let at = |o: usize| hull[o % m];
    // Twice the area of triangle (a, b, c), positive for clockwise on screen.
    let tri = |a: usize, b: usize, c: usize| cross(at(b) - at(a), at(c) - at(a));
    // For each first corner i and opposite corner k, the best corners between them are the
    // vertices farthest from the diagonal, which move forward with k (rotating pointers).
    let mut best = (f64::NEG_INFINITY, [0usize; 4]);
    for i in 0..m {
        let (mut j, mut l) = (i + 1, i + 3);
        for k in i + 2..i + m - 1 {
            while j + 1 < k && tri(i, j + 1, k) >= tri(i, j, k) {
                j += 1;
            }
            l = l.max(k + 1);
            while l + 1 < i + m && tri(k, l + 1, i) >= tri(k, l, i) {
                l += 1;
            }
            let area = tri(i, j, k) + tri(k, l, i);
            if area > best.0 {
                best = (area, [i, j, k, l]);
            }
        }
    }
    let quad = best.1.map(at);
    let sides = [0, 1, 2, 3].map(|k| (quad[(k + 1) % 4] - quad[k]).norm());
    if sides.iter().any(|&s| s < min_side) {
        return None;
    }
    let mean_side = sides.iter().sum::<f64>() / 4.0;
    let tol = 1.5 + slack + tolerance * mean_side;
    let off = |p: Vector2<f64>| {
        (0..4)
            .map(|k| segment_distance(p, quad[k], quad[(k + 1) % 4]))
            .fold(f64::INFINITY, f64::min)
    };
    let (mut on, mut perimeter) = (0.0, 0.0);
    for k in 0..m {
        let (p, q) = (hull[k], hull[(k + 1) % m]);
        let len = (q - p).norm();
        perimeter += len;
        if off(p) <= tol && off(q) <= tol {
            on += len;
        }
    }
    (on >= 0.75 * perimeter).then_some(quad)
}

/// Corners of the quadrilateral bounded by four lines (a point and a unit direction each, in
/// order around it): corner `k` joins line `k − 1` and line `k`. `None` when two consecutive
/// lines are within ~20° of parallel (no corner there).
fn corners_of(lines: &[(Vector2<f64>, Vector2<f64>); 4]) -> Option<[Vector2<f64>; 4]> {
    let mut corners = [Vector2::zeros(); 4];
    for (k, corner) in corners.iter_mut().enumerate() {
        let (p, u) = lines[(k + 3) % 4];
        let (q, v) = lines[k];
        let sine = cross(u, v);
        if sine.abs() < 0.35 {
            return None;
        }
        *corner = p + u * (cross(q - p, v) / sine);
    }
    Some(corners)
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

    /// A `w × h` image of value `background` with a square ring (outer half side 80, inner 60,
    /// turned by `angle`) of value `frame` centred at `center`.
    fn ring(
        w: usize,
        h: usize,
        center: Vector2<f64>,
        angle: f64,
        frame: f32,
        background: f32,
    ) -> Vec<f32> {
        let (s, c) = angle.sin_cos();
        (0..w * h)
            .map(|i| {
                let (dx, dy) = ((i % w) as f64 - center.x, (i / w) as f64 - center.y);
                let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
                if (60.0..80.0).contains(&u.abs().max(v.abs())) {
                    frame
                } else {
                    background
                }
            })
            .collect()
    }

    /// That ring bright on dark and dark on bright (with the polarity of each), dark hairs
    /// (grey 0.05) over the pixels `hair` says.
    fn rings_with_hairs(
        w: usize,
        h: usize,
        center: Vector2<f64>,
        angle: f64,
        hair: impl Fn(usize) -> bool,
    ) -> [(GreyImage, Polarity); 2] {
        [
            (0.9, 0.2, Polarity::BrightDots),
            (0.2, 0.9, Polarity::DarkDots),
        ]
        .map(|(frame, background, polarity)| {
            let px: Vec<f32> = ring(w, h, center, angle, frame, background)
                .into_iter()
                .enumerate()
                .map(|(i, v)| if hair(i) { 0.05 } else { v })
                .collect();
            (GreyImage::new(w, h, px).unwrap(), polarity)
        })
    }

    /// Corners of that ring's outer outline.
    fn ring_corners(center: Vector2<f64>, angle: f64) -> Quad {
        let (s, c) = angle.sin_cos();
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(u, v)| {
            // Pixels are set where |u| < 80 on their centres: the edge is at 79.5 + 0.5.
            let (u, v) = (80.0 * u, 80.0 * v);
            center + Vector2::new(c * u - s * v, s * u + c * v)
        });
        Quad { corners }
    }

    fn bright_quads(candidates: &[Candidate], polarity: Polarity) -> Vec<Quad> {
        candidates
            .iter()
            .filter(|c| c.polarity == polarity)
            .map(|c| c.quad.clone())
            .collect()
    }

    #[test]
    fn finds_a_rotated_frame_and_rejects_a_disc() {
        let (w, h) = (300usize, 260usize);
        let (center, angle) = (Vector2::new(150.0, 130.0), 0.3);
        let mut px = ring(w, h, center, angle, 0.9, 0.1);
        for (i, v) in px.iter_mut().enumerate() {
            // A disc elsewhere: bright but not a quadrilateral.
            if ((i % w) as f64 - 40.0).hypot((i / w) as f64 - 40.0) < 25.0 {
                *v = 0.9;
            }
        }
        let image = GreyImage::new(w, h, px).unwrap();
        let found =
            QuadFinder::default().find(&image, &QuadParams::default(), None, &[0.1], &|_| true);
        // The bright ring, and the dark square it encloses.
        let bright = bright_quads(&found, Polarity::BrightDots);
        assert_eq!(bright.len(), 1, "{found:?}");
        let q = &bright[0];
        let truth = ring_corners(center, angle);
        assert!(q.corner_distance(&truth) < 0.5, "{q:?}");
        assert!(q.contains(center));
        assert!(!q.contains(Vector2::new(5.0, 5.0)));
        let dark = bright_quads(&found, Polarity::DarkDots);
        assert_eq!(dark.len(), 1, "{found:?}");
        assert!((dark[0].mean_side() - 120.0).abs() < 2.0, "{dark:?}");
    }

    #[test]
    fn a_hair_across_the_frame_does_not_hide_it() {
        let (w, h) = (320usize, 300usize);
        let (center, angle) = (Vector2::new(163.0, 148.0), -0.4);
        let truth = ring_corners(center, angle);
        // A dark line 3 px wide across the whole image, cutting the ring twice.
        let hair = |i: usize| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            ((y - 20.0) - 0.8 * (x - 10.0)).abs() / 0.8f64.hypot(1.0) < 1.5
        };
        for (image, polarity) in rings_with_hairs(w, h, center, angle, hair) {
            let found =
                QuadFinder::default().find(&image, &QuadParams::default(), None, &[0.1], &|_| true);
            let quads = bright_quads(&found, polarity);
            // Bright frame: the hair cuts it; dark frame: the (dark) hair joins it to the rest.
            let best = quads
                .iter()
                .map(|q| q.corner_distance(&truth))
                .fold(f64::INFINITY, f64::min);
            assert!(best < 0.7, "{polarity:?}: {best} px, {found:?}");
        }
    }

    #[test]
    fn edges_confirm_the_frame_under_hairs_and_not_a_period_off() {
        let (w, h) = (320usize, 300usize);
        let (center, angle, period) = (Vector2::new(160.0, 150.0), 0.35, 10.0);
        let truth = ring_corners(center, angle);
        let (s, c) = angle.sin_cos();
        // Dark hairs 3 px wide: one along the inside of a side (what bends a found outline
        // most), one across the ring.
        let hairs = |i: usize| {
            let (dx, dy) = ((i % w) as f64 - center.x, (i / w) as f64 - center.y);
            let (u, v) = (c * dx + s * dy, -s * dx + c * dy);
            (u + 72.0).abs() < 1.5 || (v - 0.3 * u - 10.0).abs() < 1.5
        };
        for (image, polarity) in rings_with_hairs(w, h, center, angle, hairs) {
            assert!(
                truth.edges_confirmed(&image, polarity, period),
                "{polarity:?}"
            );
            // The outline a period off along either axis, or a period larger all round.
            let along = [Vector2::new(c, s), Vector2::new(-s, c)].map(|d| d * period);
            for moved in [along[0], -along[0], along[1], -along[1]] {
                let off = Quad {
                    corners: truth.corners.map(|p| p + moved),
                };
                assert!(
                    !off.edges_confirmed(&image, polarity, period),
                    "{polarity:?} {moved:?}"
                );
            }
            let larger = Quad {
                corners: truth.corners.map(|p| center + (p - center) * (90.0 / 80.0)),
            };
            assert!(
                !larger.edges_confirmed(&image, polarity, period),
                "{polarity:?}"
            );
        }
    }

    #[test]
    fn perspective_warp_maps_the_affine_view_onto_the_outline() {
        let q = Quad {
            corners: [
                Vector2::new(10.0, 12.0),
                Vector2::new(210.0, 30.0),
                Vector2::new(190.0, 190.0),
                Vector2::new(30.0, 170.0),
            ],
        };
        let h = square_to_quad(&q.corners).unwrap();
        let map = |m: &Matrix3<f64>, p: Vector2<f64>| {
            let r = m * Vector3::new(p.x, p.y, 1.0);
            Vector2::new(r.x / r.z, r.y / r.z)
        };
        for (u, c) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]
            .iter()
            .zip(&q.corners)
        {
            assert!((map(&h, Vector2::new(u.0, u.1)) - c).norm() < 1e-9);
        }
        // The warp fixes the centre and its neighbourhood to first order.
        let w = q.perspective_warp().unwrap();
        let m = map(&h, Vector2::new(0.5, 0.5));
        assert!((map(&w, m) - m).norm() < 1e-9);
        let d = Vector2::new(0.5, -0.3);
        assert!((map(&w, m + d) - (m + d)).norm() < 1e-2);
        // A parallelogram: no correction.
        let p = Quad {
            corners: [
                Vector2::new(0.0, 0.0),
                Vector2::new(100.0, 20.0),
                Vector2::new(130.0, 120.0),
                Vector2::new(30.0, 100.0),
            ],
        };
        let w = p.perspective_warp().unwrap();
        let x = Vector2::new(7.0, 93.0);
        assert!((map(&w, x) - x).norm() < 1e-6);
    }

    #[test]
    fn bytes_pack_into_bits() {
        let bytes: Vec<u8> = (0..70).map(|i| u8::from(i % 3 == 0 || i == 63)).collect();
        let expected = (0..64).fold(0u64, |w, i| w | u64::from(bytes[i]) << i);
        assert_eq!(pack_bits(&bytes[..64]), expected);
        assert_eq!(pack_bits(&bytes[64..]), 0b10_0100);
    }

    #[test]
    fn bit_masks_dilate_erode_and_give_runs() {
        let mut m = BitMask::default();
        m.reset(130, 5);
        // Column 63 and 64 straddle a word boundary; 129 is the last column.
        for c in [10usize, 63, 64, 129] {
            m.words[2 * m.stride + c / 64] |= 1 << (c % 64);
        }
        let mut runs = Vec::new();
        m.runs(&mut runs);
        let spans: Vec<(u32, u32, u32)> = runs.iter().map(|r| (r.row, r.start, r.end)).collect();
        assert_eq!(spans, vec![(2, 10, 11), (2, 63, 65), (2, 129, 130)]);
        let mut tmp = Vec::new();
        m.dilate(1, &mut tmp);
        m.runs(&mut runs);
        let spans: Vec<(u32, u32, u32)> = runs.iter().map(|r| (r.row, r.start, r.end)).collect();
        let row = |r| [(r, 9, 12), (r, 62, 66), (r, 128, 130)];
        let expected: Vec<(u32, u32, u32)> = [1, 2, 3].into_iter().flat_map(row).collect();
        assert_eq!(spans, expected);
        // Eroding back: the image border counts as set, so column 129 survives.
        m.erode(1, &mut tmp);
        m.runs(&mut runs);
        let spans: Vec<(u32, u32, u32)> = runs.iter().map(|r| (r.row, r.start, r.end)).collect();
        assert_eq!(spans, vec![(2, 10, 11), (2, 63, 65), (2, 129, 130)]);
        // Radius 2: a square step then a cross step, the 5×5 square without its corners.
        let mut m = BitMask::default();
        m.reset(9, 9);
        m.words[4 * m.stride] |= 1 << 4;
        m.dilate(2, &mut tmp);
        m.runs(&mut runs);
        let spans: Vec<(u32, u32, u32)> = runs.iter().map(|r| (r.row, r.start, r.end)).collect();
        assert_eq!(
            spans,
            vec![(2, 3, 6), (3, 2, 7), (4, 2, 7), (5, 2, 7), (6, 3, 6)]
        );
    }
}
