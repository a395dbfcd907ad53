//! ROS glue
