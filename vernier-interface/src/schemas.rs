//! `ros2msg` schema texts of the messages `vernier bag` writes into MCAP: the main definition,
//! then each dependency as a `MSG: pkg/Type` block, as rosbag2 records them. The
//! vernier_ros definitions are the repository's `msg/` files.

const SEPARATOR: &str =
    "================================================================================\n";

fn schema(main: &str, dependencies: &[(&str, &str)]) -> String {
    let mut out = main.trim_end().to_string();
    out.push('\n');
    for (name, text) in dependencies {
        out.push_str(SEPARATOR);
        out.push_str(&format!("MSG: {name}\n{}\n", text.trim_end()));
    }
    out
}

const TIME: (&str, &str) = ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec");
const HEADER: (&str, &str) = (
    "std_msgs/Header",
    "builtin_interfaces/Time stamp\nstring frame_id",
);
const POSE: (&str, &str) = (
    "geometry_msgs/Pose",
    "Point position\nQuaternion orientation",
);
const POINT: (&str, &str) = ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z");
const VECTOR3: (&str, &str) = ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z");
const QUATERNION: (&str, &str) = (
    "geometry_msgs/Quaternion",
    "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
);
const POSE_WITH_COVARIANCE: (&str, &str) = (
    "geometry_msgs/PoseWithCovariance",
    "Pose pose\nfloat64[36] covariance",
);

/// `geometry_msgs/msg/PoseStamped`.
pub fn pose_stamped() -> String {
    schema(
        "std_msgs/Header header\ngeometry_msgs/Pose pose",
        &[HEADER, TIME, POSE, POINT, QUATERNION],
    )
}

/// `geometry_msgs/msg/PoseWithCovarianceStamped`.
pub fn pose_with_covariance_stamped() -> String {
    schema(
        "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose",
        &[HEADER, TIME, POSE_WITH_COVARIANCE, POSE, POINT, QUATERNION],
    )
}

/// `vision_msgs/msg/Detection3DArray` (vision_msgs 4, the ROS 2 layout).
pub fn detection_3d_array() -> String {
    schema(
        "std_msgs/Header header\nDetection3D[] detections",
        &[
            HEADER,
            TIME,
            (
                "vision_msgs/Detection3D",
                "std_msgs/Header header\nObjectHypothesisWithPose[] results\nBoundingBox3D bbox\nstring id",
            ),
            (
                "vision_msgs/ObjectHypothesisWithPose",
                "ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose",
            ),
            (
                "vision_msgs/ObjectHypothesis",
                "string class_id\nfloat64 score",
            ),
            POSE_WITH_COVARIANCE,
            (
                "vision_msgs/BoundingBox3D",
                "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size",
            ),
            POSE,
            POINT,
            QUATERNION,
            VECTOR3,
        ],
    )
}

/// `vernier_ros/msg/MarkerPoseArray`.
pub fn marker_pose_array() -> String {
    schema(
        include_str!("../../msg/MarkerPoseArray.msg"),
        &[
            HEADER,
            TIME,
            (
                "vernier_ros/MarkerPose",
                include_str!("../../msg/MarkerPose.msg"),
            ),
            POSE,
            POINT,
            QUATERNION,
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schemas_name_every_dependency() {
        let s = marker_pose_array();
        assert!(s.starts_with("# Every marker measured"));
        for dep in [
            "MSG: vernier_ros/MarkerPose",
            "MSG: geometry_msgs/Quaternion",
        ] {
            assert!(s.contains(dep), "{dep}");
        }
        assert!(pose_stamped().contains("MSG: builtin_interfaces/Time\nint32 sec"));
        let d = detection_3d_array();
        for dep in [
            "MSG: vision_msgs/ObjectHypothesis\n",
            "MSG: geometry_msgs/PoseWithCovariance\n",
            "MSG: geometry_msgs/Vector3\n",
        ] {
            assert!(d.contains(dep), "{dep}");
        }
    }
}
