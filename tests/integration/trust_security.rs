//! DDS security from a ROS keystore (cargo feature `dds-security`): the node started with
//! `ROS_SECURITY_ENABLE=true`, `ROS_SECURITY_STRATEGY=Enforce` and an enclave is heard by a
//! participant authenticated with the same CAs and not by an unauthenticated one; an enclave
//! without its files is refused. The PKI is the test-only one in `tests/fixtures/dds-security`.
//!
//! Interop with rclpy is not tested: the Fast DDS in the registry's rclpy wheels is built
//! without its security plugins.
#![cfg(feature = "dds-security")]

use crate::ros_harness::*;
use pwm_actuator::ros::interface::msg::DiagnosticArray;
use ros2_client::Context;
use rustdds::{DomainParticipantBuilder, DomainParticipantSecurityConfigFiles};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

const FIXTURES: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/fixtures/dds-security");

/// A keystore holding the enclave `/pwm` made of the fixture files.
fn keystore(tag: &str) -> (PathBuf, PathBuf) {
    let ks = std::env::temp_dir().join(format!("pwm_keystore_{}_{tag}", std::process::id()));
    let enclave = ks.join("enclaves").join("pwm");
    std::fs::create_dir_all(&enclave).unwrap();
    for f in pwm_actuator::ros::config::security::ENCLAVE_FILES {
        std::fs::copy(Path::new(FIXTURES).join(f), enclave.join(f)).unwrap();
    }
    (ks, enclave)
}

/// Whether a participant on `domain` (secured with `enclave`, or not) hears `/diagnostics`.
fn hears(domain: u16, enclave: Option<&Path>, within: Duration) -> bool {
    let rt = tokio::runtime::Runtime::new().unwrap();
    rt.block_on(async {
        let mut b = DomainParticipantBuilder::new(domain);
        if let Some(dir) = enclave {
            b = b.builtin_security(
                DomainParticipantSecurityConfigFiles::with_ros_default_names(dir, String::new()),
            );
        }
        let ctx = Context::from_domain_participant(b.build().expect("participant")).unwrap();
        let mut ros = Ros::on(ctx);
        let diag = ros.sub::<DiagnosticArray>("/diagnostics", default_qos());
        next(&diag, within).await.is_some()
    })
}

fn secured_env(ks: &Path) -> Vec<(&'static str, String)> {
    vec![
        ("ROS_SECURITY_ENABLE", "true".into()),
        ("ROS_SECURITY_STRATEGY", "Enforce".into()),
        ("ROS_SECURITY_KEYSTORE", ks.to_string_lossy().into_owned()),
        ("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST".into()),
    ]
}

#[test]
fn an_enforced_enclave_secures_the_node_and_refuses_the_unauthenticated() {
    let (ks, enclave) = keystore("ok");
    let env = secured_env(&ks);
    let env: Vec<(&str, &str)> = env.iter().map(|(k, v)| (*k, v.as_str())).collect();
    let node = NodeProc::start_with(&["--ros-args", "--enclave", "/pwm"], &env);
    node.wait_running();
    assert!(
        node.log().contains("DDS security on: enclave"),
        "{}",
        node.log()
    );
    // Authenticated with the same CAs and permitted: it hears the node.
    assert!(hears(node.domain, Some(&enclave), LONG), "{}", node.log());
    // Unauthenticated: nothing, though it is on the same machine and domain.
    assert!(
        !hears(node.domain, None, Duration::from_secs(5)),
        "an unauthenticated participant heard the node"
    );
    node.stop_ok();
}

#[test]
fn an_enforced_enclave_without_its_files_is_refused() {
    let (ks, enclave) = keystore("missing");
    std::fs::remove_file(enclave.join("key.pem")).unwrap();
    let dom = Domain::acquire();
    let out = Command::new(env!("CARGO_BIN_EXE_pwm_actuator_node"))
        .args(["--ros-args", "--enclave", "/pwm"])
        .envs(secured_env(&ks))
        .env("ROS_DOMAIN_ID", dom.id.to_string())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("lacks key.pem"), "{err}");
    assert!(err.contains("Refusing to start"), "{err}");
}
