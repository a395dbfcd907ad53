//! Finder-square detection (docs/design.md#hp-finders, redesigned: regions, not edges).
//!
//! The original scans a Canny edge map, with thresholds tuned per image, for 1:1:3:1:1 runs.
//! Here a finder is recognised by its **topology**: a solid centre inside a gap inside a ring,
//! three nested regions of alternating colour of the scale-free local binarisation
//! ([`crate::binarize`]). Because the test is on nested outlines, it does not depend on:
//! - scale (module from ~1.5 px to hundreds of pixels) or rotation;
//! - polarity (bright and dark finders come out of one pass, each with its own);
//! - contrast and illumination (the threshold is the local mid-range at the finder's scale);
//! - texture inside the ring or the centre (JPEG blocks, hollow imaged dots: filled areas
//!   are used), nor mild perspective (ratios of areas, not of lengths along scan lines).
//!
//! A candidate centre region `C` is accepted with the hole `G` around it (its parent) when
//! their filled areas follow the 3 : 5 module squares of centre and gap (`√(G/C)` near 5/3),
//! they are concentric, the gap holds nothing but the centre, and both are compact. The ring
//! itself is not needed: it is whatever encloses the gap, so a ring touching other structures
//! (the edge of the part) or imaged as two outlines still counts. Text, grids, stripes and the
//! dot grid have no such nesting; what else might is rejected by the marker geometry and grid.
//!
//! The five threshold levels ([`LEVELS`]) of a pyramid level or window are labelled in one
//! raster pass ([`binarize::label_levels`]): a pixel's rank among a block's five thresholds
//! gives its colour at every level, so each row is read once, 8 pixels at a time and only in
//! blocks where some level may change colour, and each level's runs are connected to the row
//! above and measured as the row is read; the regions are those of five separate labellings,
//! each level's with its own parents and filled areas, for the nested-region test. (A
//! component tree of the rank image would share work between levels, but its runs of one rank
//! number over half of all levels' runs together, and it holds neither the parents of the
//! other colour nor the filled areas; see [`crate::binarize`].)
//!
//! A blurred finder whose gap no level of the local range opens is read in a window at a
//! threshold between its own gap's and ring's levels ([`rescue`]). A small finder (modules
//! under ~4 px) that noise breaks up at full resolution is read on the finest level smoothed
//! as well (`GreyImage::binomial_3x3`).

use crate::binarize::{self, Region, Regions, ThresholdMap, BLOCK};
use crate::grey_image::{GreyImage, Polarity, BINOMIAL_3X3_NOISE_GAIN};
use nalgebra::Vector2;
use std::borrow::Cow;

mod rescue;

/// Images (and windows) with at least this many pixels are labelled at their threshold levels
/// in parallel.
const PARALLEL_MIN_PIXELS: usize = 1 << 18;
/// Closest accepted distance between two finders of the same size, modules (see
/// [`crowded`]; two markers touching edge to edge have finders 7 modules apart).
const MIN_SPACING: f64 = 10.0;
/// Threshold levels scanned, fractions of the local range: the mid-range, two levels that
/// keep a blurred one-module gap open in bright (0.7) and dark (0.3) finders, and two for
/// finders beside a third material: where a neighbourhood also holds something much brighter
/// (darker) than the marker's own background (the bright edge of the part, a glint, a pad),
/// the range stretches, and a dark finder's gap, at the marker's background level, may sit
/// at a fifth of it (`HPCodeImage_20um.png` next to its chip's edge under a tone curve
/// `v^1.7`) and a bright finder's at four fifths.
const LEVELS: [f32; 5] = [0.5, 0.7, 0.3, 0.85, 0.15];
/// The middle levels, first in [`LEVELS`]: their regions alone seed the blurred-finder rescue
/// and the finer pyramid level's windows. The outer two lie close to one material's own
/// level, where noise forms compact specks, which would crowd a true rescue candidate
/// ([`rescue::candidates`]) and open windows all over a noisy background (they doubled the
/// pixels labelled in a 5 MP frame). A small finder needs no window of its own: the dots of
/// its marker open windows around it at the middle levels.
const MIDDLE_LEVELS: usize = 3;
/// Accepted `√(filled gap / filled centre)` (nominal 5/3: blur and threshold move it).
const GAP_RATIO: (f64, f64) = (1.35, 2.3);
/// Accepted `√(filled ring / filled gap)` when the centre merged with the gap (nominal 7/5;
/// the threshold biases of [`GAP_RATIO`]'s range move it over about this one).
const RING_RATIO: (f64, f64) = (1.15, 1.65);
/// Largest distance between the centroids of centre and gap, in gap sides.
const MAX_ECCENTRICITY: f64 = 0.12;
/// Largest area of other regions inside the gap, as a fraction of the centre.
const MAX_GAP_CLUTTER: f64 = 0.15;
/// Smallest filled centre, pixels (a 3-module centre with 1.3 px modules).
const MIN_CENTER_AREA: f64 = 12.0;
/// Accepted `filled area / bounding box area` of ring and centre (a square at 45° gives ½).
const MIN_BOX_FILL: f64 = 0.4;
/// Largest bounding-box aspect ratio of ring and centre.
const MAX_ASPECT: f64 = 1.8;

/// Largest module, pixels, of a finder taken from the smoothed reading of the finest level:
/// two pixels of the first binned level. A gap that wide always holds one whole binned pixel,
/// whatever its phase, and that level reads it; a narrower one may straddle two, each mixed
/// with the ring (clean, a binned level still opens gaps from ~1.5 of its pixels; under noise
/// it does not).
const SMOOTHED_MAX_MODULE: f64 = 4.0;

/// Most 2×2 binnings of the finder pyramid (coarsest level: a quarter of the resolution).
const MAX_BINNINGS: usize = 2;
/// A binned level is built only if it keeps at least this many pixels (256²): smaller images
/// are labelled at full resolution only, which is cheap.
const MIN_LEVEL_PIXELS: usize = 1 << 16;
/// Compact closed regions of a binned level up to this filled area, pixels, may be finders too
/// small for it: the next finer level is labelled around them. A binned level keeps the gap
/// of finders with modules from ~1.5 px open; smaller ones merge into one blob of at most
/// `(7·1.5)²` px, and the centre of a finder it resolves is `(3m)²`, so a finder of any
/// size leaves such a region at some level (the finer one finds it; dedup keeps one).
const REFINE_MAX_AREA: f64 = 121.0;
/// Smallest such region, pixels (see [`might_be_small_centre`]).
const REFINE_MIN_AREA: f64 = 4.0;
/// Margin labelled at the finer level around such a region, its blocks: the ring of the
/// finder around its centre (2 modules of up to 4 px at the finer level) and some more.
const REFINE_MARGIN_BLOCKS: usize = 2;
/// Windows covering at least this many pixels are labelled on two threads.
const PARALLEL_WINDOW_PIXELS: usize = 1 << 16;
/// A finer level is labelled whole when its windows would cover more than this fraction of it.
const WHOLE_LEVEL_FRACTION: f64 = 0.5;

/// A finder square found in the image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Finder {
    /// Centre `(col, row)`, image pixels (sub-pixel).
    pub center: Vector2<f64>,
    /// Module (one ring thickness, half a period), pixels: a quarter of the difference of the
    /// sides of ring and centre (threshold bias cancels).
    pub module_px: f64,
    /// Material brighter (finder and dots bright) or darker than the background.
    pub polarity: Polarity,
    /// How well the nesting fits the nominal shape, `[0, 1]` (1 = exact 3 : 5 : 7).
    pub score: f64,
    /// Read from its gap and ring: the centre did not stand out of the gap at any threshold
    /// level (a dim or saturated centre). Where both readings find a finder, the one through
    /// its centre is kept.
    pub centre_hidden: bool,
}

impl Finder {
    /// The same finder in the frame of the image that `level` binnings 2×2 turned into the
    /// image it was found in: binned pixel `c` covers pixels `2c, 2c + 1`, whose centre is
    /// `2c + ½`.
    fn in_full_image(self, level: usize) -> Finder {
        let scale = (1usize << level) as f64;
        Finder {
            center: self.center * scale + Vector2::repeat((scale - 1.0) / 2.0),
            module_px: self.module_px * scale,
            ..self
        }
    }
}

/// Reusable buffers of the finder search (one per detector).
///
/// The search runs coarse to fine on a pyramid of 2×2-binned copies, so that a large image
/// is read in full only once (to bin it): the coarsest level is labelled whole; each finer
/// level only around the closed regions of the level above it that are small enough to be
/// the centre of a finder that level cannot resolve ([`REFINE_MAX_AREA`]). A finder's centre
/// always stays such a region, dots or not, so no scale is skipped; clutter only costs time.
#[derive(Default)]
pub(crate) struct FinderScanner {
    /// `binned[k]`: the image binned `k + 1` times.
    binned: Vec<GreyImage>,
    /// One set of labelling buffers per thread.
    labelling: [Labelling; 2],
}

impl FinderScanner {
    /// Finds every finder square in `image`. `min_contrast` overrides the contrast floor of
    /// the local threshold (intensity units); `None` derives it from the image noise.
    pub(crate) fn find(&mut self, image: &GreyImage, min_contrast: Option<f64>) -> Vec<Finder> {
        if image.width() < 8 || image.height() < 8 {
            return Vec::new();
        }
        let levels = self.build_pyramid(image);
        let min_contrast = min_contrast.map(|c| c as f32);
        let (binned, labelling) = (&self.binned, &mut self.labelling);
        let level_image = |level: usize| match level {
            0 => image,
            _ => &binned[level - 1],
        };
        let mut found = Vec::new();
        std::thread::scope(|s| {
            // The finer levels' floors (a window's is that of its whole level: a window is
            // mostly texture), read while the coarsest level is scanned.
            let mut floors = (min_contrast.is_none() && levels > 0).then(|| {
                s.spawn(move || {
                    (0..levels)
                        .map(|level| ThresholdMap::noise_floor(level_image(level)))
                        .collect::<Vec<f32>>()
                })
            });
            let mut finer_floors = Vec::new();
            // Bounding boxes of small regions of the level above, its pixels.
            let mut small = Vec::new();
            for level in (0..=levels).rev() {
                let level_image = level_image(level);
                let windows = if level == levels {
                    vec![Window::whole(level_image)]
                } else {
                    refine_windows(level_image, &small)
                };
                if windows.is_empty() {
                    break;
                }
                let floor = match min_contrast {
                    Some(c) => Some(c),
                    // A whole level: its own blocks give its floor.
                    None if windows.len() == 1 && windows[0].is_whole(level_image) => None,
                    None => {
                        if let Some(handle) = floors.take() {
                            finer_floors = handle.join().unwrap_or_default();
                        }
                        let floor = finer_floors.get(level).copied();
                        Some(floor.unwrap_or_else(|| ThresholdMap::noise_floor(level_image)))
                    }
                };
                let (finders, finer_small) =
                    scan_windows(labelling, level_image, &windows, floor, level > 0);
                found.extend(finders.into_iter().map(|f| f.in_full_image(level)));
                small = finer_small;
            }
        });
        let unique = dedup(found);
        unique
            .iter()
            .filter(|f| !crowded(f, &unique))
            .copied()
            .collect()
    }

    /// Bins `image` into `self.binned` as far as [`MAX_BINNINGS`] and [`MIN_LEVEL_PIXELS`]
    /// allow; returns the number of binned levels.
    fn build_pyramid(&mut self, image: &GreyImage) -> usize {
        let mut levels = 0;
        let (mut w, mut h) = (image.width(), image.height());
        while levels < MAX_BINNINGS && (w / 2) * (h / 2) >= MIN_LEVEL_PIXELS {
            if self.binned.len() <= levels {
                self.binned.push(GreyImage::empty());
            }
            let (done, rest) = self.binned.split_at_mut(levels);
            let source = done.last().unwrap_or(image);
            if source.binned_2x2_into(&mut rest[0]).is_none() {
                break;
            }
            levels += 1;
            (w, h) = (w / 2, h / 2);
        }
        levels
    }
}

/// Finders of the `windows` of `image` (in its frame) and, with `want_small`, the boxes of
/// their small regions ([`might_be_small_centre`]), on two threads when there is enough work.
fn scan_windows(
    labelling: &mut [Labelling; 2],
    image: &GreyImage,
    windows: &[Window],
    floor: Option<f32>,
    want_small: bool,
) -> (Vec<Finder>, Vec<[u32; 4]>) {
    let scan_group = |labelling: &mut Labelling, group: &[Window]| {
        let (mut finders, mut small) = (Vec::new(), Vec::new());
        for w in group {
            let view = w.view(image);
            let (ox, oy) = (w.col0 as f64, w.row0 as f64);
            let mut found =
                labelling.scan(&view, floor, w.origin(), want_small.then_some(&mut small));
            if !want_small {
                // The finest level: a finder of modules under ~4 px has no coarser level that
                // reliably keeps its gap open, and white noise of a few percent breaks its
                // one-module gap and ring into specks. Read through a 3 × 3 binomial as well,
                // which keeps a 1.5-px gap open and lowers the noise 2.7×: the same scan, its
                // floor scaled with the noise. Its blurred-finder rescue reads the gaps the
                // smoothing closes (view 667 of the severity-1.5 real-view probe, seed 1).
                // Only the small finders it finds are taken: larger ones are read at a binned
                // level (itself an average) or in the raw reading, and the smoothed reading's
                // would be clutter's look-alikes crowding the two-finder hypotheses
                // (docs/design.md#hp-noisy-finders).
                let smoothed = view.binomial_3x3();
                let floor = floor.map(|f| f * BINOMIAL_3X3_NOISE_GAIN);
                let small_only = |f: &Finder| f.module_px < SMOOTHED_MAX_MODULE;
                found.extend(
                    labelling
                        .scan(&smoothed, floor, w.origin(), None)
                        .into_iter()
                        .filter(small_only),
                );
            }
            finders.extend(found.into_iter().map(|f| Finder {
                center: f.center + Vector2::new(ox, oy),
                ..f
            }));
        }
        (finders, small)
    };
    let area = |w: &Window| w.width * w.height;
    let total: usize = windows.iter().map(area).sum();
    if windows.len() < 2 || total < PARALLEL_WINDOW_PIXELS {
        return scan_group(&mut labelling[0], windows);
    }
    // Two groups of about equal area, largest windows first.
    let mut sorted = windows.to_vec();
    sorted.sort_by_key(|w| std::cmp::Reverse(area(w)));
    let (mut groups, mut areas) = ([Vec::new(), Vec::new()], [0, 0]);
    for w in sorted {
        let g = usize::from(areas[1] < areas[0]);
        areas[g] += area(&w);
        groups[g].push(w);
    }
    let [first, second] = labelling;
    let (a, b) = std::thread::scope(|s| {
        let handle = s.spawn(|| scan_group(first, &groups[0]));
        let b = scan_group(second, &groups[1]);
        (handle.join().unwrap_or_default(), b)
    });
    let (mut finders, mut small) = a;
    finders.extend(b.0);
    small.extend(b.1);
    (finders, small)
}

/// Buffers of one labelling: the threshold map and one region set per threshold level, and
/// those of the blurred-finder rescue's window scans.
#[derive(Default)]
struct Labelling {
    thresholds: ThresholdMap,
    regions: [Regions; LEVELS.len()],
    window_thresholds: ThresholdMap,
    window_regions: Regions,
}

impl Labelling {
    /// Finders of `image` in its own pixel frame. With `small`, also pushes there the bounding
    /// boxes of its small closed regions ([`REFINE_MAX_AREA`]), shifted by `origin`.
    fn scan(
        &mut self,
        image: &GreyImage,
        floor: Option<f32>,
        origin: (usize, usize),
        small: Option<&mut Vec<[u32; 4]>>,
    ) -> Vec<Finder> {
        if image.width() < 8 || image.height() < 8 {
            return Vec::new();
        }
        self.thresholds.compute(image, floor);
        self.label_levels(image);
        let (ox, oy) = (origin.0 as u32, origin.1 as u32);
        let mut finders = Vec::new();
        let mut unexplained = Vec::new();
        let want_small = small.is_some();
        let mut boxes = Vec::new();
        for (index, labels) in self.regions.iter().enumerate() {
            let regions = &labels.regions;
            let middle = index < MIDDLE_LEVELS;
            for c in regions {
                let [a, b] = finders_at(regions, c);
                // A region read only from its gap and ring did stand out as a centre: where a
                // tone curve darkens a dark finder's blurred gap, that nesting is the true
                // centre in a gap too narrow for a centre reading at every level, and its
                // gap-and-ring reading a look-alike of the other polarity (`HPCodeImage_20um.png`
                // at `v^1.81`). The rescue reads it at its own gap's and ring's levels.
                if a.is_none() && middle {
                    unexplained.extend(rescue::Unexplained::of(c));
                }
                finders.extend(a.into_iter().chain(b));
                if want_small && middle && might_be_small_centre(c) {
                    let b = c.bbox;
                    boxes.push([b[0] + ox, b[1] + oy, b[2] + ox, b[3] + oy]);
                }
            }
        }
        if let Some(out) = small {
            out.extend(boxes);
        }
        let floor = self.thresholds.floor();
        for candidate in rescue::candidates(unexplained, &finders) {
            finders.extend(rescue::blurred_finder(
                &mut self.window_thresholds,
                &mut self.window_regions,
                image,
                &candidate,
                floor,
            ));
        }
        finders
    }

    /// Labels `image` at every threshold level of [`LEVELS`] in one raster pass
    /// ([`binarize::label_levels`]); a large image in two, the middle levels on a second
    /// thread.
    fn label_levels(&mut self, image: &GreyImage) {
        let map = &self.thresholds;
        if image.width() * image.height() < PARALLEL_MIN_PIXELS {
            binarize::label_levels(&mut self.regions, image, map, &LEVELS);
            return;
        }
        let (middle, outer) = self.regions.split_at_mut(MIDDLE_LEVELS);
        std::thread::scope(|s| {
            s.spawn(|| binarize::label_levels(middle, image, map, &LEVELS[..MIDDLE_LEVELS]));
            binarize::label_levels(outer, image, map, &LEVELS[MIDDLE_LEVELS..]);
        });
    }
}

/// A rectangle of a pyramid level, its pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Window {
    col0: usize,
    row0: usize,
    width: usize,
    height: usize,
}

impl Window {
    fn whole(image: &GreyImage) -> Window {
        Window {
            col0: 0,
            row0: 0,
            width: image.width(),
            height: image.height(),
        }
    }

    fn is_whole(&self, image: &GreyImage) -> bool {
        *self == Window::whole(image)
    }

    fn origin(&self) -> (usize, usize) {
        (self.col0, self.row0)
    }

    /// The window's pixels (borrowed when it is the whole image).
    fn view<'a>(&self, image: &'a GreyImage) -> Cow<'a, GreyImage> {
        if self.is_whole(image) {
            return Cow::Borrowed(image);
        }
        match image.crop(self.col0, self.row0, self.width, self.height) {
            Ok(crop) => Cow::Owned(crop),
            // Windows are clipped to the image: cannot happen; label the whole level.
            Err(_) => Cow::Borrowed(image),
        }
    }
}

/// Windows of `image` (a pyramid level) to label: the blocks within [`REFINE_MARGIN_BLOCKS`]
/// of the `small` boxes (pixels of the level above, half this resolution), as the bounding
/// rectangles of their connected groups, merged where they overlap. The whole image when
/// that is cheaper.
fn refine_windows(image: &GreyImage, small: &[[u32; 4]]) -> Vec<Window> {
    let (w, h) = (image.width(), image.height());
    let (bw, bh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
    // Marked blocks by 2-D difference array: +1/−1 at box corners, then prefix sums.
    let mut diff = vec![0i32; (bw + 1) * (bh + 1)];
    let m = REFINE_MARGIN_BLOCKS;
    for b in small {
        let x0 = (2 * b[0] as usize / BLOCK).saturating_sub(m);
        let y0 = (2 * b[1] as usize / BLOCK).saturating_sub(m);
        let x1 = ((2 * b[2] as usize + 1) / BLOCK + m + 1).min(bw);
        let y1 = ((2 * b[3] as usize + 1) / BLOCK + m + 1).min(bh);
        if x0 >= x1 || y0 >= y1 {
            continue;
        }
        diff[y0 * (bw + 1) + x0] += 1;
        diff[y0 * (bw + 1) + x1] -= 1;
        diff[y1 * (bw + 1) + x0] -= 1;
        diff[y1 * (bw + 1) + x1] += 1;
    }
    let mut marked = vec![false; bw * bh];
    let mut count = 0;
    let mut above = vec![0i32; bw + 1];
    for y in 0..bh {
        let mut run = 0;
        for x in 0..bw {
            run += diff[y * (bw + 1) + x];
            above[x] += run;
            if above[x] > 0 {
                marked[y * bw + x] = true;
                count += 1;
            }
        }
    }
    if count == 0 {
        return Vec::new();
    }
    if count as f64 > WHOLE_LEVEL_FRACTION * (bw * bh) as f64 {
        return vec![Window::whole(image)];
    }
    let mut rects = block_groups(&mut marked, bw, bh);
    merge_overlapping(&mut rects);
    rects
        .into_iter()
        .map(|[x0, y0, x1, y1]| Window {
            col0: x0 * BLOCK,
            row0: y0 * BLOCK,
            width: ((x1 + 1) * BLOCK).min(w) - x0 * BLOCK,
            height: ((y1 + 1) * BLOCK).min(h) - y0 * BLOCK,
        })
        .collect()
}

/// A closed, compact region of the size of a small finder or finder centre (from a 2×2 blob
/// to [`REFINE_MAX_AREA`]).
fn might_be_small_centre(r: &Region) -> bool {
    !r.open && (REFINE_MIN_AREA..=REFINE_MAX_AREA).contains(&r.filled_area) && compact(r)
}

/// Bounding boxes `[x0, y0, x1, y1]` (inclusive blocks) of the 4-connected groups of marked
/// blocks (consumes the marks).
fn block_groups(marked: &mut [bool], bw: usize, bh: usize) -> Vec<[usize; 4]> {
    let mut rects = Vec::new();
    let mut stack = Vec::new();
    for start in 0..marked.len() {
        if !marked[start] {
            continue;
        }
        marked[start] = false;
        stack.push(start);
        let mut r = [bw, bh, 0, 0];
        while let Some(i) = stack.pop() {
            let (x, y) = (i % bw, i / bw);
            r = [r[0].min(x), r[1].min(y), r[2].max(x), r[3].max(y)];
            let mut visit = |j: usize| {
                if marked[j] {
                    marked[j] = false;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < bw {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - bw);
            }
            if y + 1 < bh {
                visit(i + bw);
            }
        }
        rects.push(r);
    }
    rects
}

/// Replaces overlapping rectangles by their union until none overlap.
fn merge_overlapping(rects: &mut Vec<[usize; 4]>) {
    let overlap = |a: &[usize; 4], b: &[usize; 4]| {
        a[0] <= b[2] && b[0] <= a[2] && a[1] <= b[3] && b[1] <= a[3]
    };
    let mut merged = true;
    while merged {
        merged = false;
        'outer: for i in 0..rects.len() {
            for j in i + 1..rects.len() {
                if overlap(&rects[i], &rects[j]) {
                    let b = rects.swap_remove(j);
                    let a = &mut rects[i];
                    *a = [
                        a[0].min(b[0]),
                        a[1].min(b[1]),
                        a[2].max(b[2]),
                        a[3].max(b[3]),
                    ];
                    merged = true;
                    break 'outer;
                }
            }
        }
    }
}

/// One finder per structure and size: the same finder is seen at several threshold levels, of
/// which the best-shaped is kept, a reading through its centre before any through its gap and
/// ring only (which adds the finders whose centre merged with the gap, and leaves the others
/// as the centre readings find them). Look-alikes of another size at the same place are kept too:
/// a finder's gap can pass for the centre of a finder of the other polarity whose gap is the
/// ring (module 1.5 times larger), and a centre imaged hollow can hold a smaller one. Shape
/// alone cannot always tell which is real; the marker geometry and the grid do (a look-alike's
/// module disagrees with the dot period by a factor of 1.5 or more).
fn dedup(mut found: Vec<Finder>) -> Vec<Finder> {
    found.sort_by(|a, b| {
        a.centre_hidden
            .cmp(&b.centre_hidden)
            .then(b.score.total_cmp(&a.score))
    });
    let mut kept: Vec<Finder> = Vec::with_capacity(found.len());
    for f in found {
        let mut duplicate = false;
        for k in &kept {
            let (small, large) = if k.module_px <= f.module_px {
                (k.module_px, f.module_px)
            } else {
                (f.module_px, k.module_px)
            };
            if (k.center - f.center).norm() > small {
                continue;
            }
            if large / small < 1.2 && k.polarity == f.polarity {
                duplicate = true;
            }
        }
        if !duplicate {
            kept.push(f);
        }
    }
    kept
}

/// Finder squares of one marker are at least `W − 7 ≥ 18` modules apart, so a finder with a
/// look-alike of its size closer than [`MIN_SPACING`] modules is a texture element (e.g. a
/// hollow-looking dot of a dot grid), not a finder.
fn crowded(f: &Finder, all: &[Finder]) -> bool {
    all.iter().any(|g| {
        // A concentric reading (nearer than a module) is the same square read at another
        // level, not a neighbour.
        let distance = (g.center - f.center).norm();
        // A finder read through its centre is judged among those alone, as if the readings
        // through gap and ring did not exist.
        g != f
            && (f.centre_hidden || !g.centre_hidden)
            && g.polarity == f.polarity
            && (g.module_px / f.module_px - 1.0).abs() < 0.3
            && distance < MIN_SPACING * f.module_px
            && distance >= f.module_px.min(g.module_px)
    })
}

/// The finders that the closed region `inner` and the hole of the other colour around it
/// (its parent) may be, read two ways:
///
/// * **centre and gap** (nominal `√(filled outer / filled inner)` 5/3): only the centre and the
///   gap are required: the ring may merge with whatever dark (bright) structure touches it,
///   e.g. the edge of the part the marker is on, but the gap stays a hole that holds nothing
///   but the centre;
/// * **gap and ring** (nominal 7/5, with the ring's polarity): where the centre is too dim to
///   stand out of the gap at any threshold level (a specular or hollow-looking centre under
///   a steep gamma, an overexposed image whose gaps saturate with the centre), the gap with
///   the centre in it is the inner region and the ring the outer one. Read as centre and gap,
///   that pair gives a finder 1.5 times too large, which the window's grid rejects.
///
/// The two ranges overlap (a ratio of 1.35–1.6 may be either): both are returned then, and
/// the grid decides.
fn finders_at(regions: &[Region], inner: &Region) -> [Option<Finder>; 2] {
    let Some(outer) = nested_pair(regions, inner) else {
        return [None, None];
    };
    let (side_i, side_o) = (inner.filled_area.sqrt(), outer.filled_area.sqrt());
    let ratio = side_o / side_i;
    let eccentricity = distance(inner, outer) / side_o;
    let center = (centroid(inner) + centroid(outer)) / 2.0;
    let finder = |range: (f64, f64), nominal: f64, modules: f64, material: &Region| {
        let centre_hidden = std::ptr::eq(material, outer);
        (range.0..=range.1).contains(&ratio).then(|| Finder {
            center,
            // Inner side `a·m ± 2d` and outer side `b·m ∓ 2d` for a threshold bias `d`: the
            // sum is `(a + b)·m` (3 + 5 for centre and gap, 5 + 7 for gap and ring).
            module_px: (side_i + side_o) / modules,
            polarity: material_polarity(material.bright),
            score: (-10.0 * (ratio / nominal).ln().powi(2) - (eccentricity / 0.05).powi(2)).exp(),
            centre_hidden,
        })
    };
    [
        finder(GAP_RATIO, 5.0 / 3.0, 8.0, inner),
        finder(RING_RATIO, 7.0 / 5.0, 12.0, outer),
    ]
}

/// The closed, compact hole of the other colour around the closed, compact region `inner`,
/// holding nothing else of note and centred on it: the nesting of two finder outlines.
fn nested_pair<'a>(regions: &'a [Region], inner: &Region) -> Option<&'a Region> {
    if inner.open || inner.filled_area < MIN_CENTER_AREA || !compact(inner) {
        return None;
    }
    let outer = regions.get(inner.parent?)?;
    let clutter = outer.filled_area - outer.area - inner.filled_area;
    if outer.open || !compact(outer) || clutter > MAX_GAP_CLUTTER * inner.filled_area {
        return None;
    }
    let eccentricity = distance(inner, outer) / outer.filled_area.sqrt();
    (eccentricity <= MAX_ECCENTRICITY).then_some(outer)
}

/// The polarity of a finder whose material (ring and centre) is bright, or dark.
fn material_polarity(bright: bool) -> Polarity {
    if bright {
        Polarity::BrightDots
    } else {
        Polarity::DarkDots
    }
}

fn centroid(r: &Region) -> Vector2<f64> {
    Vector2::new(r.filled_centroid[0], r.filled_centroid[1])
}

fn distance(a: &Region, b: &Region) -> f64 {
    (centroid(a) - centroid(b)).norm()
}

/// Filled region roughly square: fills its bounding box well enough (any rotation) and is not
/// elongated.
fn compact(r: &Region) -> bool {
    let w = (r.bbox[2] - r.bbox[0] + 1) as f64;
    let h = (r.bbox[3] - r.bbox[1] + 1) as f64;
    r.filled_area >= MIN_BOX_FILL * w * h && w.max(h) <= MAX_ASPECT * w.min(h)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bright finder of module `m` pixels centred at (cx, cy), axis-aligned, on black.
    fn finder_image(w: usize, h: usize, cx: f64, cy: f64, m: f64) -> GreyImage {
        let mut px = vec![0.0f32; w * h];
        paint_finder(&mut px, w, cx, cy, m);
        GreyImage::new(w, h, px).unwrap()
    }

    fn paint_finder(px: &mut [f32], w: usize, cx: f64, cy: f64, m: f64) {
        let h = px.len() / w;
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
    }

    #[test]
    fn pyramid_finds_finders_of_every_size_in_a_large_image() {
        // 1100² is binned twice; modules 2 and 5 px are too small for the coarsest level and
        // must be found by labelling finer levels around them.
        let (w, h) = (1100, 1100);
        let mut px = vec![0.0f32; w * h];
        let placed = [
            (200.3, 210.7, 2.0),
            (700.0, 300.0, 5.0),
            (520.0, 760.0, 40.0),
        ];
        for &(cx, cy, m) in &placed {
            paint_finder(&mut px, w, cx, cy, m);
        }
        let image = GreyImage::new(w, h, px).unwrap();
        let found = FinderScanner::default().find(&image, None);
        for &(cx, cy, m) in &placed {
            // Painted on whole pixels: the centre is within a pixel.
            let expected = Vector2::new(cx, cy);
            assert!(
                found.iter().any(|f| f.polarity == Polarity::BrightDots
                    && (f.center - expected).norm() < 1.0
                    && (f.module_px / m - 1.0).abs() < 0.1),
                "module {m}: {found:?}"
            );
        }
    }

    #[test]
    fn finds_one_axis_aligned_finder_of_each_polarity() {
        for m in [2.0, 6.0, 30.0] {
            let size = (14.0 * m) as usize + 20;
            let c = size as f64 / 2.0;
            let image = finder_image(size, size, c, c, m);
            let mut scanner = FinderScanner::default();
            // The gap may also pass for a dark look-alike, 1.5 times larger read as centre and
            // gap, or 2/3 as large read as gap and ring (`(3m + 5m)/12`; the smoothed reading
            // of a small finder gives that one), kept for the grid to reject; the bright
            // finder is found once, where it is.
            let found = scanner.find(&image, None);
            let bright: Vec<&Finder> = found
                .iter()
                .filter(|f| f.polarity == Polarity::BrightDots)
                .collect();
            assert_eq!(bright.len(), 1, "module {m}: {found:?}");
            assert!(
                found.iter().all(|f| f.polarity == Polarity::BrightDots
                    || (f.module_px / m - 1.5).abs() < 0.2
                    || (f.centre_hidden && (f.module_px / m - 2.0 / 3.0).abs() < 0.1)),
                "module {m}: {found:?}"
            );
            let f = *bright[0];
            assert!(
                (f.center - Vector2::new(c - 0.5, c - 0.5)).norm() < 0.6,
                "{f:?}"
            );
            assert!((f.module_px / m - 1.0).abs() < 0.1, "{f:?}");
            let dark = scanner.find(&image.inverted(), None);
            let dark: Vec<&Finder> = dark
                .iter()
                .filter(|f| f.polarity == Polarity::DarkDots)
                .collect();
            assert_eq!(dark.len(), 1);
            assert!((dark[0].module_px / m - 1.0).abs() < 0.1);
        }
    }

    #[test]
    fn finds_a_blurred_finder_whose_gap_is_grey() {
        // As the printed finders of code31.jpg: ring and centre at 1, the gap grey (0.3), dark
        // surround on two sides, a dot grid (dark dots on 0.65) on the other two, blur of 0.6
        // module. The blur lifts the gap over the lower levels of the local ranges while the
        // corners of the thin ring sink below the upper ones: no level of the local ranges
        // opens the gap and closes the ring; one between the gap's and the ring's own does.
        let m = 6.0;
        let size = (14.0 * m) as usize + 20;
        let c = size as f64 / 2.0;
        let mut px = vec![0.0f32; size * size];
        for (i, v) in px.iter_mut().enumerate() {
            let (u, w) = ((i % size) as f64 - c, (i / size) as f64 - c);
            if u.abs() < 3.5 * m && w.abs() < 3.5 * m {
                *v = 0.3;
            } else if (u > 4.5 * m && w > -3.5 * m) || (w > 4.5 * m && u > -3.5 * m) {
                let (a, b) = (
                    (u / (2.0 * m)).rem_euclid(1.0),
                    (w / (2.0 * m)).rem_euclid(1.0),
                );
                let dot = (a - 0.5).abs() < 0.25 && (b - 0.5).abs() < 0.25;
                *v = if dot { 0.15 } else { 0.65 };
            }
        }
        paint_finder(&mut px, size, c, c, m);
        crate::render::gaussian_blur(&mut px, size, size, 0.6 * m);
        let image = GreyImage::new(size, size, px).unwrap();
        for finder in the_finder_of_each_polarity(&image, m) {
            let expected = Vector2::new(c - 0.5, c - 0.5);
            assert!((finder.center - expected).norm() < 0.6, "{finder:?}");
        }
    }

    /// The one finder of module `m` (±10 %) found in `image` with bright material and in its
    /// inverse with dark material.
    fn the_finder_of_each_polarity(image: &GreyImage, m: f64) -> [Finder; 2] {
        [
            (Polarity::BrightDots, image.clone()),
            (Polarity::DarkDots, image.inverted()),
        ]
        .map(|(polarity, view)| {
            let found = FinderScanner::default().find(&view, None);
            let real: Vec<&Finder> = found
                .iter()
                .filter(|f| f.polarity == polarity && (f.module_px / m - 1.0).abs() < 0.1)
                .collect();
            assert_eq!(real.len(), 1, "module {m}, {polarity:?}: {found:?}");
            *real[0]
        })
    }

    #[test]
    fn finds_a_finder_whose_centre_does_not_stand_out_of_its_gap() {
        // Ring at 1, centre at the gap's level 0 (a dim specular centre; gap and centre
        // saturated alike once inverted): the centre is part of the gap at every threshold
        // level. The gap inside the ring is read as such, with the ring's polarity and module;
        // the centre-and-gap reading of the same outlines is a look-alike 1.5 times larger of
        // the other polarity.
        for m in [2.0, 8.0, 20.0] {
            let size = (14.0 * m) as usize + 20;
            let c = size as f64 / 2.0;
            let mut image = finder_image(size, size, c, c, m);
            for (i, v) in image.pixels_mut().iter_mut().enumerate() {
                // The painted centre's pixels: `[c − 1.5m, c + 1.5m)` along each axis.
                let (u, w) = ((i % size) as f64 - c, (i / size) as f64 - c);
                if (-1.5 * m..1.5 * m).contains(&u) && (-1.5 * m..1.5 * m).contains(&w) {
                    *v = 0.0;
                }
            }
            for finder in the_finder_of_each_polarity(&image, m) {
                assert!(finder.centre_hidden);
                let expected = Vector2::new(c - 0.5, c - 0.5);
                assert!((finder.center - expected).norm() < 0.6, "m {m}: {finder:?}");
            }
        }
    }
}
