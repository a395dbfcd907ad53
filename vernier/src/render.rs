//! Synthetic images of any layout at a known pose: the ground truth of the tests
//! (docs/design.md#rendering).
//!
//! Orthographic camera: pixel `(col, row)` is centred on image coordinates `(col, row)` and the
//! camera frame origin is the centre pixel `(C div 2, R div 2)` (as the detectors assume).
//! Two sampling models:
//! * [`Sampling::Area`] (default): each pixel is the exact fraction of its square footprint
//!   covered by the layout's rectangles (dots and solid features), i.e. a perfect box-filtered
//!   image of the fabricated marker;
//! * [`Sampling::Point`]: the layout's analytic intensity at the pixel centre, as the original's
//!   renderer does (raised-cosine dots).
//!
//! Then optional Gaussian blur (optics), additive Gaussian noise and quantisation.

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::layout::{Layout, Rect};
use crate::limits;
use crate::pose::Pose;
use nalgebra::{Matrix2, Point2, Vector2};

/// How pixels sample the layout.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Sampling {
    /// Exact area coverage of the pixel footprint by the layout rectangles.
    #[default]
    Area,
    /// Analytic intensity at the pixel centre (original renderer).
    Point,
}

/// Camera and image-formation settings of a synthetic render.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderOptions {
    /// Image width, pixels (≥ 1).
    pub width: usize,
    /// Image height, pixels (≥ 1).
    pub height: usize,
    /// Sampling model.
    pub sampling: Sampling,
    /// Gaussian blur σ, pixels (0 = none).
    pub blur_sigma: f64,
    /// Standard deviation of additive Gaussian noise, as a fraction of full scale (0.01 = 1 %).
    pub noise_std: f64,
    /// Quantise to this many bits (1..=16) after noise; `None` keeps floating point values.
    pub bit_depth: Option<u32>,
    /// Grey level of the background, `[0, 1]`.
    pub background: f32,
    /// Grey level of the dots, `[0, 1]` (below `background` for dark-dot images).
    pub foreground: f32,
    /// Seed of the noise generator (same seed, same image).
    pub seed: u64,
}

impl RenderOptions {
    /// Noise-free, unquantised, area-sampled `width × height` render, bright dots (1) on black.
    pub fn new(width: usize, height: usize) -> Self {
        RenderOptions {
            width,
            height,
            sampling: Sampling::Area,
            blur_sigma: 0.0,
            noise_std: 0.0,
            bit_depth: None,
            background: 0.0,
            foreground: 1.0,
            seed: 0,
        }
    }
}

/// Renders one layout at `pose` (orthographic; `pose.pixel_size` sets the scale).
pub fn render(layout: &dyn Layout, pose: &Pose, options: &RenderOptions) -> Result<GreyImage> {
    render_scene(&[(layout, *pose)], options)
}

/// Renders several layouts, each at its own pose, into one image (coverages add, clamped to 1).
pub fn render_scene(items: &[(&dyn Layout, Pose)], options: &RenderOptions) -> Result<GreyImage> {
    check_options(options)?;
    let (w, h) = (options.width, options.height);
    // Optical blur acts before the pixels integrate light: render on a grid `SUPERSAMPLING`
    // times finer, blur there, then bin back to pixels (box = pixel area).
    let factor = if options.blur_sigma > 0.0 {
        SUPERSAMPLING
    } else {
        1
    };
    let (fw, fh) = (w * factor, h * factor);
    let mut coverage = vec![0.0f32; fw * fh];
    for (layout, pose) in items {
        check_period(*layout, pose)?;
        // Same camera frame on the fine grid: centre pixel (C div 2, R div 2) maps to the centre
        // of the fine cell block of that pixel.
        let fine_pose = Pose {
            pixel_size: pose.pixel_size / factor as f64,
            ..*pose
        };
        // Pixel c spans fine cells c·f .. c·f + f − 1, its centre at c·f + (f − 1)/2.
        let shift = |n: usize| {
            ((n / 2) * factor) as f64 + (factor as f64 - 1.0) / 2.0 - ((n * factor) / 2) as f64
        };
        let center_shift = Vector2::new(shift(w), shift(h));
        render_layout(
            *layout,
            &fine_pose,
            (fw, fh),
            center_shift,
            options.sampling,
            &mut coverage,
        )?;
    }
    if factor > 1 {
        gaussian_blur(&mut coverage, fw, fh, options.blur_sigma * factor as f64);
        coverage = bin(&coverage, fw, factor, w, h);
    }
    finish_pixels(coverage, w, h, options)
}

/// Rejects a render size, bit depth, blur or noise outside the limits (the limit named).
fn check_options(options: &RenderOptions) -> Result<()> {
    let (w, h) = (options.width, options.height);
    if w == 0 || h == 0 {
        return Err(Error::parameter(
            "size",
            format!("render size must be positive, got {w}x{h}"),
        ));
    }
    let (max_side, max_pixels) = (limits::MAX_RENDER_SIDE, limits::MAX_RENDER_PIXELS);
    if w > max_side || h > max_side || (w as u64).saturating_mul(h as u64) > max_pixels {
        return Err(Error::parameter(
            "size",
            format!(
                "render size {w}x{h} is above the limit of {max_side} pixels per side and {}",
                limits::megapixels(max_pixels)
            ),
        ));
    }
    if let Some(bits) = options.bit_depth {
        if !(1..=16).contains(&bits) {
            return Err(Error::parameter(
                "bit_depth",
                format!("must be in 1..=16, got {bits}"),
            ));
        }
    }
    if !(0.0..=limits::MAX_BLUR_SIGMA).contains(&options.blur_sigma) {
        return Err(Error::parameter(
            "blur_sigma",
            format!(
                "must be in [0, {}] pixels, got {}",
                limits::MAX_BLUR_SIGMA,
                options.blur_sigma
            ),
        ));
    }
    if !(0.0..=limits::MAX_NOISE_STD).contains(&options.noise_std) {
        return Err(Error::parameter(
            "noise_std",
            format!(
                "must be in [0, {}] (fraction of full scale), got {}",
                limits::MAX_NOISE_STD,
                options.noise_std
            ),
        ));
    }
    if options.blur_sigma > 0.0
        && (w as u64 * h as u64).saturating_mul((SUPERSAMPLING * SUPERSAMPLING) as u64)
            > MAX_FINE_SAMPLES
    {
        return Err(Error::parameter(
            "blur_sigma",
            format!(
                "a blurred render is computed on a {SUPERSAMPLING}× finer grid: {w}x{h} is above \
                 the limit of {} for blurred renders",
                limits::megapixels(MAX_FINE_SAMPLES / (SUPERSAMPLING * SUPERSAMPLING) as u64)
            ),
        ));
    }
    Ok(())
}

/// Rejects a pose whose period is below [`limits::MIN_RENDER_PERIOD_PX`] pixels.
fn check_period(layout: &dyn Layout, pose: &Pose) -> Result<()> {
    let period_px = layout.period() / pose.pixel_size;
    if period_px.is_nan() || period_px < limits::MIN_RENDER_PERIOD_PX {
        return Err(Error::parameter(
            "pixel_size",
            format!(
                "the period ({} pattern units) is {period_px:e} pixels at pixel size {}: \
                 renders need at least {} pixels per period",
                layout.period(),
                pose.pixel_size,
                limits::MIN_RENDER_PERIOD_PX
            ),
        ));
    }
    Ok(())
}

/// The image from the coverage map: grey levels, then noise and quantisation if asked.
fn finish_pixels(
    coverage: Vec<f32>,
    w: usize,
    h: usize,
    options: &RenderOptions,
) -> Result<GreyImage> {
    let (bg, fg) = (options.background, options.foreground);
    let mut pixels: Vec<f32> = coverage
        .iter()
        .map(|&c| bg + (fg - bg) * c.min(1.0))
        .collect();
    if options.noise_std > 0.0 {
        let mut rng = SplitMix64(options.seed ^ 0x005e_ed0f_be11);
        for v in pixels.iter_mut() {
            *v += (options.noise_std * rng.gaussian()) as f32;
        }
    }
    if let Some(bits) = options.bit_depth {
        let levels = ((1u32 << bits) - 1) as f32;
        for v in pixels.iter_mut() {
            *v = (v.clamp(0.0, 1.0) * levels).round() / levels;
        }
    }
    GreyImage::new(w, h, pixels)
}

/// Supersampling factor used when an optical blur is rendered.
const SUPERSAMPLING: usize = 4;

/// Largest supersampled grid of a blurred render, samples (800 MB of `f32`).
const MAX_FINE_SAMPLES: u64 = 200_000_000;

/// Mean of each `factor × factor` block of a `fine_w`-wide image, giving `w × h` pixels.
fn bin(fine: &[f32], fine_w: usize, factor: usize, w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; w * h];
    let norm = 1.0 / (factor * factor) as f32;
    for r in 0..h {
        for c in 0..w {
            let mut s = 0.0;
            for dr in 0..factor {
                let row = &fine[(r * factor + dr) * fine_w + c * factor..];
                s += row[..factor].iter().sum::<f32>();
            }
            out[r * w + c] = s * norm;
        }
    }
    out
}

/// Adds one layout's coverage (or point intensity) into `coverage`.
fn render_layout(
    layout: &dyn Layout,
    pose: &Pose,
    (w, h): (usize, usize),
    center_shift: Vector2<f64>,
    sampling: Sampling,
    coverage: &mut [f32],
) -> Result<()> {
    let (a_inv, t) = pattern_from_pixel(pose, (w, h), center_shift)?;
    // Half-pixel steps of the footprint in pattern coordinates, and its bounding half-extent.
    let e1 = a_inv * Vector2::new(0.5, 0.0);
    let e2 = a_inv * Vector2::new(0.0, 0.5);
    let half_extent = Vector2::new(e1.x.abs() + e2.x.abs(), e1.y.abs() + e2.y.abs());
    let footprint_area = 4.0 * (e1.x * e2.y - e1.y * e2.x).abs();
    let bounds = layout.bounds();
    let mut rects: Vec<Rect> = Vec::new();
    for row in 0..h {
        for col in 0..w {
            let p = a_inv * (Vector2::new(col as f64, row as f64) - t);
            let value = match sampling {
                Sampling::Point => layout.intensity(p.x, p.y),
                Sampling::Area => {
                    let bbox = Rect::new(
                        p.x - half_extent.x,
                        p.y - half_extent.y,
                        2.0 * half_extent.x,
                        2.0 * half_extent.y,
                    );
                    if !bbox.overlaps(&bounds) {
                        continue;
                    }
                    rects.clear();
                    layout.visit_rects(&bbox, &mut |r| rects.push(r));
                    let corners = [p - e1 - e2, p + e1 - e2, p + e1 + e2, p - e1 + e2]
                        .map(|v| Point2::new(v.x, v.y));
                    let covered: f64 = rects
                        .iter()
                        .map(|r| {
                            if r.x <= bbox.x
                                && r.y <= bbox.y
                                && r.right() >= bbox.right()
                                && r.bottom() >= bbox.bottom()
                            {
                                footprint_area
                            } else {
                                clipped_area(&corners, r)
                            }
                        })
                        .sum();
                    covered / footprint_area
                }
            };
            coverage[row * w + col] += value as f32;
        }
    }
    Ok(())
}

/// The inverse `A⁻¹` of the orthographic projection pattern → pixel `pixel = A·p + t`, and
/// `t`, on a `w × h` grid whose centre is shifted by `center_shift`.
fn pattern_from_pixel(
    pose: &Pose,
    (w, h): (usize, usize),
    center_shift: Vector2<f64>,
) -> Result<(Matrix2<f64>, Vector2<f64>)> {
    if !(pose.pixel_size.is_finite() && pose.pixel_size > 0.0) {
        return Err(Error::parameter(
            "pixel_size",
            format!("must be > 0, got {}", pose.pixel_size),
        ));
    }
    // Orthographic projection pattern → pixel: pixel = A·p + t (columns 1, 2, 4 of cTp).
    // Angles wrapped exactly into [−π, π) first: a huge angle (1e15 rad) draws the same image as
    // its wrapped value, whichever trigonometric path the pose takes.
    let wrap = crate::phase::wrap_angle;
    let pose = &Pose {
        alpha: wrap(pose.alpha),
        beta: wrap(pose.beta),
        gamma: wrap(pose.gamma),
        ..*pose
    };
    let t_cp = pose.camera_from_pattern().to_homogeneous();
    let s = 1.0 / pose.pixel_size;
    let a = Matrix2::new(
        s * t_cp[(0, 0)],
        s * t_cp[(0, 1)],
        s * t_cp[(1, 0)],
        s * t_cp[(1, 1)],
    );
    let center = Vector2::new((w / 2) as f64, (h / 2) as f64) + center_shift;
    let t = Vector2::new(s * t_cp[(0, 3)], s * t_cp[(1, 3)]) + center;
    let a_inv = a.try_inverse().ok_or_else(|| {
        Error::parameter(
            "pose",
            "the pattern plane is seen edge-on (singular projection)",
        )
    })?;
    Ok((a_inv, t))
}

/// Area of the convex quadrilateral `quad` clipped to the axis-aligned rectangle `r`
/// (Sutherland–Hodgman against the four edges, then the shoelace formula).
fn clipped_area(quad: &[Point2<f64>; 4], r: &Rect) -> f64 {
    let mut poly: Vec<Point2<f64>> = quad.to_vec();
    let mut next: Vec<Point2<f64>> = Vec::with_capacity(8);
    // Each edge: (axis, bound, keep_greater).
    let edges = [
        (0usize, r.x, true),
        (0, r.right(), false),
        (1, r.y, true),
        (1, r.bottom(), false),
    ];
    for (axis, bound, keep_greater) in edges {
        next.clear();
        let inside = |p: &Point2<f64>| {
            if keep_greater {
                p[axis] >= bound
            } else {
                p[axis] <= bound
            }
        };
        for i in 0..poly.len() {
            let (cur, prev) = (poly[i], poly[(i + poly.len() - 1) % poly.len()]);
            let (cur_in, prev_in) = (inside(&cur), inside(&prev));
            if cur_in != prev_in {
                let t = (bound - prev[axis]) / (cur[axis] - prev[axis]);
                next.push(prev + (cur - prev) * t);
            }
            if cur_in {
                next.push(cur);
            }
        }
        std::mem::swap(&mut poly, &mut next);
        if poly.is_empty() {
            return 0.0;
        }
    }
    let mut twice_area = 0.0;
    for i in 0..poly.len() {
        let (p, q) = (poly[i], poly[(i + 1) % poly.len()]);
        twice_area += p.x * q.y - q.x * p.y;
    }
    twice_area.abs() / 2.0
}

/// Separable Gaussian blur, σ in pixels, edges replicated.
pub(crate) fn gaussian_blur(pixels: &mut [f32], w: usize, h: usize, sigma: f64) {
    let radius = (4.0 * sigma).ceil() as i64;
    let kernel: Vec<f32> = (-radius..=radius)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let norm: f32 = kernel.iter().sum();
    let kernel: Vec<f32> = kernel.iter().map(|k| k / norm).collect();
    let mut tmp = vec![0.0f32; w * h];
    for r in 0..h {
        for c in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let cc = (c as i64 + k as i64 - radius).clamp(0, w as i64 - 1) as usize;
                s += kv * pixels[r * w + cc];
            }
            tmp[r * w + c] = s;
        }
    }
    for r in 0..h {
        for c in 0..w {
            let mut s = 0.0;
            for (k, kv) in kernel.iter().enumerate() {
                let rr = (r as i64 + k as i64 - radius).clamp(0, h as i64 - 1) as usize;
                s += kv * tmp[rr * w + c];
            }
            pixels[r * w + c] = s;
        }
    }
}

/// Small deterministic generator (SplitMix64) with Box–Muller Gaussian samples; keeps the
/// library free of an RNG dependency.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }
    /// Uniform in (0, 1].
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64
    }
    fn gaussian(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::PeriodicLayout;

    #[test]
    fn clipped_area_of_squares() {
        let quad = [
            Point2::new(0.0, 0.0),
            Point2::new(2.0, 0.0),
            Point2::new(2.0, 2.0),
            Point2::new(0.0, 2.0),
        ];
        assert!((clipped_area(&quad, &Rect::new(1.0, 1.0, 5.0, 5.0)) - 1.0).abs() < 1e-12);
        assert!((clipped_area(&quad, &Rect::new(-1.0, -1.0, 5.0, 5.0)) - 4.0).abs() < 1e-12);
        assert_eq!(clipped_area(&quad, &Rect::new(3.0, 3.0, 1.0, 1.0)), 0.0);
        let diamond = [
            Point2::new(1.0, 0.0),
            Point2::new(2.0, 1.0),
            Point2::new(1.0, 2.0),
            Point2::new(0.0, 1.0),
        ];
        assert!((clipped_area(&diamond, &Rect::new(1.0, 0.0, 5.0, 5.0)) - 1.0).abs() < 1e-12);
    }

    #[test]
    fn area_render_conserves_dot_area() {
        // 5 px dots at period 10 px: a quarter of the covered region is bright, whatever the pose.
        let layout = PeriodicLayout::new(10.0, 41, 41).unwrap();
        for (alpha, x) in [(0.0, 0.0), (0.37, 1.3), (-2.0, -4.1)] {
            let img = render(
                &layout,
                &Pose::planar(x, 2.0, alpha, 1.0),
                &RenderOptions::new(100, 100),
            )
            .unwrap();
            let mean: f64 = img.pixels().iter().map(|&v| v as f64).sum::<f64>() / 10_000.0;
            assert!((mean - 0.25).abs() < 0.01, "alpha {alpha}: mean {mean}");
        }
    }

    #[test]
    fn pattern_origin_lands_where_the_pose_says() {
        let layout = PeriodicLayout::new(8.0, 41, 41).unwrap();
        let pose = Pose::planar(4.0, 0.0, 0.0, 1.0);
        let img = render(&layout, &pose, &RenderOptions::new(64, 64)).unwrap();
        // The central dot (4 px wide) is centred 4 px right of the centre pixel (32, 32).
        assert_eq!(img.get(36, 32), Some(1.0));
        assert_eq!(img.get(32, 32), Some(0.0));
    }

    #[test]
    fn noise_is_deterministic_and_quantised() {
        let layout = PeriodicLayout::new(8.0, 41, 41).unwrap();
        let mut opts = RenderOptions::new(32, 32);
        opts.noise_std = 0.01;
        opts.bit_depth = Some(12);
        opts.seed = 7;
        let a = render(&layout, &Pose::planar(0.0, 0.0, 0.1, 1.0), &opts).unwrap();
        let b = render(&layout, &Pose::planar(0.0, 0.0, 0.1, 1.0), &opts).unwrap();
        assert_eq!(a, b);
        assert!(a
            .pixels()
            .iter()
            .all(|v| (v * 4095.0 - (v * 4095.0).round()).abs() < 1e-3));
    }
}
