//! Square windows ("snapshots") around a marker, with radial apodisation (docs/design.md#hp-window,
//! docs/design.md#stamp-window). Shared by the HP code and stamp detectors.

use crate::error::Result;
use crate::grey_image::GreyImage;

/// A `size × size` window of an image centred on an integer pixel.
#[derive(Clone, Debug)]
pub struct Snapshot {
    /// The window's pixels (zero outside the source image).
    pub image: GreyImage,
    /// Source-image pixel `(col, row)` at the window's centre index `(size div 2, size div 2)`.
    pub center: (i64, i64),
}

impl Snapshot {
    /// Cuts the `size × size` window whose centre index `(size div 2, size div 2)` is the source
    /// pixel `center`; parts outside the source are filled with 0.
    pub fn extract(source: &GreyImage, center: (i64, i64), size: usize) -> Result<Snapshot> {
        let half = (size / 2) as i64;
        let image = source.window(center.0 - half, center.1 - half, size, size, 0.0)?;
        Ok(Snapshot { image, center })
    }

    /// Multiplies the window by the radial apodisation `w(d) = (1 + cos(π·(d/ρ)^exponent))/2`
    /// for `d < ρ = size/2`, 0 beyond, `d` being the distance to the centre index. Exponent 1 is
    /// the Hann window of the HP detector, 4 the flat-top window of the stamp detector.
    pub fn apodize(&mut self, exponent: f64) {
        let (w, h) = (self.image.width(), self.image.height());
        let rho = w.min(h) as f64 / 2.0;
        let (cx, cy) = ((w / 2) as f64, (h / 2) as f64);
        let pixels = self.image.pixels_mut();
        for r in 0..h {
            for c in 0..w {
                let d = ((c as f64 - cx).powi(2) + (r as f64 - cy).powi(2)).sqrt();
                let weight = if d < rho {
                    0.5 * (1.0 + (std::f64::consts::PI * (d / rho).powf(exponent)).cos())
                } else {
                    0.0
                };
                pixels[r * w + c] *= weight as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extract_and_apodize() {
        let source = GreyImage::new(4, 4, (0..16).map(|v| v as f32).collect()).unwrap();
        let mut s = Snapshot::extract(&source, (0, 0), 4).unwrap();
        // Centre index (2, 2) is source pixel (0, 0); rows/cols before it are outside.
        assert_eq!(s.image.get(2, 2), Some(0.0));
        assert_eq!(s.image.get(3, 3), Some(5.0));
        assert_eq!(s.image.get(0, 0), Some(0.0));
        s.apodize(1.0);
        assert_eq!(
            s.image.get(3, 3),
            Some(5.0 * 0.5 * (1.0 + (std::f64::consts::PI / 2.0 * 2f64.sqrt()).cos()) as f32)
        );
    }
}
