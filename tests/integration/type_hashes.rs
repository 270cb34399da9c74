//! The type hashes the node computes (`src/ros/interface/type_hash.rs`) against rosidl's own:
//! the `type_hashes` of the `.json` files `rosidl_generator_type_description` wrote for every
//! type, found in the Jazzy wheels' `share/` of `.venv` and in the `pwm_actuator_msgs` build of
//! `.ros-ws` (both made by `scripts/setup.sh`; `PWM_ROSIDL_SHARE` may name other `share`
//! directories, separated by `:`).
//!
//! Ignored by a plain `cargo test`, which must not need the Python venv: `scripts/test.sh` runs
//! it after its setup step (`cargo test --test integration -- --ignored type_hashes::`), and counts
//! it there.

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

/// The file name (without `.json`) rosidl writes the hash of `name` of kind `kind` in: a
/// service's request, response and event are in the service's file, every type an action
/// derives (goal, result, feedback, its services and their parts, the feedback message) in the
/// action's.
fn json_file_name(kind: &str, name: &str) -> String {
    const SERVICE: &[&str] = &["_Request", "_Response", "_Event"];
    const ACTION: &[&str] = &[
        "_SendGoal_Request",
        "_SendGoal_Response",
        "_SendGoal_Event",
        "_SendGoal",
        "_GetResult_Request",
        "_GetResult_Response",
        "_GetResult_Event",
        "_GetResult",
        "_FeedbackMessage",
        "_Goal",
        "_Result",
        "_Feedback",
    ];
    let suffixes = match kind {
        "srv" => SERVICE,
        "action" => ACTION,
        _ => &[],
    };
    suffixes
        .iter()
        .find_map(|s| name.strip_suffix(s))
        .unwrap_or(name)
        .to_string()
}

/// rosidl's hash of every type named in the `.json` file of `ros_type` (see
/// [`json_file_name`]), by type name.
fn rosidl_hashes(ros_type: &str) -> BTreeMap<String, String> {
    let mut parts = ros_type.splitn(3, '/');
    let (pkg, kind, name) = (
        parts.next().unwrap(),
        parts.next().unwrap(),
        parts.next().unwrap(),
    );
    let name = json_file_name(kind, name);
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
    // The action and the types its topics carry are among them.
    for t in [
        "pwm_actuator_msgs/action/Autotune",
        "pwm_actuator_msgs/action/Autotune_SendGoal_Request",
        "pwm_actuator_msgs/action/Autotune_SendGoal_Response",
        "pwm_actuator_msgs/action/Autotune_GetResult_Request",
        "pwm_actuator_msgs/action/Autotune_GetResult_Response",
        "pwm_actuator_msgs/action/Autotune_FeedbackMessage",
        "action_msgs/srv/CancelGoal_Request",
        "action_msgs/srv/CancelGoal_Response",
        "action_msgs/msg/GoalStatusArray",
    ] {
        assert!(ours.contains_key(t), "{t} has no computed hash");
    }
}

#[test]
fn every_derived_type_is_looked_up_in_its_interfaces_file() {
    assert_eq!(json_file_name("msg", "Float64"), "Float64");
    assert_eq!(json_file_name("srv", "Trigger_Event"), "Trigger");
    assert_eq!(
        json_file_name("action", "Autotune_GetResult_Response"),
        "Autotune"
    );
    assert_eq!(json_file_name("action", "Autotune_SendGoal"), "Autotune");
    assert_eq!(
        json_file_name("action", "Autotune_FeedbackMessage"),
        "Autotune"
    );
    assert_eq!(json_file_name("action", "Autotune_Feedback"), "Autotune");
    assert_eq!(json_file_name("action", "Autotune"), "Autotune");
}
