//! ROS name resolution for this node: the node's final name and namespace after `__node` /
//! `__ns` remapping, expansion of relative and private (`~/`) topic and service names to fully
//! qualified ones, and `-r from:=to` remapping of those, as rcl does it.
//!
//! ros2-client does not expand `~` and does not remap, so every name the node creates goes
//! through [`NodeIdentity::resolve`] first. Pure string work: nothing here touches DDS.

use crate::ros::config::args::{Remap, RemapKind};

/// The node's name before remapping.
pub const NODE_NAME: &str = "pwm_actuator";

/// A topic or service name that ROS does not accept.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid ROS name `{name}`: {reason}")]
pub struct NameError {
    /// The name.
    pub name: String,
    /// What is wrong with it.
    pub reason: &'static str,
}

/// Whether a name is a topic or a service (remap rules may be restricted to one kind).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NameKind {
    /// A topic.
    Topic,
    /// A service.
    Service,
}

/// The node's final name and namespace.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeIdentity {
    /// Base name after `__node` remapping, e.g. `pwm_actuator`.
    pub name: String,
    /// Namespace after `__ns` remapping, absolute, without a trailing `/` except for the root
    /// `/`.
    pub namespace: String,
}

fn valid_token(t: &str) -> bool {
    let mut c = t.chars();
    matches!(c.next(), Some(f) if f.is_ascii_alphabetic() || f == '_')
        && c.all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// Checks an absolute name token by token (`/` alone is not a name).
fn check_absolute(name: &str) -> Result<(), NameError> {
    let err = |reason| NameError {
        name: name.to_string(),
        reason,
    };
    let rest = name.strip_prefix('/').ok_or(err("not absolute"))?;
    if rest.is_empty() {
        return Err(err("empty"));
    }
    for t in rest.split('/') {
        if t.is_empty() {
            return Err(err("empty token (`//` or a trailing `/`)"));
        }
        if !valid_token(t) {
            return Err(err(
                "tokens are letters, digits and `_`, and do not start with a digit",
            ));
        }
        if t.contains("__") {
            return Err(err("repeated `_` is reserved"));
        }
    }
    Ok(())
}

impl NodeIdentity {
    /// The node's identity from its defaults and the remap rules (`__node`, `__ns`; the first
    /// rule for this node wins, matched against the node's original name as in rcl).
    pub fn from_remaps(
        default_name: &str,
        default_namespace: &str,
        remaps: &[Remap],
    ) -> Result<NodeIdentity, NameError> {
        let pick = |which: &str| {
            remaps
                .iter()
                .find(|r| r.from == which && r.node.as_deref().is_none_or(|n| n == default_name))
                .map(|r| r.to.clone())
        };
        let name = pick("__node").unwrap_or_else(|| default_name.to_string());
        if !valid_token(&name) {
            return Err(NameError {
                name,
                reason: "a node name is letters, digits and `_`, not starting with a digit",
            });
        }
        let mut namespace = pick("__ns").unwrap_or_else(|| default_namespace.to_string());
        while namespace.len() > 1 && namespace.ends_with('/') {
            namespace.pop();
        }
        if namespace != "/" {
            check_absolute(&namespace)?;
        }
        Ok(NodeIdentity { name, namespace })
    }

    /// `/ns/name`.
    pub fn fully_qualified(&self) -> String {
        if self.namespace == "/" {
            format!("/{}", self.name)
        } else {
            format!("{}/{}", self.namespace, self.name)
        }
    }

    /// Expands `name` to a fully qualified name: `/x` stays, `~` and `~/x` are under the node,
    /// `x` is under the namespace.
    pub fn expand(&self, name: &str) -> Result<String, NameError> {
        let full = if name.starts_with('/') {
            name.to_string()
        } else if name == "~" {
            self.fully_qualified()
        } else if let Some(rest) = name.strip_prefix("~/") {
            format!("{}/{rest}", self.fully_qualified())
        } else if name.starts_with('~') {
            return Err(NameError {
                name: name.to_string(),
                reason: "`~` must be followed by `/`",
            });
        } else if self.namespace == "/" {
            format!("/{name}")
        } else {
            format!("{}/{name}", self.namespace)
        };
        check_absolute(&full)?;
        Ok(full)
    }

    /// The fully qualified name a topic or service `name` ends up with after expansion and
    /// remapping (the first matching rule wins, as in rcl).
    pub fn resolve(
        &self,
        name: &str,
        kind: NameKind,
        remaps: &[Remap],
    ) -> Result<String, NameError> {
        let full = self.expand(name)?;
        for r in remaps {
            if r.from.starts_with("__") {
                continue;
            }
            if r.node.as_deref().is_some_and(|n| n != self.name) {
                continue;
            }
            match (r.kind, kind) {
                (RemapKind::Any, _)
                | (RemapKind::Topic, NameKind::Topic)
                | (RemapKind::Service, NameKind::Service) => {}
                _ => continue,
            }
            // A rule whose FROM cannot be expanded matches nothing.
            if self.expand(&r.from).ok().as_deref() == Some(full.as_str()) {
                return self.expand(&r.to);
            }
        }
        Ok(full)
    }
}

/// Splits a fully qualified name into the ros2-client [`ros2_client::Name`] form.
pub fn to_ros_name(full: &str) -> Result<ros2_client::Name, NameError> {
    let (ns, base) = match full.rsplit_once('/') {
        Some(("", base)) => ("/", base),
        Some((ns, base)) => (ns, base),
        None => ("/", full),
    };
    ros2_client::Name::new(ns, base).map_err(|_| NameError {
        name: full.to_string(),
        reason: "refused by ros2-client",
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::config::args::parse_remap;

    fn remaps(rules: &[&str]) -> Vec<Remap> {
        rules.iter().map(|r| parse_remap(r).unwrap()).collect()
    }

    fn node(ns: &str) -> NodeIdentity {
        NodeIdentity {
            name: "pwm_actuator".into(),
            namespace: ns.into(),
        }
    }

    #[test]
    fn expansion() {
        let n = node("/");
        assert_eq!(n.expand("~/pw01/duty").unwrap(), "/pwm_actuator/pw01/duty");
        assert_eq!(n.expand("diagnostics").unwrap(), "/diagnostics");
        assert_eq!(n.expand("/diagnostics").unwrap(), "/diagnostics");
        assert_eq!(n.expand("~").unwrap(), "/pwm_actuator");
        let n = node("/plant/hall");
        assert_eq!(
            n.expand("~/pw01/duty").unwrap(),
            "/plant/hall/pwm_actuator/pw01/duty"
        );
        assert_eq!(n.expand("pw01/duty").unwrap(), "/plant/hall/pw01/duty");
        assert_eq!(n.fully_qualified(), "/plant/hall/pwm_actuator");
        for bad in ["~x", "a//b", "a/", "1a", "a-b", "a__b", ""] {
            assert!(n.expand(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn identity_from_remaps() {
        let id = NodeIdentity::from_remaps(
            "pwm_actuator",
            "/",
            &remaps(&["__node:=heater", "__ns:=/plant/"]),
        )
        .unwrap();
        assert_eq!(id.fully_qualified(), "/plant/heater");
        let id =
            NodeIdentity::from_remaps("pwm_actuator", "/", &remaps(&["other:__node:=x"])).unwrap();
        assert_eq!(id.name, "pwm_actuator");
        let id = NodeIdentity::from_remaps("pwm_actuator", "/", &remaps(&["__ns:=/a//b"]));
        assert!(id.is_err());
        // A node-prefixed rename applies to that node only; the first matching rule wins.
        let r = remaps(&["other:__node:=x", "pwm_actuator:__node:=y", "__node:=z"]);
        assert_eq!(
            NodeIdentity::from_remaps("pwm_actuator", "/", &r)
                .unwrap()
                .name,
            "y"
        );
        assert_eq!(
            NodeIdentity::from_remaps("other", "/", &r).unwrap().name,
            "x"
        );
        assert_eq!(
            NodeIdentity::from_remaps("third", "/", &r).unwrap().name,
            "z"
        );
    }

    #[test]
    fn remapping_first_match_wins_and_respects_node_and_kind() {
        let n = node("/plant");
        let r = remaps(&[
            "~/pw01/duty:=/heater/duty",
            "~/pw01/duty:=/never",
            "other:diagnostics:=/x",
            "rosservice://~/pw01/sv:=/not_a_topic",
            "pwm_actuator:rostopic:///diagnostics:=diag",
            "~/get_parameters:=/params/get",
        ]);
        let t = NameKind::Topic;
        assert_eq!(n.resolve("~/pw01/duty", t, &r).unwrap(), "/heater/duty");
        assert_eq!(n.resolve("/diagnostics", t, &r).unwrap(), "/plant/diag");
        assert_eq!(
            n.resolve("~/pw01/sv", t, &r).unwrap(),
            "/plant/pwm_actuator/pw01/sv"
        );
        assert_eq!(
            n.resolve("~/pw01/sv", NameKind::Service, &r).unwrap(),
            "/not_a_topic"
        );
        assert_eq!(
            n.resolve("~/get_parameters", NameKind::Service, &r)
                .unwrap(),
            "/params/get"
        );
        // A relative FROM is expanded in the namespace, so it does not match a private name.
        let r = remaps(&["pw01/duty:=/x"]);
        assert_eq!(
            n.resolve("~/pw01/duty", t, &r).unwrap(),
            "/plant/pwm_actuator/pw01/duty"
        );
        assert_eq!(n.resolve("pw01/duty", t, &r).unwrap(), "/x");
    }

    #[test]
    fn ros_names() {
        let n = to_ros_name("/plant/pwm_actuator/pw01/duty").unwrap();
        assert_eq!(n.to_string(), "/plant/pwm_actuator/pw01/duty");
        assert!(n.is_absolute());
        assert_eq!(
            to_ros_name("/diagnostics").unwrap().to_string(),
            "/diagnostics"
        );
    }
}
