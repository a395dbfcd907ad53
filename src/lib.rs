//! # vernier_ros
//!
//! ROS 2 node measuring the pose of VERNIER dot markers in camera images, built on
//! `ros2-client` / `rustdds` (pure Rust: no ROS installation is needed to build or run it).
//! The measurement itself is the `vernier` crate; the node's interface without DDS (parameter
//! schema, message structs, `--ros-args`, one frame → output messages) is the
//! `vernier-interface` crate, shared with `vernier bag` and re-exported here as [`messages`],
//! [`params`], [`processing`] and [`ros_args`]. This crate is the DDS glue:
//! [`param_services`] (`ros2 param`), [`diagnostics`], [`discovery`] (the ROS discovery
//! environment variables), [`memory`] (frame-sized blocks reused, freed memory handed back)
//! and [`node`] (DDS wiring).
pub mod diagnostics;
pub mod discovery;
#[cfg(test)]
mod fuzz_tests;
pub mod memory;
pub mod node;
pub mod param_services;
pub use vernier_interface::{messages, params, processing, ros_args};
