//! Scale-free local binarisation and the nesting tree of its regions.
//!
//! Used by the coarse steps to find solid, nested shapes (HP code finder squares) whatever
//! their size, polarity, contrast or illumination:
//!
//! 1. **Local threshold** ([`ThresholdMap`]): the image is cut into 8×8 blocks, each keeps its
//!    minimum and maximum. For every block, neighbourhoods of 3, 5, 9, … 129 blocks (24 to
//!    1032 px) are tried from the smallest; the first whose range (max − min) exceeds the
//!    *contrast floor* gives the threshold, the mid-range or another level of that range
//!    ([`ThresholdMap::set_level`]: a multi-threshold scan). The floor is a multiple of the
//!    image's noise, estimated from the quietest blocks, so the threshold follows the
//!    structure of the scale at hand (a dot grid, a large uniform finder centre) and uneven
//!    illumination, while flat noisy areas stay one region. The block thresholds are smoothed
//!    over 3×3 blocks. (The neighbourhood ladder is the multi-scale form of the block
//!    mid-range binariser of ZXing's `HybridBinarizer`.)
//! 2. **Regions** ([`Regions`]): 4-connected components of both colours from row runs
//!    (union–find), each with its area, centroid, bounding box and **parent**: the region of
//!    the other colour that surrounds it (the one just above its first pixel in raster order).
//!    Every region also gets its *filled* area and centroid (itself plus everything it
//!    encloses), so a shape is measured by its outline whatever texture or holes it has inside.

use crate::grey_image::GreyImage;

/// Block side of the threshold map, pixels.
pub const BLOCK: usize = 8;
/// Neighbourhood radii tried for the local range, blocks (windows of 24 to 1032 px).
const RADII: [usize; 7] = [1, 2, 4, 8, 16, 32, 64];
/// Contrast floor: multiple of the noise standard deviation.
const NOISE_FACTOR: f32 = 6.0;
/// Contrast floor never below this, intensity units (`[0, 1]` images): quantisation ripples.
const MIN_FLOOR: f32 = 0.015;

/// Per-block thresholds of an image (reused between frames).
#[derive(Default)]
pub struct ThresholdMap {
    /// Blocks per row and per column.
    blocks: (usize, usize),
    min: Vec<f32>,
    max: Vec<f32>,
    /// Local minimum and range of each block's chosen neighbourhood (smoothed; `+∞` minimum
    /// where no neighbourhood has contrast: the block is all dark at any level).
    low: Vec<f32>,
    range: Vec<f32>,
    /// Thresholds at the level of the last [`ThresholdMap::set_level`].
    threshold: Vec<f32>,
    scratch: (Vec<f32>, Vec<f32>, Vec<f32>),
    /// Contrast floor used by the last [`ThresholdMap::compute`], intensity units.
    floor: f32,
}

impl ThresholdMap {
    /// Computes the thresholds of `image`. `min_contrast` overrides the contrast floor
    /// (intensity units); `None` takes 6 noise deviations, at least 0.015.
    pub fn compute(&mut self, image: &GreyImage, min_contrast: Option<f32>) {
        let (w, h) = (image.width(), image.height());
        let (bw, bh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
        self.blocks = (bw, bh);
        self.min.clear();
        self.min.resize(bw * bh, f32::INFINITY);
        self.max.clear();
        self.max.resize(bw * bh, f32::NEG_INFINITY);
        let mut spread = Vec::with_capacity(bw * bh);
        let px = image.pixels();
        for by in 0..bh {
            let rows = by * BLOCK..((by + 1) * BLOCK).min(h);
            for bx in 0..bw {
                let cols = bx * BLOCK..((bx + 1) * BLOCK).min(w);
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                let (mut s, mut s2, mut n) = (0.0f32, 0.0f32, 0.0f32);
                for r in rows.clone() {
                    for &v in &px[r * w + cols.start..r * w + cols.end] {
                        lo = lo.min(v);
                        hi = hi.max(v);
                        s += v;
                        s2 += v * v;
                        n += 1.0;
                    }
                }
                self.min[by * bw + bx] = lo;
                self.max[by * bw + bx] = hi;
                let mean = s / n;
                spread.push((s2 / n - mean * mean).max(0.0).sqrt());
            }
        }
        self.floor = min_contrast.unwrap_or_else(|| {
            // The quietest tenth of the blocks sees only noise in any real image.
            let k = spread.len() / 10;
            let (_, sigma, _) = spread.select_nth_unstable_by(k, f32::total_cmp);
            (NOISE_FACTOR * *sigma).max(MIN_FLOOR)
        });
        self.choose_thresholds();
    }

    /// Contrast floor of the last computation, intensity units.
    pub fn floor(&self) -> f32 {
        self.floor
    }

    /// Thresholds at `level` of the local range: `min + level·(max − min)` (0.5 = mid-range;
    /// higher levels open thin dark gaps between bright shapes, lower ones thin bright gaps).
    pub fn set_level(&mut self, level: f32) {
        self.threshold.clear();
        self.threshold
            .extend(self.low.iter().zip(&self.range).map(|(l, r)| l + level * r));
    }

    /// Threshold of block `(bx, by)` at the current level.
    #[inline]
    pub fn at_block(&self, bx: usize, by: usize) -> f32 {
        self.threshold[by * self.blocks.0 + bx]
    }

    /// Range of the smallest neighbourhood with enough contrast, then 3×3 smoothing.
    fn choose_thresholds(&mut self) {
        let (bw, bh) = self.blocks;
        let n = bw * bh;
        // (min, range) of the chosen neighbourhood; NaN = none yet.
        let mut chosen = vec![(f32::NAN, f32::NAN); n];
        let (lo, hi, tmp) = &mut self.scratch;
        for &r in &RADII {
            window_extreme(&self.min, bw, bh, r, tmp, lo, f32::min);
            window_extreme(&self.max, bw, bh, r, tmp, hi, f32::max);
            let mut open = false;
            for i in 0..n {
                if chosen[i].0.is_nan() {
                    if hi[i] - lo[i] >= self.floor {
                        chosen[i] = (lo[i], hi[i] - lo[i]);
                    } else {
                        open = true;
                    }
                }
            }
            if !open || r >= bw.max(bh) {
                break;
            }
        }
        self.low.clear();
        self.low.resize(n, f32::INFINITY);
        self.range.clear();
        self.range.resize(n, 0.0);
        for by in 0..bh {
            for bx in 0..bw {
                if chosen[by * bw + bx].0.is_nan() {
                    continue;
                }
                let (mut s, mut sr, mut k) = (0.0f32, 0.0f32, 0.0f32);
                for y in by.saturating_sub(1)..(by + 2).min(bh) {
                    for x in bx.saturating_sub(1)..(bx + 2).min(bw) {
                        let (l, r) = chosen[y * bw + x];
                        if !l.is_nan() {
                            s += l;
                            sr += r;
                            k += 1.0;
                        }
                    }
                }
                self.low[by * bw + bx] = s / k;
                self.range[by * bw + bx] = sr / k;
            }
        }
        self.set_level(0.5);
    }
}

/// `out[i]` = `op`-extreme of `values` over the `(2r+1)²` blocks around block `i` (clipped at
/// the borders); separable, `tmp` is scratch.
fn window_extreme(
    values: &[f32],
    bw: usize,
    bh: usize,
    r: usize,
    tmp: &mut Vec<f32>,
    out: &mut Vec<f32>,
    op: fn(f32, f32) -> f32,
) {
    tmp.clear();
    tmp.resize(bw * bh, 0.0);
    out.clear();
    out.resize(bw * bh, 0.0);
    for y in 0..bh {
        let row = &values[y * bw..(y + 1) * bw];
        sliding_extreme(row, r, &mut tmp[y * bw..(y + 1) * bw], op);
    }
    let mut column = vec![0.0f32; bh];
    let mut result = vec![0.0f32; bh];
    for x in 0..bw {
        for y in 0..bh {
            column[y] = tmp[y * bw + x];
        }
        sliding_extreme(&column, r, &mut result, op);
        for y in 0..bh {
            out[y * bw + x] = result[y];
        }
    }
}

/// 1-D running extreme over `[i − r, i + r]`, O(n) (van Herk / Gil–Werman).
fn sliding_extreme(v: &[f32], r: usize, out: &mut [f32], op: fn(f32, f32) -> f32) {
    let n = v.len();
    let k = 2 * r + 1;
    let mut forward = vec![0.0f32; n];
    let mut backward = vec![0.0f32; n];
    for i in 0..n {
        forward[i] = if i % k == 0 {
            v[i]
        } else {
            op(forward[i - 1], v[i])
        };
    }
    for i in (0..n).rev() {
        backward[i] = if i % k == k - 1 || i == n - 1 {
            v[i]
        } else {
            op(backward[i + 1], v[i])
        };
    }
    for (i, o) in out.iter_mut().enumerate() {
        let lo = i.saturating_sub(r);
        let hi = (i + r).min(n - 1);
        *o = op(backward[lo], forward[hi]);
    }
}

/// A horizontal run of pixels of one colour.
#[derive(Clone, Copy, Debug)]
struct Run {
    row: u32,
    start: u32,
    /// One past the last column.
    end: u32,
    bright: bool,
}

/// One 4-connected region of the binarised image.
#[derive(Clone, Copy, Debug)]
pub struct Region {
    /// Above the threshold.
    pub bright: bool,
    /// Pixels of the region itself.
    pub area: f64,
    /// Pixels inside its outer outline (itself and everything it encloses).
    pub filled_area: f64,
    /// Centroid of the filled region `(col, row)`, pixels.
    pub filled_centroid: [f64; 2],
    /// Bounding box `[col_min, row_min, col_max, row_max]`, pixels (inclusive).
    pub bbox: [u32; 4],
    /// The region of the other colour around it; `None` for regions touching the image
    /// border (they enclose nothing measurable and are enclosed by nothing).
    pub parent: Option<usize>,
    /// Number of regions directly inside it.
    pub children: u32,
    /// Touches the image border.
    pub open: bool,
}

/// Regions of a binarised image with their nesting (buffers reused between frames).
#[derive(Default)]
pub struct Regions {
    runs: Vec<Run>,
    /// Index of the first run of each row (plus one past the end).
    row_start: Vec<usize>,
    label: Vec<u32>,
    /// The regions, in raster order of their first pixel (a parent before its children).
    pub regions: Vec<Region>,
}

impl Regions {
    /// Binarises `image` with `thresholds` and labels its regions.
    pub fn label(&mut self, image: &GreyImage, thresholds: &ThresholdMap) {
        self.collect_runs(image, thresholds);
        self.connect();
        self.measure(image.width() as u32, image.height() as u32);
    }

    fn collect_runs(&mut self, image: &GreyImage, thresholds: &ThresholdMap) {
        let (w, h) = (image.width(), image.height());
        let px = image.pixels();
        self.runs.clear();
        self.row_start.clear();
        for r in 0..h {
            self.row_start.push(self.runs.len());
            let row = &px[r * w..(r + 1) * w];
            let by = r / BLOCK;
            let mut start = 0u32;
            let mut bright = row[0] > thresholds.at_block(0, by);
            for (bx, chunk) in row.chunks(BLOCK).enumerate() {
                let t = thresholds.at_block(bx, by);
                for (i, &v) in chunk.iter().enumerate() {
                    let b = v > t;
                    if b != bright {
                        let c = (bx * BLOCK + i) as u32;
                        self.runs.push(Run {
                            row: r as u32,
                            start,
                            end: c,
                            bright,
                        });
                        start = c;
                        bright = b;
                    }
                }
            }
            self.runs.push(Run {
                row: r as u32,
                start,
                end: w as u32,
                bright,
            });
        }
        self.row_start.push(self.runs.len());
    }

    /// Union–find over runs of one colour overlapping in consecutive rows (4-connectivity).
    fn connect(&mut self) {
        let n = self.runs.len();
        self.label.clear();
        self.label.extend(0..n as u32);
        for r in 1..self.row_start.len().saturating_sub(1) {
            let (mut i, i_end) = (self.row_start[r - 1], self.row_start[r]);
            let (mut j, j_end) = (self.row_start[r], self.row_start[r + 1]);
            while i < i_end && j < j_end {
                let (a, b) = (self.runs[i], self.runs[j]);
                if a.bright == b.bright && a.start < b.end && b.start < a.end {
                    union(&mut self.label, i, j);
                }
                if a.end <= b.end {
                    i += 1;
                } else {
                    j += 1;
                }
            }
        }
    }

    /// Region statistics, parents and filled measures.
    fn measure(&mut self, w: u32, h: u32) {
        let n = self.runs.len();
        // Region index per root, in order of first run (= raster order of first pixel).
        let mut index = vec![u32::MAX; n];
        let mut region_of_run = vec![0u32; n];
        let mut sums: Vec<[f64; 3]> = Vec::new();
        self.regions.clear();
        for k in 0..n {
            let root = find(&mut self.label, k);
            if index[root] == u32::MAX {
                index[root] = self.regions.len() as u32;
                self.regions.push(Region {
                    bright: self.runs[k].bright,
                    area: 0.0,
                    filled_area: 0.0,
                    filled_centroid: [0.0; 2],
                    bbox: [u32::MAX, u32::MAX, 0, 0],
                    parent: None,
                    children: 0,
                    open: false,
                });
                sums.push([0.0; 3]);
            }
            let g = index[root] as usize;
            region_of_run[k] = g as u32;
            let run = self.runs[k];
            let len = (run.end - run.start) as f64;
            let reg = &mut self.regions[g];
            reg.area += len;
            let b = &mut reg.bbox;
            b[0] = b[0].min(run.start);
            b[1] = b[1].min(run.row);
            b[2] = b[2].max(run.end - 1);
            b[3] = b[3].max(run.row);
            // Σx over the run: len·(start + end − 1)/2.
            let s = &mut sums[g];
            s[0] += len;
            s[1] += len * (run.start as f64 + run.end as f64 - 1.0) / 2.0;
            s[2] += len * run.row as f64;
        }
        // Parents: the run just above the first pixel of each region.
        let mut first_seen = vec![false; self.regions.len()];
        for k in 0..n {
            let g = region_of_run[k] as usize;
            if first_seen[g] {
                continue;
            }
            first_seen[g] = true;
            let reg = &mut self.regions[g];
            let b = reg.bbox;
            reg.open = b[0] == 0 || b[1] == 0 || b[2] + 1 >= w || b[3] + 1 >= h;
            if reg.open {
                continue;
            }
            let run = self.runs[k];
            let above = self.row_start[run.row as usize - 1]..self.row_start[run.row as usize];
            let hit =
                self.runs[above.clone()].partition_point(|r| r.end <= run.start) + above.start;
            if hit < above.end {
                reg.parent = Some(region_of_run[hit] as usize);
            }
        }
        // Filled measures, children first (a child's first pixel follows its parent's).
        for g in (0..self.regions.len()).rev() {
            let reg = &mut self.regions[g];
            reg.filled_area = sums[g][0];
            reg.filled_centroid = [sums[g][1] / sums[g][0], sums[g][2] / sums[g][0]];
            if let Some(p) = reg.parent {
                let s = sums[g];
                let t = &mut sums[p];
                t[0] += s[0];
                t[1] += s[1];
                t[2] += s[2];
                self.regions[p].children += 1;
            }
        }
    }
}

fn find(label: &mut [u32], mut i: usize) -> usize {
    while label[i] as usize != i {
        let p = label[i] as usize;
        label[i] = label[p];
        i = p;
    }
    i
}

fn union(label: &mut [u32], a: usize, b: usize) {
    let (ra, rb) = (find(label, a), find(label, b));
    // The smaller index stays root: a region's root is its first run.
    if ra < rb {
        label[rb] = ra as u32;
    } else if rb < ra {
        label[ra] = rb as u32;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sliding_extreme_matches_brute_force() {
        let v: Vec<f32> = (0..37).map(|i| ((i * 7919) % 23) as f32).collect();
        for r in [0, 1, 2, 5, 40] {
            let mut out = vec![0.0; v.len()];
            sliding_extreme(&v, r, &mut out, f32::max);
            for i in 0..v.len() {
                let lo = i.saturating_sub(r);
                let hi = (i + r).min(v.len() - 1);
                let m = v[lo..=hi].iter().copied().fold(f32::MIN, f32::max);
                assert_eq!(out[i], m, "r {r} i {i}");
            }
        }
    }

    #[test]
    fn nested_squares_form_a_tree_with_filled_measures() {
        // Bright ring 7×7 (cells of 4 px), dark gap, bright 3×3 centre, on dark.
        let (w, h) = (64, 60);
        let mut px = vec![0.1f32; w * h];
        for r in 0..h {
            for c in 0..w {
                let (u, v) = (c as i32 - 18, r as i32 - 16);
                if !(0..28).contains(&u) || !(0..28).contains(&v) {
                    continue;
                }
                let (iu, iv) = (u / 4, v / 4);
                let ring = iu == 0 || iu == 6 || iv == 0 || iv == 6;
                let centre = (2..=4).contains(&iu) && (2..=4).contains(&iv);
                if ring || centre {
                    px[r * w + c] = 0.9;
                }
            }
        }
        let image = GreyImage::new(w, h, px).unwrap();
        let mut map = ThresholdMap::default();
        map.compute(&image, None);
        let mut regions = Regions::default();
        regions.label(&image, &map);
        let centre = regions
            .regions
            .iter()
            .position(|r| r.bright && r.area == 144.0)
            .expect("centre");
        let gap = regions.regions[centre].parent.expect("gap");
        let ring = regions.regions[gap].parent.expect("ring");
        assert!(!regions.regions[gap].bright);
        assert_eq!(regions.regions[ring].filled_area, 28.0 * 28.0);
        assert_eq!(regions.regions[ring].area, 28.0 * 28.0 - 20.0 * 20.0);
        let [cx, cy] = regions.regions[ring].filled_centroid;
        assert!((cx - 31.5).abs() < 1e-9 && (cy - 29.5).abs() < 1e-9);
    }
}
