//! Floating-point rasters: marker tiles rendered by `vernier::render` and pasted into a scene,
//! Gaussian blur, the supersampled perspective warp and anti-aliased drawing primitives.

use crate::error::{Result, StressError};
use crate::geometry::{rotate, Homography, OrientedRect};
use nalgebra::Vector2;
use vernier::layout::Layout;
use vernier::render::{render, RenderOptions};
use vernier::Pose;

/// A row-major `f32` raster, pixel `(col, row)` centred on coordinates `(col, row)`.
#[derive(Clone, Debug, PartialEq)]
pub struct Plane {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width·height` values, row-major.
    pub data: Vec<f32>,
}

impl Plane {
    /// A `width × height` raster filled with `value`.
    pub fn filled(width: usize, height: usize, value: f32) -> Self {
        Plane {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    /// Bilinear sample at `(x, y)`; `fill` outside the pixel centres' hull.
    pub fn bilinear(&self, x: f64, y: f64, fill: f32) -> f32 {
        if !(x >= 0.0 && y >= 0.0) {
            return fill;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        if x0 + 1 >= self.width || y0 + 1 >= self.height {
            // The last row / column: exact hits only.
            if x0 < self.width && y0 < self.height && x == x0 as f64 && y == y0 as f64 {
                return self.data[y0 * self.width + x0];
            }
            return fill;
        }
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let i = y0 * self.width + x0;
        let top = self.data[i] * (1.0 - fx) + self.data[i + 1] * fx;
        let bottom = self.data[i + self.width] * (1.0 - fx) + self.data[i + self.width + 1] * fx;
        top * (1.0 - fy) + bottom * fy
    }

    /// Separable Gaussian blur of standard deviation `sigma` pixels, edges replicated
    /// (no-op below 0.05 px).
    pub fn blur(&mut self, sigma: f64) {
        gaussian_blur(&mut self.data, self.width, self.height, sigma);
    }

    /// Composites `alpha` (same size, `[0, 1]`) towards `target`: `v ← v·(1−a) + target·a`.
    pub fn composite(&mut self, alpha: &Plane, target: f32) {
        for (v, &a) in self.data.iter_mut().zip(&alpha.data) {
            if a > 0.0 {
                *v = *v * (1.0 - a) + target * a;
            }
        }
    }

    /// Sets every pixel to the maximum of itself and `value(local)` inside `rect`, where
    /// `local` is the pixel centre in the rectangle's own frame.
    pub fn paint_rect(&mut self, rect: &OrientedRect, value: &mut dyn FnMut(Vector2<f64>) -> f32) {
        let bh = rect.bounding_half();
        let Some((c0, c1, r0, r1)) = self.clip(rect.center, bh + Vector2::new(1.0, 1.0)) else {
            return;
        };
        for r in r0..=r1 {
            for c in c0..=c1 {
                let l = rect.local(Vector2::new(c as f64, r as f64));
                if l.x.abs() <= rect.half.x + 0.5 && l.y.abs() <= rect.half.y + 0.5 {
                    let v = value(l);
                    let px = &mut self.data[r * self.width + c];
                    *px = px.max(v);
                }
            }
        }
    }

    /// Anti-aliased thick segment from `a` to `b` (half width `half_width` pixels), painted
    /// as `max(current, value·coverage)`.
    pub fn draw_segment(&mut self, a: Vector2<f64>, b: Vector2<f64>, half_width: f64, value: f32) {
        let center = (a + b) / 2.0;
        let reach = Vector2::new((a.x - b.x).abs(), (a.y - b.y).abs()) / 2.0
            + Vector2::new(half_width + 1.5, half_width + 1.5);
        let Some((c0, c1, r0, r1)) = self.clip(center, reach) else {
            return;
        };
        let d = b - a;
        let len2 = d.norm_squared().max(1e-12);
        for r in r0..=r1 {
            for c in c0..=c1 {
                let p = Vector2::new(c as f64, r as f64);
                let t = ((p - a).dot(&d) / len2).clamp(0.0, 1.0);
                let dist = (p - (a + d * t)).norm();
                let cover = (half_width + 0.5 - dist).clamp(0.0, 1.0) as f32;
                if cover > 0.0 {
                    let px = &mut self.data[r * self.width + c];
                    *px = px.max(value * cover);
                }
            }
        }
    }

    /// Soft disc of radius `radius` and edge width `soft` pixels, painted as
    /// `max(current, value·coverage)`.
    pub fn draw_disc(&mut self, center: Vector2<f64>, radius: f64, soft: f64, value: f32) {
        let reach = radius + soft + 1.0;
        let Some((c0, c1, r0, r1)) = self.clip(center, Vector2::new(reach, reach)) else {
            return;
        };
        let soft = soft.max(0.5);
        for r in r0..=r1 {
            for c in c0..=c1 {
                let dist = (Vector2::new(c as f64, r as f64) - center).norm();
                let cover = ((radius - dist) / soft + 0.5).clamp(0.0, 1.0) as f32;
                if cover > 0.0 {
                    let px = &mut self.data[r * self.width + c];
                    *px = px.max(value * cover);
                }
            }
        }
    }

    /// Pixel index range `(c0, c1, r0, r1)` (inclusive) of the box `center ± half`, clipped
    /// to the raster; `None` when they do not meet.
    fn clip(
        &self,
        center: Vector2<f64>,
        half: Vector2<f64>,
    ) -> Option<(usize, usize, usize, usize)> {
        let lo = center - half;
        let hi = center + half;
        if !(hi.x >= 0.0 && hi.y >= 0.0 && lo.x < self.width as f64 && lo.y < self.height as f64) {
            return None;
        }
        let c0 = lo.x.floor().max(0.0) as usize;
        let r0 = lo.y.floor().max(0.0) as usize;
        let c1 = (hi.x.ceil() as usize).min(self.width - 1);
        let r1 = (hi.y.ceil() as usize).min(self.height - 1);
        Some((c0, c1, r0, r1))
    }
}

/// Separable Gaussian blur of a `w × h` row-major buffer, σ in pixels, edges replicated.
pub fn gaussian_blur(pixels: &mut [f32], w: usize, h: usize, sigma: f64) {
    if sigma.is_nan() || sigma < 0.05 || w == 0 || h == 0 {
        return;
    }
    let radius = (4.0 * sigma).ceil() as usize;
    let mut kernel: Vec<f32> = (0..=2 * radius)
        .map(|i| {
            let d = i as f64 - radius as f64;
            (-(d * d) / (2.0 * sigma * sigma)).exp() as f32
        })
        .collect();
    let norm: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= norm);
    let mut line = vec![0.0f32; w.max(h) + 2 * radius];
    // Rows.
    for r in 0..h {
        let row = &mut pixels[r * w..(r + 1) * w];
        for (i, v) in line.iter_mut().take(w + 2 * radius).enumerate() {
            *v = row[(i as i64 - radius as i64).clamp(0, w as i64 - 1) as usize];
        }
        for (c, out) in row.iter_mut().enumerate() {
            *out = kernel
                .iter()
                .zip(&line[c..c + 2 * radius + 1])
                .map(|(k, v)| k * v)
                .sum();
        }
    }
    // Columns.
    let mut column = vec![0.0f32; h];
    for c in 0..w {
        for (i, v) in line.iter_mut().take(h + 2 * radius).enumerate() {
            *v = pixels[(i as i64 - radius as i64).clamp(0, h as i64 - 1) as usize * w + c];
        }
        for (r, out) in column.iter_mut().enumerate() {
            *out = kernel
                .iter()
                .zip(&line[r..r + 2 * radius + 1])
                .map(|(k, v)| k * v)
                .sum();
        }
        for (r, v) in column.iter().enumerate() {
            pixels[r * w + c] = *v;
        }
    }
}

/// Supersampling factor of a marker tile: enough fine pixels per period that the optical blur
/// acts before pixel integration where it matters (small periods), 1 for coarse grids.
fn tile_factor(period_px: f64) -> usize {
    if period_px < 8.0 {
        4
    } else if period_px < 20.0 {
        2
    } else {
        1
    }
}

/// Adds the coverage of `layout`, whose pattern origin lies at pixel `origin` with direction
/// `alpha` and `pixel_size` pattern units per pixel, into `canvas`; `mirrored`: seen from its
/// back (a half turn about the pattern's x axis, `gamma = π`: its y axis points the other
/// way).
///
/// Same image formation as `vernier::render` with an optical blur (area sampling on a grid
/// `F` times finer, Gaussian blur of `blur_sigma` pixels there, `F × F` binning), on a tile
/// covering only the marker (plus a blur margin) and with `F` chosen from the period; parts
/// outside the canvas are dropped.
pub fn add_marker(
    canvas: &mut Plane,
    layout: &dyn Layout,
    origin: Vector2<f64>,
    alpha: f64,
    pixel_size: f64,
    blur_sigma: f64,
    mirrored: bool,
) -> Result<()> {
    if !(pixel_size.is_finite() && pixel_size > 0.0) {
        return Err(StressError::new(format!("pixel size {pixel_size}")));
    }
    let b = layout.bounds();
    let mut lo = Vector2::new(f64::INFINITY, f64::INFINITY);
    let mut hi = Vector2::new(f64::NEG_INFINITY, f64::NEG_INFINITY);
    for (x, y) in [
        (b.x, b.y),
        (b.right(), b.y),
        (b.x, b.bottom()),
        (b.right(), b.bottom()),
    ] {
        let y = if mirrored { -y } else { y };
        let p = origin + rotate(Vector2::new(x, y), alpha) / pixel_size;
        lo = lo.inf(&p);
        hi = hi.sup(&p);
    }
    let margin = (4.0 * blur_sigma).ceil() + 3.0;
    let (w, h) = (canvas.width as i64, canvas.height as i64);
    let ox = ((lo.x - margin).floor() as i64).max(0);
    let oy = ((lo.y - margin).floor() as i64).max(0);
    let ex = ((hi.x + margin).ceil() as i64).min(w - 1);
    let ey = ((hi.y + margin).ceil() as i64).min(h - 1);
    if ex < ox || ey < oy {
        return Ok(());
    }
    let (tw, th) = ((ex - ox + 1) as usize, (ey - oy + 1) as usize);
    let f = tile_factor(layout.period() / pixel_size);
    let (fw, fh) = (tw * f, th * f);
    // Fine pixel i is centred at coarse x = ox + (i + ½)/F − ½; the renderer's camera origin is
    // the fine centre pixel (fw div 2, fh div 2).
    let fine = |p: f64, o: i64, n: usize| f as f64 * (p - o as f64 + 0.5) - 0.5 - (n / 2) as f64;
    let offset = Vector2::new(fine(origin.x, ox, fw), fine(origin.y, oy, fh));
    let pose = Pose::from_origin_in_image(offset, alpha, pixel_size / f as f64);
    // Rx(π) turns pattern (x, y) into (x, −y): the same origin needs y of the other sign.
    let pose = if mirrored {
        Pose {
            y: -pose.y,
            gamma: std::f64::consts::PI,
            ..pose
        }
    } else {
        pose
    };
    let mut tile = render(layout, &pose, &RenderOptions::new(fw, fh))?
        .pixels()
        .to_vec();
    gaussian_blur(&mut tile, fw, fh, blur_sigma * f as f64);
    let norm = 1.0 / (f * f) as f32;
    for r in 0..th {
        let dst = (oy as usize + r) * canvas.width + ox as usize;
        for c in 0..tw {
            let mut s = 0.0f32;
            for dr in 0..f {
                let row = (r * f + dr) * fw + c * f;
                s += tile[row..row + f].iter().sum::<f32>();
            }
            canvas.data[dst + c] += s * norm;
        }
    }
    Ok(())
}

/// `source` (the marker plane) as seen through `homography`: each output pixel averages
/// `samples × samples` bilinear samples of the plane at the preimages of points spread over
/// its footprint; `fill` where the preimage leaves the plane raster.
pub fn warp(source: &Plane, homography: &Homography, samples: usize, fill: f32) -> Plane {
    warp_into(
        source,
        homography,
        samples,
        fill,
        (source.width, source.height),
    )
}

/// [`warp`] onto a `size = (width, height)` raster (the homography's image frame).
pub fn warp_into(
    source: &Plane,
    homography: &Homography,
    samples: usize,
    fill: f32,
    size: (usize, usize),
) -> Plane {
    let m = homography.inverse_matrix();
    let n = samples.max(1);
    let offsets: Vec<f64> = (0..n).map(|i| (i as f64 + 0.5) / n as f64 - 0.5).collect();
    let norm = 1.0 / (n * n) as f32;
    let mut out = Plane::filled(size.0, size.1, fill);
    for r in 0..size.1 {
        for c in 0..size.0 {
            let mut s = 0.0f32;
            for dy in &offsets {
                for dx in &offsets {
                    let (x, y) = (c as f64 + dx, r as f64 + dy);
                    let z = m[2][0] * x + m[2][1] * y + m[2][2];
                    s += if z > 1e-9 {
                        let u = (m[0][0] * x + m[0][1] * y + m[0][2]) / z;
                        let v = (m[1][0] * x + m[1][1] * y + m[1][2]) / z;
                        source.bilinear(u, v, fill)
                    } else {
                        fill
                    };
                }
            }
            out.data[r * size.0 + c] = s * norm;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use vernier::layout::HpCodeLayout;

    #[test]
    fn blur_keeps_the_mean_and_a_constant() {
        let mut p = Plane::filled(20, 10, 0.25);
        p.blur(1.3);
        assert!(p.data.iter().all(|v| (v - 0.25).abs() < 1e-6));
        let mut q = Plane::filled(21, 21, 0.0);
        q.data[10 * 21 + 10] = 1.0;
        q.blur(1.0);
        let sum: f32 = q.data.iter().sum();
        assert!((sum - 1.0).abs() < 1e-4, "{sum}");
    }

    #[test]
    fn tile_equals_full_render_without_blur() -> Result<()> {
        let layout = HpCodeLayout::from_code_size(10.0, 33)?.with_id(5)?;
        let (w, h) = (181, 170);
        let origin = Vector2::new(92.3, 81.7);
        let ps = 10.0 / 4.5;
        let full = render(
            &layout,
            &Pose::from_origin_in_image(origin - Vector2::new(90.0, 85.0), 0.4, ps),
            &RenderOptions::new(w, h),
        )?;
        // Period 4.5 px: the tile is rendered 4× finer and binned; exact coverage either way.
        let mut canvas = Plane::filled(w, h, 0.0);
        add_marker(&mut canvas, &layout, origin, 0.4, ps, 0.0, false)?;
        let worst = full
            .pixels()
            .iter()
            .zip(&canvas.data)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-4, "{worst}");
        Ok(())
    }

    #[test]
    fn identity_warp_is_nearly_the_source() {
        let mut p = Plane::filled(30, 30, 0.0);
        p.draw_disc(Vector2::new(15.0, 15.0), 6.0, 1.0, 1.0);
        let q = warp(&p, &Homography::identity(), 1, 0.0);
        assert_eq!(p.data[..29 * 30], q.data[..29 * 30]);
    }
}
