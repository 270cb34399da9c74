//! pwm_actuator_node: the ROS 2 node binary (wired up in a later change).
fn main() {}
