//! Scale-free local binarisation and the nesting tree of its regions (docs/design.md#hp-binarize).
//!
//! Used by the coarse steps to find solid, nested shapes (HP code finder squares) whatever
//! their size, polarity, contrast or illumination:
//!
//! 1. **Local threshold** ([`ThresholdMap`]): the image is cut into 8×8 blocks, each keeps its
//!    minimum and maximum. For every block, neighbourhoods of 3, 6, 12, … 192 blocks (24 to
//!    1536 px, the 3×3 cells of a min/max pyramid around it) are tried from the smallest; the first whose range (max − min) exceeds the
//!    *contrast floor* gives the threshold, the mid-range or another level of that range
//!    ([`ThresholdMap::thresholds_at`]: a multi-threshold scan). The floor is a multiple of the
//!    image's noise, estimated from the range of the quietest blocks, so the threshold follows the
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
/// Neighbourhood levels tried for the local range: 3·2^k blocks, k < LEVELS (24 to 1536 px).
const LEVELS: usize = 7;
/// Contrast floor: multiple of the noise standard deviation.
const NOISE_FACTOR: f32 = 6.0;
/// Expected range of the 64 samples of a block of pure Gaussian noise, in standard deviations.
const RANGE_PER_SIGMA: f32 = 4.9;
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
        let px = image.pixels();
        // Block rows are independent: two bands on two threads for large images.
        let band_rows = if w * h >= PARALLEL_MIN_PIXELS {
            bh.div_ceil(2)
        } else {
            bh
        };
        std::thread::scope(|scope| {
            let bands = self
                .min
                .chunks_mut(band_rows * bw)
                .zip(self.max.chunks_mut(band_rows * bw))
                .enumerate();
            for (band, (lo, hi)) in bands {
                let rows = &px[(band * band_rows * BLOCK * w).min(px.len())
                    ..(((band + 1) * band_rows * BLOCK) * w).min(px.len())];
                scope.spawn(move || block_extremes(rows, w, lo, hi));
            }
        });
        self.floor = min_contrast.unwrap_or_else(|| floor_from_blocks(&self.min, &self.max));
        self.choose_thresholds();
    }

    /// One threshold, `threshold` (intensity units), for every block of `image`: a global
    /// threshold, for a scan of levels over a window small enough to be one structure
    /// (the finder search's blurred-finder rescue). [`Regions::label`] then takes level 0.
    pub fn compute_uniform(&mut self, image: &GreyImage, threshold: f32) {
        let w = image.width();
        let (bw, bh) = (w.div_ceil(BLOCK), image.height().div_ceil(BLOCK));
        self.blocks = (bw, bh);
        self.min.clear();
        self.min.resize(bw * bh, f32::INFINITY);
        self.max.clear();
        self.max.resize(bw * bh, f32::NEG_INFINITY);
        block_extremes(image.pixels(), w, &mut self.min, &mut self.max);
        self.floor = 0.0;
        self.low.clear();
        self.low.resize(bw * bh, threshold);
        self.range.clear();
        self.range.resize(bw * bh, 0.0);
    }

    /// The contrast floor [`ThresholdMap::compute`] derives for `image` (6 noise deviations, at
    /// least 0.015), from the 8×8 blocks of every few block rows (a sample is enough for the
    /// quietest tenth; large images are read only in part).
    pub fn noise_floor(image: &GreyImage) -> f32 {
        let w = image.width();
        let bw = w.div_ceil(BLOCK);
        let block_rows = image.height() / BLOCK;
        let stride = (block_rows / FLOOR_SAMPLE_ROWS).max(1);
        let sampled = block_rows.div_ceil(stride);
        let (mut lo, mut hi) = (
            vec![f32::INFINITY; sampled * bw],
            vec![f32::NEG_INFINITY; sampled * bw],
        );
        let px = image.pixels();
        for (i, by) in (0..block_rows).step_by(stride).enumerate() {
            let rows = &px[by * BLOCK * w..(by + 1) * BLOCK * w];
            let range = i * bw..(i + 1) * bw;
            block_extremes(rows, w, &mut lo[range.clone()], &mut hi[range]);
        }
        if lo.is_empty() {
            return MIN_FLOOR;
        }
        floor_from_blocks(&lo, &hi)
    }

    /// Contrast floor of the last computation, intensity units.
    pub fn floor(&self) -> f32 {
        self.floor
    }

    /// Block thresholds at `level` of the local range, `min + level·(max − min)`, into `out`
    /// (row-major blocks; 0.5 = mid-range; higher levels open thin dark gaps between bright
    /// shapes, lower ones thin bright gaps).
    pub fn thresholds_at(&self, level: f32, out: &mut Vec<f32>) {
        out.clear();
        out.extend(self.low.iter().zip(&self.range).map(|(l, r)| l + level * r));
    }

    /// Range of the smallest neighbourhood with enough contrast, then 3×3 smoothing.
    fn choose_thresholds(&mut self) {
        let (bw, bh) = self.blocks;
        let n = bw * bh;
        // (min, range) of the chosen neighbourhood; NaN = none yet.
        let mut chosen = vec![(f32::NAN, f32::NAN); n];
        // Pyramid of min/max over cells of 2^k × 2^k blocks; a block's neighbourhood at level
        // k is the 3×3 cells around its own (3·2^k blocks wide), each level from the last.
        let (mut lo, mut hi) = (self.min.clone(), self.max.clone());
        let (mut cw, mut ch) = (bw, bh);
        for k in 0..LEVELS {
            let near_lo = extreme_3x3(&lo, cw, ch, f32::min);
            let near_hi = extreme_3x3(&hi, cw, ch, f32::max);
            let mut open = false;
            for by in 0..bh {
                for bx in 0..bw {
                    let i = by * bw + bx;
                    if !chosen[i].0.is_nan() {
                        continue;
                    }
                    let c = (by >> k) * cw + (bx >> k);
                    if near_hi[c] - near_lo[c] >= self.floor {
                        chosen[i] = (near_lo[c], near_hi[c] - near_lo[c]);
                    } else {
                        open = true;
                    }
                }
            }
            if !open || (cw <= 3 && ch <= 3) {
                break;
            }
            (lo, hi) = (
                pool_2x2(&lo, cw, ch, f32::min),
                pool_2x2(&hi, cw, ch, f32::max),
            );
            (cw, ch) = (cw.div_ceil(2), ch.div_ceil(2));
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
    }
}

/// Contrast floor from block extremes: the quietest tenth of the blocks sees only noise in any
/// real image, and the range of 64 Gaussian samples is about 4.9 standard deviations.
fn floor_from_blocks(min: &[f32], max: &[f32]) -> f32 {
    let mut ranges: Vec<f32> = min.iter().zip(max).map(|(l, h)| h - l).collect();
    let k = ranges.len() / 10;
    let (_, range, _) = ranges.select_nth_unstable_by(k, f32::total_cmp);
    (NOISE_FACTOR * *range / RANGE_PER_SIGMA).max(MIN_FLOOR)
}

/// Block rows sampled at least by [`ThresholdMap::noise_floor`] before it skips any.
const FLOOR_SAMPLE_ROWS: usize = 32;

/// Minimum and maximum of each 8×8 block of the rows `px` (`w` wide) into `lo`, `hi`.
fn block_extremes(px: &[f32], w: usize, lo: &mut [f32], hi: &mut [f32]) {
    let bw = w.div_ceil(BLOCK);
    for (r, row) in px.chunks_exact(w).enumerate() {
        let by = r / BLOCK;
        let lo = &mut lo[by * bw..(by + 1) * bw];
        let hi = &mut hi[by * bw..(by + 1) * bw];
        for ((chunk, l), h) in row.chunks(BLOCK).zip(lo.iter_mut()).zip(hi.iter_mut()) {
            // Branch-free selects (vectorised; `f32::min` is not, for its NaN rules).
            for &v in chunk {
                *l = if v < *l { v } else { *l };
                *h = if v > *h { v } else { *h };
            }
        }
    }
}

/// Images with at least this many pixels get their block extremes on two threads.
const PARALLEL_MIN_PIXELS: usize = 1 << 20;

/// `op`-extreme over the 3×3 cells around each cell of a `w × h` grid (clipped at borders).
fn extreme_3x3(v: &[f32], w: usize, h: usize, op: fn(f32, f32) -> f32) -> Vec<f32> {
    let mut rows = vec![0.0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let mut e = v[y * w + x];
            if x > 0 {
                e = op(e, v[y * w + x - 1]);
            }
            if x + 1 < w {
                e = op(e, v[y * w + x + 1]);
            }
            rows[y * w + x] = e;
        }
    }
    let mut out = rows.clone();
    for y in 0..h {
        for x in 0..w {
            let mut e = rows[y * w + x];
            if y > 0 {
                e = op(e, rows[(y - 1) * w + x]);
            }
            if y + 1 < h {
                e = op(e, rows[(y + 1) * w + x]);
            }
            out[y * w + x] = e;
        }
    }
    out
}

/// `op`-extreme of each 2×2 cell group of a `w × h` grid: a grid half the size (rounded up).
fn pool_2x2(v: &[f32], w: usize, h: usize, op: fn(f32, f32) -> f32) -> Vec<f32> {
    let (pw, ph) = (w.div_ceil(2), h.div_ceil(2));
    let mut out = vec![0.0f32; pw * ph];
    for y in 0..ph {
        for x in 0..pw {
            let mut e = v[(2 * y) * w + 2 * x];
            for (dx, dy) in [(1, 0), (0, 1), (1, 1)] {
                let (sx, sy) = (2 * x + dx, 2 * y + dy);
                if sx < w && sy < h {
                    e = op(e, v[sy * w + sx]);
                }
            }
            out[y * pw + x] = e;
        }
    }
    out
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
    /// Block thresholds of the current labelling.
    thresholds: Vec<f32>,
    /// The regions, in raster order of their first pixel (a parent before its children).
    pub regions: Vec<Region>,
}

impl Regions {
    /// Binarises `image` at `level` of the local ranges of `map` and labels its regions.
    pub fn label(&mut self, image: &GreyImage, map: &ThresholdMap, level: f32) {
        map.thresholds_at(level, &mut self.thresholds);
        self.collect_runs(image, map);
        self.connect();
        self.measure(image.width() as u32, image.height() as u32);
    }

    fn collect_runs(&mut self, image: &GreyImage, map: &ThresholdMap) {
        let w = image.width();
        self.runs.clear();
        self.row_start.clear();
        for (r, row) in image.pixels().chunks_exact(w).enumerate() {
            self.row_start.push(self.runs.len());
            row_runs(row, r, map, &self.thresholds, &mut self.runs);
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
        for (k, slot) in region_of_run.iter_mut().enumerate() {
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
                    open: false,
                });
                sums.push([0.0; 3]);
            }
            let g = index[root] as usize;
            *slot = g as u32;
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
            }
        }
    }
}

/// Appends the runs of row `r`: 8 pixels at a time, as a bit mask compared with the previous
/// pixel's bit, so that only colour changes cost anything.
fn row_runs(row: &[f32], r: usize, map: &ThresholdMap, thresholds: &[f32], out: &mut Vec<Run>) {
    let by = r / BLOCK;
    let first = by * map.blocks.0;
    let mut start = 0u32;
    let mut bright = row.first().is_some_and(|&v| v > thresholds[first]);
    let mut previous = bright as u32;
    for (bx, chunk) in row.chunks(BLOCK).enumerate() {
        let b = first + bx;
        let t = thresholds[b];
        let full = (1u32 << chunk.len()) - 1;
        // Most blocks lie wholly on one side of their threshold: no pixel to look at.
        let mask = if map.max[b] <= t {
            0
        } else if map.min[b] > t {
            full
        } else {
            chunk
                .iter()
                .enumerate()
                .fold(0u32, |m, (i, &v)| m | (((v > t) as u32) << i))
        };
        // Bit i set where pixel i differs from pixel i − 1.
        let mut changes = (mask ^ ((mask << 1) | previous)) & full;
        previous = (mask >> (chunk.len() - 1)) & 1;
        while changes != 0 {
            let c = (bx * BLOCK) as u32 + changes.trailing_zeros();
            out.push(Run {
                row: r as u32,
                start,
                end: c,
                bright,
            });
            start = c;
            bright = !bright;
            changes &= changes - 1;
        }
    }
    out.push(Run {
        row: r as u32,
        start,
        end: row.len() as u32,
        bright,
    });
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
    fn pooling_and_neighbourhoods_match_brute_force() {
        let (w, h) = (7, 5);
        let v: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 23) as f32).collect();
        let near = extreme_3x3(&v, w, h, f32::max);
        let pooled = pool_2x2(&v, w, h, f32::min);
        for y in 0..h {
            for x in 0..w {
                let mut m = f32::MIN;
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        m = m.max(v[yy * w + xx]);
                    }
                }
                assert_eq!(near[y * w + x], m);
            }
        }
        assert_eq!(pooled.len(), 4 * 3);
        assert_eq!(pooled[0], v[0].min(v[1]).min(v[w]).min(v[w + 1]));
        assert_eq!(pooled[3], v[6].min(v[w + 6]));
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
        regions.label(&image, &map, 0.5);
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
