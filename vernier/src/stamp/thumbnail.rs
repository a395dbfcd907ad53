//! Bitmap thumbnail: the image resampled on the marker's own half-period grid
//! (docs/design.md#stamp-thumbnail, redesigned).
//!
//! The two phase planes say where every half-period cell of the marker lies in the image: cell
//! `(i1, i2)` is centred where `φ1 = π·i1` and `φ2 = π·i2` (even indices are dots, odd ones the
//! gaps between them, or solid features). Each cell's grey level is the mean of five bilinear
//! samples around that centre (its middle third), which reads the cell however blurred the
//! image is and costs five samples per cell instead of a pass over every pixel.

use crate::grey_image::GreyImage;
use crate::phase::PhasePlane;
use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
use std::f64::consts::PI;

/// Grey levels of a rectangular block of half-period cells.
#[derive(Clone, Debug)]
pub(crate) struct Thumbnail {
    /// Smallest cell index along phase 1 (thumbnail x) and phase 2 (thumbnail y).
    pub lo: [i64; 2],
    /// Number of cells along phase 1 and phase 2.
    pub len: [usize; 2],
    /// Mean grey level per cell, row-major (`i2` rows of `i1` cells); `None` where a sample
    /// falls outside the image.
    pub values: Vec<Option<f32>>,
}

impl Thumbnail {
    /// Cell `(i1, i2)` at thumbnail index `(c, r)` (column, row from the block's first cell).
    pub fn cell(&self, c: i64, r: i64) -> [i64; 2] {
        [c + self.lo[0], r + self.lo[1]]
    }

    /// Thumbnail index `(c, r)` of cell `i`, the inverse of [`Thumbnail::cell`] (outside the
    /// block for cells beyond it).
    pub fn index(&self, i: [i64; 2]) -> (i64, i64) {
        (i[0] - self.lo[0], i[1] - self.lo[1])
    }

    /// Value of cell `(i1, i2)`, `None` outside the block or the image.
    #[cfg(test)]
    pub fn get(&self, i1: i64, i2: i64) -> Option<f32> {
        let (c, r) = self.index([i1, i2]);
        if c < 0 || r < 0 || c as usize >= self.len[0] || r as usize >= self.len[1] {
            return None;
        }
        self.values[r as usize * self.len[0] + c as usize]
    }
}

/// Maps image-frame offsets to phases: `φ = J·(x, y) + c`; `None` when the planes are parallel.
pub(crate) fn phase_jacobian(planes: &[PhasePlane; 2]) -> Option<Matrix2<f64>> {
    let j = Matrix2::new(planes[0].a, planes[0].b, planes[1].a, planes[1].b);
    (j.determinant().abs() > 1e-12).then_some(j)
}

/// Samples the cells `lo[k] ≤ i_k < lo[k] + len[k]` of `image`, the planes being expressed in
/// the frame whose origin is the image point `origin` (pixels `(col, row)`), with their offsets
/// `c` in `(−π, π]` so that cell `(0, 0)` is the dot nearest to that origin. `warp` (a
/// homography of image points, see [`crate::stamp::Quad::perspective_warp`]) moves every
/// sample from where the planes' affine view puts it to where perspective does.
pub(crate) fn sample(
    image: &GreyImage,
    origin: Vector2<f64>,
    planes: &[PhasePlane; 2],
    lo: [i64; 2],
    len: [usize; 2],
    warp: Option<&Matrix3<f64>>,
) -> Option<Thumbnail> {
    let at = |p: Vector2<f64>| match warp {
        Some(h) => {
            let q = h * Vector3::new(p.x, p.y, 1.0);
            (q.z.abs() > 1e-12).then(|| Vector2::new(q.x / q.z, q.y / q.z))
        }
        None => Some(p),
    };
    let inv = phase_jacobian(planes)?.try_inverse()?;
    // Image offset of one cell step along each phase, and of the sample spread (a sixth of a
    // cell each way).
    let step1 = inv * Vector2::new(PI, 0.0);
    let step2 = inv * Vector2::new(0.0, PI);
    let spread = [step1 / 6.0, -step1 / 6.0, step2 / 6.0, -step2 / 6.0];
    let start = origin
        + inv
            * Vector2::new(
                lo[0] as f64 * PI - planes[0].c,
                lo[1] as f64 * PI - planes[1].c,
            );
    let mut values = Vec::with_capacity(len[0] * len[1]);
    for r in 0..len[1] {
        let row_start = start + step2 * r as f64;
        for c in 0..len[0] {
            let p = row_start + step1 * c as f64;
            let mut sum = at(p).and_then(|q| image.bilinear(q.x, q.y));
            for d in &spread {
                sum = match (sum, at(p + d).and_then(|q| image.bilinear(q.x, q.y))) {
                    (Some(s), Some(v)) => Some(s + v),
                    _ => None,
                };
            }
            values.push(sum.map(|s| s / 5.0));
        }
    }
    Some(Thumbnail { lo, len, values })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_follow_the_planes() {
        // Vertical stripes: bright on even cells along x (period 8 px, cells 4 px wide).
        let (w, h) = (64usize, 48usize);
        let px: Vec<f32> = (0..w * h)
            .map(|i| if ((i % w) / 4) % 2 == 0 { 1.0 } else { 0.0 })
            .collect();
        let image = GreyImage::new(w, h, px).unwrap();
        let k = 2.0 * PI / 8.0;
        // Dots centred at columns 1.5 + 8n: phase 0 there. Frame origin at pixel (33.5, 24).
        let planes = [
            PhasePlane {
                a: k,
                b: 0.0,
                c: 0.0,
            },
            PhasePlane {
                a: 0.0,
                b: k,
                c: 0.0,
            },
        ];
        let t = sample(
            &image,
            Vector2::new(33.5, 24.0),
            &planes,
            [-3, -2],
            [7, 5],
            None,
        )
        .unwrap();
        assert_eq!(t.get(0, 0), Some(1.0));
        assert_eq!(t.get(1, 0), Some(0.0));
        assert_eq!(t.get(-2, 1), Some(1.0));
        assert_eq!(t.get(5, 0), None, "outside the block");
    }
}
