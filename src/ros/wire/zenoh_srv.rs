//! A service server of the node on Zenoh, as rmw_zenoh_cpp makes one (design.md "Service
//! Servers", `rmw_service_data.cpp`): a complete queryable on the service's data key
//! (`<domain>/<service>/<type name>/<type hash>`) and its liveliness token (`SS`). A request is
//! a query whose payload is the request's CDR bytes and whose attachment carries the client's
//! sequence number and GID; the reply carries the response's CDR bytes and an attachment with
//! the same sequence number, a fresh source timestamp and the client's GID, which is how the
//! client matches it.
//!
//! As with subscriptions ([`zenoh_sub`](super::zenoh_sub)), zenoh's callback never waits on
//! the node: a request larger than [`MAX_SAMPLE_BYTES`] is answered with an error at once and
//! counted, any other is queued (the QoS depth; the oldest, when the queue is full, answered
//! with an error and counted); one task takes them in order and answers each with the
//! handler's response. A request without a valid attachment, or that is not the service's
//! request type, is answered with an error naming why (escaped) and counted.
//!
//! An action's three services are [`ZenohRequests`] without the task: their owner takes each
//! request with a [`Responder`] and answers it when it can (a `get_result` when its goal ends).

use std::collections::{BTreeMap, VecDeque};
use std::marker::PhantomData;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use log::warn;
use ros2_client::QosProfile;
use serde::de::DeserializeOwned;
use serde::Serialize;
use tokio::sync::Notify;
use tokio::task::JoinHandle;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::{Query, Queryable};
use zenoh::Wait;

use crate::ros::config::logging::shown;
use crate::ros::interface::cdr::{cdr_bytes, from_cdr_bytes};
use crate::ros::interface::qos::{self, MAX_SAMPLE_BYTES};
use crate::ros::wire::zenoh_keys::{Attachment, EntityKind, KeyError};
use crate::ros::wire::zenoh_session::{queue_depth, NodeSession};

/// Most requests a service holds that its task has not taken yet (its QoS depth, at most
/// this).
pub const MAX_QUEUE: usize = 1000;

/// Why a service cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The service's name or type make no valid key.
    #[error("service {service}: {source}")]
    Key {
        /// The service.
        service: String,
        /// Why.
        #[source]
        source: KeyError,
    },
    /// Zenoh refused the queryable or its token.
    #[error("service {service}: cannot declare it: {why}")]
    Declare {
        /// The service.
        service: String,
        /// Zenoh's error (escaped).
        why: String,
    },
}

/// What a service refused, counted since it was made; each was answered with an error.
#[derive(Debug, Default)]
pub struct Refused {
    /// Requests larger than [`MAX_SAMPLE_BYTES`].
    pub too_large: AtomicU64,
    /// Requests pushed out of a full queue (the oldest).
    pub overflowed: AtomicU64,
    /// Requests without a valid attachment or not of the request type.
    pub malformed: AtomicU64,
}

struct Queue {
    queries: Mutex<VecDeque<Query>>,
    depth: usize,
    /// Notified at each request queued (shared by the services of one action).
    ready: Arc<Notify>,
}

/// Answers `query` with an error `why`; a failure to send is not the node's to handle.
fn refuse(query: &Query, why: &str) {
    let _ = query.reply_err(why.to_string()).wait();
}

/// A request taken, to be answered once through [`Responder::reply`] (at once, or later: an
/// action's `get_result` waits for its goal's end). Dropped unanswered, the client's query
/// ends without a reply.
pub struct Responder {
    query: Query,
    attachment: Attachment,
    key: String,
    service: Arc<str>,
}

impl std::fmt::Debug for Responder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Responder")
            .field("service", &self.service)
            .field("sequence", &self.attachment.sequence)
            .finish()
    }
}

impl Responder {
    /// Answers with `resp`: its CDR bytes, and the request's attachment with a fresh source
    /// timestamp. A failure is logged.
    pub fn reply<Resp: Serialize>(self, resp: &Resp) {
        let payload = match cdr_bytes(resp) {
            Ok(p) => p,
            Err(e) => {
                warn!("{}: cannot serialize the response: {e}", self.service);
                refuse(&self.query, "the response could not be serialized");
                return;
            }
        };
        let now = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        let reply = Attachment {
            source_timestamp_ns: now,
            ..self.attachment
        };
        if let Err(e) = self
            .query
            .reply(self.key.as_str(), payload)
            .attachment(reply.encode().to_vec())
            .wait()
        {
            warn!(
                "{}: cannot send the response: {}",
                self.service,
                shown(&e.to_string())
            );
        }
    }

    /// Answers with an error `why`.
    pub fn refuse(self, why: &str) {
        refuse(&self.query, why);
    }
}

/// The requests of one service on Zenoh, queued as they arrive, bounded, for their owner to
/// take ([`ZenohRequests::take`]); the token is withdrawn when this is dropped.
pub struct ZenohRequests<Req> {
    _queryable: Queryable<()>,
    _token: LivelinessToken,
    queue: Arc<Queue>,
    service: Arc<str>,
    /// The data key.
    pub key: String,
    /// The liveliness key.
    pub token_key: String,
    /// What it refused.
    pub refused: Arc<Refused>,
    last_warning: Mutex<Option<Instant>>,
    _types: PhantomData<fn() -> Req>,
}

impl<Req: DeserializeOwned> ZenohRequests<Req> {
    /// Declares the fully qualified `service` of ROS type `ros_type` (`std_srvs/srv/Trigger`,
    /// or an action's `pkg/action/Name_SendGoal`; its hash looked up in `hashes`) with `qos`;
    /// `ready` is notified at each request queued.
    pub fn declare(
        node: &NodeSession,
        service: &str,
        ros_type: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
        ready: Arc<Notify>,
    ) -> Result<Self, ServiceError> {
        let key_err = |source| ServiceError::Key {
            service: service.to_string(),
            source,
        };
        let declare_err = |e: zenoh::Error| ServiceError::Declare {
            service: service.to_string(),
            why: shown(&e.to_string()),
        };
        let depth = queue_depth(qos.history, MAX_QUEUE);
        let (key, token_key) = node
            .endpoint_keys(EntityKind::Service, service, ros_type, qos, hashes)
            .map_err(key_err)?;
        let queue = Arc::new(Queue {
            queries: Mutex::new(VecDeque::with_capacity(depth)),
            depth,
            ready,
        });
        let refused = Arc::new(Refused::default());
        let queryable = node
            .session()
            .declare_queryable(key.clone())
            .complete(true)
            .callback({
                let (queue, refused) = (queue.clone(), refused.clone());
                move |query: Query| {
                    // The payload, as on DDS (see zenoh_sub).
                    let size = query.payload().map_or(0, |p| p.len());
                    if size > MAX_SAMPLE_BYTES {
                        refused.too_large.fetch_add(1, Ordering::Relaxed);
                        qos::note_zenoh_too_large();
                        refuse(
                            &query,
                            &format!("request of {size} bytes, more than {MAX_SAMPLE_BYTES}"),
                        );
                        return;
                    }
                    let mut queries = queue.queries.lock().unwrap_or_else(|p| p.into_inner());
                    let pushed_out = if queries.len() >= queue.depth {
                        queries.pop_front()
                    } else {
                        None
                    };
                    queries.push_back(query);
                    drop(queries);
                    if let Some(old) = pushed_out {
                        refused.overflowed.fetch_add(1, Ordering::Relaxed);
                        refuse(
                            &old,
                            "the service's queue was full: a newer request took its place",
                        );
                    }
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
        Ok(ZenohRequests {
            _queryable: queryable,
            _token: token,
            queue,
            service: service.into(),
            key,
            token_key,
            refused,
            last_warning: Mutex::new(None),
            _types: PhantomData,
        })
    }

    /// The oldest request queued and readable, if any: one without a valid attachment or that
    /// is not of the request type is answered with an error naming why (escaped), counted,
    /// and passed over (logged at most once in 10 s).
    pub fn try_take(&self) -> Option<(Responder, Req)> {
        loop {
            let query = self
                .queue
                .queries
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .pop_front()?;
            let request = query
                .attachment()
                .ok_or_else(|| "no attachment".to_string())
                .and_then(|a| Attachment::decode(&a.to_bytes()).map_err(|e| e.to_string()))
                .and_then(|a| {
                    let bytes = query.payload().map(|p| p.to_bytes()).unwrap_or_default();
                    Ok((a, from_cdr_bytes::<Req>(&bytes)?))
                });
            match request {
                Ok((attachment, req)) => {
                    let r = Responder {
                        query,
                        attachment,
                        key: self.key.clone(),
                        service: self.service.clone(),
                    };
                    return Some((r, req));
                }
                Err(why) => {
                    self.refused.malformed.fetch_add(1, Ordering::Relaxed);
                    let why = shown(&why);
                    let mut last = self.last_warning.lock().unwrap_or_else(|p| p.into_inner());
                    if last.is_none_or(|t| t.elapsed().as_secs() >= 10) {
                        *last = Some(Instant::now());
                        warn!("{}: unreadable request on Zenoh: {why}", self.service);
                    }
                    refuse(&query, &format!("unreadable request: {why}"));
                }
            }
        }
    }

    /// Waits for the next readable request ([`ZenohRequests::try_take`]). Cancel-safe: a
    /// request taken is returned by the same poll.
    pub async fn take(&self) -> (Responder, Req) {
        loop {
            let notified = self.queue.ready.notified();
            let mut notified = std::pin::pin!(notified);
            notified.as_mut().enable();
            if let Some(r) = self.try_take() {
                return r;
            }
            notified.await;
        }
    }
}

/// A service server on Zenoh and its task; the token is withdrawn and the task aborted when it
/// is dropped.
pub struct ZenohService<Req, Resp> {
    _requests: Arc<ZenohRequests<Req>>,
    task: JoinHandle<()>,
    /// The data key.
    pub key: String,
    /// The liveliness key.
    pub token_key: String,
    /// What it refused.
    pub refused: Arc<Refused>,
    _types: PhantomData<fn(Req) -> Resp>,
}

impl<Req, Resp> Drop for ZenohService<Req, Resp> {
    fn drop(&mut self) {
        self.task.abort();
    }
}

impl<Req, Resp> ZenohService<Req, Resp>
where
    Req: DeserializeOwned + Send + 'static,
    Resp: Serialize + Send + 'static,
{
    /// Serves the fully qualified `service` of ROS type `ros_type` (`std_srvs/srv/Trigger`; its
    /// hash looked up in `hashes`) with `qos`, answering each request with what `handler`'s
    /// future gives, one at a time, in order, in a task of the current tokio runtime (a
    /// handler that failed is logged and its request answered with an error).
    pub fn serve_with<F, Fut>(
        node: &NodeSession,
        service: &str,
        ros_type: &str,
        qos: QosProfile,
        hashes: &BTreeMap<String, String>,
        handler: F,
    ) -> Result<Self, ServiceError>
    where
        F: Fn(Req) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<Resp, tokio::task::JoinError>> + Send + 'static,
    {
        let requests = Arc::new(ZenohRequests::<Req>::declare(
            node,
            service,
            ros_type,
            qos,
            hashes,
            Arc::new(Notify::new()),
        )?);
        let (key, token_key, refused) = (
            requests.key.clone(),
            requests.token_key.clone(),
            requests.refused.clone(),
        );
        let task = tokio::spawn({
            let (requests, service) = (requests.clone(), service.to_string());
            async move {
                loop {
                    let (responder, req) = requests.take().await;
                    match handler(req).await {
                        Ok(resp) => responder.reply(&resp),
                        Err(e) => {
                            warn!("{service}: the request's handler failed: {e}");
                            responder.refuse("the service's handler failed");
                        }
                    }
                }
            }
        });
        Ok(ZenohService {
            _requests: requests,
            task,
            key,
            token_key,
            refused,
            _types: PhantomData,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros::interface::msg::{EmptyRequest, TriggerResponse};
    use crate::ros::interface::type_hash::type_hashes;
    use crate::ros::wire::zenoh_keys::{parse_token, Gid, Token};
    use crate::ros::wire::zenoh_session::test_peers::{free_port, node, router};
    use std::time::{Duration, Instant};
    use zenoh::query::Reply;
    use zenoh::Session;

    /// The error `reply` carries, as text; panics if it is an answer.
    fn refusal(reply: &Reply) -> String {
        let error = reply.result().expect_err("an error reply");
        error.payload().try_to_string().unwrap().to_string()
    }

    /// One request from `client` as rmw_zenoh's client sends it; the replies.
    fn call(
        client: &Session,
        key: &str,
        payload: Vec<u8>,
        attachment: Option<Vec<u8>>,
    ) -> Vec<Reply> {
        let mut get = client
            .get(key)
            .payload(payload)
            .target(zenoh::query::QueryTarget::AllComplete)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(Duration::from_secs(5));
        if let Some(a) = attachment {
            get = get.attachment(a);
        }
        get.wait().unwrap().iter().collect()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_request_is_answered_with_the_echoed_sequence_and_the_clients_gid() {
        let port = free_port();
        let router = router(port);
        let node = node(port, 7);
        let hashes = type_hashes().unwrap();
        let calls = Arc::new(AtomicU64::new(0));
        let srv = ZenohService::<EmptyRequest, TriggerResponse>::serve_with(
            &node,
            "/pwm_actuator/reset_estop",
            "std_srvs/srv/Trigger",
            qos::services(),
            &hashes,
            {
                let calls = calls.clone();
                move |_req| {
                    let n = calls.fetch_add(1, Ordering::Relaxed) + 1;
                    async move {
                        Ok(TriggerResponse {
                            success: true,
                            message: format!("call {n}"),
                        })
                    }
                }
            },
        )
        .unwrap();
        assert!(
            srv.key
                .starts_with("7/pwm_actuator/reset_estop/std_srvs::srv::dds_::Trigger_/RIHS01_"),
            "{}",
            srv.key
        );
        match parse_token(&srv.token_key).unwrap() {
            Token::Entity(e) => {
                assert_eq!(e.kind, EntityKind::Service);
                assert_eq!(e.ty.hash, hashes["std_srvs/srv/Trigger"]);
            }
            other => panic!("{other:?}"),
        }
        let client_gid = Gid([7; 16]);
        let request = |seq: i64| {
            Attachment {
                sequence: seq,
                source_timestamp_ns: 1,
                gid: client_gid,
            }
            .encode()
            .to_vec()
        };
        // The queryable reaches the router a moment after it is declared.
        let deadline = Instant::now() + Duration::from_secs(5);
        let replies = loop {
            let r = call(
                &router,
                &srv.key,
                cdr_bytes(&EmptyRequest::default()).unwrap(),
                Some(request(41)),
            );
            if !r.is_empty() || Instant::now() > deadline {
                break r;
            }
            std::thread::sleep(Duration::from_millis(50));
        };
        assert_eq!(replies.len(), 1);
        let sample = replies[0].result().unwrap();
        let resp: TriggerResponse = from_cdr_bytes(&sample.payload().to_bytes()).unwrap();
        assert!(
            resp.success && resp.message.starts_with("call "),
            "{resp:?}"
        );
        let a = Attachment::decode(&sample.attachment().unwrap().to_bytes()).unwrap();
        assert_eq!((a.sequence, a.gid), (41, client_gid));
        assert!(a.source_timestamp_ns > 1);
        // A request without an attachment, and one that is not the request type, are
        // answered with an error and counted; the next good one is served.
        let r = call(
            &router,
            &srv.key,
            cdr_bytes(&EmptyRequest::default()).unwrap(),
            None,
        );
        let why = refusal(&r[0]);
        assert!(why.contains("no attachment"), "{why}");
        let r = call(&router, &srv.key, vec![9], Some(request(42)));
        assert!(r[0].result().is_err());
        let _counting = qos::ZENOH_TOO_LARGE_TESTS
            .lock()
            .unwrap_or_else(|p| p.into_inner());
        let too_large_before = qos::zenoh_too_large();
        // At the bound with its attachment: not too large (the payload is bounded, as on
        // DDS), only not the request type.
        let mut at_bound = vec![0u8; MAX_SAMPLE_BYTES];
        at_bound[..2].copy_from_slice(&[0xff, 0xff]); // no CDR representation
        let r = call(&router, &srv.key, at_bound, Some(request(45)));
        let why = refusal(&r[0]);
        assert!(!why.contains("more than"), "{why}");
        let r = call(
            &router,
            &srv.key,
            vec![0; MAX_SAMPLE_BYTES + 1],
            Some(request(43)),
        );
        let why = refusal(&r[0]);
        assert!(why.contains("more than"), "{why}");
        assert_eq!(srv.refused.malformed.load(Ordering::Relaxed), 3);
        assert_eq!(srv.refused.too_large.load(Ordering::Relaxed), 1);
        // Counted for /diagnostics too.
        assert_eq!(qos::zenoh_too_large(), too_large_before + 1);
        let r = call(
            &router,
            &srv.key,
            cdr_bytes(&EmptyRequest::default()).unwrap(),
            Some(request(44)),
        );
        let a =
            Attachment::decode(&r[0].result().unwrap().attachment().unwrap().to_bytes()).unwrap();
        assert_eq!(a.sequence, 44);
        drop(srv);
        node.close();
        router.close().wait().unwrap();
    }
}
