//! The node as a process under the ROS environment that concerns trust: SROS2 security
//! variables (refused when enforced, warned about when permissive), the discovery range
//! (`ROS_AUTOMATIC_DISCOVERY_RANGE`, `ROS_LOCALHOST_ONLY`, `ROS_STATIC_PEERS`) and two nodes
//! with one name on a domain.

#[path = "common/ros_harness.rs"]
mod ros_harness;

use ros_harness::*;
use std::process::Command;
use std::time::Duration;

/// Every variable these tests set, removed from the child's environment first so the
/// caller's shell cannot change a result.
const TRUST_VARS: [&str; 7] = [
    "ROS_SECURITY_ENABLE",
    "ROS_SECURITY_STRATEGY",
    "ROS_SECURITY_KEYSTORE",
    "ROS_SECURITY_ENCLAVE_OVERRIDE",
    "ROS_LOCALHOST_ONLY",
    "ROS_AUTOMATIC_DISCOVERY_RANGE",
    "ROS_STATIC_PEERS",
];

/// Runs the node with `env` and `args` until it exits by itself (or kills it after 20 s);
/// returns its exit code and stderr, and whether the trace file `csv` exists.
fn run_to_exit(env: &[(&str, &str)], args: &[&str]) -> (Option<i32>, String, bool) {
    let dom = Domain::acquire();
    let dir = std::env::temp_dir().join(format!("pwm_actuator_trust_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let csv = dir.join(format!("t{}.csv", dom.id));
    let _ = std::fs::remove_file(&csv);
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"));
    for v in TRUST_VARS {
        cmd.env_remove(v);
    }
    let mut all = vec!["--trace", csv.to_str().unwrap()];
    all.extend_from_slice(args);
    let out = cmd
        .args(&all)
        .envs(env.iter().copied())
        .env("ROS_DOMAIN_ID", dom.id.to_string())
        .env_remove("ROS_DISTRO")
        .output()
        .expect("the node binary runs");
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
        csv.exists(),
    )
}

/// Starts the node with `env` (and nothing else of [`TRUST_VARS`] from the caller) and waits
/// until it runs.
fn start(dom: &Domain, env: &[(&str, &str)], args: &[&str]) -> NodeProc {
    let mut full: Vec<(&str, &str)> = TRUST_VARS
        .iter()
        .filter(|v| !env.iter().any(|(k, _)| k == *v))
        .map(|v| (*v, ""))
        .collect();
    full.extend_from_slice(env);
    let n = NodeProc::start_with(&dom.id.to_string(), args, dom.id, &full);
    n.wait_running();
    n
}

#[test]
fn enforced_security_is_refused_before_any_output_is_opened() {
    for (env, args) in [
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Enforce"),
                ("ROS_SECURITY_KEYSTORE", "/nonexistent/keystore"),
            ],
            vec!["--ros-args", "--enclave", "/pwm_actuator"],
        ),
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Enforce"),
            ],
            vec![],
        ),
    ] {
        let (code, err, traced) = run_to_exit(&env, &args);
        assert_eq!(code, Some(2), "{env:?}: {err}");
        assert!(err.contains("DDS security is enforced"), "{err}");
        assert!(err.contains("ROS_SECURITY_STRATEGY=Enforce"), "{err}");
        assert!(err.contains("Refusing to start"), "{err}");
        assert!(!traced, "the output was opened before the refusal");
        assert!(!err.contains(" running: "), "{err}");
    }
}

#[test]
fn permissive_security_and_a_bare_enclave_start_with_one_warning() {
    for (env, args, needle) in [
        (
            vec![
                ("ROS_SECURITY_ENABLE", "true"),
                ("ROS_SECURITY_STRATEGY", "Permissive"),
                ("ROS_SECURITY_KEYSTORE", "/nonexistent/keystore"),
            ],
            vec![],
            "running UNSECURED",
        ),
        (
            vec![],
            vec!["--ros-args", "-e", "/pwm_actuator"],
            "enclave `/pwm_actuator` given but ROS_SECURITY_ENABLE is not `true`",
        ),
    ] {
        let dom = Domain::acquire();
        let n = start(&dom, &env, &args);
        let (status, log) = n.stop();
        assert_eq!(status.code(), Some(0), "{log}");
        assert_eq!(log.matches(needle).count(), 1, "{needle}: {log}");
        assert!(log.contains("[WARN]"), "{log}");
    }
    // Nothing asked: nothing said.
    let dom = Domain::acquire();
    let n = start(&dom, &[], &[]);
    std::thread::sleep(Duration::from_millis(200));
    let (_, log) = n.stop();
    assert!(!log.contains("secur"), "{log}");
}
