//! A publisher of the node on Zenoh, as rmw_zenoh_cpp makes one (design.md "Publishers",
//! `rmw_publisher_data.cpp`): an advanced publisher (zenoh-ext) on the topic's data key
//! (`<domain>/<topic>/<type name>/<type hash>`), its liveliness token (`MP`) with the type's
//! hash and the QoS, and every sample the message's CDR bytes (with the encapsulation header)
//! and the 33-byte attachment: sequence number from 1, the source timestamp, the publisher's
//! GID. A transient-local publisher keeps its last `depth` samples for late joiners in a
//! publication cache they find by publisher detection (and, reliable, announces its last sequence
//! number every 500 ms at most, so a subscriber can ask for what it missed); a reliable keep-all
//! publisher blocks when the network is congested, every other one drops, as rmw_zenoh does.

use std::collections::BTreeMap;
use std::marker::PhantomData;
use std::sync::atomic::{AtomicI64, Ordering};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use ros2_client::qos::{Durability, History, Reliability};
use ros2_client::QosProfile;
use serde::Serialize;
use zenoh::liveliness::LivelinessToken;
use zenoh::qos::CongestionControl;
use zenoh::Wait;
use zenoh_ext::{AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig};

use crate::ros::config::logging::shown;
use crate::ros::interface::cdr::cdr_bytes;
use crate::ros::interface::msg::RosMessage;
use crate::ros::wire::zenoh_keys::{Attachment, EntityKind, Gid, KeyError};
use crate::ros::wire::zenoh_session::NodeSession;

/// Most samples a transient-local publisher keeps for late joiners (its QoS depth, at most
/// this).
pub const MAX_CACHE_SAMPLES: usize = 1000;
/// How often at most a reliable transient-local publisher announces its last sequence number
/// (rmw_zenoh's sporadic heartbeat).
pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(500);

/// Why a publisher cannot be made or a sample not sent.
#[derive(Debug, thiserror::Error)]
pub enum PublisherError {
    /// The topic's name, type or QoS make no valid key.
    #[error("topic {topic}: {source}")]
    Key {
        /// The topic.
        topic: String,
        /// Why.
        #[source]
        source: KeyError,
    },
    /// A transient-local publisher that would keep every sample.
    #[error("topic {topic}: a transient-local publisher must keep the last N samples, not all")]
    KeepAllCache {
        /// The topic.
        topic: String,
    },
    /// Zenoh refused the publisher or its token.
    #[error("topic {topic}: cannot declare the publisher: {why}")]
    Declare {
        /// The topic.
        topic: String,
        /// Zenoh's error (escaped).
        why: String,
    },
    /// The message cannot be written as CDR.
    #[error("topic {topic}: cannot serialize the message: {why}")]
    Serialize {
        /// The topic.
        topic: String,
        /// Why.
        why: String,
    },
    /// Zenoh did not take the sample.
    #[error("topic {topic}: cannot send the sample: {why}")]
    Put {
        /// The topic.
        topic: String,
        /// Zenoh's error (escaped).
        why: String,
    },
}

/// A publisher of `M` on Zenoh; its token is withdrawn when it is dropped.
pub struct ZenohPublisher<M> {
    publisher: AdvancedPublisher<'static>,
    _token: LivelinessToken,
    topic: String,
    /// The data key.
    pub key: String,
    /// The liveliness key.
    pub token_key: String,
    gid: Gid,
    /// The last sequence number sent (0: none yet).
    sequence: AtomicI64,
    _message: PhantomData<fn(&M)>,
}

impl<M: RosMessage + Serialize> ZenohPublisher<M> {
    /// A publisher on the fully qualified `topic` of `node` with `qos`; the type's hash
    /// looked up in `hashes` ([`type_hashes`](crate::ros::interface::type_hash::type_hashes)).
    pub fn new(
        node: &NodeSession,
        topic: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
    ) -> Result<Self, PublisherError> {
        let ros_type = format!("{}/msg/{}", M::PACKAGE, M::NAME);
        Self::of_type(node, topic, &ros_type, qos, hashes)
    }
}

impl<M: Serialize> ZenohPublisher<M> {
    /// As [`ZenohPublisher::new`] for a message type named `ros_type`
    /// (`rcl_interfaces/msg/ParameterEvent`) rather than by [`RosMessage`].
    pub fn of_type(
        node: &NodeSession,
        topic: &str,
        ros_type: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
    ) -> Result<Self, PublisherError> {
        let key_err = |source| PublisherError::Key {
            topic: topic.to_string(),
            source,
        };
        let declare_err = |e: zenoh::Error| PublisherError::Declare {
            topic: topic.to_string(),
            why: shown(&e.to_string()),
        };
        let reliable = qos.reliability != Reliability::BestEffort;
        let transient_local = qos.durability == Durability::TransientLocal;
        let history = qos.history;
        let (key, token_key) = node
            .endpoint_keys(EntityKind::Publisher, topic, ros_type, qos, hashes)
            .map_err(key_err)?;
        let gid = Gid::of_token(&token_key);
        let congestion = if reliable && history == History::KeepAll {
            CongestionControl::Block
        } else {
            CongestionControl::Drop
        };
        let mut builder = node
            .session()
            .declare_publisher(key.clone())
            .congestion_control(congestion)
            .reliability(if reliable {
                zenoh::qos::Reliability::Reliable
            } else {
                zenoh::qos::Reliability::BestEffort
            })
            .advanced();
        if transient_local {
            let depth = match history {
                History::KeepLast { depth } => depth.clamp(1, MAX_CACHE_SAMPLES),
                History::KeepAll => {
                    return Err(PublisherError::KeepAllCache {
                        topic: topic.to_string(),
                    })
                }
            };
            builder = builder
                .cache(CacheConfig::default().max_samples(depth))
                .publisher_detection();
            if reliable {
                builder = builder.sample_miss_detection(
                    MissDetectionConfig::default().sporadic_heartbeat(HEARTBEAT_PERIOD),
                );
            }
        }
        let publisher = builder.wait().map_err(declare_err)?;
        let token = node
            .session()
            .liveliness()
            .declare_token(token_key.clone())
            .wait()
            .map_err(declare_err)?;
        Ok(ZenohPublisher {
            publisher,
            _token: token,
            topic: topic.to_string(),
            key,
            token_key,
            gid,
            sequence: AtomicI64::new(0),
            _message: PhantomData,
        })
    }

    /// Sends `msg`: its CDR bytes with the attachment (the next sequence number, now, the GID).
    pub fn publish(&self, msg: &M) -> Result<(), PublisherError> {
        let payload = cdr_bytes(msg).map_err(|e| PublisherError::Serialize {
            topic: self.topic.clone(),
            why: e.to_string(),
        })?;
        let sequence = self.sequence.fetch_add(1, Ordering::Relaxed) + 1;
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        let attachment = Attachment {
            sequence,
            source_timestamp_ns: now,
            gid: self.gid,
        };
        self.publisher
            .put(payload)
            .attachment(attachment.encode().to_vec())
            .wait()
            .map_err(|e| PublisherError::Put {
                topic: self.topic.clone(),
                why: shown(&e.to_string()),
            })
    }

    /// The publisher's GID.
    pub fn gid(&self) -> Gid {
        self.gid
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::interface::msg::{Bool, Float64};
    use crate::ros::interface::qos;
    use crate::ros::interface::type_hash::type_hashes;
    use crate::ros::wire::zenoh_keys::{parse_token, Token};
    use crate::ros::wire::zenoh_session::test_peers::{free_port, node, router};
    use std::time::Instant;

    /// Waits up to 5 s for `f` to give something.
    fn within_5_s<T>(mut f: impl FnMut() -> Option<T>) -> T {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            if let Some(t) = f() {
                return t;
            }
            assert!(Instant::now() < deadline, "nothing within 5 s");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn now_ns() -> i64 {
        SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap()
            .as_nanos() as i64
    }

    #[test]
    fn samples_carry_cdr_and_the_attachment_on_the_exact_key_and_the_token_tells_the_publisher() {
        let port = free_port();
        let router = router(port);
        let node = node(port, 5);
        let hashes = type_hashes().unwrap();
        let publisher = ZenohPublisher::<Float64>::new(
            &node,
            "/pwm_actuator/pw01/duty_echo",
            qos::commands(),
            &hashes,
        )
        .unwrap();
        assert!(
            publisher
                .key
                .starts_with("5/pwm_actuator/pw01/duty_echo/std_msgs::msg::dds_::Float64_/RIHS01_"),
            "{}",
            publisher.key
        );
        let subscriber = router
            .declare_subscriber(publisher.key.as_str())
            .wait()
            .unwrap();
        // The token, seen through the router, names the publisher, its type hash and its QoS.
        let token = within_5_s(|| {
            router
                .liveliness()
                .get("@ros2_lv/5/**/MP/**")
                .wait()
                .unwrap()
                .iter()
                .filter_map(|r| r.into_result().ok())
                .map(|s| s.key_expr().to_string())
                .next()
        });
        assert_eq!(token, publisher.token_key);
        match parse_token(&token).unwrap() {
            Token::Entity(e) => {
                assert_eq!(e.kind, EntityKind::Publisher);
                assert_eq!(e.name, "/pwm_actuator/pw01/duty_echo");
                assert_eq!(e.ty.hash, hashes["std_msgs/msg/Float64"]);
                assert_eq!(e.entity_id, 1);
            }
            other => panic!("{other:?}"),
        }
        // The subscription reaches the publisher a moment after it is declared: publish until
        // one arrives, then two more, which must follow it with the next sequence numbers.
        let first = within_5_s(|| {
            publisher.publish(&Float64 { data: 0.5 }).unwrap();
            subscriber
                .recv_timeout(Duration::from_millis(100))
                .ok()
                .flatten()
        });
        publisher.publish(&Float64 { data: 0.25 }).unwrap();
        let second = subscriber
            .recv_timeout(Duration::from_secs(5))
            .unwrap()
            .unwrap();
        let a1 = Attachment::decode(&first.attachment().unwrap().to_bytes()).unwrap();
        let a2 = Attachment::decode(&second.attachment().unwrap().to_bytes()).unwrap();
        assert_eq!(a2.sequence, a1.sequence + 1);
        assert!(a1.sequence >= 1);
        assert_eq!(a1.gid, Gid::of_token(&publisher.token_key));
        assert_eq!(a2.gid, a1.gid);
        assert!((now_ns() - a2.source_timestamp_ns).abs() < 5_000_000_000);
        let mut want = vec![0, 1, 0, 0];
        want.extend_from_slice(&0.25f64.to_le_bytes());
        assert_eq!(second.payload().to_bytes().as_ref(), want.as_slice());
        assert_eq!(second.key_expr().as_str(), publisher.key);
        drop(publisher);
        node.close();
        router.close().wait().unwrap();
    }

    #[test]
    fn a_late_joiner_of_a_transient_local_topic_gets_the_last_sample_from_the_cache() {
        let port = free_port();
        let router = router(port);
        let node = node(port, 5);
        let hashes = type_hashes().unwrap();
        let e1 = ZenohPublisher::<Bool>::new(&node, "/pwm_actuator/pw01/e1", qos::e1(), &hashes)
            .unwrap();
        e1.publish(&Bool { data: false }).unwrap();
        e1.publish(&Bool { data: true }).unwrap();
        // A late joiner asks the publication caches under the key, as an advanced subscriber
        // with history does: the last sample only (depth 1), with its attachment.
        let replies = within_5_s(|| {
            let got: Vec<_> = router
                .get(format!("{}/@adv/pub/**", e1.key))
                .accept_replies(zenoh::query::ReplyKeyExpr::Any)
                // Every reply, not the latest per key (a cache's samples share one key).
                .consolidation(zenoh::query::ConsolidationMode::None)
                .wait()
                .unwrap()
                .iter()
                .filter_map(|r| r.into_result().ok())
                .collect();
            (!got.is_empty()).then_some(got)
        });
        assert_eq!(replies.len(), 1, "depth 1 keeps one sample");
        let s = &replies[0];
        assert_eq!(s.key_expr().as_str(), e1.key);
        assert_eq!(s.payload().to_bytes().as_ref(), &[0, 1, 0, 0, 1]);
        let a = Attachment::decode(&s.attachment().unwrap().to_bytes()).unwrap();
        assert_eq!((a.sequence, a.gid), (2, e1.gid()));
        drop(e1);
        node.close();
        router.close().wait().unwrap();
    }
}
