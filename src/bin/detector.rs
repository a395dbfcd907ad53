//! `ros2 run vernier_ros detector --ros-args ...`: the marker-pose node (see `vernier_ros::node`).

use std::process::ExitCode;

/// Frame-sized blocks reused from frame to frame (`vernier_ros::memory`).
#[global_allocator]
static ALLOCATOR: vernier_ros::memory::FrameBlocks = vernier_ros::memory::FrameBlocks::new();

fn main() -> ExitCode {
    match vernier_ros::node::run(std::env::args().skip(1).collect()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("detector: {message}");
            ExitCode::FAILURE
        }
    }
}
