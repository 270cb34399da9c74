//! Two nodes with one fully qualified name on a domain: warn, as ROS 2 does (`ros2 node list`:
//! "there are nodes in the graph that share an exact name"). Both would receive the same
//! commands and parameter requests, answer the same services and log under one name.
//!
//! The check reads the `ros_discovery_info` updates ros2-client's spinner receives (each DDS
//! participant announces the ROS nodes it hosts) and warns once for each other participant
//! that hosts a node with this node's name, whenever it appears. It only logs; it must not
//! change what the node does.

use futures::{Stream, StreamExt};
use log::warn;
use ros2_client::entities_info::ParticipantEntitiesInfo;
use ros2_client::{Gid, NodeEvent};
use rustdds::RTPSEntity;
use std::collections::BTreeSet;

/// The participants already warned about, and what to compare with.
#[derive(Debug, Clone)]
pub struct NameClash {
    own: Gid,
    fqn: String,
    warned: BTreeSet<Gid>,
}

impl NameClash {
    /// Watches for other nodes named `fqn` (`/ns/name`) outside the participant `own` (this
    /// node's own).
    pub fn new(own: &rustdds::DomainParticipant, fqn: impl Into<String>) -> Self {
        Self::with_gid(Gid::from(own.guid()), fqn)
    }

    /// As [`NameClash::new`], with the participant's gid.
    pub fn with_gid(own: Gid, fqn: impl Into<String>) -> Self {
        NameClash {
            own,
            fqn: fqn.into(),
            warned: BTreeSet::new(),
        }
    }

    /// Takes one participant's announcement; returns the warning to log if it is another
    /// participant hosting a node with this name and it has not been warned about.
    pub fn update(&mut self, info: &ParticipantEntitiesInfo) -> Option<String> {
        let gid = info.gid();
        if gid == self.own {
            return None;
        }
        let same = info
            .nodes()
            .iter()
            .filter(|n| n.fully_qualified_name() == self.fqn)
            .count();
        if same == 0 || !self.warned.insert(gid) {
            return None;
        }
        Some(format!(
            "there are {} nodes with the name {} on this ROS domain (another in DDS participant \
             {gid:?}): both receive the same commands and parameter requests and log under one \
             name; give each a unique name (-r __node:=NAME or -r __ns:=/NS)",
            self.warned.len() + same.max(1),
            self.fqn
        ))
    }
}

/// Logs a warning for each other participant hosting a node named like this one, until
/// `events` ends (the node's status events, from `Node::status_receiver`).
pub async fn watch(events: impl Stream<Item = NodeEvent>, mut clash: NameClash) {
    futures::pin_mut!(events);
    while let Some(ev) = events.next().await {
        if let NodeEvent::ParticipantEntities(info) = ev {
            if let Some(w) = clash.update(&info) {
                warn!("{w}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::entities_info::NodeEntitiesInfo;
    use ros2_client::NodeName;

    fn gid(b: u8) -> Gid {
        Gid::from([b; 16])
    }

    fn info(g: u8, nodes: &[(&str, &str)]) -> ParticipantEntitiesInfo {
        ParticipantEntitiesInfo::new(
            gid(g),
            nodes
                .iter()
                .map(|(ns, n)| NodeEntitiesInfo::new(NodeName::new(ns, n).unwrap()))
                .collect(),
        )
    }

    #[test]
    fn another_participant_with_the_name_is_warned_about_once() {
        let mut c = NameClash::with_gid(gid(1), "/pwm_actuator");
        // Our own announcement, and other names or namespaces: nothing.
        assert_eq!(c.update(&info(1, &[("/", "pwm_actuator")])), None);
        assert_eq!(c.update(&info(2, &[("/", "other")])), None);
        assert_eq!(c.update(&info(2, &[("/boiler", "pwm_actuator")])), None);
        let w = c.update(&info(3, &[("/", "pwm_actuator")])).unwrap();
        assert!(
            w.contains("there are 2 nodes with the name /pwm_actuator"),
            "{w}"
        );
        // Its next announcement (a new topic, say) is not a second warning.
        assert_eq!(c.update(&info(3, &[("/", "pwm_actuator")])), None);
        // A third participant is.
        let w = c.update(&info(4, &[("/", "pwm_actuator")])).unwrap();
        assert!(w.contains("there are 3 nodes"), "{w}");
    }
}
