//! The `.msg` files in `msg/` and the serde structs of `pwm_actuator::ros::interface::msg` agree field for
//! field: same names, same types, same order (the CDR wire layout). The standard messages the
//! node mirrors are checked against their ROS 2 Jazzy definitions, quoted here.

use crate::ros_shape::{parse_msg, shape_of, Shape};
use pwm_actuator::ros::interface::msg::*;
use ros2_client::builtin_interfaces::Time;
use std::path::Path;

fn time_shape() -> Shape {
    Shape::Struct(vec![
        ("sec".into(), Shape::I32),
        ("nanosec".into(), Shape::U32),
    ])
}

/// Resolves the nested types used by the messages checked here.
fn nested(name: &str) -> Option<Shape> {
    match name {
        "builtin_interfaces/Time" => Some(time_shape()),
        "std_msgs/Header" => Some(Shape::Struct(vec![
            ("stamp".into(), time_shape()),
            ("frame_id".into(), Shape::Str),
        ])),
        "KeyValue" | "diagnostic_msgs/KeyValue" => {
            Some(Shape::Struct(parse_msg(KEY_VALUE, &nested).ok()?))
        }
        "DiagnosticStatus" | "diagnostic_msgs/DiagnosticStatus" => {
            Some(Shape::Struct(parse_msg(DIAGNOSTIC_STATUS, &nested).ok()?))
        }
        _ => None,
    }
}

fn fields(shape: Shape) -> Vec<(String, Shape)> {
    match shape {
        Shape::Struct(f) => f,
        other => panic!("not a struct: {other:?}"),
    }
}

fn check_file(stem: &str, rust: Shape) {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("msg")
        .join(format!("{stem}.msg"));
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let want = parse_msg(&text, &nested).unwrap_or_else(|e| panic!("{stem}.msg: {e}"));
    assert_eq!(
        fields(rust),
        want,
        "{stem}: Rust struct and {stem}.msg differ"
    );
}

fn t() -> Time {
    Time::from_nanos(1)
}

#[test]
fn own_messages_match_their_msg_files() {
    check_file(
        OutputEdge::NAME,
        shape_of(&OutputEdge {
            stamp: t(),
            channel: 1,
            level: true,
            seq: 1,
            lateness_ns: 0,
        }),
    );
    check_file(
        ChannelStatus::NAME,
        shape_of(&ChannelStatus {
            stamp: t(),
            channel: 1,
            enabled: false,
            active: false,
            output: false,
            duty_commanded: 0.0,
            duty_applied: 0.0,
            command_clamped: false,
            period_ms: 0.0,
            on_time_ms: 0.0,
            off_time_ms: 0.0,
            remaining_on_ms: 0.0,
            remaining_off_ms: 0.0,
            e1: false,
            min_time_limited: false,
            watchdog_tripped: false,
            rule: String::new(),
            duty_target: 0.0,
            protections: vec!["max_on".into()],
            time_base_ms: 0.0,
            on_time_input_ms: 0.0,
            off_time_input_ms: 0.0,
            remaining_on_s: 0,
            remaining_off_s: 0,
            control: String::new(),
            temperature_c: 0.0,
            temperature_age_ms: 0.0,
            setpoint_c: 0.0,
            pid_p: 0.0,
            pid_i: 0.0,
            pid_d: 0.0,
            pid_output: 0.0,
            heater_fault: String::new(),
            heater_fault_message: String::new(),
            heater_fault_lasts: false,
            model_predicted_c: 0.0,
            model_residual_c: 0.0,
            stale_readings: 0,
            last_stale_age_ms: 0.0,
            target_c: 0.0,
        }),
    );
    check_file(
        ChannelParams::NAME,
        shape_of(&ChannelParams {
            set: vec!["period_ms".into()],
            ..ChannelParams::default()
        }),
    );
    check_file(
        ValveState::NAME,
        shape_of(&ValveState {
            stamp: t(),
            name: String::new(),
            position_pct: 0.0,
            target_pct: 0.0,
            motion: String::new(),
            activity: String::new(),
            referenced: false,
            run_since_reference_s: 0.0,
            uncertainty_pct: 0.0,
            position_low_pct: 0.0,
            position_high_pct: 0.0,
            restored: false,
            recalibration_due: false,
            timed_out: false,
            estop: false,
            open_switch: false,
            close_switch: false,
            fault: String::new(),
            feedback_pct: 0.0,
            moves: 0,
            control: String::new(),
            loop_state: String::new(),
            manual: String::new(),
            setpoint: 0.0,
            process_value: 0.0,
            process_age_s: 0.0,
            stale_readings: 0,
            position_commands_refused: 0,
            setpoints_refused: 0,
            process_values_refused: 0,
            manual_refused: 0,
            starts: 0,
            starts_last_hour: 0,
            max_starts_per_h: 0,
        }),
    );
    assert_eq!(ValveState::PACKAGE, MSG_PACKAGE);
    assert_eq!(OutputEdge::PACKAGE, MSG_PACKAGE);
    assert_eq!(ChannelStatus::PACKAGE, MSG_PACKAGE);
    assert_eq!(ChannelParams::PACKAGE, MSG_PACKAGE);
}

#[test]
fn every_msg_file_is_mirrored() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("msg");
    let mut stems: Vec<String> = std::fs::read_dir(&dir)
        .expect("msg/ exists")
        .filter_map(|e| e.ok())
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x == "msg"))
        .filter_map(|p| p.file_stem().map(|s| s.to_string_lossy().into_owned()))
        .collect();
    stems.sort();
    assert_eq!(
        stems,
        [
            ChannelParams::NAME,
            ChannelStatus::NAME,
            OutputEdge::NAME,
            ValveState::NAME
        ],
        "a .msg file without a Rust mirror (or the reverse)"
    );
}

// ROS 2 Jazzy definitions (comments dropped).
const KEY_VALUE: &str = "string key\nstring value\n";
const DIAGNOSTIC_STATUS: &str = "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\n\
    byte level\nstring name\nstring message\nstring hardware_id\nKeyValue[] values\n";
const DIAGNOSTIC_ARRAY: &str = "std_msgs/Header header\nDiagnosticStatus[] status\n";
const TEMPERATURE: &str = "std_msgs/Header header\nfloat64 temperature\nfloat64 variance\n";

#[test]
fn standard_messages_match_ros() {
    let kv = || KeyValue {
        key: String::new(),
        value: String::new(),
    };
    let status = || DiagnosticStatus {
        level: 0,
        name: String::new(),
        message: String::new(),
        hardware_id: String::new(),
        values: vec![kv()],
    };
    assert_eq!(
        fields(shape_of(&kv())),
        parse_msg(KEY_VALUE, &nested).unwrap()
    );
    assert_eq!(
        fields(shape_of(&status())),
        parse_msg(DIAGNOSTIC_STATUS, &nested).unwrap()
    );
    let array = DiagnosticArray {
        header: Header {
            stamp: t(),
            frame_id: String::new(),
        },
        status: vec![status()],
    };
    assert_eq!(
        fields(shape_of(&array)),
        parse_msg(DIAGNOSTIC_ARRAY, &nested).unwrap()
    );
    assert_eq!(
        fields(shape_of(&Float64::default())),
        vec![("data".into(), Shape::F64)]
    );
    assert_eq!(
        fields(shape_of(&UInt16::default())),
        vec![("data".into(), Shape::U16)]
    );
    assert_eq!(
        fields(shape_of(&Bool::default())),
        vec![("data".into(), Shape::Bool)]
    );
    let temp = Temperature {
        header: Header {
            stamp: t(),
            frame_id: String::new(),
        },
        temperature: 0.0,
        variance: 0.0,
    };
    assert_eq!(
        fields(shape_of(&temp)),
        parse_msg(TEMPERATURE, &nested).unwrap()
    );
    assert_eq!(
        Temperature::type_name().dds_msg_type(),
        "sensor_msgs::msg::dds_::Temperature_"
    );
    assert_eq!(DiagnosticStatus::WARN, 1);
}

#[test]
fn the_msg_parser_sees_differences() {
    // A reordered or retyped field must not pass.
    let text =
        "builtin_interfaces/Time stamp\nuint8 channel\nuint64 seq\nbool level\nint64 lateness_ns\n";
    let want = parse_msg(text, &nested).unwrap();
    let edge = OutputEdge {
        stamp: t(),
        channel: 1,
        level: true,
        seq: 1,
        lateness_ns: 0,
    };
    assert_ne!(fields(shape_of(&edge)), want);
    assert!(parse_msg("float128 x\n", &nested).is_err());
    assert_eq!(
        parse_msg("# c\nint64 A=3 # const\nstring[] s # names\n", &nested).unwrap(),
        vec![("s".to_string(), Shape::Seq(Some(Box::new(Shape::Str))))]
    );
}

#[test]
fn the_autotune_action_matches_its_action_file() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("msg/action/Autotune.action");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let parts: Vec<&str> = text.split("\n---\n").collect();
    assert_eq!(parts.len(), 3, "goal, result and feedback");
    let parse = |i: usize| {
        parse_msg(parts[i], &nested).unwrap_or_else(|e| panic!("Autotune.action part {i}: {e}"))
    };
    assert_eq!(fields(shape_of(&AutotuneGoal::default())), parse(0), "goal");
    assert_eq!(
        fields(shape_of(&AutotuneResult {
            sizing: vec!["x".into()],
            ..AutotuneResult::default()
        })),
        parse(1),
        "result"
    );
    assert_eq!(
        fields(shape_of(&AutotuneFeedback::default())),
        parse(2),
        "feedback"
    );
}
