//! The tracked fit (docs/design.md#tracked-field-fit): the last frame's converged model as
//! the next frame's start, and the one pass that fits from it.

use super::*;

/// What a converged fit hands on to the next frame's fit of the same marker (tracking,
/// docs/design.md#tracked-field-fit): everything but the planes changes little between two
/// frames of a servo loop (the dots' harmonics, the illumination terms, the robust scale and
/// the cells' weights, the tilt carried in the phase model).
#[derive(Clone, Debug)]
pub(super) struct WarmModel {
    /// The model, its planes in the image frame (input pixels); its frozen weights are in
    /// `weights` (per pixel of a box that moves).
    pub(super) model: Model,
    /// The final sweeps' frozen robust weights, where they lie; `None` without them.
    pub(super) weights: Option<CarriedWeights>,
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

/// A fit's frozen robust weights ([`Model::frozen`]) and where they lie, so that the next
/// frame's first sweep solves the problem the last frame's final sweeps solved, moved with the
/// marker: a first sweep that judged the weights afresh would step to that judgment's answer
/// (the outliers' grown extents are set only once the weights freeze, [`frozen_weights`]) and
/// the next sweep back, a sweep spent for nothing.
#[derive(Clone, Debug)]
pub(super) struct CarriedWeights {
    /// Row-major over the fit's box, `width` pixels a row.
    pub(super) values: Vec<f32>,
    pub(super) width: usize,
    /// Where the box's pixel `(0, 0)` lay from the mask's nodes' centroid at the converged
    /// planes, pixels of the fit's frame (input pixels between frames).
    pub(super) origin_from_nodes: Vector2<f64>,
}

impl CarriedWeights {
    /// These weights in a frame of `scale` times as many pixels per input pixel.
    pub(super) fn scaled(&self, scale: f64) -> CarriedWeights {
        CarriedWeights {
            origin_from_nodes: self.origin_from_nodes * scale,
            ..self.clone()
        }
    }

    /// The weights of `field`'s pixels (row-major) once the marker's nodes have moved to
    /// `nodes` (the sub-image's frame): each pixel takes the weight of the pixel that lay
    /// where it lies less the nodes' move, rounded to whole pixels; NaN where that pixel was
    /// outside the last box (the first sweep judges those afresh).
    pub(super) fn moved_into(&self, field: &FieldBox, nodes: Vector2<f64>) -> Vec<f32> {
        let shift = field.origin() - nodes - self.origin_from_nodes;
        let (dx, dy) = (shift.x.round() as i64, shift.y.round() as i64);
        let height = self.values.len() / self.width.max(1);
        let (width, rows) = (field.cols.len(), field.rows.len());
        let mut moved = vec![f32::NAN; width * rows];
        for (row, out) in moved.chunks_exact_mut(width.max(1)).enumerate() {
            let old_row = row as i64 + dy;
            if old_row < 0 || old_row >= height as i64 {
                continue;
            }
            let from = old_row as usize * self.width;
            for (col, w) in out.iter_mut().enumerate() {
                let old_col = col as i64 + dx;
                if old_col >= 0 && (old_col as usize) < self.width {
                    *w = self.values[from + old_col as usize];
                }
            }
        }
        moved
    }
}

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
        warm.weights = self.weights.as_ref().map(|w| w.scaled(1.0 / f));
        Some(warm)
    }

    /// This model for a fit from planes `start`, where the mask's nodes' centroid lies at
    /// `nodes` ([`NodeMask::centroid_at`]), over a field whose normalised coordinates have
    /// half-size `scale` (one frame for all): its centre where it was from the nodes'
    /// centroid, and the linear terms' slopes rescaled to `scale`. `None` when not finite.
    pub(super) fn moved_to(
        &self,
        start: &[PhasePlane; 2],
        scale: f64,
        nodes: Vector2<f64>,
    ) -> Option<(Model, (f64, f64))> {
        let (dx, dy, s0) = self.frame;
        let at = nodes + Vector2::new(dx, dy);
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
