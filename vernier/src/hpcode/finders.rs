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

use crate::binarize::{Region, Regions, ThresholdMap};
use crate::grey_image::{GreyImage, Polarity};
use nalgebra::Vector2;

/// Images with at least this many pixels are labelled at their threshold levels in parallel.
const PARALLEL_MIN_PIXELS: usize = 1 << 18;
/// Closest accepted distance between two finders of the same size, modules (see
/// [`crowded`]; two markers touching edge to edge have finders 7 modules apart).
const MIN_SPACING: f64 = 10.0;
/// Threshold levels scanned, fractions of the local range: the mid-range, and two levels
/// that keep a blurred one-module gap open in bright (0.7) and dark (0.3) finders.
const LEVELS: [f32; 3] = [0.5, 0.7, 0.3];
/// Accepted `√(filled gap / filled centre)` (nominal 5/3: blur and threshold move it).
const GAP_RATIO: (f64, f64) = (1.35, 2.3);
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
}

/// Reusable buffers of the finder search (one per detector).
#[derive(Default)]
pub(crate) struct FinderScanner {
    thresholds: ThresholdMap,
    /// One labelling per threshold level (they run in parallel on large images).
    regions: [Regions; LEVELS.len()],
}

impl FinderScanner {
    /// Finds every finder square in `image`. `min_contrast` overrides the contrast floor of
    /// the local threshold (intensity units); `None` derives it from the image noise.
    pub(crate) fn find(&mut self, image: &GreyImage, min_contrast: Option<f64>) -> Vec<Finder> {
        if image.width() < 8 || image.height() < 8 {
            return Vec::new();
        }
        self.thresholds
            .compute(image, min_contrast.map(|c| c as f32));
        let map = &self.thresholds;
        let scan = |(labels, level): (&mut Regions, f32)| -> Vec<Finder> {
            labels.label(image, map, level);
            let regions = &labels.regions;
            regions
                .iter()
                .filter_map(|c| finder_at(regions, c))
                .collect()
        };
        let jobs = self.regions.iter_mut().zip(LEVELS);
        let found: Vec<Finder> = if image.width() * image.height() >= PARALLEL_MIN_PIXELS {
            std::thread::scope(|s| {
                let handles: Vec<_> = jobs.map(|job| s.spawn(move || scan(job))).collect();
                handles
                    .into_iter()
                    .flat_map(|h| h.join().unwrap_or_default())
                    .collect()
            })
        } else {
            jobs.flat_map(scan).collect()
        };
        let unique = dedup(found);
        unique
            .iter()
            .filter(|f| !crowded(f, &unique))
            .copied()
            .collect()
    }
}

/// One finder per structure and size: the same finder is seen at several threshold levels, of
/// which the best-shaped is kept. Look-alikes of another size at the same place are kept too:
/// a finder's gap can pass for the centre of a finder of the other polarity whose gap is the
/// ring (module 1.5 times larger), and a centre imaged hollow can hold a smaller one. Shape
/// alone cannot always tell which is real; the marker geometry and the grid do (a look-alike's
/// module disagrees with the dot period by a factor of 1.5 or more).
fn dedup(mut found: Vec<Finder>) -> Vec<Finder> {
    found.sort_by(|a, b| b.score.total_cmp(&a.score));
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
        g != f
            && g.polarity == f.polarity
            && (g.module_px / f.module_px - 1.0).abs() < 0.3
            && (g.center - f.center).norm() < MIN_SPACING * f.module_px
    })
}

/// The finder whose centre region is `centre`, if it and the gap around it form one.
///
/// Only the centre and the gap are required: the ring may merge with whatever dark (bright)
/// structure touches it, e.g. the edge of the part the marker is on, but the gap stays a hole
/// that holds nothing but the centre.
fn finder_at(regions: &[Region], centre: &Region) -> Option<Finder> {
    if centre.open || centre.filled_area < MIN_CENTER_AREA || !compact(centre) {
        return None;
    }
    let gap = regions.get(centre.parent?)?;
    let gap_clutter = gap.filled_area - gap.area - centre.filled_area;
    if gap.open || !compact(gap) || gap_clutter > MAX_GAP_CLUTTER * centre.filled_area {
        return None;
    }
    let (side_c, side_g) = (centre.filled_area.sqrt(), gap.filled_area.sqrt());
    let ratio = side_g / side_c;
    if !(GAP_RATIO.0..=GAP_RATIO.1).contains(&ratio) {
        return None;
    }
    let eccentricity = distance(centre, gap) / side_g;
    if eccentricity > MAX_ECCENTRICITY {
        return None;
    }
    let score = (-10.0 * (ratio / (5.0 / 3.0)).ln().powi(2) - (eccentricity / 0.05).powi(2)).exp();
    Some(Finder {
        center: (centroid(centre) + centroid(gap)) / 2.0,
        // Centre side 3m + 2d and gap side 5m − 2d for a threshold bias d: the sum is 8m.
        module_px: (side_c + side_g) / 8.0,
        polarity: if centre.bright {
            Polarity::BrightDots
        } else {
            Polarity::DarkDots
        },
        score,
    })
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
        for m in [2.0, 6.0, 30.0] {
            let size = (14.0 * m) as usize + 20;
            let c = size as f64 / 2.0;
            let image = finder_image(size, size, c, c, m);
            let mut scanner = FinderScanner::default();
            // The gap may also pass for a dark look-alike 1.5 times larger (kept for the grid to
            // reject); the bright finder is found once, where it is.
            let found = scanner.find(&image, None);
            let bright: Vec<&Finder> = found
                .iter()
                .filter(|f| f.polarity == Polarity::BrightDots)
                .collect();
            assert_eq!(bright.len(), 1, "module {m}: {found:?}");
            assert!(
                found
                    .iter()
                    .all(|f| f.polarity == Polarity::BrightDots
                        || (f.module_px / m - 1.5).abs() < 0.2)
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
}
