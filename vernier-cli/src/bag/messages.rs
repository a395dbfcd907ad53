//! The few ROS 2 messages `vernier bag` reads and writes, as CDR (XCDR1, little-endian)
//! serde structs, and their `ros2msg` schemas for MCAP.
//!
//! These duplicate a subset of the root package's `src/messages.rs` on purpose: the CLI must
//! not depend on the ROS node crate (and its DDS stack). The vernier_ros message definitions
//! are included from the repository's `msg/` files, so both stay in step.

use byteorder::LittleEndian;
use serde::{Deserialize, Serialize};

/// CDR encapsulation header of little-endian plain CDR payloads.
const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// `builtin_interfaces/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, < 10⁹.
    pub nanosec: u32,
}

impl Time {
    /// Seconds as a float.
    pub fn seconds(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// `std_msgs/Header`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Time,
    /// Coordinate frame.
    pub frame_id: String,
}

/// `sensor_msgs/Image`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Acquisition stamp and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding (`mono8`, `mono16`, `rgb8`, ...).
    pub encoding: String,
    /// Byte order of multi-byte samples.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Pixels.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `geometry_msgs/Point`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x, metres.
    pub x: f64,
    /// y, metres.
    pub y: f64,
    /// z, metres.
    pub z: f64,
}

/// `geometry_msgs/Quaternion` (scalar last).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// i component.
    pub x: f64,
    /// j component.
    pub y: f64,
    /// k component.
    pub z: f64,
    /// Scalar part.
    pub w: f64,
}

/// `geometry_msgs/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position, metres.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

impl Pose {
    /// The camera-from-pattern transform of a vernier pose (lengths already in metres).
    pub fn from_vernier(pose: &vernier::Pose) -> Self {
        let iso = pose.camera_from_pattern();
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
    /// Image stamp and camera frame.
    pub header: Header,
    /// Marker pose in the camera frame.
    pub pose: Pose,
}

/// `vernier_ros/MarkerPose` (msg/MarkerPose.msg).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MarkerPose {
    /// Marker ID.
    pub id: u64,
    /// Pose in the camera frame, metres.
    pub pose: Pose,
    /// Object-side pixel size, metres.
    pub pixel_size: f64,
    /// Detection quality in [0, 1].
    pub quality: f64,
    /// Row-major 6×6 covariance of (x, y, z, roll, pitch, yaw), m² and rad².
    pub covariance: [[f64; 6]; 6],
    /// Another marker of the image has the same ID.
    pub duplicate_id: bool,
    /// Confidence of the coarse decoding, `[0, 1]`; −1 for periodic grids (none).
    pub decode_confidence: f64,
}

/// `vernier_ros/MarkerPoseArray` (msg/MarkerPoseArray.msg).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MarkerPoseArray {
    /// Image stamp and camera frame.
    pub header: Header,
    /// Every marker of the image (empty when none was found).
    pub markers: Vec<MarkerPose>,
}

/// Decodes a CDR payload (with its 4-byte encapsulation header).
pub fn from_cdr<'de, T: Deserialize<'de>>(payload: &'de [u8]) -> Result<T, String> {
    let (head, body) = payload
        .split_at_checked(4)
        .ok_or("CDR payload shorter than its header")?;
    let decoded = match head[..2] {
        [0x00, 0x01] | [0x00, 0x03] => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        [0x00, 0x00] | [0x00, 0x02] => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(body),
        _ => return Err(format!("unsupported CDR encapsulation {head:02x?}")),
    };
    decoded
        .map(|(value, _)| value)
        .map_err(|e| format!("bad CDR message: {e}"))
}

/// Encodes a message as little-endian CDR with its encapsulation header.
pub fn to_cdr<T: Serialize>(value: &T) -> Result<Vec<u8>, String> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(value)
        .map_err(|e| format!("cannot encode a message: {e}"))?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&CDR_LE_HEADER);
    out.extend_from_slice(&body);
    Ok(out)
}

/// Encodes big-endian CDR (used by the tests to check both byte orders).
#[cfg(test)]
pub fn to_cdr_big_endian<T: Serialize>(value: &T) -> Vec<u8> {
    let mut out = vec![0x00, 0x00, 0x00, 0x00];
    out.extend(cdr_encoding::to_vec::<T, byteorder::BigEndian>(value).unwrap());
    out
}

const SEPARATOR: &str =
    "================================================================================\n";

/// Concatenates a `ros2msg` schema: the main definition, then each dependency as
/// `MSG: pkg/Type` blocks.
fn schema(main: &str, dependencies: &[(&str, &str)]) -> String {
    let mut out = main.trim_end().to_string();
    out.push('\n');
    for (name, text) in dependencies {
        out.push_str(SEPARATOR);
        out.push_str(&format!("MSG: {name}\n{}\n", text.trim_end()));
    }
    out
}

const TIME: &str = "int32 sec\nuint32 nanosec";
const HEADER: &str = "builtin_interfaces/Time stamp\nstring frame_id";
const POSE: &str = "Point position\nQuaternion orientation";
const POINT: &str = "float64 x\nfloat64 y\nfloat64 z";
const QUATERNION: &str = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1";

/// `geometry_msgs/msg/PoseStamped` schema text.
pub fn pose_stamped_schema() -> String {
    schema(
        "std_msgs/Header header\ngeometry_msgs/Pose pose",
        &[
            ("std_msgs/Header", HEADER),
            ("builtin_interfaces/Time", TIME),
            ("geometry_msgs/Pose", POSE),
            ("geometry_msgs/Point", POINT),
            ("geometry_msgs/Quaternion", QUATERNION),
        ],
    )
}

/// `vernier_ros/msg/MarkerPoseArray` schema text (from the repository's `msg/` files).
pub fn marker_pose_array_schema() -> String {
    schema(
        include_str!("../../../msg/MarkerPoseArray.msg"),
        &[
            ("std_msgs/Header", HEADER),
            ("builtin_interfaces/Time", TIME),
            (
                "vernier_ros/MarkerPose",
                include_str!("../../../msg/MarkerPose.msg"),
            ),
            ("geometry_msgs/Pose", POSE),
            ("geometry_msgs/Point", POINT),
            ("geometry_msgs/Quaternion", QUATERNION),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let le = to_cdr(&image).unwrap();
        // Hand-checked layout: header, sec, nanosec, frame_id (len 7 incl. NUL), padding.
        assert_eq!(&le[..12], &[0, 1, 0, 0, 12, 0, 0, 0, 0x59, 1, 0, 0]);
        assert_eq!(&le[12..23], b"\x07\0\0\0camera\0");
        assert_eq!(from_cdr::<Image>(&le).unwrap(), image);
        assert_eq!(
            from_cdr::<Image>(&to_cdr_big_endian(&image)).unwrap(),
            image
        );
        assert!(from_cdr::<Image>(&le[..3]).is_err());
        assert!(from_cdr::<Image>(&le[..30]).is_err());
    }

    #[test]
    fn schemas_name_every_dependency() {
        let s = marker_pose_array_schema();
        assert!(s.starts_with("# Every marker measured"));
        for dep in [
            "MSG: vernier_ros/MarkerPose",
            "MSG: geometry_msgs/Quaternion",
        ] {
            assert!(s.contains(dep), "{dep}");
        }
        assert!(pose_stamped_schema().contains("MSG: builtin_interfaces/Time\nint32 sec"));
    }
}
