//! Image degradations: their random severities (within lab-realistic bounds) and the pixel
//! operations applied after rendering (illumination, colour cast, noise, JPEG, quantisation).
//! Geometry (perspective), optics (blur) and scene content (clutter, dust, hair) are applied
//! by [`crate::scene`] with the help of [`crate::raster`] and [`crate::clutter`].

use crate::error::{Result, StressError};
use crate::raster::Plane;
use image::{DynamicImage, ImageBuffer, Luma, Rgb};
use rand::rngs::SmallRng;
use rand::Rng;
use rand_distr::StandardNormal;
use std::f64::consts::{PI, TAU};
use vernier::GreyImage;

/// One kind of degradation (a category of its own, or a part of "combined").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Degradation {
    /// Marker plane tilted up to 25° (homography, supersampled bilinear warp).
    Perspective,
    /// Optical Gaussian blur σ 0.5–2 px, at most a quarter of the grid period (the dots stay
    /// resolved: the grid keeps ≥ 29 % of its fundamental's contrast).
    Blur,
    /// Gaussian noise up to 3 % of full scale plus shot noise, 8–12 bits.
    Noise,
    /// JPEG at quality 50–95.
    Jpeg,
    /// Multiplicative gradient and vignetting down to 0.3 at the dimmest corner.
    Illumination,
    /// Dots only 10–20 % of full scale from the background, background offset anywhere.
    LowContrast,
    /// RGB image with per-channel gains, converted by `GreyImage::from_dynamic`.
    ColourCast,
    /// Text-like glyphs, stripes, grid paper and other markers beside the markers.
    Clutter,
    /// Dust blobs (some over markers, at most partly over one finder) and a hair crossing.
    DustHair,
}

impl Degradation {
    /// Every degradation.
    pub const ALL: [Degradation; 9] = [
        Degradation::Perspective,
        Degradation::Blur,
        Degradation::Noise,
        Degradation::Jpeg,
        Degradation::Illumination,
        Degradation::LowContrast,
        Degradation::ColourCast,
        Degradation::Clutter,
        Degradation::DustHair,
    ];

    /// Lower-case name (`perspective`, `blur`, …, `dust_hair`): a stress category's.
    pub fn name(self) -> &'static str {
        match self {
            Degradation::Perspective => "perspective",
            Degradation::Blur => "blur",
            Degradation::Noise => "noise",
            Degradation::Jpeg => "jpeg",
            Degradation::Illumination => "illumination",
            Degradation::LowContrast => "low_contrast",
            Degradation::ColourCast => "colour_cast",
            Degradation::Clutter => "clutter",
            Degradation::DustHair => "dust_hair",
        }
    }
}

/// Tilt of the marker plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tilt {
    /// Tilt angle, radians (≤ 25° as drawn; up to 60° after [`Degradations::harsher`]).
    pub angle: f64,
    /// Direction of the tilt axis in the image, radians.
    pub axis: f64,
    /// Focal length as a multiple of the image diagonal.
    pub focal_diagonals: f64,
}

/// Sensor noise.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Noise {
    /// Standard deviation of the additive Gaussian noise, fraction of full scale.
    pub gaussian: f64,
    /// Shot noise: standard deviation `shot·√value`.
    pub shot: f64,
}

/// Illumination gain field: linear gradient times radial vignetting.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Illumination {
    /// Gain at the dimmest point (the brightest is 1).
    pub min_gain: f64,
    /// Direction of decreasing light, radians.
    pub direction: f64,
    /// Share of the vignetting in the fall-off, `[0, 1]`.
    pub vignetting: f64,
    /// Vignetting centre as a fraction of the image size.
    pub center: (f64, f64),
}

/// Colour cast: per-channel gains of an RGB sensor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ColourCast {
    /// Gains of R, G, B.
    pub gains: [f64; 3],
    /// 16-bit RGB (else 8-bit).
    pub sixteen_bit: bool,
}

/// Every degradation of one scene with its severity (absent = not applied).
#[derive(Clone, Debug, PartialEq)]
pub struct Degradations {
    /// Plane tilt.
    pub perspective: Option<Tilt>,
    /// Optical blur σ, pixels (every scene has some: 0.4–0.7 px unless blurred on purpose).
    pub blur_sigma: f64,
    /// Sensor noise.
    pub noise: Option<Noise>,
    /// JPEG quality.
    pub jpeg_quality: Option<u8>,
    /// Illumination gain field.
    pub illumination: Option<Illumination>,
    /// Low-contrast grey levels.
    pub low_contrast: bool,
    /// RGB sensor with a colour cast.
    pub colour: Option<ColourCast>,
    /// Clutter beside the markers.
    pub clutter: bool,
    /// Dust and hair.
    pub dust_hair: bool,
    /// Bits of the grey output when neither JPEG nor RGB.
    pub bits: u32,
}

/// A value drawn log-uniformly from `lo..hi` (both positive).
pub(crate) fn log_uniform(rng: &mut SmallRng, lo: f64, hi: f64) -> f64 {
    (rng.random_range(lo.ln()..hi.ln())).exp()
}

impl Degradations {
    /// Draws the severities of `kinds` (an empty list: a clean scene).
    pub fn draw(kinds: &[Degradation], rng: &mut SmallRng) -> Self {
        let mut d = Degradations {
            perspective: None,
            blur_sigma: rng.random_range(0.4..0.7),
            noise: None,
            jpeg_quality: None,
            illumination: None,
            low_contrast: false,
            colour: None,
            clutter: false,
            dust_hair: false,
            bits: 16,
        };
        for kind in kinds {
            match kind {
                Degradation::Perspective => {
                    d.perspective = Some(Tilt {
                        angle: rng.random_range(0.0..25f64.to_radians()),
                        axis: rng.random_range(0.0..PI),
                        focal_diagonals: log_uniform(rng, 1.5, 10.0),
                    })
                }
                Degradation::Blur => d.blur_sigma = rng.random_range(0.5..2.0),
                Degradation::Noise => {
                    d.noise = Some(Noise {
                        gaussian: rng.random_range(0.002..0.03),
                        shot: rng.random_range(0.0..0.02),
                    });
                    d.bits = d.bits.min([8, 10, 12][rng.random_range(0..3)]);
                }
                Degradation::Jpeg => d.jpeg_quality = Some(rng.random_range(50..=95)),
                Degradation::Illumination => {
                    d.illumination = Some(Illumination {
                        min_gain: rng.random_range(0.3..0.8),
                        direction: rng.random_range(0.0..TAU),
                        vignetting: rng.random_range(0.0..1.0),
                        center: (rng.random_range(0.3..0.7), rng.random_range(0.3..0.7)),
                    })
                }
                Degradation::LowContrast => {
                    d.low_contrast = true;
                    d.bits = d.bits.min([8, 12][rng.random_range(0..2)]);
                }
                Degradation::ColourCast => {
                    // One dominant channel (blue most often), the others dimmed.
                    let dominant = [2, 2, 0, 1][rng.random_range(0..4)];
                    let mut gains = [0.0; 3];
                    for (i, g) in gains.iter_mut().enumerate() {
                        *g = if i == dominant {
                            1.0
                        } else {
                            rng.random_range(0.35..0.9)
                        };
                    }
                    d.colour = Some(ColourCast {
                        gains,
                        sixteen_bit: rng.random_bool(0.3),
                    })
                }
                Degradation::Clutter => d.clutter = true,
                Degradation::DustHair => d.dust_hair = true,
            }
        }
        d
    }

    /// The same draw made `severity` times harsher (1: unchanged), for probing past the
    /// suite's ranges without moving its random stream: tilt, blur and noise scale by it,
    /// JPEG loses `severity` times as much quality (from 100, at least 5), and the dimmest
    /// gain and a colour cast's dimmed channels are raised to its power.
    pub fn harsher(mut self, severity: f64) -> Self {
        if let Some(t) = self.perspective.as_mut() {
            t.angle = (t.angle * severity).min(60f64.to_radians());
        }
        self.blur_sigma *= severity;
        if let Some(n) = self.noise.as_mut() {
            n.gaussian *= severity;
            n.shot *= severity;
        }
        if let Some(q) = self.jpeg_quality.as_mut() {
            let lost = f64::from(100 - *q) * severity;
            *q = (100.0 - lost).clamp(5.0, 100.0).round() as u8;
        }
        if let Some(i) = self.illumination.as_mut() {
            i.min_gain = i.min_gain.powf(severity);
        }
        if let Some(c) = self.colour.as_mut() {
            for g in c.gains.iter_mut() {
                *g = g.powf(severity);
            }
        }
        self
    }

    /// One line describing the severities.
    pub fn describe(&self) -> String {
        let mut parts = vec![format!("blur σ {:.2} px", self.blur_sigma)];
        if let Some(t) = self.perspective {
            parts.push(format!(
                "tilt {:.1}° about {:.0}°, focal {:.1} diagonals",
                t.angle.to_degrees(),
                t.axis.to_degrees(),
                t.focal_diagonals
            ));
        }
        if let Some(n) = self.noise {
            parts.push(format!(
                "noise {:.1} % + shot {:.1} %·√v",
                n.gaussian * 100.0,
                n.shot * 100.0
            ));
        }
        if let Some(q) = self.jpeg_quality {
            parts.push(format!("JPEG q{q}"));
        }
        if let Some(i) = self.illumination {
            parts.push(format!(
                "illumination min gain {:.2} (vignetting share {:.2})",
                i.min_gain, i.vignetting
            ));
        }
        if self.low_contrast {
            parts.push("low contrast".into());
        }
        if let Some(c) = self.colour {
            parts.push(format!(
                "colour gains {:.2}/{:.2}/{:.2} ({}-bit RGB)",
                c.gains[0],
                c.gains[1],
                c.gains[2],
                if c.sixteen_bit { 16 } else { 8 }
            ));
        }
        if self.clutter {
            parts.push("clutter".into());
        }
        if self.dust_hair {
            parts.push("dust and hair".into());
        }
        if self.jpeg_quality.is_none() && self.colour.is_none() {
            parts.push(format!("{} bits", self.bits));
        }
        parts.join(", ")
    }
}

/// Multiplies `plane` by the gain field of `illum` ([`illumination_gain`]).
pub fn apply_illumination(plane: &mut Plane, illum: &Illumination) {
    let gain = illumination_gain(plane.width, plane.height, illum);
    apply_gain(plane, &gain);
}

/// Multiplies `plane` by `gain` (same size), pixel by pixel.
pub fn apply_gain(plane: &mut Plane, gain: &Plane) {
    for (v, g) in plane.data.iter_mut().zip(&gain.data) {
        *v *= g;
    }
}

/// The gain field of `illum` over a `width × height` image: 1 at the brightest point,
/// `min_gain` at the dimmest pixel.
pub fn illumination_gain(width: usize, height: usize, illum: &Illumination) -> Plane {
    let (w, h) = (width as f64, height as f64);
    let (s, c) = illum.direction.sin_cos();
    // Linear fall-off along `direction`, normalised to [0, 1] over the image corners.
    let proj = |x: f64, y: f64| c * x + s * y;
    let corners = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].map(|(x, y)| proj(x, y));
    let lo = corners.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = corners.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let (cx, cy) = (illum.center.0 * w, illum.center.1 * h);
    let rmax2 = [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)]
        .iter()
        .map(|(x, y)| (x - cx).powi(2) + (y - cy).powi(2))
        .fold(0.0, f64::max)
        .max(1.0);
    let raw = |x: f64, y: f64| {
        let t = (proj(x, y) - lo) / (hi - lo).max(1e-9);
        let linear = 1.0 - (1.0 - illum.vignetting) * t;
        let vignette = 1.0 - illum.vignetting * ((x - cx).powi(2) + (y - cy).powi(2)) / rmax2;
        linear * vignette
    };
    let mut min_raw = f64::INFINITY;
    for r in 0..height {
        for col in 0..width {
            min_raw = min_raw.min(raw(col as f64, r as f64));
        }
    }
    // Rescale the fall-off so that the dimmest pixel gets exactly `min_gain`.
    let k = (1.0 - illum.min_gain) / (1.0 - min_raw).max(1e-9);
    let mut gain = Plane::filled(width, height, 1.0);
    for r in 0..height {
        for col in 0..width {
            gain.data[r * width + col] = (1.0 - k * (1.0 - raw(col as f64, r as f64))) as f32;
        }
    }
    gain
}

/// Adds sensor noise to one channel.
fn add_noise(values: &mut [f32], noise: &Noise, rng: &mut SmallRng) {
    for v in values.iter_mut() {
        let sigma = noise.gaussian + noise.shot * (v.max(0.0) as f64).sqrt();
        let n: f64 = rng.sample(StandardNormal);
        *v += (sigma * n) as f32;
    }
}

fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

fn to_u16(v: f32) -> u16 {
    (v.clamp(0.0, 1.0) * 65535.0).round() as u16
}

/// Encodes `image` as JPEG at `quality` and decodes it back.
fn jpeg_roundtrip(image: &DynamicImage, quality: u8) -> Result<DynamicImage> {
    let mut bytes = Vec::new();
    let encoder = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, quality);
    image.write_with_encoder(encoder)?;
    Ok(image::load_from_memory_with_format(
        &bytes,
        image::ImageFormat::Jpeg,
    )?)
}

/// The sensor and file stages: colour cast (RGB), noise, then JPEG or quantisation, and the
/// conversion to the detector's [`GreyImage`] (through `GreyImage::from_dynamic` for RGB and
/// JPEG images).
pub fn finish(plane: &Plane, d: &Degradations, rng: &mut SmallRng) -> Result<GreyImage> {
    let (w, h) = (plane.width, plane.height);
    let (wu, hu) = (w as u32, h as u32);
    let size_err = || StressError::new("image buffer size");
    if let Some(colour) = d.colour {
        let mut channels: Vec<Vec<f32>> = colour
            .gains
            .iter()
            .map(|&g| plane.data.iter().map(|&v| v * g as f32).collect())
            .collect();
        if let Some(noise) = &d.noise {
            for ch in channels.iter_mut() {
                add_noise(ch, noise, rng);
            }
        }
        let interleaved = |i: usize| [channels[0][i], channels[1][i], channels[2][i]];
        let dynamic = if colour.sixteen_bit && d.jpeg_quality.is_none() {
            let data: Vec<u16> = (0..w * h)
                .flat_map(|i| interleaved(i).map(to_u16))
                .collect();
            DynamicImage::ImageRgb16(
                ImageBuffer::<Rgb<u16>, Vec<u16>>::from_raw(wu, hu, data).ok_or_else(size_err)?,
            )
        } else {
            let data: Vec<u8> = (0..w * h).flat_map(|i| interleaved(i).map(to_u8)).collect();
            DynamicImage::ImageRgb8(
                ImageBuffer::<Rgb<u8>, Vec<u8>>::from_raw(wu, hu, data).ok_or_else(size_err)?,
            )
        };
        let dynamic = match d.jpeg_quality {
            Some(q) => jpeg_roundtrip(&dynamic, q)?,
            None => dynamic,
        };
        return Ok(GreyImage::from_dynamic(&dynamic)?);
    }
    let mut values = plane.data.clone();
    if let Some(noise) = &d.noise {
        add_noise(&mut values, noise, rng);
    }
    if let Some(q) = d.jpeg_quality {
        let data: Vec<u8> = values.iter().map(|&v| to_u8(v)).collect();
        let grey = DynamicImage::ImageLuma8(
            ImageBuffer::<Luma<u8>, Vec<u8>>::from_raw(wu, hu, data).ok_or_else(size_err)?,
        );
        return Ok(GreyImage::from_dynamic(&jpeg_roundtrip(&grey, q)?)?);
    }
    let levels = ((1u32 << d.bits.clamp(1, 16)) - 1) as f32;
    for v in values.iter_mut() {
        *v = (v.clamp(0.0, 1.0) * levels).round() / levels;
    }
    Ok(GreyImage::new(w, h, values)?)
}
