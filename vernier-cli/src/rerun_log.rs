//! `--rerun TARGET`: logs every analysed frame to a rerun viewer or `.rrd` file (cargo feature
//! `rerun`, off by default because the SDK is a large build).
//!
//! Entities, on the `frame` timeline (image index in the run):
//! * `image`: the grey image (contrast stretched);
//! * `image/markers`: marker origins labelled with their ID; `image/axes`: each marker's
//!   pattern x axis (red) and y axis (green);
//! * `spectrum`: centred log-magnitude spectrum; `spectrum/lobes`: the two chosen lobes and
//!   their mirror images;
//! * `phase/lobe_1`, `phase/lobe_2`: wrapped band-pass phase as grey levels (0 black, 2π
//!   white: the usual sawtooth fringes; one byte per pixel keeps long runs small);
//! * `pose/marker_<id>/{x_um, y_um, alpha_rad, pixel_size_um}`: pose time series (pattern
//!   units, µm by convention);
//! * `log`: detection errors.
//!
//! The spectrum and phase views come from the phase engine run on the whole image
//! ([`vernier::phase::PhaseEngine::inspect`]), whatever the marker type: they show what the
//! fine step sees, and are skipped (with a `log` entry) when the image has no clear lobes.

use vernier::{GreyImage, MarkerPose, Polarity};

/// Where the log goes, from the `--rerun` value.
#[derive(Clone, Debug, PartialEq)]
pub enum RerunTarget {
    /// Spawn a viewer (the `rerun` executable must be on `PATH`) and stream to it.
    Spawn,
    /// Stream to a running viewer at this gRPC URL (`rerun+http://HOST:PORT/proxy`).
    Connect(String),
    /// Write an `.rrd` recording, viewable later with `rerun FILE.rrd`.
    File(std::path::PathBuf),
}

impl std::str::FromStr for RerunTarget {
    type Err = String;
    fn from_str(text: &str) -> Result<Self, String> {
        match text {
            "spawn" => Ok(RerunTarget::Spawn),
            "connect" => Ok(RerunTarget::Connect(
                "rerun+http://127.0.0.1:9876/proxy".into(),
            )),
            url if url.starts_with("rerun+http://") || url.starts_with("rerun+https://") => {
                Ok(RerunTarget::Connect(url.into()))
            }
            path if path.ends_with(".rrd") => Ok(RerunTarget::File(path.into())),
            other => Err(format!(
                "`{other}` is not a rerun target: use `spawn`, `connect`, a \
                 `rerun+http://HOST:PORT/proxy` URL or a FILE.rrd path"
            )),
        }
    }
}

/// One frame's data for the log.
// Without the feature nothing reads the fields (the log cannot be opened).
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
pub struct FrameLog<'a> {
    /// Index of the frame in the run (the `frame` timeline).
    pub frame: u64,
    /// The image as read (before any polarity inversion).
    pub image: &'a GreyImage,
    /// The detector's result for it.
    pub result: &'a Result<Vec<MarkerPose>, String>,
}

#[cfg(feature = "rerun")]
pub use with_rerun::RerunLog;
#[cfg(not(feature = "rerun"))]
pub use without_rerun::RerunLog;

#[cfg(not(feature = "rerun"))]
mod without_rerun {
    use super::{FrameLog, Polarity, RerunTarget};

    /// Stand-in when the `rerun` feature is off: opening it explains how to get it.
    pub enum RerunLog {}

    impl RerunLog {
        /// Always fails: this build has no rerun SDK.
        pub fn open(_target: &RerunTarget, _polarity: Polarity) -> Result<Self, String> {
            Err(
                "this `vernier` was built without rerun support; rebuild it with \
                 `cargo install --path vernier-cli --features rerun` (or `cargo run -p \
                 vernier-cli --features rerun -- ...`)"
                    .into(),
            )
        }

        /// Unreachable (no value of this type exists).
        pub fn log_frame(&mut self, _frame: &FrameLog<'_>) -> Result<(), String> {
            match *self {}
        }

        /// Unreachable (no value of this type exists).
        pub fn finish(self) -> Result<(), String> {
            match self {}
        }
    }
}

#[cfg(feature = "rerun")]
mod with_rerun {
    use super::{FrameLog, GreyImage, Polarity, RerunTarget};
    use rerun::{Arrows2D, Color, Image, Points2D, RecordingStream, Scalars, TextLog};
    use vernier::phase::{PhaseEngine, PhaseParams};

    /// An open recording stream plus the phase engine used for the spectrum and phase views.
    pub struct RerunLog {
        stream: RecordingStream,
        engine: PhaseEngine,
        polarity: Polarity,
    }

    fn rerun_error(e: impl std::fmt::Display) -> String {
        format!("rerun: {e}")
    }

    impl RerunLog {
        /// Opens the stream to `target`; `polarity` is the dot polarity of the images.
        pub fn open(target: &RerunTarget, polarity: Polarity) -> Result<Self, String> {
            let builder = rerun::RecordingStreamBuilder::new("vernier");
            let stream = match target {
                RerunTarget::Spawn => builder.spawn(),
                RerunTarget::Connect(url) => builder.connect_grpc_opts(url.clone()),
                RerunTarget::File(path) => builder.save(path),
            }
            .map_err(rerun_error)?;
            Ok(RerunLog {
                stream,
                engine: PhaseEngine::new(),
                polarity,
            })
        }

        /// Logs one frame (see the module docs for the entities).
        pub fn log_frame(&mut self, frame: &FrameLog<'_>) -> Result<(), String> {
            let rec = &self.stream;
            rec.set_time_sequence("frame", frame.frame as i64);
            let image = frame.image;
            rec.log(
                "image",
                &Image::from_l8(stretch_to_u8(image.pixels()), image_size(image)),
            )
            .map_err(rerun_error)?;

            let markers: &[vernier::MarkerPose] = match frame.result {
                Ok(markers) => markers,
                Err(message) => {
                    rec.log("log", &TextLog::new(message.as_str()).with_level("WARN"))
                        .map_err(rerun_error)?;
                    &[]
                }
            };
            log_markers(rec, image, markers)?;
            log_pose_series(rec, markers)?;
            self.log_phase_views(image)
        }

        /// Logs the spectrum with its lobes and the wrapped phase of each lobe, from the phase
        /// engine run on the whole image; a `log` entry instead when it finds no lobes.
        fn log_phase_views(&mut self, image: &GreyImage) -> Result<(), String> {
            let rec = &self.stream;
            let bright = image.as_bright_dots(self.polarity);
            let inspection = match self.engine.inspect(&bright, &PhaseParams::default()) {
                Ok(inspection) => inspection,
                Err(e) => {
                    return rec
                        .log(
                            "log",
                            &TextLog::new(format!("no spectrum view: {e}")).with_level("INFO"),
                        )
                        .map_err(rerun_error);
                }
            };
            let view = &inspection.spectrum;
            rec.log(
                "spectrum",
                &Image::from_l8(
                    stretch_to_u8(&view.log_magnitude),
                    [view.width as u32, view.height as u32],
                ),
            )
            .map_err(rerun_error)?;
            // Each lobe and its mirror image (the spectrum of a real image is symmetric).
            let mut lobe_points = Vec::new();
            let mut lobe_labels = Vec::new();
            for (i, lobe) in inspection.analysis.lobes.iter().enumerate() {
                for sign in [1, -1] {
                    let (x, y) = view.bin_position(sign * lobe.kx, sign * lobe.ky);
                    lobe_points.push([x as f32, y as f32]);
                    lobe_labels.push(format!("lobe {}", i + 1));
                }
            }
            rec.log(
                "spectrum/lobes",
                &Points2D::new(lobe_points)
                    .with_labels(lobe_labels)
                    .with_radii([4.0f32])
                    .with_colors([Color::from_rgb(255, 60, 60)]),
            )
            .map_err(rerun_error)?;
            for (i, phase) in inspection.wrapped_phase.iter().enumerate() {
                rec.log(
                    format!("phase/lobe_{}", i + 1),
                    &Image::from_l8(phase_to_u8(phase), image_size(image)),
                )
                .map_err(rerun_error)?;
            }
            Ok(())
        }

        /// Flushes everything to the viewer or file.
        pub fn finish(self) -> Result<(), String> {
            self.stream.flush_blocking().map_err(rerun_error)
        }
    }

    /// Width and height of `image`, pixels, as rerun takes them.
    fn image_size(image: &GreyImage) -> [u32; 2] {
        [image.width() as u32, image.height() as u32]
    }

    /// Logs the marker origins labelled with their IDs (`image/markers`) and each marker's
    /// pattern x (red) and y (green) axes (`image/axes`), a tenth of the image's smaller side
    /// long, in image pixels.
    fn log_markers(
        rec: &RecordingStream,
        image: &GreyImage,
        markers: &[vernier::MarkerPose],
    ) -> Result<(), String> {
        let axis_length = 0.1 * image.width().min(image.height()) as f32;
        let origins: Vec<[f32; 2]> = markers
            .iter()
            .map(|m| [m.origin_px.x as f32, m.origin_px.y as f32])
            .collect();
        let labels: Vec<String> = markers.iter().map(|m| format!("id {}", m.id)).collect();
        rec.log(
            "image/markers",
            &Points2D::new(origins.iter().copied())
                .with_labels(labels)
                .with_radii([3.0f32])
                .with_colors([Color::from_rgb(255, 200, 0)]),
        )
        .map_err(rerun_error)?;
        // Pattern axes in the image (y down): x_p → (cos α, sin α), y_p → (−sin α, cos α).
        let mut vectors = Vec::with_capacity(2 * markers.len());
        let mut colors = Vec::with_capacity(2 * markers.len());
        for m in markers {
            let (s, c) = (m.pose.alpha as f32).sin_cos();
            vectors.push([axis_length * c, axis_length * s]);
            colors.push(Color::from_rgb(255, 40, 40));
            vectors.push([-axis_length * s, axis_length * c]);
            colors.push(Color::from_rgb(40, 220, 40));
        }
        let axis_origins = origins.iter().flat_map(|&o| [o, o]);
        rec.log(
            "image/axes",
            &Arrows2D::from_vectors(vectors)
                .with_origins(axis_origins)
                .with_colors(colors),
        )
        .map_err(rerun_error)
    }

    /// Logs each marker's pose as scalars `pose/marker_<id>/{x_um, y_um, alpha_rad,
    /// pixel_size_um}` (pattern units, µm by convention; radians).
    fn log_pose_series(
        rec: &RecordingStream,
        markers: &[vernier::MarkerPose],
    ) -> Result<(), String> {
        for m in markers {
            let base = format!("pose/marker_{}", m.id);
            for (name, value) in [
                ("x_um", m.pose.x),
                ("y_um", m.pose.y),
                ("alpha_rad", m.pose.alpha),
                ("pixel_size_um", m.pose.pixel_size),
            ] {
                rec.log(format!("{base}/{name}"), &Scalars::single(value))
                    .map_err(rerun_error)?;
            }
        }
        Ok(())
    }

    /// Linear contrast stretch of `values` to 0–255 (a flat image becomes mid grey).
    fn stretch_to_u8(values: &[f32]) -> Vec<u8> {
        let (lo, hi) = values
            .iter()
            .filter(|v| v.is_finite())
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        if hi <= lo {
            return vec![128; values.len()];
        }
        let scale = 255.0 / (hi - lo);
        values
            .iter()
            .map(|&v| ((v - lo) * scale).clamp(0.0, 255.0).round() as u8)
            .collect()
    }

    /// Wrapped phase in `[0, 2π)` to grey levels 0–255.
    fn phase_to_u8(phase: &[f32]) -> Vec<u8> {
        let scale = 256.0 / std::f32::consts::TAU;
        phase
            .iter()
            .map(|&p| (p.rem_euclid(std::f32::consts::TAU) * scale).min(255.0) as u8)
            .collect()
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn phase_levels_span_the_turn() {
            let tau = std::f32::consts::TAU;
            assert_eq!(
                phase_to_u8(&[0.0, tau / 2.0, tau - 1e-6, tau, -0.01]),
                vec![0, 128, 255, 0, 255]
            );
        }

        #[test]
        fn stretch_handles_flat_and_nan() {
            assert_eq!(stretch_to_u8(&[0.3, 0.3]), vec![128, 128]);
            assert_eq!(stretch_to_u8(&[0.0, f32::NAN, 2.0]), vec![0, 0, 255]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::RerunTarget;

    #[test]
    fn targets_parse() {
        assert_eq!("spawn".parse(), Ok(RerunTarget::Spawn));
        assert!(matches!("connect".parse(), Ok(RerunTarget::Connect(_))));
        assert_eq!(
            "rerun+http://10.0.0.2:9876/proxy".parse(),
            Ok(RerunTarget::Connect(
                "rerun+http://10.0.0.2:9876/proxy".into()
            ))
        );
        assert_eq!("run.rrd".parse(), Ok(RerunTarget::File("run.rrd".into())));
        let err = "run.txt".parse::<RerunTarget>().unwrap_err();
        assert!(err.contains("FILE.rrd"), "{err}");
    }
}
