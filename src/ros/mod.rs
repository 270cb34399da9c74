//! The ROS 2 shell around the output thread: topics, parameters, diagnostics.
