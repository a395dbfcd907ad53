//! The tracked fit (docs/design.md#tracked-field-fit): the last frame's converged model as
//! the next frame's start, and the one pass that fits from it.

use super::*;

/// What a converged fit hands on to the next frame's fit of the same marker (tracking,
/// docs/design.md#tracked-field-fit): everything but the planes changes little between two
/// frames of a servo loop (the dots' harmonics, the illumination terms, the robust scale and
/// the cells' weights, the tilt carried in the phase model).
#[derive(Clone, Debug)]
pub(super) struct WarmModel {
    /// The model, its planes in the image frame (input pixels); no frozen weights (they are
    /// per pixel of a box that moves).
    pub(super) model: Model,
    /// The field centre `(x₀, y₀)` from the drawn nodes' centroid
    /// ([`NodeMask::centroid_at`]; the same nodes in any numbering of them), and the
    /// half-size `s` of the normalised coordinates, input pixels.
    pub(super) frame: (f64, f64, f64),
    /// The perspective carried in the final pass's phase model (zero: a flat pass).
    pub(super) taken: Vector2<f64>,
    /// The fit's planes less the window's it started from (image frame): where the next
    /// frame's fit starts from its window's.
    pub(super) correction: [PhasePlane; 2],
    /// Binning factor of the fit (1 or 2).
    pub(super) factor: usize,
    /// The final sweep's robust residual σ and inlier fraction: the next frame's first sweep
    /// on these weights must look alike to keep them ([`WarmModel::still_fits`]).
    pub(super) residual_std: f64,
    pub(super) inlier_fraction: f64,
}

/// How much a tracked frame's first sweep may depart from the last fit before its weights are
/// judged afresh ([`WarmModel::still_fits`]): the residual's σ 25 % larger (dust arrived, the
/// focus or the light changed), or 2 % of the field's weight newly rejected.
pub(super) const WARM_RESIDUAL_GROWTH: f64 = 1.25;

pub(super) const WARM_INLIER_DROP: f64 = 0.02;

impl WarmModel {
    /// Whether `step`, the first sweep of a tracked frame on this model's robust weights, shows
    /// the same field: then its weights are frozen at once; otherwise they are set afresh
    /// from its residuals, as a cold fit does.
    pub(super) fn still_fits(&self, step: &Step) -> bool {
        step.residual_std <= WARM_RESIDUAL_GROWTH * self.residual_std
            && step.inlier_fraction >= self.inlier_fraction - WARM_INLIER_DROP
    }

    /// This model in the frame of a (binned) sub-image whose pixel `(0, 0)` sits at
    /// image-frame `offset`, `f` input pixels per pixel; `None` at another binning.
    pub(super) fn in_sub_frame(&self, f: usize, offset: [f64; 2]) -> Option<WarmModel> {
        if f != self.factor {
            return None;
        }
        let f = f as f64;
        let mut warm = self.clone();
        warm.model.planes = self.model.planes.map(|p| PhasePlane {
            a: f * p.a,
            b: f * p.b,
            c: p.c + p.a * offset[0] + p.b * offset[1],
        });
        let (dx, dy, s) = self.frame;
        warm.frame = (dx / f, dy / f, s / f);
        Some(warm)
    }

    /// This model for a fit from planes `start` of the nodes of `mask` over a field whose
    /// normalised coordinates have half-size `scale` (one frame for all): its centre where it
    /// was from the nodes' centroid, and the linear terms' slopes rescaled to `scale`. `None`
    /// when `start` is singular.
    pub(super) fn moved_to(
        &self,
        start: &[PhasePlane; 2],
        scale: f64,
        mask: &NodeMask,
    ) -> Option<(Model, (f64, f64))> {
        let (dx, dy, s0) = self.frame;
        let at = mask.centroid_at(start)? + Vector2::new(dx, dy);
        let mut model = self.model.clone();
        model.planes = *start;
        let ratio = scale / s0;
        for k in [1, 2, 4, 5, 7, 8, 9, 10] {
            model.linear[k] *= ratio;
        }
        (at.x.is_finite() && at.y.is_finite() && ratio.is_finite()).then_some((model, (at.x, at.y)))
    }
}

/// The tracked fit (docs/design.md#tracked-field-fit): one pass from `warm`, with the tilt
/// that the last frame's fit carried in its phase model; `None` (the caller fits cold) when
/// that pass fails, or leaves more tilt than the noise (the tilt changed: the cold passes
/// measure it afresh).
#[inline(always)]
pub(super) fn fit_warm(
    image: &GreyImage,
    start: [PhasePlane; 2],
    mask: &NodeMask,
    goal: &Goal,
    warm: &WarmModel,
) -> Option<FieldFit> {
    let warp = match goal.tilt_centre {
        Some(centre) if warm.taken != Vector2::zeros() => Some(Warp {
            perspective: warm.taken,
            centre,
        }),
        _ => None,
    };
    let (mut fit, misfit) = fit_pass(image, start, mask, goal, warp, Some(warm))?;
    if goal.tilt_centre.is_some() && fit.perspective.is_some() && misfit > 1.0 {
        log::debug!("whole-field fit: the tilt moved ({misfit:.1} of the noise left), fit cold");
        return None;
    }
    if let Some(warp) = warp {
        fit.perspective = Some(warp.perspective + fit.tilt_left());
        fit.tilt_weight = 1.0;
    }
    Some(fit)
}
