//! # vernier_ros
//!
//! ROS 2 node measuring the pose of VERNIER dot markers in camera images, built on
//! `ros2-client` / `rustdds` (pure Rust: no ROS installation is needed to build or run it).
//! The measurement itself is the `vernier` crate; this crate is the ROS glue:
//! [`messages`] (wire types), [`ros_args`] (`--ros-args`), [`params`] (parameters),
//! [`param_services`] (`ros2 param`), [`processing`] (one frame → output messages), [`diagnostics`] and [`node`] (DDS wiring).
pub mod diagnostics;
#[cfg(test)]
mod fuzz_tests;
pub mod messages;
pub mod node;
pub mod param_services;
pub mod params;
pub mod processing;
pub mod ros_args;
