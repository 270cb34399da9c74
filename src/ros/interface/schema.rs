//! The message definitions of the types the node records in MCAP traces, in the `ros2msg`
//! schema encoding as rosbag2 writes it: the type's own `.msg` text, then each type it uses
//! (depth first, each once, a type's dependencies in name order), every one after a line of
//! 80 `=` and a line `MSG: <package>/<Type>`.
//!
//! The texts are the `.msg` files themselves: this repository's `msg/` and, for the standard
//! types, ROS 2 Jazzy's files in `interfaces/` (byte for byte as installed; the type hashes
//! are computed from the same files).

/// One message type: its package, name, `.msg` text and the types its fields use.
struct Definition {
    package: &'static str,
    name: &'static str,
    text: &'static str,
    /// The types it uses, as `<package>/<Type>`.
    uses: &'static [&'static str],
}

const DEFINITIONS: &[Definition] = &[
    Definition {
        package: "builtin_interfaces",
        name: "Time",
        text: include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/builtin_interfaces/msg/Time.msg"
        )),
        uses: &[],
    },
    Definition {
        package: "std_msgs",
        name: "Header",
        text: include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/std_msgs/msg/Header.msg"
        )),
        uses: &["builtin_interfaces/Time"],
    },
    Definition {
        package: "diagnostic_msgs",
        name: "KeyValue",
        text: include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/diagnostic_msgs/msg/KeyValue.msg"
        )),
        uses: &[],
    },
    Definition {
        package: "diagnostic_msgs",
        name: "DiagnosticStatus",
        text: include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/diagnostic_msgs/msg/DiagnosticStatus.msg"
        )),
        uses: &["diagnostic_msgs/KeyValue"],
    },
    Definition {
        package: "diagnostic_msgs",
        name: "DiagnosticArray",
        text: include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/diagnostic_msgs/msg/DiagnosticArray.msg"
        )),
        uses: &["diagnostic_msgs/DiagnosticStatus", "std_msgs/Header"],
    },
    Definition {
        package: "pwm_actuator_msgs",
        name: "OutputEdge",
        text: include_str!("../../../msg/OutputEdge.msg"),
        uses: &["builtin_interfaces/Time"],
    },
    Definition {
        package: "pwm_actuator_msgs",
        name: "ChannelStatus",
        text: include_str!("../../../msg/ChannelStatus.msg"),
        uses: &["builtin_interfaces/Time"],
    },
];

/// The schema encoding of the texts: ROS 2 `.msg` definitions.
pub const SCHEMA_ENCODING: &str = "ros2msg";

/// The line between two definitions.
pub const SEPARATOR: &str =
    "================================================================================";

fn find(package: &str, name: &str) -> Option<&'static Definition> {
    DEFINITIONS
        .iter()
        .find(|d| d.package == package && d.name == name)
}

/// The schema name of a type: `<package>/msg/<Type>`.
pub fn schema_name(package: &str, name: &str) -> String {
    format!("{package}/msg/{name}")
}

/// The full `ros2msg` definition of `<package>/<Type>` with every type it uses, or `None` for
/// a type this module does not hold.
pub fn ros2msg(package: &str, name: &str) -> Option<String> {
    let root = find(package, name)?;
    let mut text = root.text.to_string();
    let mut seen: Vec<&str> = Vec::new();
    append_uses(root, &mut text, &mut seen)?;
    Some(text)
}

fn append_uses(def: &Definition, text: &mut String, seen: &mut Vec<&'static str>) -> Option<()> {
    let mut uses = def.uses.to_vec();
    uses.sort_unstable();
    for full in uses {
        if seen.contains(&full) {
            continue;
        }
        seen.push(full);
        let (package, name) = full.split_once('/')?;
        let dep = find(package, name)?;
        text.push('\n');
        text.push_str(SEPARATOR);
        text.push_str("\nMSG: ");
        text.push_str(full);
        text.push('\n');
        text.push_str(dep.text);
        append_uses(dep, text, seen)?;
    }
    Some(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_used_type_is_held() {
        for d in DEFINITIONS {
            assert!(
                ros2msg(d.package, d.name).is_some(),
                "{}/{}",
                d.package,
                d.name
            );
        }
        assert_eq!(ros2msg("std_msgs", "Float32"), None);
    }

    #[test]
    fn a_definition_lists_each_dependency_once_depth_first_in_name_order() {
        let text = ros2msg("diagnostic_msgs", "DiagnosticArray").unwrap();
        let msg_lines: Vec<&str> = text.lines().filter(|l| l.starts_with("MSG: ")).collect();
        assert_eq!(
            msg_lines,
            [
                "MSG: diagnostic_msgs/DiagnosticStatus",
                "MSG: diagnostic_msgs/KeyValue",
                "MSG: std_msgs/Header",
                "MSG: builtin_interfaces/Time",
            ]
        );
        assert!(text.starts_with(include_str!(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/interfaces/diagnostic_msgs/msg/DiagnosticArray.msg"
        ))));
        // Each MSG line follows a separator line.
        let lines: Vec<&str> = text.lines().collect();
        for (i, l) in lines.iter().enumerate() {
            if l.starts_with("MSG: ") {
                assert_eq!(lines[i - 1], SEPARATOR);
            }
        }
        assert_eq!(SEPARATOR.len(), 80);
    }

    #[test]
    fn the_node_s_own_types_use_the_time_type() {
        for name in ["OutputEdge", "ChannelStatus"] {
            let text = ros2msg("pwm_actuator_msgs", name).unwrap();
            assert_eq!(text.matches("\nMSG: ").count(), 1, "{name}");
            assert!(text.contains("\nMSG: builtin_interfaces/Time\n"), "{name}");
            assert!(text.contains("int32 sec"), "{name}");
        }
        assert_eq!(
            schema_name("pwm_actuator_msgs", "OutputEdge"),
            "pwm_actuator_msgs/msg/OutputEdge"
        );
    }
}
