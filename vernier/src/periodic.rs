//! Detector of plain periodic dot grids (docs/design.md#periodic): the pose modulo one period and
//! the grid's 90° symmetry.

use crate::error::Result;
use crate::grey_image::{GreyImage, Polarity};
use crate::phase::{PhaseAnalysis, PhaseEngine, PhaseParams};
use crate::pose::Pose;
use nalgebra::Vector2;
use std::f64::consts::TAU;

/// Settings of [`PeriodicDetector`].
#[derive(Clone, Debug, PartialEq)]
pub struct PeriodicParams {
    /// Physical period `P` of the grid, pattern units (µm by convention). Must be > 0.
    pub period: f64,
    /// Dot polarity of the images.
    pub polarity: Polarity,
    /// Phase-engine settings.
    pub phase: PhaseParams,
}

impl PeriodicParams {
    /// Defaults for a grid of physical period `period` (pattern units).
    pub fn new(period: f64) -> Self {
        PeriodicParams {
            period,
            polarity: Polarity::BrightDots,
            phase: PhaseParams::default(),
        }
    }
}

/// One periodic-grid measurement.
#[derive(Clone, Debug)]
pub struct PeriodicDetection {
    /// Pose with `x, y ∈ [−P/2, P/2)` (pattern units) and `alpha ∈ [0, π/2)`: the grid is only
    /// known modulo one period and a quarter turn.
    pub pose: Pose,
    /// Image position `(col, row)` of the grid node the pose refers to, pixels.
    pub origin_px: Vector2<f64>,
    /// Phase-engine output the pose was computed from.
    pub analysis: PhaseAnalysis,
}

/// Measures the pose of a periodic grid filling the image. Keeps FFT plans between calls.
///
/// # Example
///
/// ```
/// use vernier::layout::PeriodicLayout;
/// use vernier::render::{render, RenderOptions};
/// use vernier::{PeriodicDetector, PeriodicParams, Pose};
///
/// # fn main() -> vernier::Result<()> {
/// // 10 µm period, 1.25 µm per pixel; the truth lies inside the reported range
/// // (x, y in [−P/2, P/2), alpha in [0, π/2)), so it comes back as is.
/// let layout = PeriodicLayout::new(10.0, 41, 41)?;
/// let truth = Pose::planar(2.5, -1.0, 0.3, 1.25);
/// let options = RenderOptions { blur_sigma: 0.5, ..RenderOptions::new(128, 128) };
/// let image = render(&layout, &truth, &options)?;
///
/// let mut detector = PeriodicDetector::new(PeriodicParams::new(10.0))?;
/// let pose = detector.detect(&image)?.pose;
/// let tolerance = 0.01 * truth.pixel_size; // 1/100 px, in µm
/// assert!((pose.x - truth.x).abs() < tolerance && (pose.y - truth.y).abs() < tolerance);
/// assert!((pose.alpha - truth.alpha).abs() < 1e-4);
/// assert!((pose.pixel_size / truth.pixel_size - 1.0).abs() < 1e-4);
/// # Ok(())
/// # }
/// ```
pub struct PeriodicDetector {
    params: PeriodicParams,
    engine: PhaseEngine,
}

impl PeriodicDetector {
    /// A detector with `params` (validated).
    pub fn new(params: PeriodicParams) -> Result<Self> {
        crate::limits::check_period(params.period)?;
        params.phase.validate()?;
        Ok(PeriodicDetector {
            params,
            engine: PhaseEngine::new(),
        })
    }

    /// Current settings.
    pub fn params(&self) -> &PeriodicParams {
        &self.params
    }

    /// Measures `image`.
    pub fn detect(&mut self, image: &GreyImage) -> Result<PeriodicDetection> {
        let image = &*image.as_bright_dots(self.params.polarity);
        let analysis = self.engine.analyze(image, &self.params.phase)?;
        let pose = periodic_pose(&analysis, self.params.period);
        let (cx, cy) = image.center();
        let origin_px = Vector2::new(cx as f64, cy as f64) + pose.origin_in_image();
        Ok(PeriodicDetection {
            pose,
            origin_px,
            analysis,
        })
    }
}

/// Pose from the two planes with zero period shifts (docs/design.md#periodic).
pub fn periodic_pose(analysis: &PhaseAnalysis, period: f64) -> Pose {
    let [p1, p2] = analysis.planes;
    Pose::planar(
        -period * p1.c / TAU,
        -period * p2.c / TAU,
        p1.angle(),
        period * p1.frequency() / TAU,
    )
}
