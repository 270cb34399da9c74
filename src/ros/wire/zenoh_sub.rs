//! A subscription of the node on Zenoh, as rmw_zenoh_cpp makes one (design.md
//! "Subscriptions"): a subscriber on the topic's exact data key and its liveliness token
//! (`MS`), the samples handed to the node's callback in a task, in order.
//!
//! What arrives is bounded before anything is decoded: zenoh's callback (on zenoh's own
//! threads, which must never wait on the node) drops a sample larger than
//! [`MAX_SAMPLE_BYTES`] (payload and attachment) and counts it, then puts the sample's bytes
//! in a queue of the QoS depth; when the queue is full the oldest sample goes, counted, as a
//! keep-last history drops it. The task takes them in order, decodes the CDR and calls the
//! callback; a sample that is not the topic's message is counted and said (escaped, once per
//! 10 s at most) and the next one taken. A transient-local subscription is not made here:
//! none of the node's inputs is one.

use std::collections::{BTreeMap, VecDeque};
use std::marker::PhantomData;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use log::warn;
use ros2_client::qos::Durability;
use ros2_client::QosProfile;
use serde::de::DeserializeOwned;
use tokio::sync::Notify;
use tokio::task::JoinHandle;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::Wait;

use crate::ros::config::logging::shown;
use crate::ros::interface::cdr::from_cdr_bytes;
use crate::ros::interface::msg::RosMessage;
use crate::ros::interface::qos::{self, MAX_SAMPLE_BYTES};
use crate::ros::wire::zenoh_keys::{EntityKind, KeyError};
use crate::ros::wire::zenoh_session::{queue_depth, NodeSession};

/// Most samples a subscription holds that its task has not taken yet (its QoS depth, at most
/// this).
pub const MAX_QUEUE: usize = 1000;

/// Why a subscription cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum SubscriptionError {
    /// The topic's name or type make no valid key.
    #[error("topic {topic}: {source}")]
    Key {
        /// The topic.
        topic: String,
        /// Why.
        #[source]
        source: KeyError,
    },
    /// A transient-local subscription (none of the node's inputs is one).
    #[error("topic {topic}: a transient-local subscription is not supported on Zenoh")]
    TransientLocal {
        /// The topic.
        topic: String,
    },
    /// Zenoh refused the subscriber or its token.
    #[error("topic {topic}: cannot declare the subscription: {why}")]
    Declare {
        /// The topic.
        topic: String,
        /// Zenoh's error (escaped).
        why: String,
    },
}

/// What a subscription dropped, counted since it was made.
#[derive(Debug, Default)]
pub struct Dropped {
    /// Samples larger than [`MAX_SAMPLE_BYTES`].
    pub too_large: AtomicU64,
    /// Samples pushed out of a full queue (the oldest).
    pub overflowed: AtomicU64,
    /// Samples that were not the topic's message.
    pub undecodable: AtomicU64,
}

/// The samples between zenoh's callback and the task.
struct Queue {
    samples: Mutex<VecDeque<Vec<u8>>>,
    depth: usize,
    ready: Notify,
}

/// A subscription of `M` on Zenoh and its task; the token is withdrawn and the task aborted
/// when it is dropped.
pub struct ZenohSubscription<M> {
    _subscriber: Subscriber<()>,
    _token: LivelinessToken,
    task: JoinHandle<()>,
    /// The data key.
    pub key: String,
    /// The liveliness key.
    pub token_key: String,
    /// What it dropped.
    pub dropped: Arc<Dropped>,
    _message: PhantomData<fn(M)>,
}

impl<M> Drop for ZenohSubscription<M> {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl<M: RosMessage + DeserializeOwned + Send + 'static> ZenohSubscription<M> {
    /// Subscribes to the fully qualified `topic` of `node` with `qos` (the type's hash looked
    /// up in `hashes`) and runs `on_msg` for every message in a task of the current tokio
    /// runtime, until this is dropped.
    pub fn listen(
        node: &NodeSession,
        topic: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
        mut on_msg: impl FnMut(M) + Send + 'static,
    ) -> Result<Self, SubscriptionError> {
        Self::listen_async(node, topic, qos, hashes, move |m| {
            on_msg(m);
            std::future::ready(())
        })
    }

    /// As [`ZenohSubscription::listen`], but `on_msg` is async and awaited before the next
    /// message is taken.
    pub fn listen_async<F, Fut>(
        node: &NodeSession,
        topic: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
        mut on_msg: F,
    ) -> Result<Self, SubscriptionError>
    where
        F: FnMut(M) -> Fut + Send + 'static,
        Fut: std::future::Future<Output = ()> + Send,
    {
        let key_err = |source| SubscriptionError::Key {
            topic: topic.to_string(),
            source,
        };
        let declare_err = |e: zenoh::Error| SubscriptionError::Declare {
            topic: topic.to_string(),
            why: shown(&e.to_string()),
        };
        if qos.durability == Durability::TransientLocal {
            return Err(SubscriptionError::TransientLocal {
                topic: topic.to_string(),
            });
        }
        let ros_type = format!("{}/msg/{}", M::PACKAGE, M::NAME);
        let depth = queue_depth(qos.history, MAX_QUEUE);
        let (key, token_key) = node
            .endpoint_keys(EntityKind::Subscription, topic, &ros_type, qos, hashes)
            .map_err(key_err)?;
        let queue = Arc::new(Queue {
            samples: Mutex::new(VecDeque::with_capacity(depth)),
            depth,
            ready: Notify::new(),
        });
        let dropped = Arc::new(Dropped::default());
        let subscriber = node
            .session()
            .declare_subscriber(key.clone())
            .callback({
                let (queue, dropped) = (queue.clone(), dropped.clone());
                move |sample| {
                    // The payload, as on DDS: the attachment (33 bytes from rmw_zenoh) is
                    // bounded with the whole message by the session's reassembly bound.
                    if sample.payload().len() > MAX_SAMPLE_BYTES {
                        dropped.too_large.fetch_add(1, Ordering::Relaxed);
                        qos::note_zenoh_too_large();
                        return;
                    }
                    let bytes = sample.payload().to_bytes().into_owned();
                    let mut samples = queue.samples.lock().unwrap_or_else(|p| p.into_inner());
                    if samples.len() >= queue.depth {
                        samples.pop_front();
                        dropped.overflowed.fetch_add(1, Ordering::Relaxed);
                    }
                    samples.push_back(bytes);
                    drop(samples);
                    queue.ready.notify_one();
                }
            })
            .wait()
            .map_err(declare_err)?;
        let token = node
            .session()
            .liveliness()
            .declare_token(token_key.clone())
            .wait()
            .map_err(declare_err)?;
        let task = tokio::spawn({
            let (queue, dropped, topic) = (queue.clone(), dropped.clone(), topic.to_string());
            async move {
                let mut last_warning: Option<std::time::Instant> = None;
                loop {
                    let next = queue
                        .samples
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .pop_front();
                    let Some(bytes) = next else {
                        queue.ready.notified().await;
                        continue;
                    };
                    match from_cdr_bytes::<M>(&bytes) {
                        Ok(m) => on_msg(m).await,
                        Err(why) => {
                            dropped.undecodable.fetch_add(1, Ordering::Relaxed);
                            if last_warning.is_none_or(|t| t.elapsed().as_secs() >= 10) {
                                last_warning = Some(std::time::Instant::now());
                                warn!("{topic}: unreadable message on Zenoh: {}", shown(&why));
                            }
                        }
                    }
                }
            }
        });
        Ok(ZenohSubscription {
            _subscriber: subscriber,
            _token: token,
            task,
            key,
            token_key,
            dropped,
            _message: PhantomData,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::interface::cdr::cdr_bytes;
    use crate::ros::interface::msg::Float64;
    use crate::ros::interface::type_hash::type_hashes;
    use crate::ros::wire::zenoh_keys::{parse_token, Token};
    use crate::ros::wire::zenoh_session::test_peers::{free_port, node, router};
    use crate::ros::wire::zenoh_session::MAX_MESSAGE_BYTES;
    use ros2_client::qos::History;
    use std::time::{Duration, Instant};

    /// Waits up to 5 s for `f` to hold.
    fn within_5_s(mut f: impl FnMut() -> bool) {
        let deadline = Instant::now() + Duration::from_secs(5);
        while !f() {
            assert!(Instant::now() < deadline, "not within 5 s");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn duties_put_on_the_exact_key_reach_the_callback_and_bad_ones_are_counted() {
        let port = free_port();
        let router = router(port);
        let node = node(port, 6);
        let hashes = type_hashes().unwrap();
        let got = Arc::new(Mutex::new(Vec::new()));
        let sub = ZenohSubscription::<Float64>::listen(
            &node,
            "/pwm_actuator/pw01/duty",
            qos::commands(),
            &hashes,
            {
                let got = got.clone();
                move |m: Float64| got.lock().unwrap().push(m.data)
            },
        )
        .unwrap();
        match parse_token(&sub.token_key).unwrap() {
            Token::Entity(e) => {
                assert_eq!(e.kind, EntityKind::Subscription);
                assert_eq!(e.qos.history, History::KeepLast { depth: 10 });
            }
            other => panic!("{other:?}"),
        }
        // The subscription reaches the router a moment after it is declared.
        let key = sub.key.clone();
        let put = |bytes: Vec<u8>| router.put(key.as_str(), bytes).wait().unwrap();
        within_5_s(|| {
            put(cdr_bytes(&Float64 { data: 12.5 }).unwrap());
            !got.lock().unwrap().is_empty()
        });
        // Not a Float64 (three bytes), then oversize, then larger than the session reassembles
        // (dropped by Zenoh, the link kept), then a good one: only that one arrives (after any
        // 12.5 still on its way).
        let _counting = qos::ZENOH_TOO_LARGE_TESTS
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        let too_large_before = qos::zenoh_too_large();
        put(vec![0, 1, 0]);
        // At the bound with rmw_zenoh's 33-byte attachment: not too large (the payload is
        // bounded, as on DDS), only not a Float64.
        let mut at_bound = vec![0u8; MAX_SAMPLE_BYTES];
        at_bound[..2].copy_from_slice(&[0xff, 0xff]); // no CDR representation
        router
            .put(key.as_str(), at_bound)
            .attachment(vec![0u8; 33])
            .wait()
            .unwrap();
        put(vec![0; MAX_SAMPLE_BYTES + 1]);
        put(vec![0; MAX_MESSAGE_BYTES + 1]);
        put(cdr_bytes(&Float64 { data: 40.0 }).unwrap());
        within_5_s(|| got.lock().unwrap().last() == Some(&40.0));
        let got = got.lock().unwrap().clone();
        assert!(got[..got.len() - 1].iter().all(|&x| x == 12.5), "{got:?}");
        assert_eq!(sub.dropped.undecodable.load(Ordering::Relaxed), 2);
        assert_eq!(sub.dropped.too_large.load(Ordering::Relaxed), 1);
        // Counted for /diagnostics too.
        assert_eq!(qos::zenoh_too_large(), too_large_before + 1);
        assert_eq!(sub.dropped.overflowed.load(Ordering::Relaxed), 0);
        drop(sub);
        node.close();
        router.close().wait().unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn the_session_configurations_access_control_decides_what_reaches_the_node() {
        use crate::ros::config::zenoh::{read, DEFAULT_SESSION_CONFIG};
        use crate::ros::interface::msg::Bool;
        use crate::ros::wire::zenoh_session::{config, NodeSession};
        let port = free_port();
        let router = router(port);
        // Zenoh's access control, as a site would put it in the session's configuration: puts
        // on pw01's duty denied as they come in, everything else allowed.
        let acl = r#"{enabled:true,default_permission:"allow",rules:[{id:"no_duty",messages:["put"],flows:["ingress"],permission:"deny",key_exprs:["*/pwm_actuator/pw01/duty/**"]}],subjects:[{id:"anyone"}],policies:[{rules:["no_duty"],subjects:["anyone"]}]}"#;
        let s = read(|k| {
            (k == "ZENOH_CONFIG_OVERRIDE").then(|| {
                format!(
                    r#"connect/endpoints=["tcp/127.0.0.1:{port}"];listen/endpoints=[];access_control={acl}"#
                )
            })
        })
        .unwrap();
        let c = config(DEFAULT_SESSION_CONFIG, &s, |w| panic!("{w}")).unwrap();
        let node =
            NodeSession::open(c, &s, 9, "/", "/", "pwm_actuator", |w| panic!("{w}")).unwrap();
        let hashes = type_hashes().unwrap();
        let duties = Arc::new(Mutex::new(Vec::new()));
        let duty = ZenohSubscription::<Float64>::listen(
            &node,
            "/pwm_actuator/pw01/duty",
            qos::commands(),
            &hashes,
            {
                let duties = duties.clone();
                move |m: Float64| duties.lock().unwrap().push(m.data)
            },
        )
        .unwrap();
        let enables = Arc::new(Mutex::new(Vec::new()));
        let enable = ZenohSubscription::<Bool>::listen(
            &node,
            "/pwm_actuator/pw01/enable",
            qos::commands(),
            &hashes,
            {
                let enables = enables.clone();
                move |m: Bool| enables.lock().unwrap().push(m.data)
            },
        )
        .unwrap();
        let (duty_key, enable_key) = (duty.key.clone(), enable.key.clone());
        // Both subscriptions reach the router; the duty put each time beside the enable never
        // arrives.
        within_5_s(|| {
            router
                .put(
                    duty_key.as_str(),
                    cdr_bytes(&Float64 { data: 30.0 }).unwrap(),
                )
                .wait()
                .unwrap();
            router
                .put(
                    enable_key.as_str(),
                    cdr_bytes(&Bool { data: true }).unwrap(),
                )
                .wait()
                .unwrap();
            enables.lock().unwrap().len() >= 3
        });
        std::thread::sleep(Duration::from_millis(300));
        assert!(
            duties.lock().unwrap().is_empty(),
            "{:?}",
            duties.lock().unwrap()
        );
        assert_eq!(duty.dropped.too_large.load(Ordering::Relaxed), 0);
        drop((duty, enable));
        node.close();
        router.close().wait().unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_callback_that_falls_behind_loses_the_oldest_samples_beyond_the_depth() {
        let port = free_port();
        let router = router(port);
        let node = node(port, 6);
        let hashes = type_hashes().unwrap();
        let (started_tx, started_rx) = std::sync::mpsc::channel::<()>();
        let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
        let got = Arc::new(Mutex::new(Vec::new()));
        let sub = ZenohSubscription::<Float64>::listen(
            &node,
            "/pwm_actuator/pw01/duty",
            qos::commands(),
            &hashes,
            {
                let got = got.clone();
                let mut first = true;
                move |m: Float64| {
                    // The first message holds the task until the test lets it go.
                    if std::mem::take(&mut first) {
                        started_tx.send(()).unwrap();
                        gate_rx.recv().unwrap();
                    }
                    got.lock().unwrap().push(m.data);
                }
            },
        )
        .unwrap();
        let key = sub.key.clone();
        let put = |x: f64| {
            router
                .put(key.as_str(), cdr_bytes(&Float64 { data: x }).unwrap())
                .wait()
                .unwrap()
        };
        // -1 until the task holds one, then 25 more while it is held: with the -1s still
        // queued, at least 15 more than the depth of 10.
        within_5_s(|| {
            put(-1.0);
            started_rx.recv_timeout(Duration::from_millis(50)).is_ok()
        });
        for i in 0..25 {
            put(f64::from(i));
        }
        within_5_s(|| sub.dropped.overflowed.load(Ordering::Relaxed) >= 15);
        gate_tx.send(()).unwrap();
        within_5_s(|| got.lock().unwrap().last() == Some(&24.0));
        // The held one, then the newest ten in order: the oldest were dropped.
        let want: Vec<f64> = std::iter::once(-1.0)
            .chain((15..25).map(f64::from))
            .collect();
        assert_eq!(*got.lock().unwrap(), want);
        drop(sub);
        node.close();
        router.close().wait().unwrap();
    }
}
