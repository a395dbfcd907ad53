//! The fine phase engine (METHOD.md §4): image → spectrum → two lobes → two phase planes.
//!
//! Steps, each in its own module:
//! 1. [`spectrum`]: real-to-complex 2-D FFT (plans and buffers cached per image size);
//! 2. [`lobes`]: the two strongest lobes in a ring of the half spectrum, ~90° apart;
//! 3. [`bandpass`]: Gaussian band-pass around each lobe on a demodulated, decimated grid,
//!    unwrapped phase, least-squares plane on the central crop (the original's estimate);
//! 4. [`refine`]: windowed Gauss–Newton refinement of both planes on the full image, which
//!    removes the harmonic leakage of step 3 (default on).
//!
//! Image frame of all results: `x = col − C div 2`, `y = row − R div 2`, pixels, y down.

pub mod bandpass;
pub mod lobes;
pub mod plane;
pub mod refine;
pub mod spectrum;

pub use bandpass::PhaseMap;
pub use lobes::Lobe;
pub use plane::{fit_plane, wrap_angle, wrap_to_pi, PhasePlane};

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use bandpass::{fast_size, BandpassPlan};
use refine::RefinePlan;
use spectrum::SpectrumPlan;

/// Smallest accepted image side, pixels: below this no lobe can be told from DC.
pub const MIN_IMAGE_SIDE: usize = 16;

/// Parameters of the phase engine (METHOD.md §7, with the same names where they exist).
#[derive(Clone, Debug, PartialEq)]
pub struct PhaseParams {
    /// Gaussian band-pass σ, spectrum bins (cycles per image). Default 3.
    pub sigma: f64,
    /// Lobes at a radius ≤ this many bins are ignored (DC, illumination gradients).
    /// Default 4: at least 4 periods must be visible. (The original uses 20.)
    pub min_frequency: f64,
    /// Lobes at a radius > this many bins are ignored. Default: no limit below Nyquist.
    pub max_frequency: f64,
    /// Minimum smoothed lobe magnitude divided by the pixel count. Default 1e-5.
    pub min_peak_power: f64,
    /// Minimum lobe magnitude divided by the mean magnitude of the search ring. Default 8:
    /// the strongest bin of white noise on a 1024² image reaches about 5.
    pub min_peak_prominence: f64,
    /// Fraction of each image side removed (half on each side) before the plane fit of the
    /// band-pass estimate, in `[0, 1)`. Default 0.5.
    pub crop_factor: f64,
    /// Windowed Gauss–Newton iterations on the full image after the band-pass estimate;
    /// 0 keeps the original method's result. Default 3 (converges in 2 on clean images).
    pub refine_iterations: usize,
    /// Inverse-transform each lobe at full image size instead of on the demodulated, decimated
    /// grid. Default false. Both evaluate the same band-limited phase field exactly, but the
    /// original's unweighted plane fit averages the leakage ripple better over every pixel, so
    /// with `refine_iterations = 0` the full-size transform is always used; with refinement the
    /// band-pass planes are only a starting point and the result is identical either way.
    pub full_resolution_bandpass: bool,
    /// Keep the decimated phase maps in the result (for display). Default false.
    pub keep_phase_maps: bool,
}

impl Default for PhaseParams {
    fn default() -> Self {
        PhaseParams {
            sigma: 3.0,
            min_frequency: 4.0,
            max_frequency: f64::INFINITY,
            min_peak_power: 1e-5,
            min_peak_prominence: 8.0,
            crop_factor: 0.5,
            refine_iterations: 3,
            full_resolution_bandpass: false,
            keep_phase_maps: false,
        }
    }
}

impl PhaseParams {
    /// Checks every field, naming the first invalid one.
    pub fn validate(&self) -> Result<()> {
        if !(self.sigma.is_finite() && self.sigma > 0.0) {
            return Err(Error::parameter(
                "sigma",
                format!("must be > 0 bins, got {}", self.sigma),
            ));
        }
        if !(self.min_frequency.is_finite() && self.min_frequency >= 0.0) {
            return Err(Error::parameter(
                "min_frequency",
                format!("must be ≥ 0 bins, got {}", self.min_frequency),
            ));
        }
        if self.max_frequency.is_nan() || self.max_frequency <= self.min_frequency {
            return Err(Error::parameter(
                "max_frequency",
                format!("must exceed min_frequency, got {}", self.max_frequency),
            ));
        }
        if self.min_peak_power.is_nan() || self.min_peak_power < 0.0 {
            return Err(Error::parameter(
                "min_peak_power",
                format!("must be ≥ 0, got {}", self.min_peak_power),
            ));
        }
        if self.min_peak_prominence.is_nan() || self.min_peak_prominence < 0.0 {
            return Err(Error::parameter(
                "min_peak_prominence",
                format!("must be ≥ 0, got {}", self.min_peak_prominence),
            ));
        }
        if !(0.0..1.0).contains(&self.crop_factor) {
            return Err(Error::parameter(
                "crop_factor",
                format!("must be in [0, 1), got {}", self.crop_factor),
            ));
        }
        Ok(())
    }
}

/// Result of the phase engine on one image.
#[derive(Clone, Debug)]
pub struct PhaseAnalysis {
    /// Image size `(rows, cols)`.
    pub size: (usize, usize),
    /// The two phase planes (image frame). Plane 1's direction is in `[0, π/2)`, plane 2's in
    /// `[π/2, π)`, both up to the refinement's sub-bin adjustment.
    pub planes: [PhasePlane; 2],
    /// The band-pass estimate before refinement (the original method's planes).
    pub bandpass_planes: [PhasePlane; 2],
    /// The two spectral lobes found.
    pub lobes: [Lobe; 2],
    /// Amplitude `A` of each fundamental cosine `A·cos φ`, intensity units.
    pub amplitudes: [f64; 2],
    /// Estimated standard deviation of each plane's offset `c` from image noise, radians
    /// (an upper bound: unmodelled harmonics count as noise).
    pub phase_std: [f64; 2],
    /// Fraction of the window-weighted image variance carried by the two fundamentals, `[0, 1]`.
    pub quality: f64,
    /// Refinement iterations run (0 when refinement is off).
    pub iterations: usize,
    /// Decimated unwrapped phase maps, when [`PhaseParams::keep_phase_maps`] is set.
    pub maps: Option<[PhaseMap; 2]>,
}

impl PhaseAnalysis {
    /// Mean grid period of the two planes, pixels.
    pub fn mean_pixel_period(&self) -> f64 {
        (self.planes[0].pixel_period() + self.planes[1].pixel_period()) / 2.0
    }
}

/// Plans and buffers for one image size.
struct SizeCache {
    rows: usize,
    cols: usize,
    sigma: f64,
    full_resolution: bool,
    spectrum: SpectrumPlan,
    bandpass: BandpassPlan,
    refine: RefinePlan,
    magnitude: Vec<f32>,
}

/// The phase engine. Keeps FFT plans and work buffers for the last few image sizes, so calling
/// it on a stream of same-size frames allocates nothing after the first frame.
#[derive(Default)]
pub struct PhaseEngine {
    caches: Vec<SizeCache>,
}

/// How many image sizes keep their plans (HP/Stamp detectors alternate full frames and
/// snapshots).
const CACHED_SIZES: usize = 4;

impl PhaseEngine {
    /// An engine with empty caches.
    pub fn new() -> Self {
        Self::default()
    }

    fn cache_for(
        &mut self,
        rows: usize,
        cols: usize,
        sigma: f64,
        full_resolution: bool,
    ) -> &mut SizeCache {
        let matches = |c: &SizeCache| {
            c.rows == rows
                && c.cols == cols
                && c.sigma == sigma
                && c.full_resolution == full_resolution
        };
        if let Some(pos) = self.caches.iter().position(matches) {
            // Most recently used goes last.
            let cache = self.caches.remove(pos);
            self.caches.push(cache);
        } else {
            if self.caches.len() >= CACHED_SIZES {
                self.caches.remove(0);
            }
            // Decimated band-pass grid: ±6σ bins around the lobe (Gaussian weight < 2e-8 beyond).
            let needed = fast_size((12.0 * sigma).ceil() as usize);
            let (mr, mc) = if full_resolution {
                (rows, cols)
            } else {
                (needed.min(rows), needed.min(cols))
            };
            self.caches.push(SizeCache {
                rows,
                cols,
                sigma,
                full_resolution,
                spectrum: SpectrumPlan::new(rows, cols),
                bandpass: BandpassPlan::new(mr, mc),
                refine: RefinePlan::new(rows, cols),
                magnitude: Vec::new(),
            });
        }
        let last = self.caches.len() - 1;
        &mut self.caches[last]
    }

    /// Measures the two phase planes of `image` (bright dots; invert dark-dot images first, see
    /// [`GreyImage::inverted`]).
    ///
    /// Errors: [`Error::InvalidImage`] if a side is below [`MIN_IMAGE_SIDE`],
    /// [`Error::InvalidParameter`] for bad `params`, [`Error::PatternNotFound`] when no two
    /// lobes stand out of the spectrum.
    pub fn analyze(&mut self, image: &GreyImage, params: &PhaseParams) -> Result<PhaseAnalysis> {
        params.validate()?;
        let (rows, cols) = (image.height(), image.width());
        if rows < MIN_IMAGE_SIDE || cols < MIN_IMAGE_SIDE {
            return Err(Error::InvalidImage(format!(
                "{cols}x{rows} pixels is too small for the phase engine (at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE})"
            )));
        }
        let full_resolution = params.full_resolution_bandpass || params.refine_iterations == 0;
        let cache = self.cache_for(rows, cols, params.sigma, full_resolution);
        let spectrum = cache.spectrum.forward(image.pixels());
        let search = lobes::LobeSearch {
            min_radius: params.min_frequency,
            max_radius: params.max_frequency,
            sigma: params.sigma,
            min_peak_power: params.min_peak_power,
            min_peak_prominence: params.min_peak_prominence,
        };
        let (lobe1, lobe2) = lobes::find_lobes(&spectrum, &search, &mut cache.magnitude).map_err(|e| {
            Error::PatternNotFound(match e {
                lobes::LobeError::NoFirstPeak { power, prominence } => format!(
                    "no spectral lobe (strongest: power {power:.2e}, prominence {prominence:.1}; need > {:.1e} and ≥ {})",
                    params.min_peak_power, params.min_peak_prominence
                ),
                lobes::LobeError::NoSecondPeak { power, prominence } => format!(
                    "only one spectral lobe, no second grid direction (next: power {power:.2e}, prominence {prominence:.1})"
                ),
            })
        })?;
        let mut maps = Vec::new();
        let mut bandpass_planes = [PhasePlane {
            a: 0.0,
            b: 0.0,
            c: 0.0,
        }; 2];
        for (k, lobe) in [lobe1, lobe2].iter().enumerate() {
            let (plane, map) = bandpass::lobe_phase(
                &spectrum,
                (lobe.kx, lobe.ky),
                params.sigma,
                params.crop_factor,
                &mut cache.bandpass,
                params.keep_phase_maps,
            )
            .ok_or_else(|| Error::PatternNotFound("phase plane fit is degenerate".into()))?;
            bandpass_planes[k] = plane;
            maps.extend(map);
        }
        let (planes, amplitudes, phase_std, quality, iterations) = if params.refine_iterations > 0 {
            let r = refine::refine(
                image.pixels(),
                bandpass_planes,
                &mut cache.refine,
                params.refine_iterations,
            );
            // Each fundamental A·cos carries A²/2 of the variance; the offset's noise follows
            // from the residual: var(c) = 2σ²/(A²·N_eff).
            let explained = (r.amplitudes[0].powi(2) + r.amplitudes[1].powi(2)) / 2.0;
            let std = |amp: f64| {
                if amp > 0.0 {
                    (2.0 * r.residual / (amp * amp * r.effective_pixels)).sqrt()
                } else {
                    f64::INFINITY
                }
            };
            let quality = if r.variance > 0.0 {
                (explained / r.variance).min(1.0)
            } else {
                0.0
            };
            (
                r.planes,
                r.amplitudes,
                [std(r.amplitudes[0]), std(r.amplitudes[1])],
                quality,
                r.iterations,
            )
        } else {
            (bandpass_planes, [f64::NAN; 2], [f64::NAN; 2], f64::NAN, 0)
        };
        let maps = <[PhaseMap; 2]>::try_from(maps).ok();
        Ok(PhaseAnalysis {
            size: (rows, cols),
            planes,
            bandpass_planes,
            lobes: [lobe1, lobe2],
            amplitudes,
            phase_std,
            quality,
            iterations,
            maps,
        })
    }
}
