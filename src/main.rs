//! `pwm_actuator_node`: the ROS 2 node (see `pwm_actuator::ros`), or `pwm_actuator_node bench
//! ...` for the timing benchmark.

mod bench;

use std::process::ExitCode;

fn main() -> ExitCode {
    let mut args = Vec::new();
    for a in std::env::args_os().skip(1) {
        match a.into_string() {
            Ok(s) => args.push(s),
            Err(bad) => {
                eprintln!("[ERROR] [pwm_actuator]: argument {bad:?} is not valid UTF-8");
                return ExitCode::from(2);
            }
        }
    }
    let code = match args.first().map(String::as_str) {
        Some("bench") => bench::main(&args[1..]),
        _ => pwm_actuator::ros::run(&args),
    };
    ExitCode::from(u8::try_from(code).unwrap_or(1))
}
