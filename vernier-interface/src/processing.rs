//! One frame, DDS-free: check the `sensor_msgs/Image`, convert it, detect the markers and
//! build every output message (SI units). The node's worker thread calls
//! [`Processor::process`]; tests call it directly.
//!
//! Numerics stay in the core: SI scaling is [`vernier::Pose::scaled`], relative poses
//! [`vernier::Pose::relative`], covariances [`vernier::MarkerPose::covariance`].

use crate::messages::{
    BoundingBox3D, CompressedImage, Detection3D, Detection3DArray, Header, Image,
    MarkerPose as MarkerMsg, MarkerPoseArray, ObjectHypothesis, ObjectHypothesisWithPose, Pose,
    PoseStamped, PoseWithCovariance, PoseWithCovarianceStamped, TfMessage, Transform,
    TransformStamped, Vector3,
};
use crate::params::NodeParams;
use vernier::detector::DetectorConfig;
use vernier::{Detector, GreyImage, MarkerPose, PixelFormat};

/// Why an image message is unusable (counted as a bad message in diagnostics).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BadImage(pub String);

impl std::fmt::Display for BadImage {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// Checks an image message without converting it: known encoding, non-zero size,
/// `step ≥ width × bytes per pixel` and `data.len() == step × height`.
pub fn check_image(msg: &Image) -> Result<PixelFormat, BadImage> {
    let format = PixelFormat::from_ros_encoding(&msg.encoding, msg.is_bigendian != 0)
        .ok_or_else(|| BadImage(format!("unknown encoding `{}`", msg.encoding)))?;
    if msg.width == 0 || msg.height == 0 {
        return Err(BadImage(format!(
            "zero-size image {}x{}",
            msg.width, msg.height
        )));
    }
    let row = (msg.width as u64) * format.bytes_per_pixel() as u64;
    if (msg.step as u64) < row {
        return Err(BadImage(format!(
            "step {} is shorter than a row of {} {} pixels ({row} bytes)",
            msg.step, msg.width, msg.encoding
        )));
    }
    let expected = msg.step as u64 * msg.height as u64;
    if msg.data.len() as u64 != expected {
        return Err(BadImage(format!(
            "{} data bytes, expected step × height = {} × {} = {expected}",
            msg.data.len(),
            msg.step,
            msg.height
        )));
    }
    Ok(format)
}

/// Converts a checked image message to grey levels in `[0, 1]`.
pub fn to_grey(msg: &Image) -> Result<GreyImage, BadImage> {
    let format = check_image(msg)?;
    GreyImage::from_raw(
        msg.width as usize,
        msg.height as usize,
        msg.step as usize,
        format,
        &msg.data,
    )
    .map_err(|e| BadImage(e.to_string()))
}

/// `frame_id` of the outputs when neither `camera_frame` nor the image header names one (tf2
/// ignores transforms with an empty frame).
pub const DEFAULT_CAMERA_FRAME: &str = "camera";

/// Everything published for one frame. All poses in metres and radians, stamped with the
/// image stamp, expressed in the camera frame (x right, y down, z into the scene).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameOutput {
    /// `~/markers`: every tracked marker (empty when none was found).
    pub markers: MarkerPoseArray,
    /// `~/detections`: the same markers as `vision_msgs` detections (empty when none).
    pub detections: Detection3DArray,
    /// `~/marker_<id>/pose`, one per tracked ID (the first marker when an ID repeats).
    pub poses: Vec<(u64, PoseStamped)>,
    /// `~/marker_<id>/pose_with_covariance`, alongside each of `poses`.
    pub poses_with_covariance: Vec<(u64, PoseWithCovarianceStamped)>,
    /// `~/relative/marker_<a>_<b>/pose`: pose of `b` in `a`'s frame, for configured pairs
    /// whose both markers were found.
    pub relative: Vec<((u64, u64), PoseStamped)>,
    /// `/tf` transforms camera → marker (empty when `publish_tf` is off).
    pub tf: TfMessage,
    /// Why detection found nothing, when it failed (the frame itself was valid).
    pub detect_error: Option<String>,
    /// The markers as measured (pattern units), for the debug image.
    pub raw: Vec<MarkerPose>,
    /// Neither `camera_frame` nor the image named a frame: [`DEFAULT_CAMERA_FRAME`] was used.
    pub frame_defaulted: bool,
}

/// Keeps one detector (FFT plans, buffers) and rebuilds it when the parameters change.
pub struct Processor {
    detector: Detector,
    config: DetectorConfig,
    params: NodeParams,
    generation: u64,
    /// The last frame processed, grey; raw frames are converted into its buffer, allocated
    /// once per size rather than once per frame.
    frame: Option<GreyImage>,
}

impl Processor {
    /// A processor for `params` (generation `generation`).
    pub fn new(params: NodeParams, generation: u64) -> Result<Processor, String> {
        let (detector, config) = params.build_detector()?;
        Ok(Processor {
            detector,
            config,
            params,
            generation,
            frame: None,
        })
    }

    /// The last frame processed, grey (`None` before the first one): what the debug image
    /// draws on.
    pub fn last_frame(&self) -> Option<&GreyImage> {
        self.frame.as_ref()
    }

    /// The parameters in use.
    pub fn params(&self) -> &NodeParams {
        &self.params
    }

    /// Physical period of the pattern in use, pattern units (the raw markers' units).
    pub fn period(&self) -> f64 {
        self.config.period()
    }

    /// Generation of the parameters in use.
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// Switches to new parameters (the next frame uses them). On error the old ones stay, and
    /// generation `generation` counts as handled (it is not retried on every frame).
    pub fn update(&mut self, params: NodeParams, generation: u64) -> Result<(), String> {
        self.generation = generation;
        if params.settings != self.params.settings {
            let (detector, config) = params.build_detector()?;
            self.detector = detector;
            self.config = config;
        }
        self.params = params;
        Ok(())
    }

    /// Processes one image message. `Err` means the message itself is bad; a valid image
    /// without markers gives an empty marker array and `detect_error`. The frame, grey, is
    /// then [`Processor::last_frame`].
    pub fn process(&mut self, msg: &Image) -> Result<FrameOutput, BadImage> {
        vernier::limits::check_image_pixels(
            u64::from(msg.width),
            u64::from(msg.height),
            self.params.max_image_pixels,
        )
        .map_err(|e| BadImage(e.to_string()))?;
        let format = check_image(msg)?;
        let (width, height, step) = (msg.width as usize, msg.height as usize, msg.step as usize);
        let bad = |e: vernier::Error| BadImage(e.to_string());
        let grey = match &mut self.frame {
            Some(frame) => {
                frame
                    .assign_raw(width, height, step, format, &msg.data)
                    .map_err(bad)?;
                frame
            }
            None => self
                .frame
                .insert(GreyImage::from_raw(width, height, step, format, &msg.data).map_err(bad)?),
        };
        Ok(detect_frame(
            &mut self.detector,
            &self.params,
            &self.config,
            grey,
            &msg.header,
        ))
    }

    /// Processes one `sensor_msgs/CompressedImage` (PNG or JPEG, as image_transport's
    /// `compressed` plugin publishes them; the format is found from the bytes). Its size is
    /// checked against `max_image_pixels` from the file header, before decoding.
    pub fn process_compressed(&mut self, msg: &CompressedImage) -> Result<FrameOutput, BadImage> {
        let format = msg.format.to_ascii_lowercase();
        if format.contains("compresseddepth") {
            return Err(BadImage(format!(
                "compressed depth images (`{}`) are not marker images",
                msg.format
            )));
        }
        let limits = vernier::DecodeLimits::with_max_pixels(self.params.max_image_pixels);
        let name = std::path::Path::new("compressed image");
        let grey = GreyImage::decode_bytes(&msg.data, name, &limits)
            .map_err(|e| BadImage(format!("`{}` message: {e}", msg.format)))?;
        let grey = self.frame.insert(grey);
        Ok(detect_frame(
            &mut self.detector,
            &self.params,
            &self.config,
            grey,
            &msg.header,
        ))
    }
}

/// Detects the markers of `grey` with `detector` and builds the frame's messages.
fn detect_frame(
    detector: &mut Detector,
    params: &NodeParams,
    config: &DetectorConfig,
    grey: &GreyImage,
    header: &Header,
) -> FrameOutput {
    let found = match params.tracking {
        Some(every) => detector.detect_next(grey, every),
        None => detector.detect(grey),
    };
    let (mut markers, detect_error) = match found {
        Ok(markers) => (markers, None),
        Err(e) => (Vec::new(), Some(e.to_string())),
    };
    markers.retain(|m| params.tracks(m.id) && m.quality >= params.min_quality);
    vernier::detector::flag_duplicate_ids(&mut markers);
    build_output(header, markers, detect_error, params, config.period())
}

/// Builds the output messages of one frame from the detected markers (pattern units).
pub fn build_output(
    image_header: &Header,
    markers: Vec<MarkerPose>,
    detect_error: Option<String>,
    params: &NodeParams,
    period: f64,
) -> FrameOutput {
    let frame_id = if !params.camera_frame.is_empty() {
        params.camera_frame.clone()
    } else if !image_header.frame_id.is_empty() {
        image_header.frame_id.clone()
    } else {
        DEFAULT_CAMERA_FRAME.to_string()
    };
    let frame_defaulted = params.camera_frame.is_empty() && image_header.frame_id.is_empty();
    let header = Header {
        stamp: image_header.stamp,
        frame_id,
    };
    let mut out = FrameOutput {
        markers: MarkerPoseArray {
            header: header.clone(),
            markers: Vec::with_capacity(markers.len()),
        },
        detections: Detection3DArray {
            header: header.clone(),
            detections: Vec::with_capacity(markers.len()),
        },
        detect_error,
        frame_defaulted,
        ..FrameOutput::default()
    };
    for m in &markers {
        push_marker(&mut out, m, &header, params, period);
    }
    push_relative_poses(&mut out, &markers, &header, params);
    out.raw = markers;
    out
}

/// Adds marker `m`'s messages to `out`: its array entries always, its pose topics and
/// transform only for the first marker of its ID.
fn push_marker(
    out: &mut FrameOutput,
    m: &MarkerPose,
    header: &Header,
    params: &NodeParams,
    period: f64,
) {
    let scale = params.metres_per_unit;
    // The same marker in SI units: its covariance then comes out in m² directly.
    let si = MarkerPose {
        pose: m.pose.scaled(scale),
        tilt_covariance: m.tilt_covariance.map(|t| t.scaled(scale)),
        ..m.clone()
    };
    let camera_from_marker = si.pose.camera_from_pattern();
    let pose = Pose::from_isometry(&camera_from_marker);
    let with_covariance = PoseWithCovariance {
        pose,
        // Over the window the marker's planes were fitted on.
        covariance: si.covariance(period * scale, m.window_px as f64).into(),
    };
    let marker_frame = format!("{}{}", params.marker_frame_prefix, m.id);
    out.markers.markers.push(MarkerMsg {
        id: m.id,
        pose,
        pixel_size: si.pose.pixel_size,
        quality: m.quality,
        covariance: with_covariance.covariance,
        duplicate_id: m.duplicate_id,
        decode_confidence: m.decode_confidence.unwrap_or(-1.0),
        measured_pixel_size: m.measured_pixel_size * scale,
        measured_pixel_size_std: m.pixel_size_std * scale,
    });
    // The analysed window, flat: what the measurement covers on the part.
    let side = m.window_px as f64 * si.pose.pixel_size;
    out.detections.detections.push(Detection3D {
        header: header.clone(),
        results: vec![ObjectHypothesisWithPose {
            hypothesis: ObjectHypothesis {
                class_id: m.id.to_string(),
                score: m.quality,
            },
            pose: with_covariance,
        }],
        bbox: BoundingBox3D {
            center: pose,
            size: Vector3 {
                x: side,
                y: side,
                z: 0.0,
            },
        },
        id: marker_frame.clone(),
    });
    if out.poses.iter().any(|(id, _)| *id == m.id) {
        return;
    }
    push_pose_topics(out, m.id, with_covariance, marker_frame, header, params);
}

/// Adds the per-ID pose, pose-with-covariance and (with `publish_tf`) transform of the
/// marker `id` in the frame `marker_frame`.
fn push_pose_topics(
    out: &mut FrameOutput,
    id: u64,
    with_covariance: PoseWithCovariance,
    marker_frame: String,
    header: &Header,
    params: &NodeParams,
) {
    let pose = with_covariance.pose;
    out.poses.push((
        id,
        PoseStamped {
            header: header.clone(),
            pose,
        },
    ));
    out.poses_with_covariance.push((
        id,
        PoseWithCovarianceStamped {
            header: header.clone(),
            pose: with_covariance,
        },
    ));
    if params.publish_tf {
        out.tf.transforms.push(TransformStamped {
            header: header.clone(),
            child_frame_id: marker_frame,
            transform: Transform {
                translation: Vector3 {
                    x: pose.position.x,
                    y: pose.position.y,
                    z: pose.position.z,
                },
                rotation: pose.orientation,
            },
        });
    }
}

/// Adds the pose of `b` in `a`'s frame for each of `relative_pairs` whose two markers are
/// both found.
fn push_relative_poses(
    out: &mut FrameOutput,
    markers: &[MarkerPose],
    header: &Header,
    params: &NodeParams,
) {
    let scale = params.metres_per_unit;
    for &(a, b) in &params.relative_pairs {
        let find = |id: u64| markers.iter().find(|m| m.id == id);
        if let (Some(ma), Some(mb)) = (find(a), find(b)) {
            let a_from_b = ma.pose.scaled(scale).relative(&mb.pose.scaled(scale));
            out.relative.push((
                (a, b),
                PoseStamped {
                    header: Header {
                        stamp: header.stamp,
                        frame_id: format!("{}{}", params.marker_frame_prefix, a),
                    },
                    pose: Pose::from_isometry(&a_from_b),
                },
            ));
        }
    }
}

/// An `rgb8` copy of `grey` with each marker's origin marked by a red cross and its x axis
/// by a green segment (the optional `~/debug_image`).
pub fn annotate(grey: &GreyImage, markers: &[MarkerPose], header: &Header) -> Image {
    let (w, h) = (grey.width(), grey.height());
    let mut data = Vec::with_capacity(w * h * 3);
    for &v in grey.pixels() {
        let g = (v.clamp(0.0, 1.0) * 255.0).round() as u8;
        data.extend([g, g, g]);
    }
    let mut put = |x: f64, y: f64, rgb: [u8; 3]| {
        if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
            let i = ((y as usize) * w + x as usize) * 3;
            if let Some(px) = data.get_mut(i..i + 3) {
                px.copy_from_slice(&rgb);
            }
        }
    };
    let arm = (w.min(h) as f64 / 40.0).max(5.0);
    for m in markers {
        let (cx, cy) = (m.origin_px.x.round(), m.origin_px.y.round());
        for d in -(arm as i64)..=(arm as i64) {
            put(cx + d as f64, cy, [255, 0, 0]);
            put(cx, cy + d as f64, [255, 0, 0]);
        }
        let (s, c) = m.pose.alpha.sin_cos();
        for t in 0..(3 * arm as i64) {
            put(
                (cx + c * t as f64).round(),
                (cy + s * t as f64).round(),
                [0, 255, 0],
            );
        }
    }
    Image {
        header: header.clone(),
        height: h as u32,
        width: w as u32,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: (w * 3) as u32,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::Time;
    use crate::params::ParamValue;
    use vernier::layout::PeriodicLayout;
    use vernier::render::{render, RenderOptions};

    fn params(overrides: &[(&str, ParamValue)]) -> NodeParams {
        let owned: Vec<(String, ParamValue)> = overrides
            .iter()
            .map(|(n, v)| (n.to_string(), v.clone()))
            .collect();
        NodeParams::from_overrides(&owned)
            .map(|s| s.params)
            .unwrap_or_else(|e| panic!("{e}"))
    }

    fn mono8(width: u32, height: u32, data: Vec<u8>) -> Image {
        Image {
            header: Header {
                stamp: Time { sec: 5, nanosec: 6 },
                frame_id: "camera".into(),
            },
            height,
            width,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: width,
            data,
        }
    }

    /// A 256×256 periodic grid (period 8 µm at 1 µm/px) at a known pose, 8-bit.
    fn grid_frame(pose: &vernier::Pose) -> Image {
        let layout = PeriodicLayout::new(8.0, 81, 81).unwrap_or_else(|e| panic!("{e}"));
        let mut opts = RenderOptions::new(256, 256);
        opts.blur_sigma = 0.5;
        opts.bit_depth = Some(8);
        let img = render(&layout, pose, &opts).unwrap_or_else(|e| panic!("{e}"));
        let bytes = img
            .pixels()
            .iter()
            .map(|v| (v * 255.0).round() as u8)
            .collect();
        mono8(256, 256, bytes)
    }

    #[test]
    fn bad_messages_are_rejected_with_reasons() {
        let good = mono8(4, 2, vec![0; 8]);
        assert_eq!(check_image(&good), Ok(PixelFormat::Mono8));
        let cases = [
            (
                Image {
                    encoding: "yuv422".into(),
                    ..good.clone()
                },
                "encoding",
            ),
            (
                Image {
                    data: vec![0; 7],
                    ..good.clone()
                },
                "data bytes",
            ),
            (
                Image {
                    width: 0,
                    step: 0,
                    data: vec![],
                    ..good.clone()
                },
                "zero-size",
            ),
            (
                Image {
                    height: 0,
                    data: vec![],
                    ..good.clone()
                },
                "zero-size",
            ),
            (
                Image {
                    step: 3,
                    data: vec![0; 6],
                    ..good.clone()
                },
                "step",
            ),
            (
                Image {
                    encoding: "rgb8".into(),
                    ..good.clone()
                },
                "step",
            ),
            (
                Image {
                    width: u32::MAX,
                    height: u32::MAX,
                    step: u32::MAX,
                    ..good.clone()
                },
                "data bytes",
            ),
        ];
        for (msg, reason) in cases {
            let err = check_image(&msg).err().map(|e| e.0).unwrap_or_default();
            assert!(err.contains(reason), "`{err}` lacks `{reason}`");
        }
        for encoding in ["mono16", "rgb8", "bgr8", "rgba8", "bgra8"] {
            let bpp = PixelFormat::from_ros_encoding(encoding, false)
                .map(|f| f.bytes_per_pixel())
                .unwrap_or(0) as u32;
            let msg = Image {
                encoding: encoding.into(),
                step: 4 * bpp,
                data: vec![0; (8 * bpp) as usize],
                ..good.clone()
            };
            assert!(to_grey(&msg).is_ok(), "{encoding}");
        }
    }

    #[test]
    fn outputs_are_si_stamped_and_empty_on_loss() {
        let p = params(&[
            ("period", ParamValue::Double(8.0)),
            ("camera_frame", ParamValue::String("cam_optical".into())),
        ]);
        let mut processor = Processor::new(p, 0).unwrap_or_else(|e| panic!("{e}"));
        let truth = vernier::Pose::planar(1.25, -2.5, 0.3, 1.0);
        let out = processor
            .process(&grid_frame(&truth))
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(out.markers.header.stamp, Time { sec: 5, nanosec: 6 });
        assert_eq!(out.markers.header.frame_id, "cam_optical");
        assert_eq!(out.markers.markers.len(), 1);
        let m = &out.markers.markers[0];
        let expected = truth.scaled(1e-6).camera_from_pattern().translation.vector;
        let err_m = ((m.pose.position.x - expected.x).powi(2)
            + (m.pose.position.y - expected.y).powi(2))
        .sqrt();
        // 1e-3 px at 1 µm/px = 1e-9 m.
        assert!(err_m < 1e-9, "position error {err_m} m");
        assert!((m.pixel_size - 1e-6).abs() < 1e-9);
        assert!(
            m.covariance.0[0] > 0.0 && m.covariance.0[0] < 1e-15,
            "{}",
            m.covariance.0[0]
        );
        assert_eq!(out.poses.len(), 1);
        assert_eq!(out.tf.transforms.len(), 1);
        assert_eq!(out.tf.transforms[0].child_frame_id, "vernier_marker_0");
        // A blank frame: valid message, nothing found, empty array with the stamp.
        let empty = processor
            .process(&mono8(256, 256, vec![0; 256 * 256]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(empty.markers.markers.is_empty());
        assert!(empty.poses.is_empty() && empty.tf.transforms.is_empty());
        assert!(empty.detect_error.is_some());
        assert_eq!(empty.markers.header.stamp, Time { sec: 5, nanosec: 6 });
        // The frame buffer, reused across sizes, holds the last frame as a fresh conversion
        // gives it; a bad message leaves it as it was.
        let blank = mono8(256, 256, vec![0; 256 * 256]);
        let fresh = to_grey(&blank).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(processor.last_frame(), Some(&fresh));
        let short = mono8(256, 256, vec![0; 100]);
        assert!(processor.process(&short).is_err());
        assert_eq!(processor.last_frame(), Some(&fresh));
    }

    #[test]
    fn detections_carry_id_quality_and_covariance() {
        let p = params(&[("period", ParamValue::Double(8.0))]);
        let mut processor = Processor::new(p, 0).unwrap_or_else(|e| panic!("{e}"));
        let truth = vernier::Pose::planar(1.25, -2.5, 0.3, 1.0);
        let mut frame = grid_frame(&truth);
        frame.header.frame_id.clear();
        let out = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        assert!(out.frame_defaulted);
        assert_eq!(out.detections.header.frame_id, DEFAULT_CAMERA_FRAME);
        assert_eq!(out.detections.detections.len(), 1);
        let d = &out.detections.detections[0];
        let m = &out.markers.markers[0];
        assert_eq!(d.results[0].hypothesis.class_id, m.id.to_string());
        assert_eq!(d.results[0].hypothesis.score, m.quality);
        assert_eq!(d.results[0].pose.pose, m.pose);
        assert_eq!(d.results[0].pose.covariance, m.covariance);
        assert_eq!(d.id, "vernier_marker_0");
        assert!(d.bbox.size.x > 0.0 && d.bbox.size.z == 0.0);
        assert_eq!(out.poses_with_covariance.len(), 1);
        assert_eq!(out.poses_with_covariance[0].1.pose.covariance, m.covariance);
        // Nothing found: the detection array is published empty, with the stamp.
        let empty = processor
            .process(&mono8(256, 256, vec![0; 256 * 256]))
            .unwrap_or_else(|e| panic!("{e}"));
        assert!(empty.detections.detections.is_empty());
        assert_eq!(empty.detections.header.stamp, frame.header.stamp);
    }

    #[test]
    fn compressed_frames_give_the_raw_frames_result() {
        let p = params(&[("period", ParamValue::Double(8.0))]);
        let mut processor = Processor::new(p, 0).unwrap_or_else(|e| panic!("{e}"));
        let truth = vernier::Pose::planar(0.75, 1.5, -0.2, 1.0);
        let raw = grid_frame(&truth);
        let expected = processor.process(&raw).unwrap_or_else(|e| panic!("{e}"));
        let grey = image::GrayImage::from_raw(raw.width, raw.height, raw.data.clone());
        let grey = grey.unwrap_or_else(|| panic!("bad test image"));
        for (format, codec) in [
            ("png", image::ImageFormat::Png),
            ("mono8; jpeg compressed mono8", image::ImageFormat::Jpeg),
        ] {
            let mut bytes = std::io::Cursor::new(Vec::new());
            grey.write_to(&mut bytes, codec)
                .unwrap_or_else(|e| panic!("{e}"));
            let msg = CompressedImage {
                header: raw.header.clone(),
                format: format.into(),
                data: bytes.into_inner(),
            };
            let out = processor
                .process_compressed(&msg)
                .unwrap_or_else(|e| panic!("{format}: {e}"));
            assert_eq!(out.markers.markers.len(), 1, "{format}");
            let (a, b) = (
                &out.markers.markers[0].pose,
                &expected.markers.markers[0].pose,
            );
            let err = (a.position.x - b.position.x).hypot(a.position.y - b.position.y);
            // PNG is lossless; JPEG moves the phase by a small fraction of a pixel (1 µm).
            let tolerance = if codec == image::ImageFormat::Png {
                1e-15
            } else {
                5e-9
            };
            assert!(err <= tolerance, "{format}: {err} m");
        }
        let garbage = CompressedImage {
            header: raw.header.clone(),
            format: "jpeg".into(),
            data: vec![0xff, 0xd8, 0xff, 0x00, 1, 2, 3],
        };
        assert!(processor.process_compressed(&garbage).is_err());
        let depth = CompressedImage {
            format: "16UC1; compressedDepth png".into(),
            ..garbage
        };
        let e = processor
            .process_compressed(&depth)
            .err()
            .unwrap_or(BadImage(String::new()));
        assert!(e.0.contains("depth"), "{e}");
    }

    /// An 8-bit `size × size` frame of `layout` rendered at `truth`, blurred by `blur` px.
    fn rendered_mono8(
        layout: &dyn vernier::layout::Layout,
        truth: &vernier::Pose,
        size: usize,
        blur: f64,
    ) -> Image {
        let options = RenderOptions {
            blur_sigma: blur,
            ..RenderOptions::new(size, size)
        };
        let image = render(layout, truth, &options).unwrap_or_else(|e| panic!("{e}"));
        let data = image
            .pixels()
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        mono8(size as u32, size as u32, data)
    }

    #[test]
    fn pose_3d_publishes_tilts_with_their_covariance() {
        let layout =
            vernier::layout::MegarenaLayout::new(10.0, 8).unwrap_or_else(|e| panic!("{e}"));
        let truth = vernier::Pose {
            x: -3000.0,
            y: -4200.0,
            z: 0.0,
            alpha: 0.8,
            beta: 0.2,
            gamma: -0.1,
            pixel_size: 1.1,
        };
        let frame = rendered_mono8(&layout, &truth, 512, 0.6);
        let megarena = |pose_3d: bool| {
            params(&[
                ("pattern_type", ParamValue::String("megarena".into())),
                ("period", ParamValue::Double(10.0)),
                ("code_depth", ParamValue::Integer(8)),
                ("pose_3d", ParamValue::Boolean(pose_3d)),
            ])
        };
        let mut flat = Processor::new(megarena(false), 0).unwrap_or_else(|e| panic!("{e}"));
        let out = flat.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        let cov = out.markers.markers[0].covariance.0;
        assert_eq!((cov[21], cov[28]), (1e6, 1e6), "roll and pitch unobserved");
        let mut tilted = Processor::new(megarena(true), 0).unwrap_or_else(|e| panic!("{e}"));
        let out = tilted.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        let m = &out.markers.markers[0];
        let o = m.pose.orientation;
        let q = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            o.w, o.x, o.y, o.z,
        ));
        let (roll, pitch, _) = q.euler_angles();
        // Orthographic render: either mirror solution (β, γ) or (−β, −γ).
        assert!((pitch.abs() - 0.2).abs() < 1e-3, "pitch {pitch}");
        assert!((roll.abs() - 0.1).abs() < 1e-3, "roll {roll}");
        assert!(pitch * roll < 0.0, "signs of ({pitch}, {roll})");
        let cov = m.covariance.0;
        assert!(cov[21] > 0.0 && cov[21] < 1e-4, "roll variance {}", cov[21]);
        assert!(
            cov[28] > 0.0 && cov[28] < 1e-4,
            "pitch variance {}",
            cov[28]
        );
        assert_eq!(
            out.detections.detections[0].results[0].pose.covariance.0,
            cov
        );
    }

    #[test]
    fn pose_3d_of_an_hp_code_publishes_its_depth_from_the_focal_length() {
        // An HP code tilted by (0.2, -0.25) rad at the image centre: with `focal_length_px`,
        // the published translation's z is pixel size × focal (metres) with a real variance;
        // roll and pitch are measured. Without it, z stays unobserved.
        let layout = vernier::layout::HpCodeLayout::from_code_size(10.0, 33)
            .and_then(|l| l.with_id(3))
            .unwrap_or_else(|e| panic!("{e}"));
        let truth = vernier::Pose {
            alpha: 0.4,
            beta: 0.2,
            gamma: -0.25,
            ..vernier::Pose::planar(0.0, 0.0, 0.0, 0.9)
        };
        let frame = rendered_mono8(&layout, &truth, 320, 0.5);
        let hp = |focal: f64| {
            params(&[
                ("pattern_type", ParamValue::String("hpcode".into())),
                ("period", ParamValue::Double(10.0)),
                ("code_size", ParamValue::Integer(33)),
                ("pose_3d", ParamValue::Boolean(true)),
                ("focal_length_px", ParamValue::Double(focal)),
            ])
        };
        let mut with_focal = Processor::new(hp(8000.0), 0).unwrap_or_else(|e| panic!("{e}"));
        let out = with_focal.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        let m = &out.markers.markers[0];
        let depth = 0.9 * 8000.0 * 1e-6;
        assert!(
            (m.pose.position.z / depth - 1.0).abs() < 1e-3,
            "{:?}",
            m.pose
        );
        let cov = m.covariance.0;
        assert!(cov[14] > 0.0 && cov[14] < 1e-12, "z variance {}", cov[14]);
        assert!(cov[21] > 0.0 && cov[21] < 1e-4, "roll variance {}", cov[21]);
        assert!(
            cov[28] > 0.0 && cov[28] < 1e-4,
            "pitch variance {}",
            cov[28]
        );
        let mut orthographic = Processor::new(hp(0.0), 0).unwrap_or_else(|e| panic!("{e}"));
        let out = orthographic
            .process(&frame)
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(out.markers.markers[0].covariance.0[14], 1e6, "z unobserved");
    }

    #[test]
    fn parameter_updates_apply_to_the_next_frame() {
        let p = params(&[("period", ParamValue::Double(8.0))]);
        let mut processor = Processor::new(p.clone(), 0).unwrap_or_else(|e| panic!("{e}"));
        let frame = grid_frame(&vernier::Pose::planar(0.5, 0.25, 0.1, 1.0));
        let before = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        // Doubling the physical period doubles the measured pixel size (the image is the same).
        let q = p
            .with("period", &ParamValue::Double(16.0))
            .and_then(|q| q.with("publish_tf", &ParamValue::Boolean(false)))
            .and_then(|q| q.with("period_unit", &ParamValue::String("nm".into())))
            .unwrap_or_else(|e| panic!("{e}"));
        processor.update(q, 1).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(processor.generation(), 1);
        let after = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        let ratio = after.markers.markers[0].pixel_size / before.markers.markers[0].pixel_size;
        // 2× the period in nm instead of µm: 2e-3 × the metres per pixel.
        assert!((ratio - 2e-3).abs() < 1e-9, "ratio {ratio}");
        assert!(after.tf.transforms.is_empty());
        // Tracking only another id publishes an empty array.
        let r = processor
            .params()
            .with("marker_ids", &ParamValue::IntegerArray(vec![4]))
            .unwrap_or_else(|e| panic!("{e}"));
        processor.update(r, 2).unwrap_or_else(|e| panic!("{e}"));
        let none = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        assert!(none.markers.markers.is_empty());
        // A quality threshold above 1 is rejected before it reaches the processor.
        assert!(processor
            .params()
            .with("min_quality", &ParamValue::Double(2.0))
            .is_err());
    }

    #[test]
    fn a_failed_rebuild_keeps_the_previous_detector() {
        let dir = std::env::temp_dir().join(format!("vernier_ros_proc_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap_or(());
        let file = dir.join("grid.json");
        std::fs::write(
            &file,
            r#"{"PeriodicPattern": {"period": 8.0, "nRows": 81, "nCols": 81}}"#,
        )
        .unwrap_or(());
        let file_text = file.display().to_string();
        let p = params(&[("pattern_file", ParamValue::String(file_text))]);
        let q = p
            .with("period", &ParamValue::Double(16.0))
            .unwrap_or_else(|e| panic!("{e}"));
        let mut processor = Processor::new(p, 0).unwrap_or_else(|e| panic!("{e}"));
        // The pattern file vanishes between validation and the next frame.
        std::fs::remove_dir_all(&dir).unwrap_or(());
        assert!(processor.update(q, 1).is_err());
        assert_eq!(processor.generation(), 1, "not retried on every frame");
        assert_eq!(processor.params().settings.period, None);
        let frame = grid_frame(&vernier::Pose::planar(0.5, 0.25, 0.1, 1.0));
        let out = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
        assert!((out.markers.markers[0].pixel_size - 1e-6).abs() < 1e-9);
    }

    #[test]
    fn a_calibrated_pixel_size_is_published_beside_the_measured_one() {
        // The grid is rendered at 1 µm per pixel; the node is told 1.001 µm (in metres).
        let frame = grid_frame(&vernier::Pose::planar(0.5, 0.25, 0.1, 1.0));
        let measure = |calibrated: Option<f64>| {
            let mut values = vec![("period", ParamValue::Double(8.0))];
            if let Some(v) = calibrated {
                values.push(("pixel_size", ParamValue::Double(v)));
            }
            let mut processor =
                Processor::new(params(&values), 0).unwrap_or_else(|e| panic!("{e}"));
            let out = processor.process(&frame).unwrap_or_else(|e| panic!("{e}"));
            out.markers.markers[0].clone()
        };
        let (own, calibrated) = (measure(None), measure(Some(1.001e-6)));
        assert_eq!(calibrated.pixel_size, 1.001e-6);
        assert_eq!(calibrated.measured_pixel_size, own.pixel_size);
        assert!((own.measured_pixel_size - 1e-6).abs() < 1e-10);
        assert!(own.measured_pixel_size_std > 0.0 && own.measured_pixel_size_std < 1e-10);
        // Same image position, converted with the given scale.
        let ratio = calibrated.pose.position.x / own.pose.position.x;
        assert!(
            (ratio * own.pixel_size / 1.001e-6 - 1.0).abs() < 1e-9,
            "{ratio}"
        );
        // Out of range (10 cm per pixel is the largest) is refused with the parameter's name.
        let refused = params(&[("period", ParamValue::Double(8.0))])
            .with("pixel_size", &ParamValue::Double(0.5))
            .map(|_| ())
            .unwrap_err();
        assert!(refused.contains("pixel_size"), "{refused}");
    }

    #[test]
    fn relative_pairs_give_b_in_a_frame() {
        // Two synthetic markers (as a multi-marker detector would report them), µm.
        let p = params(&[
            ("period", ParamValue::Double(8.0)),
            (
                "relative_pairs",
                ParamValue::StringArray(vec!["3:9".into(), "3:4".into()]),
            ),
        ]);
        let marker = |id: u64, pose: vernier::Pose| MarkerPose {
            id,
            pose,
            origin_px: nalgebra::Vector2::new(0.0, 0.0),
            quality: 0.9,
            phase_std: [1e-4, 1e-4],
            duplicate_id: false,
            decode_confidence: None,
            pose_3d_cue_strength: None,
            window_px: 256,
            yaw_std: None,
            slope_std: None,
            measured_pixel_size: pose.pixel_size,
            pixel_size_std: 0.0,
            tilt_covariance: None,
        };
        let a = vernier::Pose::planar(10.0, 20.0, 0.5, 1.0);
        let b = vernier::Pose::from_origin_in_image(
            a.origin_in_image() + vernier::pose::rotate2(nalgebra::Vector2::new(30.0, 4.0), 0.5),
            0.7,
            1.0,
        );
        let out = build_output(
            &mono8(1, 1, vec![0]).header,
            vec![marker(3, a), marker(9, b)],
            None,
            &p,
            8.0,
        );
        assert_eq!(out.relative.len(), 1, "pair 3:4 has no marker 4");
        let ((ia, ib), rel) = &out.relative[0];
        assert_eq!((*ia, *ib), (3, 9));
        assert_eq!(rel.header.frame_id, "vernier_marker_3");
        // b's origin is 30 µm along a's x axis and 4 µm along its y axis, turned by 0.2 rad.
        assert!(
            (rel.pose.position.x - 30e-6).abs() < 1e-12,
            "{:?}",
            rel.pose
        );
        assert!((rel.pose.position.y - 4e-6).abs() < 1e-12, "{:?}", rel.pose);
        let q = rel.pose.orientation;
        assert!((2.0 * q.z.atan2(q.w) - 0.2).abs() < 1e-12);
    }

    #[test]
    fn hp_code_pair_through_the_detector() {
        // Two HP codes (W 33, period 8 µm at 1 µm/px: 8 px) with IDs 37 and 300 in one 8-bit
        // frame, far from the centre: every published pose and the pair's relative pose agree
        // with the truth within the image-position (1e-3 px) and scale (1e-5) errors.
        let p = params(&[
            ("pattern_type", ParamValue::String("hpcode".into())),
            ("period", ParamValue::Double(8.0)),
            ("code_size", ParamValue::Integer(33)),
            (
                "relative_pairs",
                ParamValue::StringArray(vec!["37:300".into()]),
            ),
        ]);
        let layout = |id| {
            vernier::layout::HpCodeLayout::from_code_size(8.0, 33)
                .and_then(|l| l.with_id(id))
                .unwrap_or_else(|e| panic!("{e}"))
        };
        let (la, lb) = (layout(37), layout(300));
        let a =
            vernier::Pose::from_origin_in_image(nalgebra::Vector2::new(-110.3, -98.6), 0.4, 1.0);
        let b =
            vernier::Pose::from_origin_in_image(nalgebra::Vector2::new(108.7, 101.2), -2.0, 1.0);
        let mut opts = RenderOptions::new(512, 512);
        opts.blur_sigma = 0.5;
        opts.bit_depth = Some(8);
        let items: [(&dyn vernier::layout::Layout, vernier::Pose); 2] = [(&la, a), (&lb, b)];
        let img = vernier::render::render_scene(&items, &opts).unwrap_or_else(|e| panic!("{e}"));
        let bytes = img
            .pixels()
            .iter()
            .map(|v| (v * 255.0).round() as u8)
            .collect();
        let mut processor = Processor::new(p, 0).unwrap_or_else(|e| panic!("{e}"));
        let out = processor
            .process(&mono8(512, 512, bytes))
            .unwrap_or_else(|e| panic!("{e}"));
        let mut ids: Vec<u64> = out.markers.markers.iter().map(|m| m.id).collect();
        ids.sort_unstable();
        assert_eq!(ids, vec![37, 300], "{:?}", out.detect_error);
        for (id, truth) in [(37, a), (300, b)] {
            let published = out.poses.iter().find(|(i, _)| *i == id);
            let Some((_, pose)) = published else {
                panic!("no pose for marker {id}")
            };
            let expected = truth.scaled(1e-6).camera_from_pattern().translation.vector;
            let err_m = ((pose.pose.position.x - expected.x).powi(2)
                + (pose.pose.position.y - expected.y).powi(2))
            .sqrt();
            // 1e-3 px plus the scale error (1e-5) over the marker's distance from the centre.
            let tol_m = (1e-3 + 1e-5 * truth.origin_in_image().norm()) * 1e-6;
            assert!(
                err_m < tol_m,
                "marker {id}: error {err_m:.3e} m > {tol_m:.3e} m"
            );
        }
        assert_eq!(out.relative.len(), 1);
        let ((ia, ib), rel) = &out.relative[0];
        assert_eq!((*ia, *ib), (37, 300));
        assert_eq!(rel.header.frame_id, "vernier_marker_37");
        let truth = a.scaled(1e-6).relative(&b.scaled(1e-6));
        let t = truth.translation.vector;
        let err_m =
            ((rel.pose.position.x - t.x).powi(2) + (rel.pose.position.y - t.y).powi(2)).sqrt();
        // 2e-3 px, the scale error over both markers' distances and a 2e-5 rad yaw error of
        // marker a over their separation (≈ 300 px).
        let tol_m = (2e-3 + 1e-5 * 300.0 + 2e-5 * 300.0) * 1e-6;
        assert!(
            err_m < tol_m,
            "relative error {err_m:.3e} m > {tol_m:.3e} m"
        );
        let q = rel.pose.orientation;
        let yaw_err = vernier::phase::wrap_to_pi(2.0 * q.z.atan2(q.w) - (-2.0 - 0.4));
        assert!(yaw_err.abs() < 4e-5, "relative yaw error {yaw_err:.3e} rad");
    }
}
