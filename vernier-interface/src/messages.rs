//! ROS 2 message types the node reads and writes, as serde structs whose field order matches
//! the `.msg` definitions, so that the OMG CDR encoding ([`crate::cdr`]) is the ROS wire
//! format. The node publishes them over DDS; `vernier bag` reads and writes them in MCAP.
//!
//! Each struct names its ROS type through [`RosType`]. Lengths are metres, angles radians,
//! times ROS `builtin_interfaces/Time`. Default values are those of the `.msg` definitions
//! (a quaternion defaults to the identity, `w = 1`).

use serde::{Deserialize, Serialize};

/// A message type with its ROS package and name (`sensor_msgs` / `Image` →
/// DDS type `sensor_msgs::msg::dds_::Image_`).
pub trait RosType: Serialize + serde::de::DeserializeOwned {
    /// ROS package that defines the type.
    const PACKAGE: &'static str;
    /// Type name inside the package.
    const NAME: &'static str;
    /// `package/msg/Name`, as rosbag2 and MCAP name the type.
    fn ros_name() -> String {
        format!("{}/msg/{}", Self::PACKAGE, Self::NAME)
    }
}

macro_rules! ros_message {
    ($t:ty, $package:literal, $name:literal) => {
        impl RosType for $t {
            const PACKAGE: &'static str = $package;
            const NAME: &'static str = $name;
        }
        #[cfg(feature = "ros2-client")]
        impl ros2_client::Message for $t {}
    };
}

/// `builtin_interfaces/Time`: seconds and nanoseconds since the epoch (or since start for
/// simulated clocks).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Time {
    /// Whole seconds.
    pub sec: i32,
    /// Nanoseconds within the second, `[0, 1e9)`.
    pub nanosec: u32,
}

impl Time {
    /// The current wall-clock time.
    pub fn now() -> Time {
        let since = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default();
        Time {
            sec: i32::try_from(since.as_secs()).unwrap_or(i32::MAX),
            nanosec: since.subsec_nanos(),
        }
    }

    /// Seconds as a floating-point number.
    pub fn as_secs_f64(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }
}

/// `rosgraph_msgs/Clock`: the simulated time on `/clock` (`ros2 bag play --clock`, simulators).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Clock {
    /// The current simulated time.
    pub clock: Time,
}
ros_message!(Clock, "rosgraph_msgs", "Clock");

/// `std_msgs/Header`: acquisition time and coordinate frame of the data.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time of the data.
    pub stamp: Time,
    /// Frame the data is expressed in.
    pub frame_id: String,
}

/// `sensor_msgs/Image`: an uncompressed image.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Acquisition time and optical frame of the camera.
    pub header: Header,
    /// Number of rows, pixels.
    pub height: u32,
    /// Number of columns, pixels.
    pub width: u32,
    /// Pixel encoding (`mono8`, `mono16`, `rgb8`, `bgr8`, `rgba8`, `bgra8` are read).
    pub encoding: String,
    /// 1 when multi-byte samples are big-endian.
    pub is_bigendian: u8,
    /// Length of a row, bytes.
    pub step: u32,
    /// `step × height` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}
ros_message!(Image, "sensor_msgs", "Image");

/// `geometry_msgs/Point`, metres.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// z, metres.
    pub z: f64,
}

/// `geometry_msgs/Vector3`, metres (as a translation).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x component.
    pub x: f64,
    /// y component.
    pub y: f64,
    /// z component.
    pub z: f64,
}

/// `geometry_msgs/Quaternion` (unit quaternion, scalar last).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// Vector part, x.
    pub x: f64,
    /// Vector part, y.
    pub y: f64,
    /// Vector part, z.
    pub z: f64,
    /// Scalar part.
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/Pose`: position (metres) and orientation of a frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Origin of the frame, metres.
    pub position: Point,
    /// Orientation of the frame.
    pub orientation: Quaternion,
}

impl Pose {
    /// From an isometry whose translation is in metres.
    pub fn from_isometry(iso: &nalgebra::Isometry3<f64>) -> Pose {
        let t = iso.translation.vector;
        let q = iso.rotation.quaternion();
        Pose {
            position: Point {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            orientation: Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        }
    }
}

/// `geometry_msgs/PoseStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Image stamp and the frame the pose is expressed in.
    pub header: Header,
    /// The pose, metres.
    pub pose: Pose,
}
ros_message!(PoseStamped, "geometry_msgs", "PoseStamped");

/// `geometry_msgs/Transform`: translation (metres) and rotation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation, metres.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

/// `geometry_msgs/TransformStamped`: `child_frame_id` expressed in `header.frame_id`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and parent frame.
    pub header: Header,
    /// Child frame.
    pub child_frame_id: String,
    /// Pose of the child frame in the parent frame.
    pub transform: Transform,
}

/// `tf2_msgs/TFMessage`: a batch of transforms for `/tf`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}
ros_message!(TfMessage, "tf2_msgs", "TFMessage");

/// `diagnostic_msgs/KeyValue`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyValue {
    /// Name of the value.
    pub key: String,
    /// The value, as text.
    pub value: String,
}

/// `diagnostic_msgs/DiagnosticStatus`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticStatus {
    /// 0 OK, 1 WARN, 2 ERROR, 3 STALE ([`diagnostic_level`]).
    pub level: u8,
    /// Name of the component.
    pub name: String,
    /// Human-readable summary.
    pub message: String,
    /// Hardware the component runs on.
    pub hardware_id: String,
    /// Measurements.
    pub values: Vec<KeyValue>,
}

/// `DiagnosticStatus::level` values.
pub mod diagnostic_level {
    /// Everything is fine.
    pub const OK: u8 = 0;
    /// Working, with problems.
    pub const WARN: u8 = 1;
    /// Not working.
    pub const ERROR: u8 = 2;
}

/// `diagnostic_msgs/DiagnosticArray`, published on `/diagnostics`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DiagnosticArray {
    /// Publication time.
    pub header: Header,
    /// One status per component.
    pub status: Vec<DiagnosticStatus>,
}
ros_message!(DiagnosticArray, "diagnostic_msgs", "DiagnosticArray");

/// A row-major 6×6 covariance, CDR `float64[36]` (a fixed array: no length prefix).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance36(pub [f64; 36]);

impl Default for Covariance36 {
    fn default() -> Self {
        Covariance36([0.0; 36])
    }
}

impl From<[[f64; 6]; 6]> for Covariance36 {
    fn from(m: [[f64; 6]; 6]) -> Self {
        let mut flat = [0.0; 36];
        for (dst, src) in flat.chunks_exact_mut(6).zip(m.iter()) {
            dst.copy_from_slice(src);
        }
        Covariance36(flat)
    }
}

impl Serialize for Covariance36 {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut tuple = serializer.serialize_tuple(36)?;
        for v in &self.0 {
            tuple.serialize_element(v)?;
        }
        tuple.end()
    }
}

impl<'de> Deserialize<'de> for Covariance36 {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = Covariance36;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64 values")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut seq: A,
            ) -> Result<Covariance36, A::Error> {
                let mut out = [0.0; 36];
                for (i, slot) in out.iter_mut().enumerate() {
                    *slot = seq
                        .next_element()?
                        .ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance36(out))
            }
        }
        deserializer.deserialize_tuple(36, Visitor)
    }
}

/// `sensor_msgs/CompressedImage`: a PNG or JPEG image, as image_transport's `compressed`
/// plugin publishes it on `<image topic>/compressed`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Acquisition time and optical frame of the camera.
    pub header: Header,
    /// `png`, `jpeg`, or image_transport's `"<encoding>; png compressed <encoding>"` form.
    pub format: String,
    /// The encoded file bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}
ros_message!(CompressedImage, "sensor_msgs", "CompressedImage");

/// `geometry_msgs/PoseWithCovariance`: a pose and the row-major covariance of
/// `(x, y, z, rot x, rot y, rot z)` about it, m² and rad², in the pose's parent frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose, metres.
    pub pose: Pose,
    /// Row-major 6×6 covariance; 1e6 marks an unobserved axis.
    pub covariance: Covariance36,
}

/// `geometry_msgs/PoseWithCovarianceStamped`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovarianceStamped {
    /// Image stamp and the frame the pose is expressed in.
    pub header: Header,
    /// The pose and its covariance.
    pub pose: PoseWithCovariance,
}
ros_message!(
    PoseWithCovarianceStamped,
    "geometry_msgs",
    "PoseWithCovarianceStamped"
);

/// `vision_msgs/ObjectHypothesis` (vision_msgs 4, ROS 2).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesis {
    /// Class of the object: here the decimal marker ID.
    pub class_id: String,
    /// Confidence: here the marker quality, `[0, 1]`.
    pub score: f64,
}

/// `vision_msgs/ObjectHypothesisWithPose`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ObjectHypothesisWithPose {
    /// Class and score.
    pub hypothesis: ObjectHypothesis,
    /// Pose of the marker frame in the camera frame, with covariance.
    pub pose: PoseWithCovariance,
}

/// `vision_msgs/BoundingBox3D`: a box centred on a pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct BoundingBox3D {
    /// Centre and orientation of the box, metres.
    pub center: Pose,
    /// Side lengths along the box axes, metres.
    pub size: Vector3,
}

/// `vision_msgs/Detection3D`: one marker.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Detection3D {
    /// Image stamp and camera frame.
    pub header: Header,
    /// One hypothesis: the marker ID with its quality and pose.
    pub results: Vec<ObjectHypothesisWithPose>,
    /// The analysed window around the marker, flat (z size 0), metres.
    pub bbox: BoundingBox3D,
    /// The marker's TF frame name (`<marker_frame_prefix><id>`).
    pub id: String,
}

/// `vision_msgs/Detection3DArray`, published on `~/detections` for every processed frame,
/// empty when nothing was found.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Detection3DArray {
    /// Image stamp and camera frame.
    pub header: Header,
    /// The markers found, possibly none.
    pub detections: Vec<Detection3D>,
}
ros_message!(Detection3DArray, "vision_msgs", "Detection3DArray");

/// `vernier_ros/MarkerPose` (msg/MarkerPose.msg): one measured marker, SI units.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerPose {
    /// Marker identity (decoded ID; 0 for periodic and Megarena patterns).
    pub id: u64,
    /// Pose of the marker frame in the camera frame, metres.
    pub pose: Pose,
    /// Object-side size of one pixel, metres.
    pub pixel_size: f64,
    /// Fraction of the image variance explained by the grid fundamentals, `[0, 1]`.
    pub quality: f64,
    /// Row-major covariance of `(x, y, z, rot x, rot y, rot z)`, m² and rad²; 1e6 marks an
    /// unobserved axis.
    pub covariance: Covariance36,
    /// Another marker in the same image has the same ID.
    pub duplicate_id: bool,
    /// Confidence of the coarse decoding, `[0, 1]`; −1 for periodic grids (none).
    pub decode_confidence: f64,
    /// The marker's own measured scale, metres per pixel (`pixel_size` unless a calibrated
    /// pixel size is set).
    pub measured_pixel_size: f64,
    /// Standard deviation of `measured_pixel_size`, metres per pixel.
    pub measured_pixel_size_std: f64,
}

/// `vernier_ros/MarkerPoseArray` (msg/MarkerPoseArray.msg), published on `~/markers` for every
/// processed frame, empty when nothing was found.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerPoseArray {
    /// Image stamp and camera frame.
    pub header: Header,
    /// The markers found, possibly none.
    pub markers: Vec<MarkerPose>,
}
ros_message!(MarkerPoseArray, "vernier_ros", "MarkerPoseArray");

#[cfg(test)]
mod tests {
    use super::*;

    use crate::cdr::{body_from_cdr, body_to_cdr, from_cdr, to_cdr, to_cdr_big_endian};

    fn cdr<T: Serialize>(value: &T) -> Vec<u8> {
        body_to_cdr(value).unwrap_or_default()
    }

    #[test]
    fn image_layout_matches_ros_cdr() {
        let image = Image {
            header: Header {
                stamp: Time { sec: 1, nanosec: 2 },
                frame_id: "cam".into(),
            },
            height: 1,
            width: 2,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 2,
            data: vec![7, 9],
        };
        let bytes = cdr(&image);
        let mut expected = Vec::new();
        expected.extend(1i32.to_le_bytes());
        expected.extend(2u32.to_le_bytes());
        expected.extend(4u32.to_le_bytes());
        expected.extend(b"cam\0");
        expected.extend(1u32.to_le_bytes());
        expected.extend(2u32.to_le_bytes());
        expected.extend(6u32.to_le_bytes());
        expected.extend(b"mono8\0");
        expected.push(0); // is_bigendian
        expected.push(0); // padding to 4
        expected.extend(2u32.to_le_bytes());
        expected.extend(2u32.to_le_bytes());
        expected.extend([7, 9]);
        assert_eq!(bytes, expected);
    }

    #[test]
    fn marker_array_round_trips_with_fixed_covariance() {
        let mut cov = [[0.0; 6]; 6];
        cov[0][0] = 1.5;
        cov[5][5] = 2.5;
        let array = MarkerPoseArray {
            header: Header::default(),
            markers: vec![MarkerPose {
                id: 7,
                covariance: cov.into(),
                ..MarkerPose::default()
            }],
        };
        let bytes = cdr(&array);
        // header 13 (+3 padding) + sequence length 4 (+4 padding: u64 aligns to 8) + id 8
        // + pose 56 + 2 doubles 16 + 36 doubles 288 + bool 1 (+7 padding) + 3 doubles 24.
        assert_eq!(bytes.len(), 16 + 4 + 4 + 8 + 56 + 16 + 288 + 1 + 7 + 24);
        let back: MarkerPoseArray = body_from_cdr(&bytes).unwrap_or_default();
        assert_eq!(back, array);
        assert_eq!(back.markers[0].covariance.0[35], 2.5);
    }

    #[test]
    fn image_round_trips_in_both_byte_orders() {
        let image = Image {
            header: Header {
                stamp: Time {
                    sec: 12,
                    nanosec: 345,
                },
                frame_id: "camera".into(),
            },
            height: 2,
            width: 3,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 3,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        let le = to_cdr(&image).unwrap_or_default();
        // Hand-checked layout: header, sec, nanosec, frame_id (len 7 incl. NUL), padding.
        assert_eq!(&le[..12], &[0, 1, 0, 0, 12, 0, 0, 0, 0x59, 1, 0, 0]);
        assert_eq!(&le[12..23], b"\x07\0\0\0camera\0");
        assert_eq!(from_cdr::<Image>(&le), Ok(image.clone()));
        assert_eq!(from_cdr::<Image>(&to_cdr_big_endian(&image)), Ok(image));
        assert!(from_cdr::<Image>(&le[..3]).is_err());
        assert!(from_cdr::<Image>(&le[..30]).is_err());
    }

    #[test]
    fn detection_array_layout() {
        let array = Detection3DArray {
            header: Header::default(),
            detections: vec![Detection3D {
                results: vec![ObjectHypothesisWithPose {
                    hypothesis: ObjectHypothesis {
                        class_id: "7".into(),
                        score: 0.5,
                    },
                    ..ObjectHypothesisWithPose::default()
                }],
                id: "m".into(),
                ..Detection3D::default()
            }],
        };
        let bytes = cdr(&array);
        // header 8 + empty string 5 (+3) | detections 4 | header 13 (+3) | results 4 |
        // class_id "7" 6 (+2) | score 8 | pose 56 + cov 288 | bbox 56 + 24 | id "m" 6.
        assert_eq!(bytes.len(), 16 + 4 + 16 + 4 + 8 + 8 + 56 + 288 + 80 + 6);
        assert_eq!(body_from_cdr::<Detection3DArray>(&bytes), Ok(array));
    }
}
