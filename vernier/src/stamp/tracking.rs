//! Tracking stamps from frame to frame (docs/design.md#tracking): each marker of the last
//! frame is read again where it is predicted, in the window it was read in, with its frame
//! outline moved there and re-fitted to this frame's edges, and its whole-field fit started
//! from the last frame's model (docs/design.md#tracked-field-fit). The frame search, the
//! costliest step before the fit, is skipped; every check on the reading stays.

use super::{StampDetection, StampDetector, StampSearch, WindowReading};
use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use crate::parallel;
use crate::phase::FieldFit;
use crate::stamp::quads::Quad;
use nalgebra::Vector2;

impl StampDetector {
    /// The markers of `previous` (the last frame's detections) found again in `image`
    /// without the frame search, each from its last reading moved to `predicted[i]` (its
    /// predicted central dot, image pixels). `None` when any marker is not found again with
    /// the same bitmap and handedness, or in full-image search: the caller then runs
    /// [`StampDetector::detect`].
    pub fn track(
        &mut self,
        image: &GreyImage,
        previous: &[StampDetection],
        predicted: &[Vector2<f64>],
    ) -> Result<Option<Vec<StampDetection>>> {
        if self.mode == StampSearch::FullImage
            || previous.is_empty()
            || previous.len() != predicted.len()
        {
            return Ok(None);
        }
        self.measured.clear();
        let mut read: Vec<(WindowReading, Option<&FieldFit>)> = Vec::new();
        for (last, &to) in previous.iter().zip(predicted) {
            match self.read_again(image, last, to)? {
                Some(reading) => read.push((reading, last.field.as_ref())),
                None => return Ok(None),
            }
        }
        let this = &*self;
        let mut workers = vec![(); parallel::thread_count(this.params.threads, read.len())];
        let fits = parallel::map_in_order(&mut workers, &read, |_, (r, last)| {
            this.field_for(image, r, *last)
        })
        .ok_or_else(|| {
            Error::PatternNotFound("internal: a stamp-tracking thread panicked".into())
        })?;
        let mut found = Vec::with_capacity(read.len());
        for (((reading, _), fit), last) in read.into_iter().zip(fits).zip(previous) {
            match this.finish(image, reading, fit) {
                Some(d) if d.mirrored == last.mirrored => found.push(d),
                _ => return Ok(None),
            }
        }
        Ok(Some(found))
    }

    /// The reading of `last` in this frame, its central dot predicted at `to`: its window
    /// moved with it, its frame outline moved and re-fitted to the edges within a period.
    /// `None` when the outline or the bitmap is not found again there.
    fn read_again(
        &mut self,
        image: &GreyImage,
        last: &StampDetection,
        to: Vector2<f64>,
    ) -> Result<Option<WindowReading>> {
        let shift = to - last.origin_px;
        if !(shift.x.is_finite() && shift.y.is_finite()) {
            return Ok(None);
        }
        let center = (
            last.window_center.0 + shift.x.round() as i64,
            last.window_center.1 + shift.y.round() as i64,
        );
        let period = self.params.period / last.pose.pixel_size;
        let frame = match &last.frame {
            Some(outline) => {
                let moved = Quad {
                    corners: outline.corners.map(|c| c + shift),
                };
                match moved.refined(image, last.polarity, period.max(1.5)) {
                    Some(refined) => Some(refined),
                    None => return Ok(None),
                }
            }
            None => None,
        };
        let reading = self.read_window(image, center, last.window_size, frame, last.polarity)?;
        Ok(reading.filter(|r| r.found.bitmap == last.id))
    }
}
