//! The type hashes the node computes (`src/ros/interface/type_hash.rs`) against rosidl's own:
//! the `type_hashes` of the `.json` files `rosidl_generator_type_description` wrote for every
//! type, found in the Jazzy wheels' `share/` of `.venv` and in the `pwm_actuator_msgs` build of
//! `.ros-ws` (both made by `scripts/setup.sh`; `PWM_ROSIDL_SHARE` may name other `share`
//! directories, separated by `:`).
//!
//! Ignored by a plain `cargo test`, which must not need the Python venv: `scripts/test.sh` runs
//! it after its setup step (`cargo test --test type_hashes -- --ignored`), and counts it there.

use pwm_actuator::ros::interface::type_hash::type_hashes;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// The `share` directories to read rosidl's `.json` files from.
fn share_dirs() -> Vec<PathBuf> {
    if let Ok(dirs) = std::env::var("PWM_ROSIDL_SHARE") {
        return dirs.split(':').map(PathBuf::from).collect();
    }
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    vec![
        root.join(".venv/share"),
        root.join(".ros-ws/install/pwm_actuator_msgs/share"),
    ]
}

/// rosidl's hash of every type named in the `.json` file of `ros_type` (a service's request,
/// response and event are in the service's file), by type name.
fn rosidl_hashes(ros_type: &str) -> BTreeMap<String, String> {
    let mut parts = ros_type.splitn(3, '/');
    let (pkg, kind, mut name) = (
        parts.next().unwrap(),
        parts.next().unwrap(),
        parts.next().unwrap(),
    );
    if kind == "srv" {
        for suffix in ["_Request", "_Response", "_Event"] {
            name = name.strip_suffix(suffix).unwrap_or(name);
        }
    }
    let dirs = share_dirs();
    let path = dirs
        .iter()
        .map(|d| d.join(pkg).join(kind).join(format!("{name}.json")))
        .find(|p| p.exists())
        .unwrap_or_else(|| {
            panic!("no rosidl .json for {ros_type} under {dirs:?}: run scripts/setup.sh first")
        });
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    json["type_hashes"]
        .as_array()
        .unwrap_or_else(|| panic!("{}: no type_hashes", path.display()))
        .iter()
        .map(|h| {
            (
                h["type_name"].as_str().unwrap().to_string(),
                h["hash_string"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
#[ignore = "reads rosidl's .json from .venv and .ros-ws (scripts/setup.sh); scripts/test.sh runs it"]
fn every_computed_hash_is_rosidls() {
    let ours = type_hashes().expect("the compiled-in definitions give every hash");
    let mut compared = 0;
    let mut wrong = Vec::new();
    for (ros_type, hash) in &ours {
        // The type's own file, and every file that names it as a referenced type agrees.
        let theirs = rosidl_hashes(ros_type);
        match theirs.get(ros_type) {
            Some(h) if h == hash => compared += 1,
            other => wrong.push(format!("{ros_type}: ours {hash}, rosidl {other:?}")),
        }
        for (referenced, h) in &theirs {
            if let Some(mine) = ours.get(referenced) {
                if mine != h {
                    wrong.push(format!(
                        "{referenced} (in {ros_type}'s file): ours {mine}, rosidl {h}"
                    ));
                }
            }
        }
    }
    println!("{compared} type hashes equal rosidl's");
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert_eq!(compared, ours.len());
}
