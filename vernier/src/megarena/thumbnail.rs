//! Dot sampling on the lattice given by the two phase planes: the "thumbnail" of present and
//! missing dots (docs/design.md#megarena-thumbnail, redesigned).
//!
//! The original classifies every pixel by its unwrapped phases. Here the (more accurate) planes
//! are used directly: lattice node `(n1, n2)` is the image point where `φ1 = 2π·n1` and
//! `φ2 = 2π·n2`, i.e. a dot centre, and the grey level is sampled there (bilinear
//! interpolation). One sample per node is enough: every decision downstream (orientation, bits,
//! presence) pools many nodes.
//!
//! Once the orientation is known ([`Thumbnail::subtract_background`]), each node's **contrast**
//! is its level minus the local background, taken as the median level of the four nearest
//! missing-dot nodes (the corner dot `(3i, 3j)` of every 3×3 cell is never fabricated, so the
//! background is sampled every third node in both directions, immune to illumination
//! gradients, and a spurious dot on one of them does not matter).
//!
//! Thumbnail axis k follows phase k (index `n_k`), over the orders that the image actually covers
//! (the original sized both axes from the row and column counts,
//! docs/design.md#defect-megarena-check). Cost: one bilinear sample per node inside the image,
//! `≈ R·C/p²` for a pixel period `p` (10⁴ at 1024² and 10 px).

use super::orientation::Orientation;
use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::order_stats::median;
use crate::phase::PhasePlane;
use std::f64::consts::TAU;

/// Grey levels and contrasts on the lattice nodes covered by the image.
///
/// Node `(n1, n2)` (phase orders: `φ_k = 2π·n_k` there) is stored at index
/// `(n1 − first[0])·dims[1] + (n2 − first[1])` of each array.
#[derive(Clone, Debug, Default)]
pub struct Thumbnail {
    /// Phase orders of the first stored node along each axis.
    pub first: [i64; 2],
    /// Number of nodes along each axis.
    pub dims: [usize; 2],
    /// Grey level at each node, NaN outside the image.
    pub level: Vec<f32>,
    /// Contrast of each node (level minus local background), grey-level units; NaN until
    /// [`Thumbnail::subtract_background`] and where no background is available.
    pub contrast: Vec<f32>,
    /// Local background level of each node, grey-level units; NaN where `contrast` is NaN.
    pub background_level: Vec<f32>,
}

impl Thumbnail {
    /// Array index of node `(n1, n2)`, `None` outside the thumbnail.
    fn index(&self, n1: i64, n2: i64) -> Option<usize> {
        let i = usize::try_from(n1 - self.first[0]).ok()?;
        let j = usize::try_from(n2 - self.first[1]).ok()?;
        (i < self.dims[0] && j < self.dims[1]).then_some(i * self.dims[1] + j)
    }

    /// Contrast of node `(n1, n2)` (phase orders), `None` outside the thumbnail or unknown.
    pub fn get(&self, n1: i64, n2: i64) -> Option<f32> {
        let v = *self.contrast.get(self.index(n1, n2)?)?;
        v.is_finite().then_some(v)
    }

    /// Grey level of node `(n1, n2)`, `None` outside the thumbnail or the image.
    pub fn level_at(&self, n1: i64, n2: i64) -> Option<f32> {
        let v = *self.level.get(self.index(n1, n2)?)?;
        v.is_finite().then_some(v)
    }

    /// Range of phase orders `first..first + dims` along axis `k` (0 or 1).
    pub fn orders(&self, k: usize) -> std::ops::Range<i64> {
        let k = k.min(1);
        self.first[k]..self.first[k] + self.dims[k] as i64
    }

    /// Samples `image` on the lattice of `planes` (image frame of [`PhasePlane`]), reusing the
    /// buffers of `self`; contrasts are reset to NaN. Errors when the planes are degenerate
    /// (parallel grid directions).
    pub fn sample(&mut self, image: &GreyImage, planes: &[PhasePlane; 2]) -> Result<()> {
        let lattice = Lattice::new(image, planes)?;
        let (w, h) = (image.width() as f64, image.height() as f64);
        // Phase orders covered by the image: extremes of each plane over the four corners.
        let corners = [
            (0.0, 0.0),
            (w - 1.0, 0.0),
            (0.0, h - 1.0),
            (w - 1.0, h - 1.0),
        ];
        let mut first = [0i64; 2];
        let mut dims = [0usize; 2];
        for k in 0..2 {
            let orders = corners.map(|(c, r)| lattice.phase(k, c, r) / TAU);
            let lo = orders.iter().copied().fold(f64::INFINITY, f64::min).ceil();
            let hi = orders
                .iter()
                .copied()
                .fold(f64::NEG_INFINITY, f64::max)
                .floor();
            if !(lo.is_finite() && hi.is_finite()) || hi < lo || hi - lo > 1e6 {
                return Err(Error::PatternNotFound(format!(
                    "grid phase {k} spans no usable range of periods over the image ({lo}..{hi})"
                )));
            }
            first[k] = lo as i64;
            dims[k] = (hi - lo) as usize + 1;
        }
        self.first = first;
        self.dims = dims;
        let [d1, d2] = dims;
        self.level.clear();
        self.level.resize(d1 * d2, f32::NAN);
        for (i, row) in self.level.chunks_exact_mut(d2.max(1)).enumerate() {
            // Walk along axis 2 from the node (i, 0).
            let (mut c, mut r) = lattice.position((first[0] + i as i64) as f64, first[1] as f64);
            let (dc, dr) = lattice.step[1];
            for v in row.iter_mut() {
                if let Some(level) = image.bilinear(c, r) {
                    *v = level;
                }
                c += dc;
                r += dr;
            }
        }
        self.contrast.clear();
        self.contrast.resize(d1 * d2, f32::NAN);
        self.background_level.clear();
        self.background_level.resize(d1 * d2, f32::NAN);
        Ok(())
    }

    /// Computes every node's contrast against the median level of its four nearest missing-dot
    /// nodes (residues `orientation.missing`).
    pub fn subtract_background(&mut self, orientation: &Orientation) {
        let [d1, d2] = self.dims;
        // Index offsets (from the first stored order) of the first missing-dot line per axis;
        // missing nodes are then every third index, starting at -3..0 to cover the border.
        let first_missing = [0, 1].map(|k| {
            let m = orientation.missing[k] as i64;
            (m - self.first[k]).rem_euclid(3) - 3
        });
        // Levels of the missing-dot nodes on the grid of every third index, padded by one on
        // each side: `grid[(a, b)]` = node (first_missing + 3a, first_missing + 3b).
        let (g1, g2) = (d1 / 3 + 3, d2 / 3 + 3);
        let mut grid = vec![f32::NAN; g1 * g2];
        for a in 0..g1 {
            for b in 0..g2 {
                let i = first_missing[0] + 3 * a as i64;
                let j = first_missing[1] + 3 * b as i64;
                if (0..d1 as i64).contains(&i) && (0..d2 as i64).contains(&j) {
                    if let (Some(slot), Some(&v)) = (
                        grid.get_mut(a * g2 + b),
                        self.level.get(i as usize * d2 + j as usize),
                    ) {
                        *slot = v;
                    }
                }
            }
        }
        for i in 0..d1 {
            let a = ((i as i64 - first_missing[0]) / 3) as usize;
            for j in 0..d2 {
                let idx = i * d2 + j;
                let Some(level) = self.level.get(idx).copied().filter(|v| v.is_finite()) else {
                    continue;
                };
                let b = ((j as i64 - first_missing[1]) / 3) as usize;
                let mut around = [0.0f32; 4];
                let mut count = 0;
                for (da, db) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    if let Some(&v) = grid.get((a + da) * g2 + b + db) {
                        if v.is_finite() {
                            around[count] = v;
                            count += 1;
                        }
                    }
                }
                let Some(background) = median(&mut around[..count]) else {
                    continue;
                };
                if let (Some(c), Some(bg)) = (
                    self.contrast.get_mut(idx),
                    self.background_level.get_mut(idx),
                ) {
                    *c = level - background;
                    *bg = background;
                }
            }
        }
    }
}

/// Pixel positions of lattice points: `(col, row) = centre + J⁻¹·(2π·n − c)`.
pub(super) struct Lattice {
    planes: [PhasePlane; 2],
    /// Image centre pixel `(C div 2, R div 2)`.
    center: (f64, f64),
    /// Pixel displacement per unit of `n1` and of `n2` (columns of `2π·J⁻¹`).
    pub(super) step: [(f64, f64); 2],
    /// Pixel position of the lattice point `n = (0, 0)`.
    origin: (f64, f64),
}

impl Lattice {
    pub(super) fn new(image: &GreyImage, planes: &[PhasePlane; 2]) -> Result<Self> {
        let [p1, p2] = planes;
        let det = p1.a * p2.b - p1.b * p2.a;
        let scale = p1.frequency() * p2.frequency();
        if !(det.is_finite() && scale > 0.0 && det.abs() > 0.05 * scale) {
            return Err(Error::PatternNotFound(
                "the two grid directions are (nearly) parallel".into(),
            ));
        }
        // J = [[a1, b1], [a2, b2]]; J⁻¹ = [[b2, −b1], [−a2, a1]]/det.
        let inv = |u: f64, v: f64| ((p2.b * u - p1.b * v) / det, (-p2.a * u + p1.a * v) / det);
        let step = [inv(TAU, 0.0), inv(0.0, TAU)];
        let (cx, cy) = image.center();
        let center = (cx as f64, cy as f64);
        let o = inv(-p1.c, -p2.c);
        Ok(Lattice {
            planes: *planes,
            center,
            step,
            origin: (center.0 + o.0, center.1 + o.1),
        })
    }

    /// Phase `k` at pixel `(col, row)`.
    fn phase(&self, k: usize, col: f64, row: f64) -> f64 {
        self.planes[k.min(1)].at(col - self.center.0, row - self.center.1)
    }

    /// Pixel position `(col, row)` of the lattice point with (fractional) orders `(n1, n2)`.
    pub(super) fn position(&self, n1: f64, n2: f64) -> (f64, f64) {
        (
            self.origin.0 + n1 * self.step[0].0 + n2 * self.step[1].0,
            self.origin.1 + n1 * self.step[0].1 + n2 * self.step[1].1,
        )
    }
}
