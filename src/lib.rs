//! pwm_actuator: time-proportioned pulses (software PWM) for slow actuators — heaters, valves,
//! relays — driven the way PLC PWM function blocks drive them, as a ROS 2 node.
//!
//! Data flows one way: ROS callbacks -> requests -> the output thread ([`output_thread`]) -> the
//! channel core ([`core`]) -> an output backend ([`output`]); edges, flags and status flow back
//! from the output thread to the ROS side ([`ros`]) for publishing.
#![warn(missing_docs)]

pub mod clock;
pub mod core;
pub mod error;
pub mod output;
pub mod output_thread;
pub mod ros;
pub mod safe_off;
pub mod service;
