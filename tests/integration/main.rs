//! The integration tests: one test binary, one module per subject, so that the library and its
//! dependencies are linked once for all of them rather than once per file.
//!
//! The modules run as threads of one process, two at a time by default, beside each other's
//! tests as well as their own. None of them may rely on being alone in the process: no
//! environment variable set with `set_var`, no panic hook, signal disposition, rlimit or
//! process-wide real-time setting, nothing counted process-wide. Each node under test is a
//! child process on a ROS domain of its own (`ros_harness::Domain`, a lock file per domain), and
//! each in-process output thread has its own sink. A test that must be alone in its process
//! (tests/idle_wakeups.rs, which counts the wake-ups of the thread named `pwm-output`) is a test
//! target of its own.

#[path = "../common/ros_harness.rs"]
mod ros_harness;
#[path = "../common/ros_shape.rs"]
mod ros_shape;

mod docs;
mod liveness;
mod log_flood;
mod node_exit;
mod output_gpio_sim;
mod output_thread;
mod output_thread_safety;
mod params_bounds;
mod ros_bridge;
mod ros_cli;
mod ros_msgs;
mod ros_params;
mod ros_remap;
mod ros_topics;
mod service_notify;
mod trust_env;
mod trust_security;
mod type_hashes;
