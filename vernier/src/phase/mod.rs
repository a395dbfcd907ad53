//! The fine phase engine (docs/design.md#phase-engine): image → spectrum → two lobes → two phase
//! planes.
//!
//! Steps, each in its own module:
//! 1. `spectrum`: real-to-complex 2-D FFT (plans and buffers cached per image size);
//! 2. `lobes`: the two strongest lobes in a ring of the half spectrum, ~90° apart;
//! 3. `bandpass`: Gaussian band-pass around each lobe on a demodulated, decimated grid,
//!    unwrapped phase, least-squares plane on the central crop (the original's estimate);
//! 4. `refine`: windowed Gauss–Newton refinement of both planes on the full image, which
//!    removes the harmonic leakage of step 3 (default on).
//!
//! [`inspect`] adds display products (spectrum, wrapped phase) for viewers.
//!
//! Image frame of all results: `x = col − C div 2`, `y = row − R div 2`, pixels, y down.

mod bandpass;
pub(crate) mod fft_size;
pub mod field_fit;
pub mod inspect;
mod lobes;
mod noise;
mod normal_equations;
pub mod plane;
mod refine;
mod spectrum;

pub use bandpass::PhaseMap;
pub use field_fit::{
    fit_dot_field, fit_dot_field_against, fit_dot_field_tracked, FieldFit, NodeMask, Rival,
    TiltStart,
};
pub use inspect::{PhaseInspection, SpectrumView};
pub use lobes::Lobe;
pub use plane::{fit_plane, wrap_angle, wrap_to_pi, PhasePlane};

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::lru::Lru;
use bandpass::BandpassPlan;
pub(crate) use noise::quantisation_variance_in;
use noise::NoisePlan;
use refine::RefinePlan;
use spectrum::SpectrumPlan;

/// Smallest accepted image side, pixels: below this no lobe can be told from DC.
pub const MIN_IMAGE_SIDE: usize = 16;

/// Parameters of the phase engine (docs/design.md#settings; the original's names where it has
/// them).
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
    /// Minimum lobe prominence: root of its 3×3 neighbourhood energy over that of an average
    /// neighbourhood of the search ring. Default 5: the strongest lobe of white noise on a
    /// 1024² image reaches about 2.
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
    /// Run the spectral stage (FFT, lobe search, band-pass; docs/design.md#phase-binning) on a
    /// 2×2-binned copy of images of at least 128 px per side, 4× cheaper; the full-size
    /// refinement then restores full accuracy (tests/periodic_roundtrip.rs checks both give the
    /// same result). Only used when refining; grids finer than 6 px per period fall back to the
    /// full-size stage. Default true.
    pub spectrum_binning: bool,
    /// Keep the decimated phase maps in the result (for display). Default false.
    pub keep_phase_maps: bool,
    /// Least white-noise variance of the analysed image, intensity units²: the rounding of its
    /// source when the analysed image is a scaled copy whose own values no longer show the
    /// source's levels (the stamp's apodised windows, docs/design.md#uncertainty). Default 0:
    /// the rounding is read from the analysed image itself.
    pub rounding_variance: f64,
}

/// Where a coarse step that already sees the grid (e.g. the HP code finders) expects the two
/// spectral lobes of an image: the lobe search then looks only there, with a lower prominence
/// threshold. A search over a few dozen bins instead of the whole ring keeps the same
/// false-alarm rate at a much lower threshold, so a grid buried in noise is still measured,
/// and clutter elsewhere in the spectrum can never be taken for it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LobePrior {
    /// Expected frequency vector of each grid direction, cycles per pixel `(col, row)` in the
    /// analysed image (either sign: a lobe and its mirror are the same).
    pub frequencies: [[f64; 2]; 2],
    /// Search radius around each, as a fraction of its length (scale error, angle error and
    /// perspective of the coarse step); at least 2 bins.
    pub tolerance: f64,
    /// Smallest prominence accepted there (see [`PhaseParams::min_peak_prominence`]).
    pub min_prominence: f64,
}

impl Default for PhaseParams {
    fn default() -> Self {
        PhaseParams {
            sigma: 3.0,
            min_frequency: 4.0,
            max_frequency: f64::INFINITY,
            min_peak_power: 1e-5,
            min_peak_prominence: 5.0,
            crop_factor: 0.5,
            refine_iterations: 3,
            full_resolution_bandpass: false,
            spectrum_binning: true,
            keep_phase_maps: false,
            rounding_variance: 0.0,
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
        if !(self.rounding_variance.is_finite() && self.rounding_variance >= 0.0) {
            return Err(Error::parameter(
                "rounding_variance",
                format!("must be ≥ 0, got {}", self.rounding_variance),
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
    /// The estimate of the spectral stage, before the full-size refinement (the original
    /// method's planes when `refine_iterations = 0`).
    pub bandpass_planes: [PhasePlane; 2],
    /// The two spectral lobes found (bins of the analysed spectrum: the 2×2-binned image's for
    /// images of at least 128 px per side when refining).
    pub lobes: [Lobe; 2],
    /// Amplitude `A` of each fundamental cosine `A·cos φ`, intensity units.
    pub amplitudes: [f64; 2],
    /// Estimated standard deviation of each plane's offset `c` from white image noise, radians
    /// (docs/design.md#uncertainty; at least the floor set by [`MIN_NOISE_STD`]).
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

/// Planes refined against the image, with their quality figures.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refinement {
    /// Refined planes (image frame).
    pub planes: [PhasePlane; 2],
    /// Amplitude `A` of each fundamental cosine, intensity units.
    pub amplitudes: [f64; 2],
    /// Estimated standard deviation of each plane's offset `c` from white image noise, radians
    /// (docs/design.md#uncertainty).
    pub phase_std: [f64; 2],
    /// Fraction of the weighted image variance carried by the two fundamentals, `[0, 1]`.
    pub quality: f64,
    /// Gauss–Newton iterations run.
    pub iterations: usize,
}

/// Floor of the white-noise standard deviation behind [`Refinement::phase_std`], fraction of
/// full scale: the quantisation noise of a 16-bit image, `1/(65535·√12)` ≈ 4.4e-6, the finest
/// input the library reads. A noise-free render then reports a tiny but positive uncertainty
/// instead of 0 (a singular covariance breaks filters that invert it). It does not cover the
/// model error of noise-free images (up to ~7e-4 px on sharp, aliased dots,
/// docs/design.md#accuracy).
pub const MIN_NOISE_STD: f64 = 1.0 / (65535.0 * 3.464_101_615_137_754_6);

impl Refinement {
    /// Quality figures of a fit. `white_noise` is the robust noise variance of the image
    /// ([`noise`], docs/design.md#uncertainty); the fit residual, which also counts the dots'
    /// harmonics and anything else the two cosines do not model, is an upper bound of it and is
    /// used when the estimate is missing or larger. Neither changes the planes.
    fn from_fit(r: &refine::Refined, white_noise: Option<f64>) -> Self {
        // Each fundamental A·cos carries A²/2 of the variance; the offset's noise follows from
        // the white-noise variance σ²: var(c) = 2σ²/(A²·N_eff).
        let explained = (r.amplitudes[0].powi(2) + r.amplitudes[1].powi(2)) / 2.0;
        let variance = white_noise
            .map_or(r.residual, |v| v.min(r.residual))
            .max(MIN_NOISE_STD * MIN_NOISE_STD);
        let std = |amp: f64| {
            if amp > 0.0 && r.effective_pixels > 0.0 {
                (2.0 * variance / (amp * amp * r.effective_pixels)).sqrt()
            } else {
                f64::INFINITY
            }
        };
        Refinement {
            planes: r.planes,
            amplitudes: r.amplitudes,
            phase_std: [std(r.amplitudes[0]), std(r.amplitudes[1])],
            quality: if r.variance > 0.0 {
                (explained / r.variance).min(1.0)
            } else {
                0.0
            },
            iterations: r.iterations,
        }
    }
}

/// Plans and buffers for one image size (each part built on first use).
struct SizeCache {
    rows: usize,
    cols: usize,
    sigma: f64,
    full_resolution: bool,
    spectrum: Option<SpectrumPlan>,
    bandpass: Option<BandpassPlan>,
    refine: Option<RefinePlan>,
    noise: Option<NoisePlan>,
    /// 2×2-binned copy of the image for the coarse stage.
    binned: Vec<f32>,
}

/// The FFT planners of one engine: one per engine, as rustfft advises, so that plans of all
/// sizes share the planner's caches of butterflies and twiddle factors.
pub(crate) struct Planners {
    complex: rustfft::FftPlanner<f32>,
    real: realfft::RealFftPlanner<f32>,
}

impl Default for Planners {
    fn default() -> Self {
        Planners {
            complex: rustfft::FftPlanner::new(),
            real: realfft::RealFftPlanner::new(),
        }
    }
}

impl SizeCache {
    fn spectrum(&mut self, planners: &mut Planners) -> &mut SpectrumPlan {
        let (rows, cols) = (self.rows, self.cols);
        self.spectrum.get_or_insert_with(|| {
            SpectrumPlan::new(rows, cols, &mut planners.real, &mut planners.complex)
        })
    }
    fn bandpass(&mut self, planners: &mut Planners) -> &mut BandpassPlan {
        let (rows, cols) = (self.rows, self.cols);
        let (sigma, full) = (self.sigma, self.full_resolution);
        self.bandpass.get_or_insert_with(|| {
            // Decimated band-pass grid: ±6σ bins around the lobe (Gaussian weight < 2e-8 beyond).
            let needed = fft_size::at_least((12.0 * sigma).ceil() as usize);
            let (mr, mc) = if full {
                (rows, cols)
            } else {
                (needed.min(rows), needed.min(cols))
            };
            BandpassPlan::new(mr, mc, &mut planners.complex)
        })
    }
    fn refine(&mut self) -> &mut RefinePlan {
        let (rows, cols) = (self.rows, self.cols);
        self.refine
            .get_or_insert_with(|| RefinePlan::new(rows, cols))
    }
    fn noise(&mut self) -> &mut NoisePlan {
        let (rows, cols) = (self.rows, self.cols);
        self.noise.get_or_insert_with(|| NoisePlan::new(rows, cols))
    }
}

/// The phase engine. One FFT planner, and FFT plans and the image-sized work buffers (spectrum,
/// band-pass grid, refinement kernels, binned copy) for the last few image sizes: on a stream
/// of same-size frames those are built once. What is still allocated per call is small and
/// proportional to a side or to the band-pass grid (coordinate and weight rows in the
/// refinement, the decimated phase maps), not to the image.
///
/// # Example
///
/// A periodic grid of 10 µm period seen at 1.25 µm per pixel (8 px per period), rendered at a
/// known pose; the two phase planes give the grid's pixel period and direction:
///
/// ```
/// use vernier::layout::PeriodicLayout;
/// use vernier::render::{render, RenderOptions};
/// use vernier::{PhaseEngine, PhaseParams, Pose};
///
/// # fn main() -> vernier::Result<()> {
/// let layout = PeriodicLayout::new(10.0, 41, 41)?;
/// let truth = Pose::planar(2.5, -1.0, 0.3, 1.25);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(128, 128) };
/// let image = render(&layout, &truth, &options)?;
///
/// let mut engine = PhaseEngine::new(); // keep it: plans are reused for same-size frames
/// let analysis = engine.analyze(&image, &PhaseParams::default())?;
/// for plane in &analysis.planes {
///     assert!((plane.pixel_period() - 8.0).abs() < 1e-3); // pixels per period
/// }
/// // Plane 1 is the grid direction in [0, π/2): here the pattern x axis, at `alpha`.
/// assert!((analysis.planes[0].angle() - truth.alpha).abs() < 1e-4);
/// assert!(analysis.quality > 0.5);
/// # Ok(())
/// # }
/// ```
pub struct PhaseEngine {
    /// Plans and buffers by `(rows, cols, σ bits, full resolution)`.
    caches: Lru<(usize, usize, u64, bool), SizeCache>,
    planners: Planners,
}

impl Default for PhaseEngine {
    fn default() -> Self {
        PhaseEngine {
            caches: Lru::new(CACHED_SIZES),
            planners: Planners::default(),
        }
    }
}

/// How many image sizes keep their plans (HP/Stamp detectors alternate full frames and
/// snapshots; binning adds the half size).
const CACHED_SIZES: usize = 6;

/// Images at least this large on both sides run the spectral stage on a 2×2-binned copy.
const BINNING_MIN_SIDE: usize = 128;

/// Shortest grid period, in binned pixels, accepted from the binned stage: below this the
/// binned spectrum folds harmonics onto the fundamentals and the full-size search is used.
const BINNED_MIN_PERIOD: f64 = 3.0;

/// Band-pass result of the spectral stage.
struct SpectralEstimate {
    lobes: [Lobe; 2],
    planes: [PhasePlane; 2],
    maps: Option<[PhaseMap; 2]>,
}

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
    ) -> (&mut SizeCache, &mut Planners) {
        let key = (rows, cols, sigma.to_bits(), full_resolution);
        let cache = self.caches.get_or_insert_with(key, || SizeCache {
            rows,
            cols,
            sigma,
            full_resolution,
            spectrum: None,
            bandpass: None,
            refine: None,
            noise: None,
            binned: Vec::new(),
        });
        (cache, &mut self.planners)
    }

    /// Measures the two phase planes of `image` (bright dots; invert dark-dot images first, see
    /// [`GreyImage::inverted`]).
    ///
    /// Errors: [`Error::InvalidImage`] if a side is below [`MIN_IMAGE_SIDE`],
    /// [`Error::InvalidParameter`] for bad `params`, [`Error::PatternNotFound`] when no two
    /// lobes stand out of the spectrum.
    pub fn analyze(&mut self, image: &GreyImage, params: &PhaseParams) -> Result<PhaseAnalysis> {
        self.analyze_with_prior(image, params, None)
    }

    /// [`PhaseEngine::analyze`], with the lobes searched only where `prior` expects them.
    pub fn analyze_with_prior(
        &mut self,
        image: &GreyImage,
        params: &PhaseParams,
        prior: Option<&LobePrior>,
    ) -> Result<PhaseAnalysis> {
        params.validate()?;
        let (rows, cols) = (image.height(), image.width());
        if rows < MIN_IMAGE_SIDE || cols < MIN_IMAGE_SIDE {
            return Err(Error::InvalidImage(format!(
                "{cols}x{rows} pixels is too small for the phase engine (at least {MIN_IMAGE_SIDE}x{MIN_IMAGE_SIDE})"
            )));
        }
        let refining = params.refine_iterations > 0;
        let full_resolution = params.full_resolution_bandpass || !refining;
        let binning = refining
            && params.spectrum_binning
            && !params.full_resolution_bandpass
            && rows.min(cols) >= BINNING_MIN_SIDE;

        // Coarse stage on the binned image when allowed, else (or if the grid is too fine for
        // it) on the image itself.
        let mut coarse = None;
        if binning {
            coarse = self.binned_estimate(image, params, prior)?;
        }
        let coarse = match coarse {
            Some(c) => c,
            None => {
                let (cache, planners) = self.cache_for(rows, cols, params.sigma, full_resolution);
                spectral_estimate(image.pixels(), cache, planners, params, prior, 1.0)?
            }
        };
        let refined = if refining {
            let (cache, _) = self.cache_for(rows, cols, params.sigma, full_resolution);
            let r = refine::refine(
                image.pixels(),
                coarse.planes,
                cache.refine(),
                params.refine_iterations,
            );
            let noise = noise::noise_variance(
                image.pixels(),
                None,
                &r.planes,
                cache.noise(),
                params.rounding_variance,
            );
            Refinement::from_fit(&r, noise)
        } else {
            Refinement {
                planes: coarse.planes,
                amplitudes: [f64::NAN; 2],
                phase_std: [f64::NAN; 2],
                quality: f64::NAN,
                iterations: 0,
            }
        };
        let Refinement {
            planes,
            amplitudes,
            phase_std,
            quality,
            iterations,
        } = refined;
        Ok(PhaseAnalysis {
            size: (rows, cols),
            planes,
            bandpass_planes: coarse.planes,
            lobes: coarse.lobes,
            amplitudes,
            phase_std,
            quality,
            iterations,
            maps: coarse.maps,
        })
    }

    /// Refines `start` planes against `image` (docs/design.md#phase-weighted) with a per-pixel
    /// weight map (row-major, same size as the image, values ≥ 0; NaN counts as 0) multiplying the
    /// engine's window.
    ///
    /// For coarse steps that know which pixels do not follow the periodic model: a Megarena's
    /// missing code dots, an HP code's finders and ID dots, a stamp's frame and glyphs. Giving
    /// them weight 0 removes the bias they cause (up to 1e-2 px on a Megarena with the plain
    /// refinement). No detector calls it at present (they keep such pixels out by other means).
    /// Cost ≈ 50 multiply-adds per pixel and iteration.
    pub fn refine_weighted(
        &mut self,
        image: &GreyImage,
        weights: &[f32],
        start: [PhasePlane; 2],
        iterations: usize,
    ) -> Result<Refinement> {
        let (rows, cols) = (image.height(), image.width());
        if weights.len() != rows * cols {
            return Err(Error::parameter(
                "weights",
                format!("{} weights for a {cols}x{rows} image", weights.len()),
            ));
        }
        if rows < MIN_IMAGE_SIDE || cols < MIN_IMAGE_SIDE {
            return Err(Error::InvalidImage(format!(
                "{cols}x{rows} pixels is too small for the phase engine"
            )));
        }
        let (cache, _) = self.cache_for(rows, cols, PhaseParams::default().sigma, false);
        let r = refine::refine_weighted(
            image.pixels(),
            weights,
            start,
            cache.refine(),
            iterations.max(1),
        );
        if r.effective_pixels <= 0.0 {
            return Err(Error::PatternNotFound(
                "all refinement weights are zero".into(),
            ));
        }
        let noise =
            noise::noise_variance(image.pixels(), Some(weights), &r.planes, cache.noise(), 0.0);
        Ok(Refinement::from_fit(&r, noise))
    }

    /// Spectral stage on the 2×2-binned image, plus one refinement step there; planes returned
    /// in the full image's frame. `None` when the grid is too fine for the binned image.
    fn binned_estimate(
        &mut self,
        image: &GreyImage,
        params: &PhaseParams,
        prior: Option<&LobePrior>,
    ) -> Result<Option<SpectralEstimate>> {
        let (rows, cols) = (image.height(), image.width());
        let (rb, cb) = (rows / 2, cols / 2);
        let (cache, planners) = self.cache_for(rb, cb, params.sigma, false);
        let mut binned = std::mem::take(&mut cache.binned);
        crate::grey_image::bin_2x2(image.pixels(), cols, rb, cb, &mut binned);
        let estimate = spectral_estimate(&binned, cache, planners, params, prior, 2.0);
        let result = match estimate {
            Ok(mut e)
                if e.planes
                    .iter()
                    .all(|p| p.pixel_period() >= BINNED_MIN_PERIOD) =>
            {
                // One cheap refinement step on the binned image brings the start point within
                // ~1e-4 rad, so the full-size refinement usually needs a single step.
                let r = refine::refine(&binned, e.planes, cache.refine(), 1);
                e.planes = r.planes;
                // Binned pixel i covers pixels 2i, 2i+1 (centre 2i + 0.5): change of frame.
                let shift = |n: usize, nb: usize| ((n / 2) as f64 - 0.5) / 2.0 - (nb / 2) as f64;
                let (sx, sy) = (shift(cols, cb), shift(rows, rb));
                e.planes = e.planes.map(|p| {
                    PhasePlane {
                        a: p.a / 2.0,
                        b: p.b / 2.0,
                        c: p.c + p.a * sx + p.b * sy,
                    }
                    .with_wrapped_offset()
                });
                if let Some(maps) = e.maps.as_mut() {
                    for m in maps.iter_mut() {
                        m.step_x *= 2.0;
                        m.step_y *= 2.0;
                        m.offset = (0.5, 0.5);
                    }
                }
                Ok(Some(e))
            }
            Ok(_) => Ok(None),
            // Too weak after binning (or only one lobe left): let the full-size stage decide.
            Err(Error::PatternNotFound(_)) => Ok(None),
            Err(other) => Err(other),
        };
        cache.binned = binned;
        result
    }
}

/// Spectrum, lobe search and band-pass planes (docs/design.md#phase-engine) of a `cache`-sized
/// image.
/// `prior` is in cycles per pixel of the full image, `binning` pixels per pixel of `pixels`.
fn spectral_estimate(
    pixels: &[f32],
    cache: &mut SizeCache,
    planners: &mut Planners,
    params: &PhaseParams,
    prior: Option<&LobePrior>,
    binning: f64,
) -> Result<SpectralEstimate> {
    let search = lobes::LobeSearch {
        min_radius: params.min_frequency,
        max_radius: params.max_frequency,
        sigma: params.sigma,
        min_peak_power: params.min_peak_power,
        min_peak_prominence: params.min_peak_prominence,
    };
    // Borrow the two plans separately (the spectrum view borrows the spectrum plan).
    cache.bandpass(planners);
    let (Some(spectrum_plan), Some(bandpass_plan)) = ({
        cache.spectrum(planners);
        (cache.spectrum.as_mut(), cache.bandpass.as_mut())
    }) else {
        return Err(Error::PatternNotFound("internal: plans missing".into()));
    };
    let spectrum = spectrum_plan.forward(pixels);
    let guide = prior.map(|p| {
        let (rows, cols) = (cache.rows as f64, cache.cols as f64);
        let bins = |f: [f64; 2]| [f[0] * binning * cols, f[1] * binning * rows];
        let expected = p.frequencies.map(bins);
        lobes::Guide {
            expected,
            radius: expected.map(|e| (p.tolerance * e[0].hypot(e[1])).max(2.0)),
            min_prominence: p.min_prominence,
        }
    });
    let (lobe1, lobe2) = lobes::find_lobes(&spectrum, &search, guide.as_ref()).map_err(|e| {
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
    let mut planes = [PhasePlane {
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
            bandpass_plan,
            params.keep_phase_maps,
        )
        .ok_or_else(|| Error::PatternNotFound("phase plane fit is degenerate".into()))?;
        planes[k] = plane;
        maps.extend(map);
    }
    Ok(SpectralEstimate {
        lobes: [lobe1, lobe2],
        planes,
        maps: <[PhaseMap; 2]>::try_from(maps).ok(),
    })
}
