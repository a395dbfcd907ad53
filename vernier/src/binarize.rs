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
//! 2. **Regions** ([`Regions`]): 4-connected components of both colours from row runs, each
//!    with its area, centroid, bounding box and **parent**: the region of the other colour
//!    that surrounds it (the one just above its first pixel in raster order). Every region also
//!    gets its *filled* area and centroid (itself plus everything it encloses), so a shape is
//!    measured by its outline whatever texture or holes it has inside.
//! 3. **Every level in one pass** ([`label_levels`]): a multi-threshold scan labels all its
//!    levels in one raster pass. The thresholds of a block rise with the level, so a pixel's
//!    *rank*, the number of thresholds it exceeds, tells its colour at every level: it is
//!    bright at the levels below its rank. Ranks are computed 8 pixels at a time (packed
//!    compares), only in blocks whose extremes differ in rank or whose rank differs from the
//!    block before (8-pixel blocks classified once per block row), and where the rank changes
//!    along a row, the levels between the two ranks change colour. Each level's runs are then
//!    connected to those of the row above at once: run-based labelling with a union–find of
//!    provisional labels whose measures are tallied as runs are labelled, so that the second
//!    pass runs over labels, not pixels or runs (Rosenfeld and Pfaltz, *Sequential operations
//!    in digital picture processing*, J. ACM 13(4), 1966; He, Chao and Suzuki, *A run-based
//!    two-scan labeling algorithm*, IEEE Trans. Image Process. 17(5), 2008). Only two rows of
//!    runs per level are kept. A component tree of the rank image (Najman and Couprie,
//!    *Building the component tree in quasi-linear time*, IEEE Trans. Image Process. 15(11),
//!    2006; Nistér and Stewénius, *Linear time maximally stable extremal regions*, ECCV 2008)
//!    would share unions between levels, but its runs of one rank number 54 % to 80 % of the
//!    runs of all five levels together on a real frame's pyramid, its two trees (bright and
//!    dark regions) would each take them all, and each level's regions would still need their
//!    parents of the other colour and their filled areas, which neither tree holds.

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
        if w * h < PARALLEL_MIN_PIXELS {
            block_extremes(px, w, &mut self.min, &mut self.max);
        } else {
            let band_rows = bh.div_ceil(2);
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
        }
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

/// No label (the first row has no run above it).
const NO_LABEL: u32 = u32::MAX;

/// Measures of the runs given one provisional label (until labels are merged into regions).
#[derive(Clone, Copy, Debug)]
struct Tally {
    area: u64,
    /// Sums of the columns and rows of its pixels.
    sum_x: u64,
    sum_y: u64,
    /// `[col_min, row_min, col_max, row_max]`, inclusive.
    bbox: [u32; 4],
    /// Provisional label of the run above its first pixel ([`NO_LABEL`] on the first row).
    above: u32,
    bright: bool,
}

impl Tally {
    /// The tally of a region whose first run is `[start, end)` of row `row`, `bright` or not,
    /// below a run labelled `above`.
    fn new(start: u32, end: u32, row: u32, bright: bool, above: u32) -> Tally {
        Tally {
            area: 0,
            sum_x: 0,
            sum_y: 0,
            bbox: [start, row, end - 1, row],
            above,
            bright,
        }
    }

    /// Adds the run `[start, end)` of row `row` (a row at or below all those added before).
    fn add(&mut self, start: u32, end: u32, row: u32) {
        let len = u64::from(end - start);
        self.area += len;
        // Σx over the run: len·(start + end − 1)/2, an integer.
        self.sum_x += len * (u64::from(start) + u64::from(end) - 1) / 2;
        self.sum_y += len * u64::from(row);
        let b = &mut self.bbox;
        b[0] = b[0].min(start);
        b[2] = b[2].max(end - 1);
        b[3] = row;
    }

    fn merge(&mut self, other: &Tally) {
        self.area += other.area;
        self.sum_x += other.sum_x;
        self.sum_y += other.sum_y;
        let (a, b) = (&mut self.bbox, other.bbox);
        *a = [
            a[0].min(b[0]),
            a[1].min(b[1]),
            a[2].max(b[2]),
            a[3].max(b[3]),
        ];
    }
}

/// One 4-connected region of the binarised image.
#[derive(Clone, Copy, Debug, PartialEq)]
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
    /// The blocks of the current block row where a row may change colour.
    edges: Vec<Edge>,
    /// The runs of the row above the one being labelled: where each ends (one past its last
    /// column; a run starts where the one before it ends, and colours alternate from the
    /// row's first), its provisional label, and the colour of the first.
    above_ends: Vec<u32>,
    above_labels: Vec<u32>,
    above_bright: bool,
    /// The same for the row being labelled.
    ends: Vec<u32>,
    labels: Vec<u32>,
    bright: bool,
    /// Union–find forest of the provisional labels (a root is the smallest label of its
    /// region: that of its first run in raster order).
    parent_label: Vec<u32>,
    tallies: Vec<Tally>,
    /// Region of each provisional label, then filled sums of each region.
    region_of_label: Vec<u32>,
    filled: Vec<[u64; 3]>,
    /// The regions, in raster order of their first pixel (a parent before its children).
    pub regions: Vec<Region>,
}

impl Regions {
    /// Binarises `image` at `level` of the local ranges of `map` and labels its regions.
    pub fn label(&mut self, image: &GreyImage, map: &ThresholdMap, level: f32) {
        label_levels(std::slice::from_mut(self), image, map, &[level]);
    }

    fn start(&mut self) {
        self.above_ends.clear();
        self.above_labels.clear();
        self.ends.clear();
        self.labels.clear();
        self.parent_label.clear();
        self.tallies.clear();
    }

    /// Gives each run of the current row (row `r`) the label of the runs of its colour it
    /// touches in the row above, merging theirs, or a new one, and tallies it; the row then
    /// becomes the row above.
    fn connect_row(&mut self, r: u32) {
        let (above, above_labels) = (&self.above_ends, &self.above_labels);
        let n = above.len();
        let (mut i, mut start) = (0, 0);
        for (j, &end) in self.ends.iter().enumerate() {
            let bright = self.bright ^ (j % 2 == 1);
            // The run above that holds `start`.
            while i < n && above[i] <= start {
                i += 1;
            }
            let mut label = NO_LABEL;
            // Runs alternate in colour: those of the run's colour above it are every other one
            // from the first or the second that it touches.
            let mut k = i + usize::from(self.above_bright ^ (i % 2 == 1) != bright);
            while k < n && (k == 0 || above[k - 1] < end) {
                let other = find(&mut self.parent_label, above_labels[k]);
                label = if label == NO_LABEL {
                    other
                } else {
                    union_roots(&mut self.parent_label, label, other)
                };
                k += 2;
            }
            if label == NO_LABEL {
                // The region's first pixel so far: the run above it is of the other colour.
                label = self.tallies.len() as u32;
                let over = above_labels.get(i).copied().unwrap_or(NO_LABEL);
                self.tallies.push(Tally::new(start, end, r, bright, over));
                self.parent_label.push(label);
            }
            self.labels.push(label);
            self.tallies[label as usize].add(start, end, r);
            start = end;
        }
        std::mem::swap(&mut self.above_ends, &mut self.ends);
        std::mem::swap(&mut self.above_labels, &mut self.labels);
        self.above_bright = self.bright;
        self.ends.clear();
        self.labels.clear();
    }

    /// Regions from the labels: their measures, parents and filled measures.
    fn finish(&mut self, w: u32, h: u32) {
        let n = self.tallies.len();
        // Each label's tally into its root's (a root precedes its other labels).
        for l in 0..n {
            let root = find(&mut self.parent_label, l as u32) as usize;
            if root != l {
                let t = self.tallies[l];
                self.tallies[root].merge(&t);
            }
        }
        self.regions.clear();
        self.filled.clear();
        self.region_of_label.clear();
        self.region_of_label.resize(n, 0);
        for l in 0..n {
            let root = self.parent_label[l] as usize;
            if root != l {
                self.region_of_label[l] = self.region_of_label[root];
                continue;
            }
            self.region_of_label[l] = self.regions.len() as u32;
            let t = &self.tallies[l];
            let b = t.bbox;
            let open = b[0] == 0 || b[1] == 0 || b[2] + 1 >= w || b[3] + 1 >= h;
            let parent = match (open, t.above) {
                (false, above) if above != NO_LABEL => {
                    Some(self.region_of_label[above as usize] as usize)
                }
                _ => None,
            };
            self.regions.push(Region {
                bright: t.bright,
                area: t.area as f64,
                filled_area: 0.0,
                filled_centroid: [0.0; 2],
                bbox: b,
                parent,
                open,
            });
            self.filled.push([t.area, t.sum_x, t.sum_y]);
        }
        // Filled measures, children first (a child's first pixel follows its parent's).
        for g in (0..self.regions.len()).rev() {
            let s = self.filled[g];
            let reg = &mut self.regions[g];
            let area = s[0] as f64;
            reg.filled_area = area;
            reg.filled_centroid = [s[1] as f64 / area, s[2] as f64 / area];
            if let Some(p) = reg.parent {
                let t = &mut self.filled[p];
                t[0] += s[0];
                t[1] += s[1];
                t[2] += s[2];
            }
        }
    }
}

/// Binarises `image` at each of `levels` of the local ranges of `map` and labels the regions
/// of each into `sets` (one per level), in one raster pass: each row is read once, binarised
/// at every level at once, and labelled while it and the row above are at hand (run-based
/// connected components, one union–find of provisional labels per level, measures tallied as
/// runs are labelled: Rosenfeld and Pfaltz's two passes, the second over labels, not pixels).
pub fn label_levels(sets: &mut [Regions], image: &GreyImage, map: &ThresholdMap, levels: &[f32]) {
    let (w, h) = (image.width(), image.height());
    for (sets, levels) in sets.chunks_mut(MAX_LEVELS).zip(levels.chunks(MAX_LEVELS)) {
        let Some(first) = sets.first_mut() else {
            continue;
        };
        let mut edges = std::mem::take(&mut first.edges);
        let ladder = Ladder::new(levels);
        for set in sets.iter_mut() {
            set.start();
        }
        for (r, row) in image.pixels().chunks_exact(w).enumerate() {
            if r % BLOCK == 0 {
                block_edges(map, r / BLOCK, &ladder, &mut edges);
            }
            row_runs(row, &edges, &ladder, sets);
            for set in sets.iter_mut() {
                set.connect_row(r as u32);
            }
        }
        for set in sets.iter_mut() {
            set.finish(w as u32, h as u32);
        }
        sets[0].edges = edges;
    }
}

/// Most levels binarised in one pass ([`label_levels`] makes one pass per this many).
const MAX_LEVELS: usize = 8;

/// The levels of one pass in increasing order. The block thresholds `low + level · range` rise
/// with the level (the range is never negative), so a pixel is bright at the levels below its
/// *rank*, the number of thresholds it exceeds, and dark at the others: one number per pixel
/// tells its colour at every level, and where it changes along a row the levels between the
/// two ranks change colour.
struct Ladder {
    /// Levels, increasing.
    levels: [f32; MAX_LEVELS],
    /// Set (index in the caller's order) of each of them.
    set: [usize; MAX_LEVELS],
    len: usize,
}

impl Ladder {
    fn new(levels: &[f32]) -> Ladder {
        let len = levels.len().min(MAX_LEVELS);
        let mut set: [usize; MAX_LEVELS] = std::array::from_fn(|k| k);
        set[..len].sort_by(|&a, &b| levels[a].total_cmp(&levels[b]));
        Ladder {
            levels: std::array::from_fn(|k| if k < len { levels[set[k]] } else { 0.0 }),
            set,
            len,
        }
    }
}

/// A block of a block row where a row's rank ([`Ladder`]) may change: a block whose pixels do
/// not all share one rank, or whose one rank differs from the block's before it.
#[derive(Clone, Copy, Debug)]
struct Edge {
    /// Block column.
    column: u32,
    /// The rank of all its pixels, or [`MIXED`].
    rank: u8,
    /// Its thresholds at the ladder's levels, increasing.
    thresholds: [f32; MAX_LEVELS],
}

/// [`Edge::rank`] of a block whose pixels differ in rank.
const MIXED: u8 = u8::MAX;

/// The [`Edge`]s of block row `by` into `out`: the first block, every mixed block and every
/// block after a block of another rank or a mixed one. Between two of them, the rank stays
/// that of the last pixel read.
fn block_edges(map: &ThresholdMap, by: usize, ladder: &Ladder, out: &mut Vec<Edge>) {
    let bw = map.blocks.0;
    let range = by * bw..(by + 1) * bw;
    let blocks = map.low[range.clone()]
        .iter()
        .zip(&map.range[range.clone()])
        .zip(map.min[range.clone()].iter().zip(&map.max[range]));
    out.clear();
    let mut last = MIXED;
    for (column, ((low, range), (min, max))) in blocks.enumerate() {
        let thresholds: [f32; MAX_LEVELS] = std::array::from_fn(|k| low + ladder.levels[k] * range);
        let thresholds = &thresholds[..ladder.len];
        // A pixel's rank rises with its value: the block's extremes bound its pixels' ranks.
        let (lowest, highest) = (rank(*min, thresholds), rank(*max, thresholds));
        let rank = if lowest == highest { lowest } else { MIXED };
        if rank == MIXED || rank != last {
            let mut edge = Edge {
                column: column as u32,
                rank,
                thresholds: [f32::INFINITY; MAX_LEVELS],
            };
            edge.thresholds[..ladder.len].copy_from_slice(thresholds);
            out.push(edge);
        }
        last = rank;
    }
}

/// The number of `thresholds` that `v` exceeds.
fn rank(v: f32, thresholds: &[f32]) -> u8 {
    thresholds.iter().map(|&t| u8::from(v > t)).sum()
}

/// The runs of one row at each level of `ladder`, as the first run's colour and every run's
/// end in its set, given the [`Edge`]s of its block row: at each, the ranks of its 8 pixels
/// side by side in a word, compared with the word shifted by one pixel, so that only changes
/// cost anything.
fn row_runs(row: &[f32], edges: &[Edge], ladder: &Ladder, sets: &mut [Regions]) {
    let n = ladder.len;
    let mut previous = match (edges.first(), row.first()) {
        (Some(e), Some(&v)) if e.rank == MIXED => rank(v, &e.thresholds[..n]),
        (Some(e), _) => e.rank,
        _ => 0,
    };
    // The row's first colour at each level: bright below the first pixel's rank.
    for (k, &set) in ladder.set.iter().enumerate().take(n) {
        sets[set].bright = k < usize::from(previous);
    }
    for e in edges {
        let col0 = e.column as usize * BLOCK;
        let Some(chunk) = row.get(col0..(col0 + BLOCK).min(row.len())) else {
            break;
        };
        let ranks = if e.rank == MIXED {
            block_ranks(chunk, &e.thresholds[..n])
        } else {
            u64::from(e.rank) * 0x0101_0101_0101_0101
        };
        // Byte i of `ranks` against pixel i − 1's: non-zero bytes of `changes` mark changes.
        let before = (ranks << 8) | u64::from(previous);
        let bytes = if chunk.len() == BLOCK {
            u64::MAX
        } else {
            (1u64 << (8 * chunk.len())) - 1
        };
        let mut changes = (ranks ^ before) & bytes;
        previous = (ranks >> (8 * (chunk.len() - 1))) as u8;
        while changes != 0 {
            let shift = changes.trailing_zeros() & !7;
            let (old, new) = ((before >> shift) as u8, (ranks >> shift) as u8);
            let c = (col0 + shift as usize / 8) as u32;
            for k in usize::from(old.min(new))..usize::from(old.max(new)).min(n) {
                sets[ladder.set[k]].ends.push(c);
            }
            changes &= !(0xff << shift);
        }
    }
    for k in 0..n {
        sets[ladder.set[k]].ends.push(row.len() as u32);
    }
}

/// The ranks of the pixels of `chunk` (up to 8) against `thresholds` (increasing), byte `i`
/// that of pixel `i` (the bytes past the chunk are those of its last pixel or zero).
fn block_ranks(chunk: &[f32], thresholds: &[f32]) -> u64 {
    #[cfg(target_arch = "x86_64")]
    if let Ok(block) = <&[f32; BLOCK]>::try_from(chunk) {
        use std::arch::x86_64::{
            _mm_castps_si128, _mm_cmpgt_ps, _mm_cvtsi128_si64, _mm_loadu_ps, _mm_packs_epi32,
            _mm_packus_epi16, _mm_set1_ps, _mm_setzero_si128, _mm_sub_epi32,
        };
        // SAFETY: SSE2 is part of x86_64; the two unaligned loads read lanes 0–3 and 4–7 of
        // the eight-lane array.
        return unsafe {
            let (low, high) = (
                _mm_loadu_ps(block.as_ptr()),
                _mm_loadu_ps(block.as_ptr().add(4)),
            );
            let (mut rank_low, mut rank_high) = (_mm_setzero_si128(), _mm_setzero_si128());
            for &t in thresholds {
                // A true compare is all ones (−1): subtracting it counts it.
                let t = _mm_set1_ps(t);
                rank_low = _mm_sub_epi32(rank_low, _mm_castps_si128(_mm_cmpgt_ps(low, t)));
                rank_high = _mm_sub_epi32(rank_high, _mm_castps_si128(_mm_cmpgt_ps(high, t)));
            }
            let words = _mm_packs_epi32(rank_low, rank_high);
            _mm_cvtsi128_si64(_mm_packus_epi16(words, words)) as u64
        };
    }
    chunk.iter().enumerate().fold(0u64, |word, (i, &v)| {
        word | (u64::from(rank(v, thresholds)) << (8 * i))
    })
}

/// Root of label `i`, compressing the path (halving).
fn find(parent: &mut [u32], mut i: u32) -> u32 {
    while parent[i as usize] != i {
        let p = parent[i as usize];
        parent[i as usize] = parent[p as usize];
        i = p;
    }
    i
}

/// Merges the sets of roots `a` and `b`; the smaller label stays root (it is the first run).
fn union_roots(parent: &mut [u32], a: u32, b: u32) -> u32 {
    if a < b {
        parent[b as usize] = a;
        a
    } else {
        parent[a as usize] = b;
        b
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

    /// The regions of `image` binarised at `level` of `map`, by flood fill: the definition
    /// [`label_levels`] must follow (4-connected regions in raster order of their first pixel,
    /// the parent of a closed one the region of the pixel above its first pixel).
    fn flood_fill_regions(image: &GreyImage, map: &ThresholdMap, level: f32) -> Vec<Region> {
        let (w, h) = (image.width(), image.height());
        let bw = map.blocks.0;
        let bright: Vec<bool> = (0..w * h)
            .map(|i| {
                let b = (i / w / BLOCK) * bw + (i % w) / BLOCK;
                image.pixels()[i] > map.low[b] + level * map.range[b]
            })
            .collect();
        let mut region_of = vec![usize::MAX; w * h];
        let mut regions: Vec<Region> = Vec::new();
        let mut sums: Vec<[f64; 3]> = Vec::new();
        let mut first_pixel = Vec::new();
        for seed in 0..w * h {
            if region_of[seed] != usize::MAX {
                continue;
            }
            let g = regions.len();
            let mut reg = Region {
                bright: bright[seed],
                area: 0.0,
                filled_area: 0.0,
                filled_centroid: [0.0; 2],
                bbox: [u32::MAX, u32::MAX, 0, 0],
                parent: None,
                open: false,
            };
            let mut sum = [0.0f64; 3];
            let mut stack = vec![seed];
            region_of[seed] = g;
            while let Some(i) = stack.pop() {
                let (x, y) = (i % w, i / w);
                reg.area += 1.0;
                sum = [sum[0] + 1.0, sum[1] + x as f64, sum[2] + y as f64];
                let b = &mut reg.bbox;
                *b = [
                    b[0].min(x as u32),
                    b[1].min(y as u32),
                    b[2].max(x as u32),
                    b[3].max(y as u32),
                ];
                let mut visit = |j: usize| {
                    if region_of[j] == usize::MAX && bright[j] == bright[seed] {
                        region_of[j] = g;
                        stack.push(j);
                    }
                };
                if x > 0 {
                    visit(i - 1);
                }
                if x + 1 < w {
                    visit(i + 1);
                }
                if y > 0 {
                    visit(i - w);
                }
                if y + 1 < h {
                    visit(i + w);
                }
            }
            let b = reg.bbox;
            reg.open = b[0] == 0 || b[1] == 0 || b[2] as usize + 1 >= w || b[3] as usize + 1 >= h;
            regions.push(reg);
            sums.push(sum);
            first_pixel.push(seed);
        }
        for g in 0..regions.len() {
            if !regions[g].open {
                regions[g].parent = Some(region_of[first_pixel[g] - w]);
            }
        }
        fill_holes(&mut regions, sums);
        regions
    }

    /// Filled area and centroid of each region: its own pixel sums `[n, Σx, Σy]` plus those
    /// of the regions it encloses (children come after their parents).
    fn fill_holes(regions: &mut [Region], mut sums: Vec<[f64; 3]>) {
        for g in (0..regions.len()).rev() {
            let s = sums[g];
            regions[g].filled_area = s[0];
            regions[g].filled_centroid = [s[1] / s[0], s[2] / s[0]];
            if let Some(p) = regions[g].parent {
                for k in 0..3 {
                    sums[p][k] += s[k];
                }
            }
        }
    }

    #[test]
    fn one_pass_over_all_levels_labels_each_as_a_flood_fill_does() {
        // Blurred squares and rings of both colours on a ramp, with noise: regions nested a
        // few deep, specks, and blocks of every kind (uniform, mixed) at every level.
        let (w, h) = (157, 131);
        let mut state = 12345u32;
        let mut noise = || {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let mut px = vec![0.0f32; w * h];
        for (i, v) in px.iter_mut().enumerate() {
            let (x, y) = ((i % w) as f32, (i / w) as f32);
            let ring =
                |cx: f32, cy: f32, r: f32| ((x - cx).abs().max((y - cy).abs()) - r).abs() < 4.0;
            let inside = |cx: f32, cy: f32, r: f32| (x - cx).abs().max((y - cy).abs()) < r;
            *v = 0.2 + 0.002 * x;
            if ring(50.0, 60.0, 25.0) || inside(50.0, 60.0, 8.0) || inside(120.0, 30.0, 3.0) {
                *v = 0.9;
            }
            if ring(115.0, 95.0, 18.0) || inside(115.0, 95.0, 5.0) {
                *v = 0.05;
            }
            *v += 0.08 * noise();
        }
        let image = GreyImage::new(w, h, px).unwrap();
        let mut map = ThresholdMap::default();
        map.compute(&image, None);
        let levels = [0.5, 0.7, 0.3, 0.85, 0.15];
        let mut sets: Vec<Regions> = (0..levels.len()).map(|_| Regions::default()).collect();
        // Twice: buffers reused.
        for _ in 0..2 {
            label_levels(&mut sets, &image, &map, &levels);
            for (set, &level) in sets.iter().zip(&levels) {
                let expected = flood_fill_regions(&image, &map, level);
                assert!(expected.len() > 20, "level {level}: {}", expected.len());
                assert!(expected.iter().filter(|r| r.parent.is_some()).count() > 5);
                assert_eq!(set.regions, expected, "level {level}");
            }
        }
        let mut single = Regions::default();
        single.label(&image, &map, 0.3);
        assert_eq!(single.regions, sets[2].regions);
    }
}
