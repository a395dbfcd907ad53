//! The Cramér–Rao bound of a marker's position in a scene: the least position error any
//! unbiased estimator can reach on that image, whatever its method.
//!
//! It is computed where the image is the marker's render plus independent sensor noise and
//! nothing else that hides information in a way the bound cannot state: no perspective,
//! colour cast, dust or hair (see [`kind`]). Then the Fisher information of the marker's
//! `(x, y, alpha, pixel size)` is `F = Σ_pixels J Jᵀ / σ²`, with
//!
//! * `J` the derivatives of the clean pixel value: `(fg − bg) · gain · ∂coverage/∂θ`, the
//!   coverage rendered by [`add_marker`] (the scene's own image formation) at `θ ± h`, central
//!   differences (steps moving the marker by 0.01 px, at its border for alpha and scale);
//! * `σ = gaussian + shot·√v` the scene's sensor noise at the clean value `v` (what
//!   [`crate::degrade::finish`] draws).
//!
//! The bound is `(F⁻¹)ₓₓ + (F⁻¹)ᵧᵧ`, the least mean square of the radial position error, with
//! angle and scale as unknowns alongside (hence the full inverse). Everything else is taken as
//! known (the dot shape, grey levels, blur, illumination), and the quantisation and the
//! clipping at 0 and 1 are left out: each only removes information, so the figure stays a
//! lower bound for every unbiased estimator, the detector included.
//!
//! **JPEG: a model, not a bound.** A grey JPEG file quantises each 8 × 8 block's orthonormal
//! DCT coefficient `(u, v)` with the step `Q_uv` of its quality's luminance table (ITU T.81
//! Annex K.1 scaled as libjpeg does, as the `image` crate's encoder does). Taking that rounding
//! as independent uniform noise of variance `Q_uv²/12` per coefficient (the additive model of
//! quantisation, Widrow & Kollár, *Quantization Noise*, 2008), beside the sensor noise (white,
//! so the same variance on every coefficient) and the 8-bit rounding before it, gives the same
//! Fisher sum over coefficients instead of pixels ([`BoundKind::JpegModel`]). The rounding is
//! deterministic, so no Cramér–Rao bound holds for it; the model says how much of the dots'
//! signal the file keeps at each frequency, and errors far above its figure point at the
//! estimator, errors near it at the file. It overstates what a coefficient rounded to zero
//! still says (nothing, to small moves).
//!
//! **Two reference estimators on each JPEG file** ([`KnownShapeErrors`]) test the model
//! against the file itself: least squares that know everything but the pose (dot shape, grey
//! levels, blur, illumination), one Gauss–Newton step from the true pose (`δ = A⁻¹ Jᵀ W e`,
//! `e` the file's pixels minus the clean render; exact to first order, and the errors are
//! ~1e-3 px). One weighs every pixel alike, as the detector's fit does; the other weighs each
//! block's DCT coefficient by the model's variance, as generalised least squares under the
//! model would. The weighted one reaching `M` on the actual files says that the model's
//! figure is there to take, by an estimator that knows the file's table and the dots' shape.
//!
//! An estimator at the bound has a radial error with `P(|e| > r) = exp(−r²/B²)` (`B²` the
//! bound; the two axes' variances nearly equal on these square markers), so its p99 over a
//! set of markers solves `mean exp(−r²/Bᵢ²) = 0.01` ([`efficient_quantile`]).

use crate::degrade::{Degradations, Noise};
use crate::error::Result;
use crate::markers::Placed;
use crate::raster::{add_marker, Plane};
use nalgebra::{Matrix4, Vector2, Vector4, Vector5};
use vernier::layout::Layout;
use vernier::GreyImage;

/// Marker shift of the central differences, pixels (at its border for alpha and scale).
const STEP_PX: f64 = 0.01;

/// What a marker's figure is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoundKind {
    /// The Cramér–Rao bound: the render plus independent sensor noise.
    CramerRao,
    /// A grey JPEG file, its rounding taken as additive noise per DCT coefficient: an
    /// estimate, not a bound (see the module's documentation).
    JpegModel,
}

/// A marker's position bound.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PositionBound {
    /// `B`, the least RMS radial error of its origin, pixels.
    pub px: f64,
    /// What `B` is.
    pub kind: BoundKind,
    /// The reference estimators' errors on the file ([`BoundKind::JpegModel`] with the image
    /// given, [`Formation::observed`]).
    pub known_shape: Option<KnownShapeErrors>,
}

/// The radial origin errors (pixels) of the two reference estimators on one marker of a grey
/// JPEG file: least squares that know the dot shape, grey levels and blur, linearised about
/// the true pose (module documentation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KnownShapeErrors {
    /// Every pixel weighted alike.
    pub unweighted: f64,
    /// Each block's DCT coefficient weighted by the model's variance.
    pub weighted: f64,
}

/// Which figure a scene's markers have, if any: none with perspective, a colour cast, dust or
/// hair (blur, illumination, low contrast and clutter beside the markers keep the image an
/// affine function of each marker's coverage plus noise); the JPEG model for a grey JPEG file;
/// the Cramér–Rao bound for sensor noise alone.
pub fn kind(d: &Degradations) -> Option<BoundKind> {
    if d.perspective.is_some() || d.colour.is_some() || d.dust_hair {
        None
    } else if d.jpeg_quality.is_some() {
        Some(BoundKind::JpegModel)
    } else if d.noise.is_some() {
        Some(BoundKind::CramerRao)
    } else {
        None
    }
}

/// What the bound needs to know of a scene's image formation.
pub struct Formation<'a> {
    /// The clean image (markers, clutter, illumination; before noise), fraction of full scale.
    pub clean: &'a Plane,
    /// Illumination gain per pixel, `None` for 1 everywhere.
    pub gain: Option<&'a Plane>,
    /// Dot grey level minus background grey level, fraction of full scale.
    pub contrast: f64,
    /// Optical blur σ, pixels.
    pub blur_sigma: f64,
    /// Sensor noise, if any.
    pub noise: Option<Noise>,
    /// JPEG quality of a grey JPEG file, `None` for a lossless one.
    pub jpeg_quality: Option<u8>,
    /// The image the detector reads (same size as `clean`), for the reference estimators of
    /// a JPEG file ([`KnownShapeErrors`]); `None` to leave them out.
    pub observed: Option<&'a GreyImage>,
}

impl Formation<'_> {
    /// Variance of the sensor noise at pixel `i`, fraction of full scale squared.
    fn noise_variance(&self, i: usize) -> f64 {
        self.noise.map_or(0.0, |n| {
            let v = (self.clean.data[i] as f64).max(0.0);
            (n.gaussian + n.shot * v.sqrt()).powi(2)
        })
    }
}

/// The bound `B` (pixels) of marker `m` drawn from `layout`: `E|e|² ≥ B²` for the radial
/// error `e` of its origin, image pixels; with `f.jpeg_quality` set, the JPEG model's figure
/// instead (no bound), with the reference estimators' errors where `f.observed` is given.
/// `None` when the Fisher information is singular (a marker nearly out of the frame).
pub fn position_bound(
    layout: &dyn Layout,
    m: &Placed,
    f: &Formation,
) -> Result<Option<PositionBound>> {
    let w = f.clean.width;
    let border = m.side_px() * std::f64::consts::FRAC_1_SQRT_2;
    let steps = [
        STEP_PX,
        STEP_PX,
        STEP_PX / border,
        STEP_PX / border * m.pixel_size,
    ];
    let region = changed_region(m, f);
    let derivatives = step_renders(layout, m, f, &region, &steps)?;
    let rw = region.c1 - region.c0;
    // The derivatives of the clean pixel value at region pixel (r, c).
    let slope = |r: usize, c: usize| -> Vector4<f64> {
        let (i, local) = ((r + region.r0) * w + c + region.c0, r * rw + c);
        let scale = f.contrast * f.gain.map_or(1.0, |g| g.data[i] as f64);
        Vector4::from_fn(|k, _| {
            let (plus, minus, span) = &derivatives[k];
            scale * (plus.data[local] as f64 - minus.data[local] as f64) / span
        })
    };
    let (fisher, kind, known_shape) = match f.jpeg_quality {
        None => {
            let weight = |i: usize| {
                let variance = f.noise_variance(i);
                if variance > 0.0 {
                    1.0 / variance
                } else {
                    0.0
                }
            };
            let (fisher, _) = pixel_sums(w, &region, slope, weight, |_| 0.0);
            (fisher, BoundKind::CramerRao, None)
        }
        Some(quality) => {
            let (fisher, known_shape) = jpeg_model(f, &region, quality, slope);
            (fisher, BoundKind::JpegModel, known_shape)
        }
    };
    Ok(fisher
        .try_inverse()
        .map(|inverse| (inverse[(0, 0)] + inverse[(1, 1)]).sqrt())
        .filter(|b| b.is_finite() && *b > 0.0)
        .map(|px| PositionBound {
            px,
            kind,
            known_shape,
        }))
}

/// The pixels a move of `m` can change: the footprint's box, a tenth of the side for the
/// layout's own bounds, and the blur margin of `add_marker`, clipped to the frame.
fn changed_region(m: &Placed, f: &Formation) -> Region {
    let (w, h) = (f.clean.width, f.clean.height);
    let half = m.footprint().bounding_half();
    let reach = half.x.max(half.y) + 0.1 * m.side_px() + (4.0 * f.blur_sigma).ceil() + 5.0;
    let clip = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n);
    Region {
        r0: clip(m.origin.y - reach, h),
        r1: clip(m.origin.y + reach + 1.0, h),
        c0: clip(m.origin.x - reach, w),
        c1: clip(m.origin.x + reach + 1.0, w),
    }
}

/// `m` rendered on `region` moved by `±steps[k]` in each pose parameter `k` (x, y, angle,
/// pixel size): `(plus, minus, 2·step)` per parameter, for central differences.
fn step_renders(
    layout: &dyn Layout,
    m: &Placed,
    f: &Formation,
    region: &Region,
    steps: &[f64; 4],
) -> Result<Vec<(Plane, Plane, f64)>> {
    let (rw, rh) = (region.c1 - region.c0, region.r1 - region.r0);
    let corner = Vector2::new(region.c0 as f64, region.r0 as f64);
    let render = |k: usize, sign: f64| -> Result<Plane> {
        let mut moved = *m;
        let s = sign * steps[k];
        match k {
            0 => moved.origin.x += s,
            1 => moved.origin.y += s,
            2 => moved.alpha += s,
            _ => moved.pixel_size += s,
        }
        let mut canvas = Plane::filled(rw, rh, 0.0);
        add_marker(
            &mut canvas,
            layout,
            moved.origin - corner,
            moved.alpha,
            moved.pixel_size,
            f.blur_sigma,
            moved.mirrored,
        )?;
        Ok(canvas)
    };
    let mut derivatives = Vec::with_capacity(4);
    for (k, step) in steps.iter().enumerate() {
        let (plus, minus) = (render(k, 1.0)?, render(k, -1.0)?);
        derivatives.push((plus, minus, 2.0 * step));
    }
    Ok(derivatives)
}

/// The JPEG model's Fisher sum of a marker (`slope` its `J` on `region`) in a grey file of
/// `quality`, with the reference estimators' errors where `f.observed` is given.
fn jpeg_model(
    f: &Formation,
    region: &Region,
    quality: u8,
    slope: impl Fn(usize, usize) -> Vector4<f64>,
) -> (Matrix4<f64>, Option<KnownShapeErrors>) {
    let residual = |i: usize| {
        f.observed.map_or(0.0, |image| {
            f64::from(image.pixels()[i]) - f64::from(f.clean.data[i])
        })
    };
    let (fisher, weighted) = jpeg_sums(f, region, &jpeg_variances(quality), &slope, residual);
    let known_shape = f.observed.and_then(|_| {
        let (matrix, unweighted) = pixel_sums(f.clean.width, region, &slope, |_| 1.0, residual);
        Some(KnownShapeErrors {
            unweighted: origin_error(&matrix, &unweighted)?,
            weighted: origin_error(&fisher, &weighted)?,
        })
    });
    (fisher, known_shape)
}

/// The radial origin error of the least-squares step `δ = A⁻¹ b` (pixels), `None` where `A`
/// is singular.
fn origin_error(a: &Matrix4<f64>, b: &Vector4<f64>) -> Option<f64> {
    let step = a.try_inverse()? * b;
    Some(step[0].hypot(step[1])).filter(|e| e.is_finite())
}

/// The image rows `r0..r1` and columns `c0..c1` a marker's moves can change.
struct Region {
    r0: usize,
    r1: usize,
    c0: usize,
    c1: usize,
}

/// `Σ ω J Jᵀ` and `Σ ω J e` over the region's pixels of an image `width` pixels wide, with
/// `ω = weight(i)` and `e = residual(i)` at image index `i` (pixels of weight 0 left out) and
/// `slope(r, c)` the `J` of region pixel `(r, c)`. With `ω = 1/σ²` the first is the Fisher
/// information under white noise.
fn pixel_sums(
    width: usize,
    region: &Region,
    slope: impl Fn(usize, usize) -> Vector4<f64>,
    weight: impl Fn(usize) -> f64,
    residual: impl Fn(usize) -> f64,
) -> (Matrix4<f64>, Vector4<f64>) {
    let mut matrix = Matrix4::zeros();
    let mut rhs = Vector4::zeros();
    for r in region.r0..region.r1 {
        for c in region.c0..region.c1 {
            let i = r * width + c;
            let weight = weight(i);
            if weight > 0.0 {
                let j = slope(r - region.r0, c - region.c0);
                matrix += j * j.transpose() * weight;
                rhs += j * (residual(i) * weight);
            }
        }
    }
    (matrix, rhs)
}

/// JPEG block size, pixels.
const BLOCK: usize = 8;

/// ITU T.81 Annex K.1 luminance quantisation table, row-major (`v·8 + u`, `v` the vertical
/// frequency).
#[rustfmt::skip]
const LUMA_TABLE: [u16; 64] = [
    16, 11, 10, 16,  24,  40,  51,  61,
    12, 12, 14, 19,  26,  58,  60,  55,
    14, 13, 16, 24,  40,  57,  69,  56,
    14, 17, 22, 29,  51,  87,  80,  62,
    18, 22, 37, 56,  68, 109, 103,  77,
    24, 35, 55, 64,  81, 104, 113,  92,
    49, 64, 78, 87, 103, 121, 120, 101,
    72, 92, 95, 98, 112, 100, 103,  99,
];

/// The luminance steps of JPEG `quality` (1–100), scaled as libjpeg does, 8-bit grey levels.
fn luma_steps(quality: u8) -> [f64; 64] {
    let q = u32::from(quality.clamp(1, 100));
    let scale = if q < 50 { 5000 / q } else { 200 - 2 * q };
    LUMA_TABLE.map(|t| ((u32::from(t) * scale + 50) / 100).clamp(1, 255) as f64)
}

/// The variance the additive model gives each DCT coefficient `(u, v)` (index `v·8 + u`) of
/// a grey JPEG file of `quality`, fraction of full scale squared: its step's rounding,
/// `Q_uv²/12`, and the 8-bit rounding before it, `1/12` of a level squared (white, so the same
/// on every coefficient).
fn jpeg_variances(quality: u8) -> [f64; 64] {
    let level = 1.0 / 255.0;
    luma_steps(quality).map(|q| ((q * level).powi(2) + level * level) / 12.0)
}

/// The orthonormal 8-point DCT-II basis, `[k][n]`.
fn dct_basis() -> [[f64; BLOCK]; BLOCK] {
    let n = BLOCK as f64;
    std::array::from_fn(|k| {
        let norm = if k == 0 {
            (1.0 / n).sqrt()
        } else {
            (2.0 / n).sqrt()
        };
        std::array::from_fn(|x| {
            norm * ((2 * x + 1) as f64 * k as f64 * std::f64::consts::PI / (2.0 * n)).cos()
        })
    })
}

/// The Fisher sum of a grey JPEG file under the additive model (module documentation): over
/// the 8 × 8 blocks the region touches (whole blocks inside the image; the encoder pads the
/// last ones, left out), `Σ_uv D_uv D_uvᵀ / (σ̄² + variances_uv)`, with `D_uv` the block's
/// DCT of `J`, `σ̄²` the block's mean sensor noise variance ([`jpeg_variances`]); and
/// `Σ_uv D_uv E_uv / (σ̄² + variances_uv)`, `E_uv` the block's DCT of `residual(i)` (image
/// index `i`) on the region's pixels: the generalised least-squares sums under the model.
fn jpeg_sums(
    f: &Formation,
    region: &Region,
    variances: &[f64; 64],
    slope: impl Fn(usize, usize) -> Vector4<f64>,
    residual: impl Fn(usize) -> f64,
) -> (Matrix4<f64>, Vector4<f64>) {
    let (w, h) = (f.clean.width, f.clean.height);
    let basis = dct_basis();
    let mut fisher = Matrix4::zeros();
    let mut rhs = Vector4::zeros();
    // The region's J and residual on one block, the residual as a fifth component.
    let mut block = [[Vector5::<f64>::zeros(); BLOCK]; BLOCK];
    for by in region.r0 / BLOCK..region.r1.div_ceil(BLOCK).min(h / BLOCK) {
        for bx in region.c0 / BLOCK..region.c1.div_ceil(BLOCK).min(w / BLOCK) {
            let mut noise = 0.0;
            for (y, row) in block.iter_mut().enumerate() {
                for (x, j) in row.iter_mut().enumerate() {
                    let (r, c) = (by * BLOCK + y, bx * BLOCK + x);
                    noise += f.noise_variance(r * w + c);
                    let inside =
                        (region.r0..region.r1).contains(&r) && (region.c0..region.c1).contains(&c);
                    *j = if inside {
                        slope(r - region.r0, c - region.c0).push(residual(r * w + c))
                    } else {
                        Vector5::zeros()
                    };
                }
            }
            let white = noise / (BLOCK * BLOCK) as f64;
            // The DCT along the rows, then down the columns (the basis is separable).
            let rows: [[Vector5<f64>; BLOCK]; BLOCK] = std::array::from_fn(|y| {
                std::array::from_fn(|u| (0..BLOCK).map(|x| block[y][x] * basis[u][x]).sum())
            });
            for (v, bv) in basis.iter().enumerate() {
                for u in 0..BLOCK {
                    let de: Vector5<f64> = (0..BLOCK).map(|y| rows[y][u] * bv[y]).sum();
                    let d = de.fixed_rows::<4>(0);
                    let weight = 1.0 / (white + variances[v * BLOCK + u]);
                    fisher += d * d.transpose() * weight;
                    rhs += d * (de[4] * weight);
                }
            }
        }
    }
    (fisher, rhs)
}

/// The `q` quantile (e.g. 0.99) of the radial errors of an estimator at the bound over markers
/// of bounds `bounds` (pixels): the `r` with `mean exp(−r²/Bᵢ²) = 1 − q`. `None` without
/// bounds.
pub fn efficient_quantile(bounds: &[f64], q: f64) -> Option<f64> {
    let largest = bounds.iter().copied().fold(0.0, f64::max);
    if bounds.is_empty() || largest <= 0.0 {
        return None;
    }
    let exceed =
        |r: f64| bounds.iter().map(|b| (-(r / b).powi(2)).exp()).sum::<f64>() / bounds.len() as f64;
    // The tail is decreasing in r; at r = largest · √(ln 1/(1 − q)) it is ≤ 1 − q.
    let (mut lo, mut hi) = (0.0, largest * (1.0 / (1.0 - q)).ln().sqrt());
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if exceed(mid) > 1.0 - q {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(hi)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The zig-zag order of a JPEG quantisation segment: entry `i` is natural index `ZIGZAG[i]`.
    #[rustfmt::skip]
    const ZIGZAG: [usize; 64] = [
         0,  1,  8, 16,  9,  2,  3, 10, 17, 24, 32, 25, 18, 11,  4,  5,
        12, 19, 26, 33, 40, 48, 41, 34, 27, 20, 13,  6,  7, 14, 21, 28,
        35, 42, 49, 56, 57, 50, 43, 36, 29, 22, 15, 23, 30, 37, 44, 51,
        58, 59, 52, 45, 38, 31, 39, 46, 53, 60, 61, 54, 47, 55, 62, 63,
    ];

    /// The first (luminance) table of the file the suite's JPEG stage writes at `quality`.
    fn written_luma_table(quality: u8) -> [f64; 64] {
        let grey = image::GrayImage::from_fn(16, 16, |x, y| image::Luma([(x * 9 + y * 5) as u8]));
        let mut bytes = Vec::new();
        let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality);
        image::DynamicImage::ImageLuma8(grey)
            .write_with_encoder(encoder)
            .unwrap();
        // DQT: FF DB, length (2 bytes), precision/id (1 byte), then 64 8-bit entries.
        let at = bytes.windows(2).position(|w| w == [0xFF, 0xDB]).unwrap() + 5;
        let mut table = [0.0; 64];
        for (i, &natural) in ZIGZAG.iter().enumerate() {
            table[natural] = bytes[at + i] as f64;
        }
        table
    }

    #[test]
    fn the_modelled_steps_are_the_ones_the_suite_s_files_carry() {
        for quality in [50, 63, 73, 88, 95] {
            assert_eq!(
                luma_steps(quality),
                written_luma_table(quality),
                "quality {quality}"
            );
        }
    }

    #[test]
    fn the_block_sum_equals_the_pixel_sum_under_white_noise() {
        // An orthonormal transform keeps a white noise white: with the same variance on every
        // coefficient the DCT-domain sums (information and residual) are the pixel-domain
        // ones. Region (5..19) × (3..21) on a 24 × 24 image, arbitrary slopes and residual.
        let clean = Plane::filled(24, 24, 0.5);
        let formation = |gaussian: f64| Formation {
            clean: &clean,
            gain: None,
            contrast: 1.0,
            blur_sigma: 0.5,
            noise: Some(Noise {
                gaussian,
                shot: 0.0,
            }),
            jpeg_quality: None,
            observed: None,
        };
        let region = Region {
            r0: 5,
            r1: 19,
            c0: 3,
            c1: 21,
        };
        let slope = |r: usize, c: usize| {
            Vector4::from_fn(|k, _| ((r * 7 + c * 3 + k * 5) as f64 * 0.37).sin())
        };
        let (g, extra): (f64, f64) = (0.01, 2e-4);
        let residual = |i: usize| ((i * 11) as f64 * 0.23).cos();
        let white = formation((g * g + extra).sqrt());
        let weight = |i: usize| 1.0 / white.noise_variance(i);
        let pixels = pixel_sums(24, &region, slope, weight, residual);
        let blocks = jpeg_sums(&formation(g), &region, &[extra; 64], slope, residual);
        assert!(
            (pixels.0 - blocks.0).norm() < 1e-9 * pixels.0.norm(),
            "{} vs {}",
            pixels.0,
            blocks.0
        );
        assert!(
            (pixels.1 - blocks.1).norm() < 1e-9 * pixels.1.norm(),
            "{} vs {}",
            pixels.1,
            blocks.1
        );
    }

    #[test]
    fn one_marker_s_quantile_is_the_rayleigh_quantile() {
        let r = efficient_quantile(&[2.0], 0.99).unwrap();
        assert!((r - 2.0 * 100f64.ln().sqrt()).abs() < 1e-9);
    }

    #[test]
    fn a_mixture_s_quantile_lies_between_its_members() {
        let r = efficient_quantile(&[1.0, 3.0], 0.99).unwrap();
        let (a, b) = (100f64.ln().sqrt(), 3.0 * 100f64.ln().sqrt());
        assert!(r > a && r < b, "{r}");
        let tail = ((-(r / 1.0f64).powi(2)).exp() + (-(r / 3.0f64).powi(2)).exp()) / 2.0;
        assert!((tail - 0.01).abs() < 1e-9);
    }
}
