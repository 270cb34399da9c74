//! Start-up inputs a careless or hostile user can hand the node as a process: parameter files
//! that are too big, alias bombs, deep nesting, floods of unknown keys, and parameter values
//! the node cannot use. Each is a bad configuration: exit 2 with a reason, before any output
//! is touched, and a bounded amount of log.

use crate::ros_harness::Domain;
use std::path::PathBuf;
use std::process::Command;

fn run(args: &[&str]) -> (Option<i32>, String) {
    let held = Domain::acquire();
    let out = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"))
        .args(args)
        .env("ROS_DOMAIN_ID", held.id.to_string())
        .output()
        .expect("the node binary runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn file(name: &str, text: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("pwm_actuator_bounds_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// Each level is ten aliases of the one before: 10^6 leaves from about 500 bytes.
fn alias_bomb() -> String {
    let mut t = String::from("/**:\n  ros__parameters:\n    l0: &l0 [x]\n");
    for l in 1..=6 {
        let refs = vec![format!("*l{}", l - 1); 10].join(", ");
        t.push_str(&format!("    l{l}: &l{l} [{refs}]\n"));
    }
    t
}

#[test]
fn hostile_parameter_files_exit_2_with_a_reason() {
    let mut big = String::from("/**:\n  ros__parameters:\n    channels: 1\n");
    while big.len() <= 1 << 20 {
        big.push_str("# padding padding padding padding padding padding padding padding\n");
    }
    let deep = format!(
        "/**:\n  ros__parameters:\n    a: {}1{}\n",
        "[".repeat(200),
        "]".repeat(200)
    );
    for (name, text, why) in [
        ("bomb.yaml", alias_bomb(), "more than 100000 nodes"),
        ("big.yaml", big, "larger than 1 MiB"),
        ("deep.yaml", deep, "nested deeper than 64 levels"),
    ] {
        let path = file(name, &text);
        let (code, err) = run(&["--ros-args", "--params-file", path.to_str().unwrap()]);
        assert_eq!(code, Some(2), "{name}: {err}");
        assert!(err.contains(why), "{name}: expected {why:?} in:\n{err}");
        assert!(
            err.contains(name),
            "{name}: the file is not named in:\n{err}"
        );
    }
}

#[test]
fn unknown_keys_give_a_bounded_number_of_warnings() {
    // 40 000 keys this node does not have, and a configuration error after them.
    let mut text = String::from("/**:\n  ros__parameters:\n    output: gpio\n");
    for i in 0..40_000 {
        text.push_str(&format!("    unknown_{i}: 1\n"));
    }
    let path = file("unknown.yaml", &text);
    let (code, err) = run(&["--ros-args", "--params-file", path.to_str().unwrap()]);
    assert_eq!(code, Some(2), "{err}");
    let lines = err.lines().filter(|l| l.contains("ignoring")).count();
    assert!(lines <= 11, "{lines} lines of warnings");
    assert!(
        err.contains("ignoring 39990 more values for parameters this node does not have"),
        "{err}"
    );
}

#[test]
fn unusable_status_rates_exit_2() {
    let path = file(
        "rate.yaml",
        "/**:\n  ros__parameters:\n    status_rate_hz: 1.0e-20\n",
    );
    for args in [
        &["--status-rate", "5e-324"][..],
        &["--ros-args", "-p", "status_rate_hz:=1e-20"][..],
        &["--ros-args", "--params-file", path.to_str().unwrap()][..],
    ] {
        let (code, err) = run(args);
        assert_eq!(code, Some(2), "{args:?}: {err}");
        assert!(err.contains("is outside 0.01..1000.0"), "{args:?}: {err}");
    }
}
