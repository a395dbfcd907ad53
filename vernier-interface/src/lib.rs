//! # vernier-interface
//!
//! The vernier_ros node's interface, without any DDS code, so that the node and
//! `vernier bag` share one source of truth:
//!
//! * [`params`]: the parameter schema (names, types, defaults, units, ranges, descriptions),
//!   validation with reasons, and the mapping onto the detector's settings; params/detector.yaml
//!   is generated from it;
//! * [`ros_args`]: `--ros-args` and ROS 2 parameter files (node-name patterns, nesting);
//! * [`messages`]: the ROS message structs (sensor_msgs, geometry_msgs, tf2_msgs,
//!   diagnostic_msgs, vision_msgs, vernier_ros) whose CDR encoding ([`cdr`]) is the wire format,
//!   and their `ros2msg` schemas for MCAP ([`schemas`]);
//! * [`processing`]: one image message → every output message, SI units.
//!
//! The `ros2-client` feature (the node's) marks the messages as `ros2_client::Message` and
//! converts [`params::ParamValue`] to and from `ros2_client::ParameterValue`.
#![deny(missing_docs)]

pub mod cdr;
pub mod messages;
pub mod params;
pub mod processing;
pub mod ros_args;
pub mod schemas;
