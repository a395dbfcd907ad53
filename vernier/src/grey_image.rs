//! Grey-level images in `[0, 1]`, the input of every detector (docs/design.md#input-images).
//!
//! Pixels are `f32`, row-major, index `row·width + col`; pixel `(col, row)` is at image
//! coordinates `(x, y) = (col, row)` with y down. 8-bit values are divided by 255, 16-bit by
//! 65535; colour is converted with the Rec. 601 weights `0.299 R + 0.587 G + 0.114 B`.
//! Odd sizes are fine.

use crate::error::{Error, Result};
use crate::image_file::{decode_image_bytes, decode_image_file, DecodeLimits};
use std::path::Path;

/// Whether the dots are brighter or darker than the background.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// Bright dots on a dark background (the method's convention: phase 0 = dot centre).
    #[default]
    BrightDots,
    /// Dark dots on a bright background: the image is inverted before measurement, so poses
    /// refer to the dot centres (the original reports them shifted by half a period).
    DarkDots,
}

impl Polarity {
    /// +1 for bright dots, −1 for dark ones: `sign × intensity` is higher on the dots' (and
    /// their finders' and frames') material than on the background.
    pub fn sign(self) -> f32 {
        match self {
            Polarity::BrightDots => 1.0,
            Polarity::DarkDots => -1.0,
        }
    }
}

impl std::str::FromStr for Polarity {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "bright" | "bright_dots" => Ok(Polarity::BrightDots),
            "dark" | "dark_dots" => Ok(Polarity::DarkDots),
            other => Err(Error::parameter(
                "polarity",
                format!("expected `bright` or `dark`, got `{other}`"),
            )),
        }
    }
}

/// Parses a polarity setting as users type it: `auto` (`None`: found per marker where the
/// marker type can, bright dots otherwise), `bright` or `dark`.
pub fn parse_polarity_setting(s: &str) -> Result<Option<Polarity>> {
    match s {
        "auto" | "" => Ok(None),
        other => other.parse().map(Some).map_err(|_| {
            Error::parameter(
                "polarity",
                format!("expected `auto`, `bright` or `dark`, got `{other}`"),
            )
        }),
    }
}

/// Pixel layout of a raw buffer (the ROS `sensor_msgs/Image` encodings the library reads).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelFormat {
    /// 1 byte per pixel.
    Mono8,
    /// 2 bytes per pixel, little- or big-endian as given.
    Mono16 {
        /// Byte order of the samples.
        big_endian: bool,
    },
    /// 3 bytes R, G, B.
    Rgb8,
    /// 3 bytes B, G, R.
    Bgr8,
    /// 4 bytes R, G, B, A (alpha ignored).
    Rgba8,
    /// 4 bytes B, G, R, A (alpha ignored).
    Bgra8,
}

impl PixelFormat {
    /// Bytes per pixel.
    pub fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Mono8 => 1,
            PixelFormat::Mono16 { .. } => 2,
            PixelFormat::Rgb8 | PixelFormat::Bgr8 => 3,
            PixelFormat::Rgba8 | PixelFormat::Bgra8 => 4,
        }
    }
    /// Parses a ROS encoding name (`mono8`, `mono16`, `rgb8`, `bgr8`, `rgba8`, `bgra8`).
    pub fn from_ros_encoding(encoding: &str, big_endian: bool) -> Option<Self> {
        Some(match encoding {
            "mono8" | "8UC1" => PixelFormat::Mono8,
            "mono16" | "16UC1" => PixelFormat::Mono16 { big_endian },
            "rgb8" => PixelFormat::Rgb8,
            "bgr8" | "8UC3" => PixelFormat::Bgr8,
            "rgba8" => PixelFormat::Rgba8,
            "bgra8" | "8UC4" => PixelFormat::Bgra8,
            _ => return None,
        })
    }
}

/// White-noise gain of [`GreyImage::binomial_3x3`]: `√Σw² = 6/16` over its 3 × 3 weights,
/// the factor on a white noise's standard deviation.
pub(crate) const BINOMIAL_3X3_NOISE_GAIN: f32 = 0.375;

const LUMA_R: f32 = 0.299;
const LUMA_G: f32 = 0.587;
const LUMA_B: f32 = 0.114;

/// A grey image with `f32` pixels nominally in `[0, 1]` (row-major).
#[derive(Clone, Debug, PartialEq)]
pub struct GreyImage {
    width: usize,
    height: usize,
    pixels: Vec<f32>,
}

impl GreyImage {
    /// Wraps row-major pixels. Errors if the size is zero, the length is not
    /// `width·height`, or a value is not finite (NaN, ±∞).
    pub fn new(width: usize, height: usize, pixels: Vec<f32>) -> Result<Self> {
        check_size(width, height)?;
        if pixels.len() != width * height {
            return Err(Error::InvalidImage(format!(
                "{} pixel values for a {width}x{height} image (expected {})",
                pixels.len(),
                width * height
            )));
        }
        // One vectorised pass (no early exit) to learn whether a sample is not finite; only
        // then the search for the first one, for the message.
        let all_finite = pixels
            .chunks(4096)
            .all(|c| c.iter().fold(true, |ok, v| ok & v.is_finite()));
        if let Some(i) = (!all_finite)
            .then(|| pixels.iter().position(|v| !v.is_finite()))
            .flatten()
        {
            return Err(Error::InvalidImage(format!(
                "pixel ({}, {}) is not a finite number ({})",
                i % width,
                i / width,
                pixels[i]
            )));
        }
        Ok(GreyImage {
            width,
            height,
            pixels,
        })
    }

    /// From `f64` samples (used as is, like the original's double arrays).
    pub fn from_f64(width: usize, height: usize, values: &[f64]) -> Result<Self> {
        Self::new(width, height, values.iter().map(|&v| v as f32).collect())
    }

    /// From a raw buffer whose rows are `step` bytes apart (`step ≥ width·bytes_per_pixel`).
    pub fn from_raw(
        width: usize,
        height: usize,
        step: usize,
        format: PixelFormat,
        data: &[u8],
    ) -> Result<Self> {
        let mut image = GreyImage::unfilled();
        image.assign_raw(width, height, step, format, data)?;
        Ok(image)
    }

    /// [`GreyImage::from_raw`] into this image, reusing its pixel buffer: a stream of frames
    /// of one size allocates (and page-faults in) its 4 bytes per pixel once, not per frame.
    /// On error the image is left as it was.
    pub fn assign_raw(
        &mut self,
        width: usize,
        height: usize,
        step: usize,
        format: PixelFormat,
        data: &[u8],
    ) -> Result<()> {
        check_size(width, height)?;
        let bpp = format.bytes_per_pixel();
        let row_bytes = width
            .checked_mul(bpp)
            .ok_or_else(|| Error::InvalidImage("image width overflows".into()))?;
        if step < row_bytes {
            return Err(Error::InvalidImage(format!(
                "row step {step} bytes is shorter than a row ({row_bytes} bytes)"
            )));
        }
        let needed = step
            .checked_mul(height)
            .ok_or_else(|| Error::InvalidImage("image size overflows".into()))?;
        if data.len() != needed {
            return Err(Error::InvalidImage(format!(
                "{} data bytes for {height} rows of {step} bytes (expected {needed})",
                data.len()
            )));
        }
        let rows = (width, height, step);
        let out = &mut self.pixels;
        match format {
            PixelFormat::Mono8 => convert_rows::<_, 1>(data, rows, out, |p| unit(p[0])),
            PixelFormat::Mono16 { big_endian } => convert_rows::<_, 2>(data, rows, out, |b| {
                unit(match big_endian {
                    true => u16::from_be_bytes([b[0], b[1]]),
                    false => u16::from_le_bytes([b[0], b[1]]),
                })
            }),
            PixelFormat::Rgb8 => convert_rows::<_, 3>(data, rows, out, |p| luma(p[0], p[1], p[2])),
            PixelFormat::Rgba8 => convert_rows::<_, 4>(data, rows, out, |p| luma(p[0], p[1], p[2])),
            PixelFormat::Bgr8 => convert_rows::<_, 3>(data, rows, out, |p| luma(p[2], p[1], p[0])),
            PixelFormat::Bgra8 => convert_rows::<_, 4>(data, rows, out, |p| luma(p[2], p[1], p[0])),
        }
        self.width = width;
        self.height = height;
        Ok(())
    }

    /// An image of no pixels, to be filled ([`GreyImage::assign_raw`]); never handed out.
    pub(crate) fn unfilled() -> Self {
        GreyImage {
            width: 0,
            height: 0,
            pixels: Vec::new(),
        }
    }

    /// Fills the image from a decoder's packed samples of colour type `colour` (16-bit
    /// samples in native byte order, as `image`'s decoders write them), reusing the pixel
    /// buffer. `false`, the image untouched, for a colour type with no integer samples.
    pub(crate) fn assign_decoded(
        &mut self,
        (width, height): (usize, usize),
        colour: image::ColorType,
        samples: &[u8],
    ) -> Result<bool> {
        use image::ColorType as C;
        check_size(width, height)?;
        let out = &mut self.pixels;
        let grey16 = |b: &[u8]| unit(u16::from_ne_bytes([b[0], b[1]]));
        let luma16 = |b: &[u8]| {
            let s = |k: usize| u16::from_ne_bytes([b[2 * k], b[2 * k + 1]]);
            luma(s(0), s(1), s(2))
        };
        let rgb8 = |p: &[u8]| luma(p[0], p[1], p[2]);
        match colour {
            C::L8 => convert_rows::<_, 1>(samples, (width, height, width), out, |p| unit(p[0])),
            C::La8 => {
                convert_rows::<_, 2>(samples, (width, height, 2 * width), out, |p| unit(p[0]))
            }
            C::Rgb8 => convert_rows::<_, 3>(samples, (width, height, 3 * width), out, rgb8),
            C::Rgba8 => convert_rows::<_, 4>(samples, (width, height, 4 * width), out, rgb8),
            C::L16 => convert_rows::<_, 2>(samples, (width, height, 2 * width), out, grey16),
            C::La16 => convert_rows::<_, 4>(samples, (width, height, 4 * width), out, grey16),
            C::Rgb16 => convert_rows::<_, 6>(samples, (width, height, 6 * width), out, luma16),
            C::Rgba16 => convert_rows::<_, 8>(samples, (width, height, 8 * width), out, luma16),
            _ => return Ok(false),
        }
        self.width = width;
        self.height = height;
        Ok(true)
    }

    /// From 8-bit grey samples, row-major.
    pub fn from_u8(width: usize, height: usize, values: &[u8]) -> Result<Self> {
        Self::from_raw(width, height, width, PixelFormat::Mono8, values)
    }

    /// From 16-bit grey samples, row-major.
    pub fn from_u16(width: usize, height: usize, values: &[u16]) -> Result<Self> {
        check_size(width, height)?;
        if values.len() != width * height {
            return Err(Error::InvalidImage(format!(
                "{} samples for a {width}x{height} image",
                values.len()
            )));
        }
        Ok(GreyImage {
            width,
            height,
            pixels: packed_grey::<_, 1>(values, width, height),
        })
    }

    /// Reads a PNG, JPEG, TIFF or PNM file (8/16-bit, grey, grey+alpha, RGB or RGBA) within
    /// the default [`DecodeLimits`] (100 MP). See [`decode_image_file`] for the checks.
    pub fn open(path: impl AsRef<Path>) -> Result<Self> {
        Self::open_with_limits(path, &DecodeLimits::default())
    }

    /// [`GreyImage::open`] with explicit limits (`--max-pixels`).
    pub fn open_with_limits(path: impl AsRef<Path>, limits: &DecodeLimits) -> Result<Self> {
        let path = path.as_ref();
        let decoded = decode_image_file(path, limits)?;
        Self::from_dynamic(&decoded).map_err(|e| Error::ImageRead {
            path: path.to_path_buf(),
            reason: e.to_string(),
        })
    }

    /// Decodes an in-memory image file (the bytes of a PNG, JPEG, TIFF or PNM) within
    /// `limits`; `name` labels the errors. The checks of [`decode_image_file`] apply.
    pub fn decode_bytes(bytes: &[u8], name: &Path, limits: &DecodeLimits) -> Result<Self> {
        let decoded = decode_image_bytes(bytes, name, limits)?;
        Self::from_dynamic(&decoded).map_err(|e| Error::ImageRead {
            path: name.to_path_buf(),
            reason: e.to_string(),
        })
    }

    /// Converts a decoded `image` crate picture.
    pub fn from_dynamic(decoded: &image::DynamicImage) -> Result<Self> {
        use image::DynamicImage as D;
        let (w, h) = (decoded.width() as usize, decoded.height() as usize);
        check_size(w, h)?;
        let pixels: Vec<f32> = match decoded {
            D::ImageLuma8(i) => packed_grey::<_, 1>(i.as_raw(), w, h),
            D::ImageLumaA8(i) => packed_grey::<_, 2>(i.as_raw(), w, h),
            D::ImageRgb8(i) => packed_grey::<_, 3>(i.as_raw(), w, h),
            D::ImageRgba8(i) => packed_grey::<_, 4>(i.as_raw(), w, h),
            D::ImageLuma16(i) => packed_grey::<_, 1>(i.as_raw(), w, h),
            D::ImageLumaA16(i) => packed_grey::<_, 2>(i.as_raw(), w, h),
            D::ImageRgb16(i) => packed_grey::<_, 3>(i.as_raw(), w, h),
            D::ImageRgba16(i) => packed_grey::<_, 4>(i.as_raw(), w, h),
            // Floating-point samples may hold NaN or infinities: checked.
            other => return Self::new(w, h, other.to_luma32f().into_raw()),
        };
        // Integer samples scaled to [0, 1] are finite: no second pass over the image.
        Ok(GreyImage {
            width: w,
            height: h,
            pixels,
        })
    }

    /// Width `C`, pixels (columns).
    pub fn width(&self) -> usize {
        self.width
    }
    /// Height `R`, pixels (rows).
    pub fn height(&self) -> usize {
        self.height
    }
    /// Row-major pixel values.
    pub fn pixels(&self) -> &[f32] {
        &self.pixels
    }

    /// Bilinear interpolation at `(col, row)`, pixels; `None` outside
    /// `[0, width−1] × [0, height−1]` (and for NaN). The one sampler of the coarse steps
    /// (HP code ID dots, stamp and Megarena thumbnails, stamp edge profiles).
    #[inline]
    pub fn bilinear(&self, col: f64, row: f64) -> Option<f32> {
        let (w, h) = (self.width, self.height);
        if !(col >= 0.0 && row >= 0.0 && col <= (w - 1) as f64 && row <= (h - 1) as f64) {
            return None;
        }
        // In range, so the truncations are floors inside the image; the right/bottom
        // neighbour is clamped for samples on the last column/row.
        let (c0, r0) = (col as usize, row as usize);
        let (fc, fr) = ((col - c0 as f64) as f32, (row - r0 as f64) as f32);
        let (c1, r1) = ((c0 + 1).min(w - 1), (r0 + 1).min(h - 1));
        let px = self.pixels();
        let (top, bottom) = (px.get(r0 * w..)?, px.get(r1 * w..)?);
        let (t0, t1, b0, b1) = (top.get(c0)?, top.get(c1)?, bottom.get(c0)?, bottom.get(c1)?);
        let upper = t0 + (t1 - t0) * fc;
        let lower = b0 + (b1 - b0) * fc;
        Some(upper + (lower - upper) * fr)
    }
    /// Mutable row-major pixel values.
    pub fn pixels_mut(&mut self) -> &mut [f32] {
        &mut self.pixels
    }
    /// Value at `(col, row)`, or `None` outside the image.
    pub fn get(&self, col: usize, row: usize) -> Option<f32> {
        (col < self.width && row < self.height).then(|| self.pixels[row * self.width + col])
    }
    /// The image centre pixel `(C div 2, R div 2)`: the origin of the camera frame.
    pub fn center(&self) -> (usize, usize) {
        (self.width / 2, self.height / 2)
    }

    /// The four corner pixels in the image frame (pixels from [`GreyImage::center`], y down):
    /// top-left, top-right, bottom-left, bottom-right.
    pub(crate) fn corners_from_center(&self) -> [(f64, f64); 4] {
        let (cx, cy) = self.center();
        let (left, top) = (-(cx as f64), -(cy as f64));
        let right = self.width.saturating_sub(1 + cx) as f64;
        let bottom = self.height.saturating_sub(1 + cy) as f64;
        [(left, top), (right, top), (left, bottom), (right, bottom)]
    }

    /// `1 − value` for every pixel (turns dark dots into bright dots).
    pub fn inverted(&self) -> GreyImage {
        GreyImage {
            width: self.width,
            height: self.height,
            pixels: self.pixels.iter().map(|v| 1.0 - v).collect(),
        }
    }

    /// The image as the phase engine expects it for `polarity`: borrowed as is for bright dots,
    /// an inverted copy for dark dots.
    pub fn as_bright_dots(&self, polarity: Polarity) -> std::borrow::Cow<'_, GreyImage> {
        match polarity {
            Polarity::BrightDots => std::borrow::Cow::Borrowed(self),
            Polarity::DarkDots => std::borrow::Cow::Owned(self.inverted()),
        }
    }

    /// The `width × height` window whose top-left pixel is `(col0, row0)`; parts outside the
    /// image are filled with `fill`. Errors on a zero size.
    pub fn window(
        &self,
        col0: i64,
        row0: i64,
        width: usize,
        height: usize,
        fill: f32,
    ) -> Result<GreyImage> {
        check_size(width, height)?;
        let count = width
            .checked_mul(height)
            .filter(|&n| n as u64 <= WINDOW_MAX_PIXELS)
            .ok_or_else(|| {
                Error::InvalidImage(format!(
                    "window {width}×{height} is larger than the limit of {}",
                    crate::limits::megapixels(WINDOW_MAX_PIXELS)
                ))
            })?;
        let mut pixels = vec![fill; count];
        for r in 0..height {
            let src_r = row0 + r as i64;
            if src_r < 0 || src_r >= self.height as i64 {
                continue;
            }
            let c_start = (-col0).clamp(0, width as i64) as usize;
            let c_end = (self.width as i64 - col0).clamp(0, width as i64) as usize;
            if c_start >= c_end {
                continue;
            }
            let src = src_r as usize * self.width;
            let (s0, s1) = (
                (col0 + c_start as i64) as usize,
                (col0 + c_end as i64) as usize,
            );
            pixels[r * width + c_start..r * width + c_end]
                .copy_from_slice(&self.pixels[src + s0..src + s1]);
        }
        Ok(GreyImage {
            width,
            height,
            pixels,
        })
    }

    /// A 0×0 placeholder for buffers filled later (never handed to users).
    pub(crate) fn empty() -> GreyImage {
        GreyImage {
            width: 0,
            height: 0,
            pixels: Vec::new(),
        }
    }

    /// This image binned 2×2 into `out` (its buffer reused; see [`bin_2x2`] for the frame).
    /// `None` when a side is below 2 pixels.
    pub(crate) fn binned_2x2_into(&self, out: &mut GreyImage) -> Option<()> {
        let (cb, rb) = (self.width / 2, self.height / 2);
        if cb == 0 || rb == 0 {
            return None;
        }
        bin_2x2(&self.pixels, self.width, rb, cb, &mut out.pixels);
        (out.width, out.height) = (cb, rb);
        Some(())
    }

    /// The crop `[col0, col0+width) × [row0, row0+height)`, which must lie inside the image.
    pub fn crop(&self, col0: usize, row0: usize, width: usize, height: usize) -> Result<GreyImage> {
        if col0 + width > self.width || row0 + height > self.height {
            return Err(Error::InvalidImage(format!(
                "crop {width}x{height} at ({col0}, {row0}) exceeds the {}x{} image",
                self.width, self.height
            )));
        }
        self.window(col0 as i64, row0 as i64, width, height, 0.0)
    }

    /// The 3 × 3 binomial low-pass `[1 2 1]/4` along each axis, edges replicated: a Gaussian
    /// of σ ≈ 0.71 px that keeps one-pixel-wide structure and lowers white noise's standard
    /// deviation by [`BINOMIAL_3X3_NOISE_GAIN`] (the 3-tap sibling of Burt and Adelson's 5-tap kernel,
    /// *The Laplacian pyramid as a compact image code*, IEEE Trans. Commun., 1983).
    pub(crate) fn binomial_3x3(&self) -> GreyImage {
        let (w, h) = (self.width, self.height);
        let smooth = |prev: f32, at: f32, next: f32| 0.25 * (prev + next) + 0.5 * at;
        let mut rows = vec![0.0f32; w * h];
        for (src, dst) in self.pixels.chunks_exact(w).zip(rows.chunks_exact_mut(w)) {
            for (c, out) in dst.iter_mut().enumerate() {
                let (left, right) = (src[c.saturating_sub(1)], src[(c + 1).min(w - 1)]);
                *out = smooth(left, src[c], right);
            }
        }
        let mut pixels = vec![0.0f32; w * h];
        for (r, out) in pixels.chunks_exact_mut(w).enumerate() {
            let (up, down) = (r.saturating_sub(1), (r + 1).min(h - 1));
            let row = |i: usize| &rows[i * w..(i + 1) * w];
            for (((o, &a), &m), &b) in out.iter_mut().zip(row(up)).zip(row(r)).zip(row(down)) {
                *o = smooth(a, m, b);
            }
        }
        GreyImage { pixels, ..*self }
    }

    /// Transposed image (rows become columns): `out(col = r, row = c) = in(col = c, row = r)`.
    pub fn transposed(&self) -> GreyImage {
        let (w, h) = (self.width, self.height);
        let mut pixels = vec![0.0; w * h];
        for r in 0..h {
            for c in 0..w {
                pixels[c * h + r] = self.pixels[r * w + c];
            }
        }
        GreyImage {
            width: h,
            height: w,
            pixels,
        }
    }

    /// Mirror image left–right: `out(col) = in(C − 1 − col)`.
    pub fn flipped_horizontally(&self) -> GreyImage {
        let mut pixels = self.pixels.clone();
        for row in pixels.chunks_exact_mut(self.width) {
            row.reverse();
        }
        GreyImage { pixels, ..*self }
    }

    /// Mirror image top–bottom: `out(row) = in(R − 1 − row)`.
    pub fn flipped_vertically(&self) -> GreyImage {
        let mut pixels = Vec::with_capacity(self.pixels.len());
        for row in self.pixels.chunks_exact(self.width).rev() {
            pixels.extend_from_slice(row);
        }
        GreyImage { pixels, ..*self }
    }

    /// Rotated by 90° clockwise on screen: `out(col = R−1−r, row = c) = in(col = c, row = r)`.
    pub fn rotated_90_clockwise(&self) -> GreyImage {
        self.transposed().flipped_horizontally()
    }

    /// Quantised samples `round(clamp(v, 0, 1)·(2^bits − 1))` for `bits` in 1..=16.
    pub fn quantized(&self, bits: u32) -> Vec<u16> {
        let max = ((1u32 << bits.clamp(1, 16)) - 1) as f32;
        self.pixels
            .iter()
            .map(|&v| (v.clamp(0.0, 1.0) * max).round() as u16)
            .collect()
    }

    /// Writes a grey PNG: 8-bit when `bits ≤ 8`, else 16-bit with the `bits`-bit value scaled to
    /// the full 16-bit range (a 12-bit image keeps 4096 distinct levels).
    pub fn save_png(&self, path: impl AsRef<Path>, bits: u32) -> Result<()> {
        let path = path.as_ref();
        let write_err = |reason: String| Error::ImageWrite {
            path: path.to_path_buf(),
            reason,
        };
        let bytes = self.encode_png(bits).map_err(write_err)?;
        // Encoded in memory, then written and synced with every error checked (the `image`
        // crate's `save` drops its buffered writer unflushed: a full disk went unnoticed).
        crate::output::write_file(path, &bytes).map_err(|e| write_err(e.to_string()))
    }

    /// The PNG file [`GreyImage::save_png`] writes, in memory.
    pub fn encode_png(&self, bits: u32) -> std::result::Result<Vec<u8>, String> {
        use image::ImageEncoder;
        let (w, h) = (self.width as u32, self.height as u32);
        let mut out = Vec::new();
        let encoder = image::codecs::png::PngEncoder::new(&mut out);
        if bits <= 8 {
            let data: Vec<u8> = self
                .quantized(bits)
                .iter()
                .map(|&v| (v as u32 * 255 / ((1 << bits.max(1)) - 1)) as u8)
                .collect();
            encoder
                .write_image(&data, w, h, image::ExtendedColorType::L8)
                .map_err(|e| e.to_string())?;
        } else {
            let levels = ((1u32 << bits.min(16)) - 1) as f64;
            let data: Vec<u8> = self
                .quantized(bits)
                .iter()
                .flat_map(|&v| ((v as f64 * 65535.0 / levels).round() as u16).to_ne_bytes())
                .collect();
            encoder
                .write_image(&data, w, h, image::ExtendedColorType::L16)
                .map_err(|e| e.to_string())?;
        }
        Ok(out)
    }
}

/// Largest window or crop [`GreyImage::window`] builds, pixels (a
/// [`limits::MAX_WINDOW_SIZE`](crate::limits::MAX_WINDOW_SIZE) square).
const WINDOW_MAX_PIXELS: u64 =
    (crate::limits::MAX_WINDOW_SIZE as u64) * (crate::limits::MAX_WINDOW_SIZE as u64);

fn check_size(width: usize, height: usize) -> Result<()> {
    if width == 0 || height == 0 {
        return Err(Error::InvalidImage(format!(
            "empty image ({width}x{height} pixels)"
        )));
    }
    Ok(())
}

/// The integer sample types of the input layouts.
trait Sample: Copy {
    /// The value of full scale (white).
    const FULL_SCALE: f32;
    /// The sample as a number, `0..=FULL_SCALE`.
    fn value(self) -> f32;
}

impl Sample for u8 {
    const FULL_SCALE: f32 = 255.0;
    fn value(self) -> f32 {
        self as f32
    }
}

impl Sample for u16 {
    const FULL_SCALE: f32 = 65535.0;
    fn value(self) -> f32 {
        self as f32
    }
}

/// A grey sample in `[0, 1]`.
fn unit<T: Sample>(v: T) -> f32 {
    v.value() / T::FULL_SCALE
}

/// The Rec. 601 luma of a colour sample, in `[0, 1]`.
fn luma<T: Sample>(r: T, g: T, b: T) -> f32 {
    (LUMA_R * r.value() + LUMA_G * g.value() + LUMA_B * b.value()) / T::FULL_SCALE
}

/// The grey values of a packed `width × height` image of `N` samples per pixel: grey (and
/// alpha) for `N < 3`, R, G, B (and alpha) otherwise.
fn packed_grey<T: Sample, const N: usize>(data: &[T], width: usize, height: usize) -> Vec<f32> {
    let mut out = Vec::new();
    convert_rows::<T, N>(data, (width, height, width * N), &mut out, |p| match N {
        1 | 2 => unit(p[0]),
        _ => luma(p[0], p[1], p[2]),
    });
    out
}

/// Converts the first `height` rows of `data`, each `step` samples apart and holding `width`
/// pixels of `N` samples, with `pixel` (row-major, `width × height` values): the one
/// conversion loop of every integer input layout. Rows missing from a short `data` stay 0
/// (the callers check the length first); `out` is cleared first, its capacity kept. Two
/// threads (bands of rows) did not make a 5 MP frame faster end to end (7.6 ms per tracked
/// window-only frame either way), so the loop stays on one; the 20 MB of `f32` it writes per
/// frame, rather than its arithmetic, is the likely limit.
fn convert_rows<T, const N: usize>(
    data: &[T],
    (width, height, step): (usize, usize, usize),
    out: &mut Vec<f32>,
    pixel: impl Fn(&[T]) -> f32,
) {
    let total = width * height;
    // Written once, not zeroed first: the zeroing was a second pass over the 20 MB. The
    // buffer's pages stay mapped from the frame before.
    crate::frame_buffer::reserve_fresh(out, total);
    if width > 0 && step > 0 {
        for row in data.chunks(step).take(height) {
            let start = out.len();
            out.extend(row.chunks_exact(N).take(width).map(&pixel));
            out.resize(start + width, 0.0);
        }
    }
    out.resize(total, 0.0);
}

/// Outputs of at least this many pixels are binned on two threads.
const PARALLEL_BIN_PIXELS: usize = 1 << 18;

/// 2×2 box average of a `cols`-wide image into `rb × cb` pixels (an odd last row/column is
/// dropped): binned pixel `(c, r)` covers pixels `2c, 2c + 1` × `2r, 2r + 1`, so its centre
/// is at `(2c + 0.5, 2r + 0.5)` in the input. Needs `rb ≤ rows / 2`, `cb ≤ cols / 2`.
pub(crate) fn bin_2x2(pixels: &[f32], cols: usize, rb: usize, cb: usize, out: &mut Vec<f32>) {
    out.clear();
    out.resize(rb * cb, 0.0);
    if rb == 0 || cb == 0 {
        return;
    }
    let bin_rows = |first_row: usize, band: &mut [f32]| {
        for (i, dst) in band.chunks_exact_mut(cb).enumerate() {
            let r = first_row + i;
            let top = &pixels[2 * r * cols..2 * r * cols + 2 * cb];
            let bottom = &pixels[(2 * r + 1) * cols..(2 * r + 1) * cols + 2 * cb];
            for ((d, t), b) in dst
                .iter_mut()
                .zip(top.chunks_exact(2))
                .zip(bottom.chunks_exact(2))
            {
                *d = 0.25 * (t[0] + t[1] + b[0] + b[1]);
            }
        }
    };
    if rb * cb < PARALLEL_BIN_PIXELS {
        bin_rows(0, out);
        return;
    }
    let half = rb.div_ceil(2);
    let (first, second) = out.split_at_mut(half * cb);
    std::thread::scope(|s| {
        s.spawn(|| bin_rows(0, first));
        bin_rows(half, second);
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An impulse spreads into the binomial's weights `[1 2 1]ᵀ[1 2 1]/16` (so `Σw² = (6/16)²`,
    /// the finder search's noise gain), a flat image and its edges stay flat.
    #[test]
    fn binomial_3x3_spreads_an_impulse_into_its_weights() {
        let mut pixels = vec![0.25f32; 5 * 5];
        pixels[2 * 5 + 2] = 1.25;
        let image = GreyImage::new(5, 5, pixels).unwrap_or_else(|e| panic!("{e}"));
        let smoothed = image.binomial_3x3();
        let weights = [1.0, 2.0, 1.0];
        let mut sum_squares = 0.0;
        for r in 0..5 {
            for c in 0..5 {
                let v = smoothed.get(c, r).unwrap_or(f32::NAN) - 0.25;
                let near = (1..=3).contains(&r) && (1..=3).contains(&c);
                let expected = if near {
                    weights[r - 1] * weights[c - 1] / 16.0
                } else {
                    0.0
                };
                assert!(
                    (v - expected).abs() < 1e-6,
                    "({c}, {r}): {v} against {expected}"
                );
                sum_squares += v * v;
            }
        }
        assert!((sum_squares.sqrt() - BINOMIAL_3X3_NOISE_GAIN).abs() < 1e-6);
        let flat = GreyImage::new(3, 4, vec![0.5; 12]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(flat.binomial_3x3(), flat);
    }

    #[test]
    fn bilinear_interpolates_and_rejects_outside() {
        let img = GreyImage::new(2, 2, vec![0.0, 1.0, 0.5, 0.5]).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(img.bilinear(0.5, 0.0), Some(0.5));
        assert_eq!(img.bilinear(1.0, 1.0), Some(0.5));
        assert!((img.bilinear(0.5, 0.5).unwrap_or(0.0) - 0.5).abs() < 1e-6);
        assert_eq!(img.bilinear(-0.1, 0.0), None);
        assert_eq!(img.bilinear(0.0, f64::NAN), None);
    }

    #[test]
    fn raw_formats_and_errors() {
        let img = GreyImage::from_raw(2, 1, 8, PixelFormat::Bgra8, &[0, 0, 255, 9, 255, 0, 0, 9])
            .unwrap();
        assert!((img.pixels()[0] - 0.299).abs() < 1e-6 && (img.pixels()[1] - 0.114).abs() < 1e-6);
        let img = GreyImage::from_raw(
            1,
            2,
            4,
            PixelFormat::Mono16 { big_endian: true },
            &[0xff, 0xff, 0, 0, 0, 0, 0, 0],
        )
        .unwrap();
        assert_eq!(img.pixels(), &[1.0, 0.0]);
        assert!(GreyImage::from_raw(2, 2, 2, PixelFormat::Mono8, &[0; 3]).is_err());
        assert!(GreyImage::from_raw(2, 2, 1, PixelFormat::Mono8, &[0; 2]).is_err());
        assert!(GreyImage::from_raw(0, 2, 0, PixelFormat::Mono8, &[]).is_err());
        let e = GreyImage::new(2, 1, vec![0.0, f32::NAN])
            .unwrap_err()
            .to_string();
        assert!(e.contains("(1, 0)"), "{e}");
    }

    #[test]
    fn geometric_transforms() {
        let img = GreyImage::new(3, 2, vec![1., 2., 3., 4., 5., 6.]).unwrap();
        assert_eq!(img.transposed().pixels(), &[1., 4., 2., 5., 3., 6.]);
        assert_eq!(
            img.rotated_90_clockwise().pixels(),
            &[4., 1., 5., 2., 6., 3.]
        );
        assert_eq!(img.flipped_vertically().pixels(), &[4., 5., 6., 1., 2., 3.]);
        let w = img.window(-1, 1, 3, 2, 0.5).unwrap();
        assert_eq!(w.pixels(), &[0.5, 4., 5., 0.5, 0.5, 0.5]);
    }
}
