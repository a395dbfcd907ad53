//! Finder-square detection (METHOD.md §5.2.1, redesigned).
//!
//! The original runs a 2-D Canny detector with hand-tuned thresholds and scans its edge map for
//! 1:1:3:1:1 runs. Here every image row and column is scanned for **signed 1-D edges** (local
//! maxima of the central difference `v[i+1] − v[i−1]` above a threshold chosen from the image's
//! own gradient statistics, sub-pixel by parabola), and a finder cross-section is six
//! consecutive edges of alternating sign spaced 1:1:3:1:1 (ring, gap, centre, gap, ring). The
//! edge signs give the polarity (bright or dark finder) for free.
//!
//! Cross-sections on consecutive rows (columns) that agree in centre and width are chained into
//! one row (column) cluster; a finder is a row cluster and a column cluster that cross at their
//! centres. For a rotated square the chord midpoints of parallel scan lines lie on a straight
//! line through the centre, so each cluster's centre is fitted as a line and the finder centre
//! is where the row line and the column line meet (sub-pixel, unbiased by the rotation).

use crate::grey_image::{GreyImage, Polarity};
use nalgebra::Vector2;

/// Edge threshold floor, intensity units: edges weaker than 1 % of full scale are ignored even
/// on noise-free images (they are rendering or quantisation ripples, not finder boundaries).
const MIN_EDGE_THRESHOLD: f32 = 0.01;
/// Auto threshold: multiple of the robust gradient noise (MAD of the central difference).
const NOISE_FACTOR: f32 = 5.0;
/// Auto threshold: fraction of the 99.9th percentile of the gradient magnitude.
const CONTRAST_FRACTION: f32 = 0.1;
/// Smallest finder module (one ring thickness) measured along a scan line, pixels.
const MIN_MODULE_PX: f32 = 1.2;
/// The six edges of a cross-section must all reach this fraction of the strongest one.
const MIN_EDGE_RATIO: f32 = 0.3;

/// A finder square found in the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Finder {
    /// Centre `(col, row)`, image pixels (sub-pixel).
    pub center: Vector2<f64>,
    /// Length of the finder's chord through its centre along the scan axes, pixels: the side
    /// `7·module` divided by `cos θ`, `θ` being the finder's rotation folded into `[0, π/4]`.
    pub chord: f64,
    /// Material brighter (finder and dots bright) or darker than the background.
    pub polarity: Polarity,
    /// Number of row cross-sections that support it.
    pub row_hits: usize,
    /// Number of column cross-sections that support it.
    pub col_hits: usize,
}

/// A signed edge on a scan line: sub-pixel position and central difference (positive =
/// intensity rising along the scan direction).
#[derive(Clone, Copy, Debug)]
struct Edge {
    pos: f32,
    gradient: f32,
}

/// A 1:1:3:1:1 cross-section on one scan line.
#[derive(Clone, Copy, Debug)]
struct Hit {
    /// Row (for row scans) or column index.
    line: u32,
    /// Mean of the six edge positions along the line, pixels.
    center: f32,
    /// Distance from the first to the last edge, pixels (7 modules along the line).
    width: f32,
    bright: bool,
}

/// Images smaller than this many pixels are scanned on one thread.
const PARALLEL_MIN_PIXELS: usize = 1 << 19;
/// Every `ROW_STEP`-th row is scanned: a finder's centre square (3 modules) still crosses
/// several scan rows for modules ≥ 2 px, and the columns are scanned at full resolution.
const ROW_STEP: usize = 2;
/// Most threads used by the row scan.
const MAX_THREADS: usize = 4;
/// Column search window around a row cluster, in chords: half-width across, half-height along.
const COLUMN_REACH: (f32, f32) = (0.35, 0.9);

/// Reusable buffers of the finder search (one per detector, sized on first use).
#[derive(Default)]
pub(crate) struct FinderScanner {
    bands: Vec<RowScan>,
    histogram: Vec<u64>,
    /// Transposed pixels of a column search window.
    block: Vec<f32>,
    magnitude: Vec<f32>,
    flags: Vec<u8>,
    line_edges: Vec<Edge>,
    row_hits: Vec<Hit>,
    col_hits: Vec<Hit>,
}

impl FinderScanner {
    /// Finds every finder square in `image`. `edge_threshold` is the minimum central
    /// difference of an edge (intensity units); `None` chooses it from the image.
    ///
    /// Every row is scanned; columns are scanned only across the row clusters (a finder needs
    /// both), which keeps the cost to one streaming pass over the image.
    pub(crate) fn find(&mut self, image: &GreyImage, edge_threshold: Option<f64>) -> Vec<Finder> {
        let (w, h) = (image.width(), image.height());
        if w < 8 || h < 8 {
            return Vec::new();
        }
        let threshold = match edge_threshold {
            Some(t) => t as f32,
            None => self.auto_threshold(image),
        };
        self.scan_rows(image, threshold);
        let rows = clusters(&self.row_hits);
        self.scan_columns(image, &rows, threshold);
        let cols = clusters(&self.col_hits);
        match_clusters(&rows, &cols)
    }

    /// Edge threshold from the gradient statistics of 32 rows and 32 columns: above the noise
    /// (5 robust standard deviations of the central difference) and above 10 % of the strong
    /// edges (99.9th percentile), never below 1 % of full scale. The sampled lines are placed
    /// symmetrically, so a rotated or flipped image gets the same threshold.
    fn auto_threshold(&mut self, image: &GreyImage) -> f32 {
        const LINES: usize = 16;
        const BINS: usize = 4096;
        let (w, h) = (image.width(), image.height());
        let px = image.pixels();
        self.histogram.clear();
        self.histogram.resize(BINS, 0);
        let histogram = &mut self.histogram;
        let mut add = |g: f32| {
            histogram[((g.abs() * BINS as f32) as usize).min(BINS - 1)] += 1;
        };
        let picks = |len: usize| {
            (0..LINES).flat_map(move |k| {
                let i = ((2 * k + 1) * len) / (2 * 2 * LINES);
                [i, len - 1 - i]
            })
        };
        for r in picks(h) {
            for t in px[r * w..(r + 1) * w].windows(3) {
                add(t[2] - t[0]);
            }
        }
        for c in picks(w) {
            for r in 1..h - 1 {
                add(px[(r + 1) * w + c] - px[(r - 1) * w + c]);
            }
        }
        let n: u64 = self.histogram.iter().sum();
        let quantile = |q: f64| {
            let target = (q * n as f64).ceil() as u64;
            let mut cumulative = 0;
            for (bin, &count) in self.histogram.iter().enumerate() {
                cumulative += count;
                if cumulative >= target.max(1) {
                    return (bin as f32 + 0.5) / BINS as f32;
                }
            }
            1.0
        };
        let sigma = 1.4826 * quantile(0.5);
        (NOISE_FACTOR * sigma)
            .max(CONTRAST_FRACTION * quantile(0.999))
            .max(MIN_EDGE_THRESHOLD)
    }

    /// Row cross-sections of the whole image, in horizontal bands (one thread per band on
    /// large images); fills `row_hits`, sorted by row.
    fn scan_rows(&mut self, image: &GreyImage, threshold: f32) {
        let (w, h) = (image.width(), image.height());
        let threads = if w * h >= PARALLEL_MIN_PIXELS {
            std::thread::available_parallelism()
                .map_or(1, |n| n.get())
                .clamp(1, MAX_THREADS)
        } else {
            1
        };
        if self.bands.len() != threads {
            self.bands.resize_with(threads, RowScan::default);
        }
        let band_rows = h.div_ceil(threads);
        let px = image.pixels();
        if threads == 1 {
            self.bands[0].scan(px, w, 0..h, threshold);
        } else {
            std::thread::scope(|scope| {
                for (i, band) in self.bands.iter_mut().enumerate() {
                    let rows = (i * band_rows).min(h)..((i + 1) * band_rows).min(h);
                    scope.spawn(move || band.scan(px, w, rows, threshold));
                }
            });
        }
        self.row_hits.clear();
        for band in &self.bands {
            self.row_hits.extend_from_slice(&band.hits);
        }
    }

    /// Column cross-sections through each row cluster (its centre columns, over the finder's
    /// height and some margin); fills `col_hits`, sorted by column, without duplicates.
    fn scan_columns(&mut self, image: &GreyImage, rows: &[Cluster], threshold: f32) {
        let (w, h) = (image.width(), image.height());
        let px = image.pixels();
        self.col_hits.clear();
        for cluster in rows {
            let (cx, cy, chord) = (
                cluster.center as f32,
                cluster.line as f32,
                cluster.width as f32,
            );
            let span = |centre: f32, reach: f32, len: usize| {
                let lo = (centre - reach * chord).floor().max(0.0) as usize;
                let hi = ((centre + reach * chord).ceil().max(0.0) as usize + 1).min(len);
                (lo.min(hi), hi)
            };
            let (c0, c1) = span(cx, COLUMN_REACH.0, w);
            let (r0, r1) = span(cy, COLUMN_REACH.1, h);
            let n = r1 - r0;
            if c0 >= c1 || n < 5 {
                continue;
            }
            // Transpose the window so each column is contiguous.
            self.block.clear();
            self.block.resize((c1 - c0) * n, 0.0);
            for r in r0..r1 {
                for (c, &v) in px[r * w + c0..r * w + c1].iter().enumerate() {
                    self.block[c * n + (r - r0)] = v;
                }
            }
            self.magnitude.resize(n, 0.0);
            self.flags.resize(n, 0);
            for (i, column) in self.block.chunks_exact(n).enumerate() {
                self.line_edges.clear();
                row_edges(
                    column,
                    threshold,
                    &mut self.magnitude,
                    &mut self.flags,
                    &mut self.line_edges,
                );
                for e in &mut self.line_edges {
                    e.pos += r0 as f32;
                }
                cross_sections(&self.line_edges, (c0 + i) as u32, &mut self.col_hits);
            }
        }
        // Overlapping windows see the same cross-sections.
        self.col_hits
            .sort_by(|a, b| a.line.cmp(&b.line).then(a.center.total_cmp(&b.center)));
        self.col_hits
            .dedup_by(|a, b| a.line == b.line && a.center == b.center);
    }
}

/// Buffers and results of the row scan of one horizontal band of rows.
#[derive(Default)]
struct RowScan {
    /// `|v[c+1] − v[c−1]|` of the current row.
    magnitude: Vec<f32>,
    /// Edge flags of the current row (1 = edge).
    flags: Vec<u8>,
    line_edges: Vec<Edge>,
    hits: Vec<Hit>,
}

impl RowScan {
    /// Cross-sections of rows `rows` of the `w`-wide image `px`.
    fn scan(&mut self, px: &[f32], w: usize, rows: std::ops::Range<usize>, thr: f32) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { self.scan_avx2(px, w, rows, thr) };
            return;
        }
        self.scan_generic(px, w, rows, thr);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn scan_avx2(&mut self, px: &[f32], w: usize, rows: std::ops::Range<usize>, thr: f32) {
        self.scan_generic(px, w, rows, thr);
    }

    #[inline(always)]
    fn scan_generic(&mut self, px: &[f32], w: usize, rows: std::ops::Range<usize>, thr: f32) {
        self.hits.clear();
        self.magnitude.resize(w, 0.0);
        self.flags.resize(w, 0);
        for r in rows.filter(|r| r % ROW_STEP == 0) {
            self.line_edges.clear();
            row_edges(
                &px[r * w..(r + 1) * w],
                thr,
                &mut self.magnitude,
                &mut self.flags,
                &mut self.line_edges,
            );
            cross_sections(&self.line_edges, r as u32, &mut self.hits);
        }
    }
}

/// `flags[i] = 1` where `|cur[i]| ≥ thr` is a local maximum between `|prev[i]|` (strictly)
/// and `|next[i]|` (branch-free, vectorised).
#[inline(always)]
fn flag_maxima(prev: &[f32], cur: &[f32], next: &[f32], thr: f32, flags: &mut [u8]) {
    for (((f, p), c), n) in flags.iter_mut().zip(prev).zip(cur).zip(next) {
        let (p, c, n) = (p.abs(), c.abs(), n.abs());
        *f = ((c >= thr) & (c > p) & (c >= n)) as u8;
    }
}

/// Calls `f` with the index of every non-zero flag (flags are 0 or 1), skipping zero runs
/// eight at a time.
#[inline(always)]
fn for_each_flag(flags: &[u8], mut f: impl FnMut(usize)) {
    let words = flags.chunks_exact(8);
    let tail_start = flags.len() - words.remainder().len();
    for (k, chunk) in words.enumerate() {
        let mut word = u64::from_le_bytes([
            chunk[0], chunk[1], chunk[2], chunk[3], chunk[4], chunk[5], chunk[6], chunk[7],
        ]);
        while word != 0 {
            f(8 * k + word.trailing_zeros() as usize / 8);
            word &= word - 1;
        }
    }
    for (i, &flag) in flags[tail_start..].iter().enumerate() {
        if flag != 0 {
            f(tail_start + i);
        }
    }
}

/// Edges of one row: local maxima of `|v[c+1] − v[c−1]|` at or above `threshold`
/// (`magnitude` and `flags` are scratch buffers of the row's length).
#[inline(always)]
fn row_edges(row: &[f32], thr: f32, magnitude: &mut [f32], flags: &mut [u8], out: &mut Vec<Edge>) {
    let n = row.len();
    if n < 5 {
        return;
    }
    magnitude[0] = 0.0;
    magnitude[n - 1] = 0.0;
    for ((m, a), b) in magnitude[1..n - 1].iter_mut().zip(row).zip(&row[2..]) {
        *m = (b - a).abs();
    }
    // Maxima at c = 2 ..= n − 3 (both neighbours have a central difference).
    flags[..2].fill(0);
    flags[n - 2..].fill(0);
    flag_maxima(
        &magnitude[1..n - 3],
        &magnitude[2..n - 2],
        &magnitude[3..n - 1],
        thr,
        &mut flags[2..n - 2],
    );
    for_each_flag(flags, |c| {
        out.push(Edge {
            pos: c as f32 + parabola_offset(magnitude[c - 1], magnitude[c], magnitude[c + 1]),
            gradient: row[c + 1] - row[c - 1],
        })
    });
}

/// Sub-pixel offset of the vertex of the parabola through `(−1, a), (0, m), (1, b)`, in
/// `[−0.5, 0.5]`.
fn parabola_offset(a: f32, m: f32, b: f32) -> f32 {
    let denom = a - 2.0 * m + b;
    if denom < 0.0 {
        (0.5 * (a - b) / denom).clamp(-0.5, 0.5)
    } else {
        0.0
    }
}

/// Scans the edges of one line for six consecutive alternating edges spaced 1:1:3:1:1.
fn cross_sections(edges: &[Edge], line: u32, out: &mut Vec<Hit>) {
    // Number of consecutive sign alternations ending at the current edge.
    let mut alternating = 0usize;
    for i in 1..edges.len() {
        if (edges[i].gradient > 0.0) != (edges[i - 1].gradient > 0.0) {
            alternating += 1;
        } else {
            alternating = 0;
        }
        if alternating < 5 {
            continue;
        }
        let e = &edges[i - 5..=i];
        let s0 = e[0].gradient > 0.0;
        let width = e[5].pos - e[0].pos;
        let m = width / 7.0;
        if m < MIN_MODULE_PX {
            continue;
        }
        let d = [
            e[1].pos - e[0].pos,
            e[2].pos - e[1].pos,
            e[3].pos - e[2].pos,
            e[4].pos - e[3].pos,
            e[5].pos - e[4].pos,
        ];
        // Tolerances: relative (blur, rotation) plus half a pixel (edge localisation).
        let tol = 0.45 * m + 0.5;
        if [0, 1, 3, 4].iter().any(|&k| (d[k] - m).abs() > tol)
            || (d[2] - 3.0 * m).abs() > 0.8 * m + 0.5
            || (d[0] - d[4]).abs() > 0.35 * m + 0.75
            || (d[1] - d[3]).abs() > 0.35 * m + 0.75
        {
            continue;
        }
        let (lo, hi) = e.iter().fold((f32::INFINITY, 0.0f32), |(lo, hi), x| {
            (lo.min(x.gradient.abs()), hi.max(x.gradient.abs()))
        });
        if lo < MIN_EDGE_RATIO * hi {
            continue;
        }
        out.push(Hit {
            line,
            center: e.iter().map(|x| x.pos).sum::<f32>() / 6.0,
            width,
            bright: s0,
        });
    }
}

/// Cross-sections of one finder on neighbouring lines, summarised.
#[derive(Clone, Copy, Debug)]
struct Cluster {
    count: usize,
    /// Mean line index.
    line: f64,
    /// Centre along the line at `line` and its slope per line (chord midpoints of a rotated
    /// square lie on a straight line through its centre).
    center: f64,
    slope: f64,
    width: f64,
    bright: bool,
}

/// Chains hits of lines at most 2 apart whose centres and widths agree, and summarises each
/// chain. `hits` must be sorted by line.
fn clusters(hits: &[Hit]) -> Vec<Cluster> {
    let n = hits.len();
    let mut parent: Vec<usize> = (0..n).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let mut start = 0;
    for j in 0..n {
        while hits[start].line + 2 < hits[j].line {
            start += 1;
        }
        for i in start..j {
            let (a, b) = (&hits[i], &hits[j]);
            if a.line == b.line || a.bright != b.bright {
                continue;
            }
            let tol = 0.15 * a.width.max(b.width) + 1.0;
            if (a.center - b.center).abs() <= tol && (a.width - b.width).abs() <= tol {
                let (ra, rb) = (root(&mut parent, i), root(&mut parent, j));
                if ra != rb {
                    parent[ra] = rb;
                }
            }
        }
    }
    // Accumulate per root: count, Σl, Σc, Σl², Σlc, Σw.
    let mut sums: Vec<[f64; 6]> = vec![[0.0; 6]; n];
    for (i, hit) in hits.iter().enumerate() {
        let r = root(&mut parent, i);
        let (l, c) = (hit.line as f64, hit.center as f64);
        let s = &mut sums[r];
        s[0] += 1.0;
        s[1] += l;
        s[2] += c;
        s[3] += l * l;
        s[4] += l * c;
        s[5] += hit.width as f64;
    }
    (0..n)
        .filter(|&i| parent[i] == i)
        .map(|i| {
            let s = sums[i];
            let k = s[0];
            let (ml, mc) = (s[1] / k, s[2] / k);
            let var = s[3] / k - ml * ml;
            let cov = s[4] / k - ml * mc;
            // A chord-midpoint line steeper than 45° cannot come from a square.
            let slope = if var > 0.5 {
                (cov / var).clamp(-1.0, 1.0)
            } else {
                0.0
            };
            Cluster {
                count: k as usize,
                line: ml,
                center: mc,
                slope,
                width: s[5] / k,
                bright: hits[i].bright,
            }
        })
        .collect()
}

/// Pairs row clusters with column clusters that cross at their centres.
fn match_clusters(rows: &[Cluster], cols: &[Cluster]) -> Vec<Finder> {
    // Candidate pairs with their mismatch; then greedy one-to-one.
    let mut pairs = Vec::new();
    for (i, r) in rows.iter().enumerate() {
        for (j, c) in cols.iter().enumerate() {
            if r.bright != c.bright {
                continue;
            }
            let width = 0.5 * (r.width + c.width);
            if (r.width - c.width).abs() > 0.25 * width + 1.0 {
                continue;
            }
            // Row cluster: x = r.center + r.slope·(y − r.line); column cluster:
            // y = c.center + c.slope·(x − c.line). Solve for the crossing.
            let det = 1.0 - r.slope * c.slope;
            if det.abs() < 1e-6 {
                continue;
            }
            let x = (r.center - r.slope * r.line + r.slope * (c.center - c.slope * c.line)) / det;
            let y = c.center + c.slope * (x - c.line);
            // Rows of the hits lie within the centre square (±1.5 module ≈ ±0.21 width) of the
            // crossing, likewise the columns.
            let (dy, dx) = ((y - r.line).abs(), (x - c.line).abs());
            let reach = 0.3 * width + 1.0;
            if dx > reach || dy > reach {
                continue;
            }
            pairs.push(((dx * dx + dy * dy) / (width * width), i, j, x, y, width));
        }
    }
    pairs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (mut row_used, mut col_used) = (vec![false; rows.len()], vec![false; cols.len()]);
    let mut finders: Vec<Finder> = Vec::new();
    for (_, i, j, x, y, width) in pairs {
        if row_used[i] || col_used[j] {
            continue;
        }
        row_used[i] = true;
        col_used[j] = true;
        if rows[i].count + cols[j].count < 3 {
            continue;
        }
        let center = Vector2::new(x, y);
        // Two clusters of one finder split by a gap in the scan: keep the better supported.
        if let Some(f) = finders
            .iter_mut()
            .find(|f| (f.center - center).norm() < 0.25 * width)
        {
            if f.row_hits + f.col_hits < rows[i].count + cols[j].count {
                f.center = center;
                f.chord = width;
                f.row_hits = rows[i].count;
                f.col_hits = cols[j].count;
            }
            continue;
        }
        finders.push(Finder {
            center,
            chord: width,
            polarity: if rows[i].bright {
                Polarity::BrightDots
            } else {
                Polarity::DarkDots
            },
            row_hits: rows[i].count,
            col_hits: cols[j].count,
        });
    }
    finders
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bright finder of module `m` pixels centred at (cx, cy), axis-aligned, on black.
    fn finder_image(w: usize, h: usize, cx: f64, cy: f64, m: f64) -> GreyImage {
        let mut px = vec![0.0f32; w * h];
        for r in 0..h {
            for c in 0..w {
                let (u, v) = ((c as f64 - cx) / m + 3.5, (r as f64 - cy) / m + 3.5);
                if !(0.0..7.0).contains(&u) || !(0.0..7.0).contains(&v) {
                    continue;
                }
                let (iu, iv) = (u as usize, v as usize);
                let ring = iu == 0 || iu == 6 || iv == 0 || iv == 6;
                let centre = (2..=4).contains(&iu) && (2..=4).contains(&iv);
                if ring || centre {
                    px[r * w + c] = 1.0;
                }
            }
        }
        GreyImage::new(w, h, px).unwrap()
    }

    #[test]
    fn finds_one_axis_aligned_finder_of_each_polarity() {
        let image = finder_image(120, 100, 60.0, 50.0, 6.0);
        let mut scanner = FinderScanner::default();
        let found = scanner.find(&image, None);
        assert_eq!(found.len(), 1, "{found:?}");
        let f = found[0];
        assert_eq!(f.polarity, Polarity::BrightDots);
        assert!((f.center - Vector2::new(59.5, 49.5)).norm() < 0.6, "{f:?}");
        assert!((f.chord - 42.0).abs() < 1.5, "{f:?}");
        let dark = scanner.find(&image.inverted(), None);
        assert_eq!(dark.len(), 1);
        assert_eq!(dark[0].polarity, Polarity::DarkDots);
    }

    #[test]
    fn parabola_vertex() {
        assert_eq!(parabola_offset(1.0, 2.0, 1.0), 0.0);
        assert!((parabola_offset(1.0, 2.0, 2.0) - 0.5).abs() < 1e-6);
        assert_eq!(parabola_offset(0.0, 0.0, 0.0), 0.0);
    }
}
