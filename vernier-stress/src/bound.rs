//! The Cramér–Rao bound of a marker's position in a scene: the least position error any
//! unbiased estimator can reach on that image, whatever its method.
//!
//! It is computed where the image is the marker's render plus independent sensor noise and
//! nothing else that hides information in a way the bound cannot state: no perspective, JPEG,
//! colour cast, dust or hair (see [`applies`]). Then the Fisher information of the marker's
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
//! An estimator at the bound has a radial error with `P(|e| > r) = exp(−r²/B²)` (`B²` the
//! bound; the two axes' variances nearly equal on these square markers), so its p99 over a
//! set of markers solves `mean exp(−r²/Bᵢ²) = 0.01` ([`efficient_quantile`]).

use crate::degrade::{Degradations, Noise};
use crate::error::Result;
use crate::markers::Placed;
use crate::raster::{add_marker, Plane};
use nalgebra::{Matrix4, Vector2, Vector4};
use vernier::layout::Layout;

/// Marker shift of the central differences, pixels (at its border for alpha and scale).
const STEP_PX: f64 = 0.01;

/// True when a scene's markers have a bound: sensor noise, and none of perspective, JPEG,
/// colour cast, dust or hair (blur, illumination, low contrast and clutter beside the markers
/// keep the image an affine function of each marker's coverage plus independent noise).
pub fn applies(d: &Degradations) -> bool {
    d.noise.is_some()
        && d.perspective.is_none()
        && d.jpeg_quality.is_none()
        && d.colour.is_none()
        && !d.dust_hair
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
    /// Sensor noise.
    pub noise: Noise,
}

/// The bound `B` (pixels) of marker `m` drawn from `layout`: `E|e|² ≥ B²` for the radial
/// error `e` of its origin, image pixels. `None` when the Fisher information is singular (a
/// marker nearly out of the frame).
pub fn position_bound(layout: &dyn Layout, m: &Placed, f: &Formation) -> Result<Option<f64>> {
    let (w, h) = (f.clean.width, f.clean.height);
    let border = m.side_px() * std::f64::consts::FRAC_1_SQRT_2;
    let steps = [
        STEP_PX,
        STEP_PX,
        STEP_PX / border,
        STEP_PX / border * m.pixel_size,
    ];
    // The pixels a move can change: the footprint's box, a tenth of the side for the layout's
    // own bounds, and the blur margin of `add_marker`; rendered on that part of the frame.
    let half = m.footprint().bounding_half();
    let reach = half.x.max(half.y) + 0.1 * m.side_px() + (4.0 * f.blur_sigma).ceil() + 5.0;
    let clip = |v: f64, n: usize| (v.floor().max(0.0) as usize).min(n);
    let (c0, c1) = (
        clip(m.origin.x - reach, w),
        clip(m.origin.x + reach + 1.0, w),
    );
    let (r0, r1) = (
        clip(m.origin.y - reach, h),
        clip(m.origin.y + reach + 1.0, h),
    );
    let (rw, rh) = (c1 - c0, r1 - r0);
    let corner = Vector2::new(c0 as f64, r0 as f64);
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
    let mut fisher = Matrix4::<f64>::zeros();
    for r in 0..rh {
        for c in 0..rw {
            let (i, local) = ((r + r0) * w + c + c0, r * rw + c);
            let gain = f.gain.map_or(1.0, |g| g.data[i] as f64);
            let v = (f.clean.data[i] as f64).max(0.0);
            let sigma = f.noise.gaussian + f.noise.shot * v.sqrt();
            let scale = f.contrast * gain / sigma;
            let j = Vector4::from_fn(|k, _| {
                let (plus, minus, span) = &derivatives[k];
                scale * (plus.data[local] as f64 - minus.data[local] as f64) / span
            });
            fisher += j * j.transpose();
        }
    }
    Ok(fisher
        .try_inverse()
        .map(|inverse| (inverse[(0, 0)] + inverse[(1, 1)]).sqrt())
        .filter(|b| b.is_finite() && *b > 0.0))
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
