//! Unsharp masking against a box mean, for reading HP code finders and dots that blur has
//! merged (docs/design.md#hp-blurred-finders).
//!
//! `v + GAIN·(v − B∗v)`, `B` the mean over a square box [`BOX_MODULES`] modules a side, read
//! from a summed-area table (F. C. Crow, *Summed-area tables for texture mapping*, SIGGRAPH
//! 1984) so that a pixel costs the same at every module, from one pixel to tens.

use crate::grey_image::GreyImage;

/// Gain of the detail term: `v + GAIN·(v − B∗v)`. A numeric model of an HP code finder
/// (centre, gap and ring one module each, the gap at 35 % of the ring's level) under a
/// Gaussian blur of σ modules: the ring's least level less the gap's greatest, over the
/// filter's white-noise gain (one arbitrary unit for every figure), is 0.05, −1.5 and −2.6 at
/// σ 0.6, 0.7 and 0.8 raw (beyond 0.6 no threshold lies between gap and ring), and 2.4, 0.9
/// and 0.0 so sharpened. A gain of 3 adds 0.1–0.2; a box of 4.5 modules does less (1.6, 0.3,
/// −0.5); a Gaussian of σ one module in place of the box, 1.9, 0.6 and −0.2.
pub(crate) const GAIN: f32 = 2.0;

/// Side of the box, modules (a module is half a period of the dot grid): a finder centre's
/// own size.
pub(crate) const BOX_MODULES: f64 = 3.0;

/// A rectangle of an image prepared for sharpening at one module: the rectangle with the
/// margin its boxes read around it (clipped to the image) and that part's summed-area table.
/// Every coordinate in and out is the image's.
pub(crate) struct Sharpener {
    /// The rectangle and its margin.
    part: GreyImage,
    /// Image pixel `(col, row)` of `part`'s `(0, 0)`.
    part_origin: (usize, usize),
    /// The rectangle `(col0, row0)`, `(width, height)`, image pixels.
    rect: ((usize, usize), (usize, usize)),
    /// Half-side of the box, pixels: half of [`BOX_MODULES`] modules, at least 1.
    half: i64,
    /// `sums[r·(w + 1) + c]`: the sum of `part`'s pixels above row `r` and left of column `c`.
    sums: Vec<f64>,
}

impl Sharpener {
    /// Prepares the rectangle at `origin` of `size` (image pixels) of `image` for sharpening
    /// at a module of `module` pixels (one pass over the part); `None` when the rectangle
    /// leaves the image.
    pub(crate) fn around(
        image: &GreyImage,
        origin: (usize, usize),
        size: (usize, usize),
        module: f64,
    ) -> Option<Self> {
        if origin.0 + size.0 > image.width() || origin.1 + size.1 > image.height() {
            return None;
        }
        let half = ((0.5 * BOX_MODULES * module).round() as i64).max(1);
        let margin = usize::try_from(half).ok()?;
        let (c0, r0) = (
            origin.0.saturating_sub(margin),
            origin.1.saturating_sub(margin),
        );
        let c1 = (origin.0 + size.0 + margin).min(image.width());
        let r1 = (origin.1 + size.1 + margin).min(image.height());
        let part = image.crop(c0, r0, c1 - c0, r1 - r0).ok()?;
        let (w, h) = (part.width(), part.height());
        let mut sums = vec![0.0f64; (w + 1) * (h + 1)];
        for (r, row) in part.pixels().chunks_exact(w.max(1)).take(h).enumerate() {
            let mut along = 0.0;
            for (c, &v) in row.iter().enumerate() {
                along += f64::from(v);
                sums[(r + 1) * (w + 1) + c + 1] = sums[r * (w + 1) + c + 1] + along;
            }
        }
        Some(Sharpener {
            part,
            part_origin: (c0, r0),
            rect: (origin, size),
            half,
            sums,
        })
    }

    /// The sharpened level at image point `(col, row)`: the bilinear sample `v` and `v +
    /// GAIN·(v − mean)`, the box means around the four nearest pixels interpolated alike (a
    /// mean taken at the nearest pixel alone jumps from one pixel to the next, a ripple that
    /// the gain amplifies); `None` outside the part.
    pub(crate) fn at(&self, col: f64, row: f64) -> Option<f32> {
        let col = col - self.part_origin.0 as f64;
        let row = row - self.part_origin.1 as f64;
        let v = self.part.bilinear(col, row)?;
        let (c0, r0) = (col.floor(), row.floor());
        let (fc, fr) = ((col - c0) as f32, (row - r0) as f32);
        let (c0, r0) = (c0 as i64, r0 as i64);
        let mean = |c: i64, r: i64| self.mean(c, r);
        let upper = mean(c0, r0) + (mean(c0 + 1, r0) - mean(c0, r0)) * fc;
        let lower = mean(c0, r0 + 1) + (mean(c0 + 1, r0 + 1) - mean(c0, r0 + 1)) * fc;
        let mean = upper + (lower - upper) * fr;
        Some(v + GAIN * (v - mean))
    }

    /// The rectangle sharpened, each pixel `v + GAIN·(v − mean)`.
    pub(crate) fn window(&self) -> Option<GreyImage> {
        let ((col0, row0), (width, height)) = self.rect;
        let (dc, dr) = (col0 - self.part_origin.0, row0 - self.part_origin.1);
        let mut pixels = Vec::with_capacity(width * height);
        for r in dr..dr + height {
            for c in dc..dc + width {
                let v = self.part.get(c, r)?;
                pixels.push(v + GAIN * (v - self.mean(c as i64, r as i64)));
            }
        }
        GreyImage::new(width, height, pixels).ok()
    }

    /// The mean over the box centred on `part`'s pixel `(col, row)`, clipped to the part.
    fn mean(&self, col: i64, row: i64) -> f32 {
        let (w, h) = (self.part.width() as i64, self.part.height() as i64);
        let (c0, c1) = (
            (col - self.half).clamp(0, w),
            (col + self.half + 1).clamp(0, w),
        );
        let (r0, r1) = (
            (row - self.half).clamp(0, h),
            (row + self.half + 1).clamp(0, h),
        );
        let area = ((c1 - c0) * (r1 - r0)) as f64;
        if area <= 0.0 {
            return 0.0;
        }
        let at = |r: i64, c: i64| self.sums[(r * (w + 1) + c) as usize];
        ((at(r1, c1) - at(r0, c1) - at(r1, c0) + at(r0, c0)) / area) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_means_match_a_direct_sum() {
        let pixels: Vec<f32> = (0..35 * 20)
            .map(|i| ((i * 37) % 101) as f32 / 100.0)
            .collect();
        let image = GreyImage::new(35, 20, pixels).unwrap();
        // Modules of 1.4, 2, 2.7 and 20 px: boxes 2, 3, 4 and 30 px each way.
        for (module, half) in [(1.4, 2i64), (2.0, 3), (2.7, 4), (20.0, 30)] {
            let sharpener = Sharpener::around(&image, (0, 0), (35, 20), module).unwrap();
            assert_eq!(sharpener.half, half);
            for &(c, r) in &[(10i64, 7i64), (0, 0), (34, 19), (17, 10)] {
                let (mut sum, mut n) = (0.0f64, 0.0f64);
                for rr in (r - half).max(0)..(r + half + 1).min(20) {
                    for cc in (c - half).max(0)..(c + half + 1).min(35) {
                        sum += f64::from(image.get(cc as usize, rr as usize).unwrap());
                        n += 1.0;
                    }
                }
                let direct = (sum / n) as f32;
                let mean = sharpener.mean(c, r);
                assert!((mean - direct).abs() < 1e-5, "({c}, {r}, {half})");
            }
        }
    }

    #[test]
    fn flat_images_are_unchanged_and_an_edge_overshoots() {
        let flat = GreyImage::new(40, 30, vec![0.4; 1200]).unwrap();
        let window = Sharpener::around(&flat, (5, 5), (30, 20), 2.0)
            .unwrap()
            .window();
        assert!(window
            .unwrap()
            .pixels()
            .iter()
            .all(|&v| (v - 0.4).abs() < 1e-5));
        // A vertical step from 0.2 to 0.8 at column 20: sharpened with boxes of 3 px each way,
        // it dips below 0.2 just before the step and rises above 0.8 just after it, and stays
        // the step farther away than the box's half-side; the window and the point samples
        // agree, in image coordinates.
        let step: Vec<f32> = (0..1200)
            .map(|i| if i % 40 < 20 { 0.2 } else { 0.8 })
            .collect();
        let image = GreyImage::new(40, 30, step).unwrap();
        let sharpener = Sharpener::around(&image, (3, 10), (34, 10), 2.0).unwrap();
        let row: Vec<f32> = (0..40)
            .map(|c| sharpener.at(c as f64, 15.0).unwrap())
            .collect();
        assert!(row[19] < 0.15 && row[20] > 0.85, "{row:?}");
        assert!((row[10] - 0.2).abs() < 1e-5 && (row[30] - 0.8).abs() < 1e-5);
        let window = sharpener.window().unwrap();
        for c in 0..34 {
            assert_eq!(window.get(c, 5), Some(row[c + 3]));
        }
        assert_eq!(sharpener.at(39.5, 15.0), None);
        assert!(Sharpener::around(&image, (10, 10), (31, 5), 2.0).is_none());
    }
}
