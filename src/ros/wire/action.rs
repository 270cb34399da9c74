//! An action server on the five endpoints ros2-client makes for an action (the `send_goal`,
//! `cancel_goal` and `get_result` services, the `feedback` and `status` topics), keeping the
//! goals the way rcl's action server does, with bounds:
//!
//! - every request is answered as soon as it is taken, and none waits for another: a goal is
//!   accepted or rejected by its owner at once ([`Event::Goal`]); a cancel is answered with
//!   rcl's return codes; a `get_result` for a goal that has ended is answered with its status
//!   and result, for a goal that has not with them once it ends, and for a goal this server does
//!   not know (never accepted, rejected, or no longer kept) at once with `STATUS_UNKNOWN` and an
//!   empty result, as rclcpp and rclpy answer it;
//! - what is kept: per accepted goal its id, acceptance stamp and status; per goal that has not
//!   ended at most [`RESULT_WAITERS`] `get_result` requests (more are answered at once with
//!   `STATUS_UNKNOWN`); per ended goal its result, for [`RESULT_KEPT`] after it ended (rcl's
//!   default `result_timeout`) and for at most [`ENDED_KEPT`] ended goals, the oldest ended
//!   going first. A rejected goal and a request for an unknown goal leave nothing behind.
//!   How many goals run at once is the owner's choice (the autotune takes one).
//! - the status topic (transient local) carries every goal kept, and is published on every
//!   change: acceptance, execution, cancel, end, and a result no longer kept.
//!
//! ros2-client's own `AsyncActionServer` reads the `get_result` requests only while it sends a
//! result: its owner cannot take a goal while it waits for the client of the last one to ask,
//! and the requests for other goals it reads meanwhile are kept without bound. This server uses
//! ros2-client for the endpoints only (their names, types and QoS, and so their type hashes,
//! are ros2-client's), and keeps the goals in [`GoalTable`], which is sans-IO and tested here.

use log::{debug, warn};
use ros2_client::action::{
    ActionServer as Endpoints, CancelGoalRequest, CancelGoalResponse, GetResultRequest,
    GetResultResponse, GoalEndStatus, GoalId, GoalInfo, GoalStatusEnum, SendGoalRequest,
    SendGoalResponse,
};
use ros2_client::action_msgs::{CancelGoalResponseEnum, GoalStatus, GoalStatusArray};
use ros2_client::builtin_interfaces::Time;
use ros2_client::{Message, RmwRequestId};
use serde::Serialize;
use std::future::Future;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

/// How long the result of an ended goal is kept for its client to ask for it: rcl's and
/// rclpy's default `result_timeout`, 15 minutes.
pub const RESULT_KEPT: Duration = Duration::from_secs(900);
/// How many ended goals an action server keeps at most; beyond, the one that ended first goes
/// (its `get_result` is then answered with `STATUS_UNKNOWN`).
pub const ENDED_KEPT: usize = 16;
/// How many `get_result` requests wait for one goal that has not ended, at most; a request
/// beyond is answered at once with `STATUS_UNKNOWN`.
pub const RESULT_WAITERS: usize = 16;

/// One goal that was accepted: its id and acceptance stamp, its status, and once it ended,
/// when and its result; until then the `get_result` requests waiting for it (`Q`: a request
/// id).
#[derive(Debug)]
struct Goal<R, Q> {
    info: GoalInfo,
    status: GoalStatusEnum,
    ended: Option<(Instant, R)>,
    waiting: Vec<Q>,
}

/// What becomes of a `get_result` request.
#[derive(Debug, PartialEq)]
pub enum ResultAnswer<R, Q> {
    /// Answer `Q` now with this status and result: the goal has ended.
    Now(Q, GoalStatusEnum, R),
    /// Answer `Q` now with `STATUS_UNKNOWN`: no such goal is kept.
    Unknown(Q),
    /// Answer `Q` now with `STATUS_UNKNOWN`: [`RESULT_WAITERS`] requests wait for the goal
    /// already.
    Full(Q),
    /// Kept: answered when the goal ends.
    Waiting,
}

/// The goals of one action server, as rcl keeps them (`rcl_action_server_t`'s goal handles and
/// `result_timeout`), with the bounds of the module's documentation. No I/O and no clock: the
/// caller passes the time.
#[derive(Debug)]
pub struct GoalTable<R, Q> {
    /// In the order they were accepted.
    goals: Vec<Goal<R, Q>>,
}

impl<R, Q> Default for GoalTable<R, Q> {
    fn default() -> Self {
        GoalTable { goals: Vec::new() }
    }
}

fn end_status(s: GoalEndStatus) -> GoalStatusEnum {
    match s {
        GoalEndStatus::Succeeded => GoalStatusEnum::Succeeded,
        GoalEndStatus::Aborted => GoalStatusEnum::Aborted,
        GoalEndStatus::Canceled => GoalStatusEnum::Canceled,
    }
}

impl<R: Clone, Q> GoalTable<R, Q> {
    fn find(&mut self, id: &GoalId) -> Option<&mut Goal<R, Q>> {
        self.goals.iter_mut().find(|g| g.info.goal_id == *id)
    }

    /// Whether a goal with `id` is kept (accepted, and not ended longer than it is kept).
    pub fn contains(&self, id: &GoalId) -> bool {
        self.goals.iter().any(|g| g.info.goal_id == *id)
    }

    /// How many goals are kept.
    pub fn len(&self) -> usize {
        self.goals.len()
    }

    /// Whether no goal is kept.
    pub fn is_empty(&self) -> bool {
        self.goals.is_empty()
    }

    /// Records the goal `id` as accepted with `stamp`; false (and nothing changes) when a goal
    /// with that id is kept already.
    pub fn accept(&mut self, id: GoalId, stamp: Time) -> bool {
        if self.contains(&id) {
            return false;
        }
        self.goals.push(Goal {
            info: GoalInfo { goal_id: id, stamp },
            status: GoalStatusEnum::Accepted,
            ended: None,
            waiting: Vec::new(),
        });
        true
    }

    /// An accepted goal starts executing; false unless it was accepted and nothing more.
    pub fn execute(&mut self, id: &GoalId) -> bool {
        match self.find(id) {
            Some(g) if g.status == GoalStatusEnum::Accepted => {
                g.status = GoalStatusEnum::Executing;
                true
            }
            _ => false,
        }
    }

    /// Answers a cancel request as `rcl_action_process_cancel_request` does, and marks the
    /// goals it names as canceling: a goal id alone (stamp zero) names that goal
    /// (`ERROR_UNKNOWN_GOAL_ID` when it is not kept, `ERROR_GOAL_TERMINATED` when it has
    /// ended); both zero name every goal that has not ended; a stamp names every goal accepted
    /// at or before it, and the goal id besides. A goal already canceling is listed again.
    pub fn cancel(&mut self, req: &GoalInfo) -> CancelGoalResponse {
        let answer = |return_code, goals_canceling| CancelGoalResponse {
            return_code,
            goals_canceling,
        };
        let stamp = req.stamp.to_nanos();
        if req.goal_id != GoalId::ZERO && stamp == 0 {
            return match self.find(&req.goal_id) {
                None => answer(CancelGoalResponseEnum::UnknownGoal, Vec::new()),
                Some(g) if g.ended.is_some() => {
                    answer(CancelGoalResponseEnum::GoalTerminated, Vec::new())
                }
                Some(g) => {
                    g.status = GoalStatusEnum::Canceling;
                    answer(CancelGoalResponseEnum::None, vec![g.info.clone()])
                }
            };
        }
        let until = if req.goal_id == GoalId::ZERO && stamp == 0 {
            i64::MAX
        } else {
            stamp
        };
        let canceling = self
            .goals
            .iter_mut()
            .filter(|g| g.ended.is_none())
            .filter(|g| g.info.stamp.to_nanos() <= until || g.info.goal_id == req.goal_id)
            .map(|g| {
                g.status = GoalStatusEnum::Canceling;
                g.info.clone()
            })
            .collect();
        answer(CancelGoalResponseEnum::None, canceling)
    }

    /// What becomes of the `get_result` request `q` for the goal `id`.
    pub fn result(&mut self, id: &GoalId, q: Q) -> ResultAnswer<R, Q> {
        match self.find(id) {
            None => ResultAnswer::Unknown(q),
            Some(Goal {
                status,
                ended: Some((_, r)),
                ..
            }) => ResultAnswer::Now(q, *status, r.clone()),
            Some(g) if g.waiting.len() >= RESULT_WAITERS => ResultAnswer::Full(q),
            Some(g) => {
                g.waiting.push(q);
                ResultAnswer::Waiting
            }
        }
    }

    /// The goal `id` ended at `now` with `status` and `result`: returns the requests waiting for
    /// its result (to be answered with them). Beyond [`ENDED_KEPT`] ended goals, the one that
    /// ended first is no longer kept. A goal not kept or already ended is left as it is.
    pub fn end(&mut self, id: &GoalId, status: GoalEndStatus, result: R, now: Instant) -> Vec<Q> {
        let Some(g) = self.find(id).filter(|g| g.ended.is_none()) else {
            return Vec::new();
        };
        g.status = end_status(status);
        g.ended = Some((now, result));
        let waiting = std::mem::take(&mut g.waiting);
        while self.goals.iter().filter(|g| g.ended.is_some()).count() > ENDED_KEPT {
            let first = self
                .goals
                .iter()
                .enumerate()
                .filter_map(|(i, g)| g.ended.as_ref().map(|(t, _)| (*t, i)))
                .min();
            if let Some((_, i)) = first {
                self.goals.remove(i);
            }
        }
        waiting
    }

    /// Drops the goals that ended [`RESULT_KEPT`] or longer before `now`; true if any went.
    pub fn expire(&mut self, now: Instant) -> bool {
        let before = self.goals.len();
        self.goals.retain(|g| {
            g.ended
                .as_ref()
                .is_none_or(|(t, _)| now.saturating_duration_since(*t) < RESULT_KEPT)
        });
        self.goals.len() != before
    }

    /// When the next ended goal stops being kept, if any has ended.
    pub fn next_expiry(&self) -> Option<Instant> {
        self.goals
            .iter()
            .filter_map(|g| g.ended.as_ref().map(|(t, _)| *t + RESULT_KEPT))
            .min()
    }

    /// The status of every goal kept, in the order they were accepted.
    pub fn statuses(&self) -> GoalStatusArray {
        GoalStatusArray {
            status_list: self
                .goals
                .iter()
                .map(|g| GoalStatus {
                    goal_info: g.info.clone(),
                    status: g.status,
                })
                .collect(),
        }
    }
}

/// The goal and stamp a cancel request names. ros2-client keeps the request's one field to
/// itself; its serde form (the same data the request arrived as) gives it back. `None` if that
/// fails, which the type's derived serde implementations do not let happen.
fn cancel_target(req: &CancelGoalRequest) -> Option<GoalInfo> {
    #[derive(serde::Deserialize)]
    struct Fields {
        goal_info: GoalInfo,
    }
    serde_json::to_value(req)
        .and_then(serde_json::from_value::<Fields>)
        .ok()
        .map(|f| f.goal_info)
}

/// A goal request waiting for its owner's answer: [`ActionServer::accept`] or
/// [`ActionServer::reject`], which answer the client.
#[must_use = "a goal request is answered by accept or reject"]
#[derive(Debug)]
pub struct GoalRequest<G> {
    /// The goal's id, chosen by the client.
    pub id: GoalId,
    /// What the goal asks.
    pub goal: G,
    req: Request,
}

/// What the owner of an action server is told.
#[derive(Debug)]
pub enum Event<G> {
    /// A new goal, to be accepted or rejected at once.
    Goal(GoalRequest<G>),
    /// The client canceled these goals (their status is canceling now, and the cancel was
    /// answered); each still ends with [`ActionServer::end`].
    Cancel(Vec<GoalId>),
}

/// A request taken from one of the action's services, by which it is answered.
#[derive(Debug)]
pub enum Request {
    /// On DDS: the request's id.
    Dds(RmwRequestId),
    /// On Zenoh: the query itself.
    #[cfg(feature = "zenoh")]
    Zenoh(crate::ros::wire::zenoh_srv::Responder),
}

/// An action's five endpoints on the middleware in use.
pub enum ActionEndpoints<G, R, F>
where
    G: Message + Clone,
    R: Message + Clone,
    F: Message,
{
    /// ros2-client's, on DDS.
    Dds(Box<Endpoints<G, R, F>>),
    /// On Zenoh, as rmw_zenoh makes them.
    #[cfg(feature = "zenoh")]
    Zenoh(Box<zenoh_action::ZenohActionEndpoints<G, F>>),
}

/// One request taken from an endpoint (an unreadable one: why, as text).
enum Incoming<G> {
    Goal(Result<(Request, SendGoalRequest<G>), String>),
    Cancel(Result<(Request, CancelGoalRequest), String>),
    Result(Result<(Request, GetResultRequest), String>),
}

/// A request of one middleware answered through the other's endpoints: never made, as an
/// action's requests and endpoints come from one [`ActionEndpoints`].
#[cfg(feature = "zenoh")]
const OTHER_MIDDLEWARE: &str = "a request of another middleware";

/// Polls `f` once. The futures of ros2-client's `async_receive_request` keep nothing between
/// polls: the reader holds the waker, and a request taken is returned by the same poll.
fn poll_once<T>(f: impl Future<Output = T>, cx: &mut Context<'_>) -> Poll<T> {
    std::pin::pin!(f).poll(cx)
}

/// The next request on any of ros2-client's three services, looking at `first` first.
async fn next_dds<G, R, F>(ep: &mut Endpoints<G, R, F>, first: usize) -> Incoming<G>
where
    G: Message + Clone + 'static,
    R: Message + Clone + 'static,
    F: Message + 'static,
{
    fn ours<T>(r: ros2_client::ReadResult<(RmwRequestId, T)>) -> Result<(Request, T), String> {
        r.map(|(id, t)| (Request::Dds(id), t))
            .map_err(|e| e.to_string())
    }
    std::future::poll_fn(|cx| {
        for k in 0..3 {
            let got = match (first + k) % 3 {
                0 => poll_once(ep.goal_server().async_receive_request(), cx)
                    .map(|r| Incoming::Goal(ours(r))),
                1 => poll_once(ep.cancel_server().async_receive_request(), cx)
                    .map(|r| Incoming::Cancel(ours(r))),
                _ => poll_once(ep.result_server().async_receive_request(), cx)
                    .map(|r| Incoming::Result(ours(r))),
            };
            if got.is_ready() {
                return got;
            }
        }
        Poll::Pending
    })
    .await
}

/// An action server: the action's endpoints ([`ActionEndpoints`]), and the goals
/// ([`GoalTable`]).
pub struct ActionServer<G, R, F>
where
    G: Message + Clone,
    R: Message + Clone,
    F: Message,
{
    name: String,
    ep: ActionEndpoints<G, R, F>,
    goals: GoalTable<R, Request>,
    /// Which endpoint is looked at first by the next [`ActionServer::next`], so that a flood
    /// on one cannot starve the others.
    turn: usize,
}

impl<G, R, F> ActionServer<G, R, F>
where
    G: Message + Clone + 'static,
    R: Message + Clone + Default + 'static,
    F: Message + 'static,
{
    /// The server of `ep`, named `name` in the log (`pw01: autotune`).
    pub fn new(name: String, ep: ActionEndpoints<G, R, F>) -> Self {
        ActionServer {
            name,
            ep,
            goals: GoalTable::default(),
            turn: 0,
        }
    }

    /// The goals kept.
    pub fn goals(&self) -> &GoalTable<R, Request> {
        &self.goals
    }

    /// Waits for the next request on any of the three services and answers it if it can: a
    /// cancel or a `get_result` at once (a `get_result` for a goal that has not ended is kept,
    /// bounded), a goal whose id is kept already with a rejection. Returns what the owner must
    /// act on: a new goal, or goals canceled. Cancel-safe: a request taken is handled before
    /// this returns.
    pub async fn next(&mut self) -> Option<Event<G>> {
        let first = self.turn;
        self.turn = (self.turn + 1) % 3;
        let incoming = match &mut self.ep {
            ActionEndpoints::Dds(ep) => next_dds(ep, first).await,
            #[cfg(feature = "zenoh")]
            ActionEndpoints::Zenoh(ep) => ep.next(first).await,
        };
        self.handle(incoming)
    }

    fn handle(&mut self, incoming: Incoming<G>) -> Option<Event<G>> {
        let name = &self.name;
        match incoming {
            Incoming::Goal(Ok((req, SendGoalRequest { goal_id, goal }))) => {
                if self.goals.contains(&goal_id) {
                    warn!("{name}: goal {goal_id:?} rejected: a goal with this id is kept");
                    self.answer_goal(req, false, Time::ZERO);
                    return None;
                }
                Some(Event::Goal(GoalRequest {
                    id: goal_id,
                    goal,
                    req,
                }))
            }
            Incoming::Cancel(Ok((req, cancel))) => {
                let response = match cancel_target(&cancel) {
                    Some(info) => self.goals.cancel(&info),
                    None => {
                        warn!("{name}: a cancel request that cannot be read was rejected");
                        CancelGoalResponse {
                            return_code: CancelGoalResponseEnum::Rejected,
                            goals_canceling: Vec::new(),
                        }
                    }
                };
                let ids: Vec<GoalId> = response.goals_canceling.iter().map(|g| g.goal_id).collect();
                if !ids.is_empty() {
                    self.publish_statuses();
                }
                self.answer_cancel(req, response);
                (!ids.is_empty()).then_some(Event::Cancel(ids))
            }
            Incoming::Result(Ok((req, GetResultRequest { goal_id }))) => {
                match self.goals.result(&goal_id, req) {
                    ResultAnswer::Now(q, status, result) => self.answer_result(q, status, result),
                    ResultAnswer::Unknown(q) => {
                        debug!("{name}: result of unknown goal {goal_id:?} asked");
                        self.answer_result(q, GoalStatusEnum::Unknown, R::default());
                    }
                    ResultAnswer::Full(q) => {
                        warn!(
                            "{name}: {RESULT_WAITERS} requests wait for the result of goal \
                             {goal_id:?} already; one more answered with an unknown status"
                        );
                        self.answer_result(q, GoalStatusEnum::Unknown, R::default());
                    }
                    ResultAnswer::Waiting => {}
                }
                None
            }
            Incoming::Goal(Err(e)) => {
                warn!("{name}: unreadable goal request: {e}");
                None
            }
            Incoming::Cancel(Err(e)) => {
                warn!("{name}: unreadable cancel request: {e}");
                None
            }
            Incoming::Result(Err(e)) => {
                warn!("{name}: unreadable result request: {e}");
                None
            }
        }
    }

    /// Answers `req` with `resp`: on DDS through `send` with the request's id, on Zenoh as the
    /// query's reply. A failure is warned about as "cannot `what`".
    fn answer<T: Serialize, E: std::fmt::Display>(
        &self,
        req: Request,
        resp: T,
        what: &str,
        send: impl FnOnce(&Endpoints<G, R, F>, RmwRequestId, T) -> Result<(), E>,
    ) {
        let sent = match (&self.ep, req) {
            (ActionEndpoints::Dds(ep), Request::Dds(id)) => {
                send(ep, id, resp).map_err(|e| e.to_string())
            }
            #[cfg(feature = "zenoh")]
            (ActionEndpoints::Zenoh(_), Request::Zenoh(r)) => {
                r.reply(&resp);
                Ok(())
            }
            #[cfg(feature = "zenoh")]
            _ => Err(OTHER_MIDDLEWARE.to_string()),
        };
        if let Err(e) = sent {
            warn!("{}: cannot {what}: {e}", self.name);
        }
    }

    fn answer_goal(&self, req: Request, accepted: bool, stamp: Time) {
        let resp = SendGoalResponse { accepted, stamp };
        self.answer(req, resp, "answer a goal request", |ep, id, r| {
            ep.send_goal_response(id, r)
        });
    }

    fn answer_cancel(&self, req: Request, resp: CancelGoalResponse) {
        self.answer(req, resp, "answer a cancel", |ep, id, r| {
            ep.send_cancel_response(id, r)
        });
    }

    fn answer_result(&self, req: Request, status: GoalStatusEnum, result: R) {
        let resp = GetResultResponse { status, result };
        self.answer(req, resp, "send a result", |ep, id, r| {
            ep.send_result(id, r)
        });
    }

    fn publish_statuses(&self) {
        let statuses = self.goals.statuses();
        let sent = match &self.ep {
            ActionEndpoints::Dds(ep) => ep.send_goal_statuses(statuses).map_err(|e| e.to_string()),
            #[cfg(feature = "zenoh")]
            ActionEndpoints::Zenoh(ep) => ep.status.publish(&statuses).map_err(|e| e.to_string()),
        };
        if let Err(e) = sent {
            warn!("{}: cannot publish the goal statuses: {e}", self.name);
        }
    }

    /// Accepts the goal and answers its client; its status is accepted. Returns its id and
    /// what it asks.
    pub fn accept(&mut self, g: GoalRequest<G>) -> (GoalId, G) {
        let stamp = Time::now();
        // The id was not kept when the request was taken, and nothing is accepted in between.
        self.goals.accept(g.id, stamp);
        self.answer_goal(g.req, true, stamp);
        self.publish_statuses();
        (g.id, g.goal)
    }

    /// Rejects the goal and answers its client; `why` goes to the log (the answer has no room
    /// for it). Nothing of the goal is kept.
    pub fn reject(&mut self, g: GoalRequest<G>, why: &str) {
        warn!("{}: goal {:?} rejected: {why}", self.name, g.id);
        self.answer_goal(g.req, false, Time::ZERO);
    }

    /// The accepted goal `id` is executing.
    pub fn execute(&mut self, id: &GoalId) {
        if self.goals.execute(id) {
            self.publish_statuses();
        }
    }

    /// Publishes feedback of the goal `id`.
    pub fn feedback(&self, id: GoalId, feedback: F) {
        let sent = match &self.ep {
            ActionEndpoints::Dds(ep) => ep.send_feedback(id, feedback).map_err(|e| e.to_string()),
            #[cfg(feature = "zenoh")]
            ActionEndpoints::Zenoh(ep) => ep
                .feedback
                .publish(&ros2_client::action::FeedbackMessage {
                    goal_id: id,
                    feedback,
                })
                .map_err(|e| e.to_string()),
        };
        if let Err(e) = sent {
            warn!("{}: cannot publish feedback: {e}", self.name);
        }
    }

    /// The goal `id` ended with `status` and `result`: the requests waiting for its result are
    /// answered, and it is kept for later ones (see [`GoalTable::end`]).
    pub fn end(&mut self, id: &GoalId, status: GoalEndStatus, result: R) {
        for q in self.goals.end(id, status, result.clone(), Instant::now()) {
            self.answer_result(q, end_status(status), result.clone());
        }
        self.publish_statuses();
    }

    /// Drops the results kept [`RESULT_KEPT`] or longer, and publishes the statuses if any
    /// went. Returns when to call it next, if any result is kept.
    pub fn expire(&mut self) -> Option<Instant> {
        if self.goals.expire(Instant::now()) {
            self.publish_statuses();
        }
        self.goals.next_expiry()
    }
}

/// The action's endpoints on Zenoh, as rmw_zenoh makes an action: three services and two
/// topics under `<action>/_action/`, with the types rosidl gives an action.
#[cfg(feature = "zenoh")]
pub mod zenoh_action {
    use super::{Incoming, Request};
    use crate::ros::wire::zenoh_pub::{PublisherError, ZenohPublisher};
    use crate::ros::wire::zenoh_session::NodeSession;
    use crate::ros::wire::zenoh_srv::{ServiceError, ZenohRequests};
    use ros2_client::action::{
        ActionServerQosPolicies, CancelGoalRequest, FeedbackMessage, GetResultRequest,
        SendGoalRequest,
    };
    use ros2_client::action_msgs::GoalStatusArray;
    use ros2_client::Message;
    use std::collections::BTreeMap;
    use std::sync::Arc;
    use tokio::sync::Notify;

    /// Why the action's endpoints cannot be made.
    #[derive(Debug, thiserror::Error)]
    pub enum ActionError {
        /// One of its services.
        #[error(transparent)]
        Service(#[from] ServiceError),
        /// One of its topics.
        #[error(transparent)]
        Topic(#[from] PublisherError),
    }

    /// The three services' requests (one notification for all) and the two publishers.
    pub struct ZenohActionEndpoints<G, F> {
        goal: ZenohRequests<SendGoalRequest<G>>,
        cancel: ZenohRequests<CancelGoalRequest>,
        result: ZenohRequests<GetResultRequest>,
        ready: Arc<Notify>,
        /// `<action>/_action/feedback`.
        pub feedback: ZenohPublisher<FeedbackMessage<F>>,
        /// `<action>/_action/status` (transient local: late joiners get the goals kept).
        pub status: ZenohPublisher<GoalStatusArray>,
    }

    impl<G: Message, F: Message> ZenohActionEndpoints<G, F> {
        /// The endpoints of the fully qualified action `action` of type
        /// `<package>/action/<name>` (`ros_type`) with `qos`.
        pub fn new(
            node: &NodeSession,
            action: &str,
            ros_type: &str,
            qos: ActionServerQosPolicies,
            hashes: &BTreeMap<String, String>,
        ) -> Result<Self, ActionError> {
            let ready = Arc::new(Notify::new());
            let service = |name: &str| format!("{action}/_action/{name}");
            Ok(ZenohActionEndpoints {
                goal: ZenohRequests::declare(
                    node,
                    &service("send_goal"),
                    &format!("{ros_type}_SendGoal"),
                    qos.goal_service,
                    hashes,
                    ready.clone(),
                )?,
                cancel: ZenohRequests::declare(
                    node,
                    &service("cancel_goal"),
                    "action_msgs/srv/CancelGoal",
                    qos.cancel_service,
                    hashes,
                    ready.clone(),
                )?,
                result: ZenohRequests::declare(
                    node,
                    &service("get_result"),
                    &format!("{ros_type}_GetResult"),
                    qos.result_service,
                    hashes,
                    ready.clone(),
                )?,
                ready,
                feedback: ZenohPublisher::of_type(
                    node,
                    &service("feedback"),
                    &format!("{ros_type}_FeedbackMessage"),
                    qos.feedback_publisher,
                    hashes,
                )?,
                status: ZenohPublisher::of_type(
                    node,
                    &service("status"),
                    "action_msgs/msg/GoalStatusArray",
                    qos.status_publisher,
                    hashes,
                )?,
            })
        }

        /// The next readable request of the three services, looking at `first` first
        /// (0 goal, 1 cancel, 2 result). Cancel-safe: a request taken is returned by the same
        /// poll.
        pub(super) async fn next(&self, first: usize) -> Incoming<G> {
            loop {
                let notified = self.ready.notified();
                let mut notified = std::pin::pin!(notified);
                notified.as_mut().enable();
                for k in 0..3 {
                    match (first + k) % 3 {
                        0 => {
                            if let Some((r, q)) = self.goal.try_take() {
                                return Incoming::Goal(Ok((Request::Zenoh(r), q)));
                            }
                        }
                        1 => {
                            if let Some((r, q)) = self.cancel.try_take() {
                                return Incoming::Cancel(Ok((Request::Zenoh(r), q)));
                            }
                        }
                        _ => {
                            if let Some((r, q)) = self.result.try_take() {
                                return Incoming::Result(Ok((Request::Zenoh(r), q)));
                            }
                        }
                    }
                }
                notified.await;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    type Table = GoalTable<u32, u32>;

    fn stamp(s: i64) -> Time {
        Time::from_nanos(s * 1_000_000_000)
    }

    fn status_of(t: &Table, id: &GoalId) -> Option<GoalStatusEnum> {
        t.statuses()
            .status_list
            .iter()
            .find(|s| s.goal_info.goal_id == *id)
            .map(|s| s.status)
    }

    #[test]
    fn an_unknown_goal_is_answered_at_once_and_leaves_nothing() {
        let mut t = Table::default();
        for q in 0..100_000 {
            assert_eq!(t.result(&GoalId::new_random(), q), ResultAnswer::Unknown(q));
        }
        assert!(t.is_empty());
        assert_eq!(
            t.cancel(&GoalInfo {
                goal_id: GoalId::new_random(),
                stamp: Time::ZERO
            })
            .return_code,
            CancelGoalResponseEnum::UnknownGoal
        );
        assert!(t.is_empty());
    }

    #[test]
    fn a_result_asked_before_the_end_is_answered_at_the_end_and_kept_after() {
        let (mut t, t0) = (Table::default(), Instant::now());
        let id = GoalId::new_random();
        assert!(t.accept(id, stamp(1)));
        assert!(!t.accept(id, stamp(2)), "an id kept is not accepted twice");
        assert!(t.execute(&id));
        assert_eq!(status_of(&t, &id), Some(GoalStatusEnum::Executing));
        assert_eq!(t.result(&id, 7), ResultAnswer::Waiting);
        assert_eq!(t.result(&id, 8), ResultAnswer::Waiting);
        assert_eq!(t.end(&id, GoalEndStatus::Succeeded, 42, t0), vec![7, 8]);
        assert_eq!(
            t.end(&id, GoalEndStatus::Aborted, 0, t0),
            Vec::<u32>::new(),
            "an ended goal stays as it ended"
        );
        assert_eq!(status_of(&t, &id), Some(GoalStatusEnum::Succeeded));
        assert_eq!(
            t.result(&id, 9),
            ResultAnswer::Now(9, GoalStatusEnum::Succeeded, 42)
        );
        // Kept for RESULT_KEPT, then gone: unknown.
        assert!(!t.expire(t0 + RESULT_KEPT - Duration::from_millis(1)));
        assert_eq!(t.next_expiry(), Some(t0 + RESULT_KEPT));
        assert!(t.expire(t0 + RESULT_KEPT));
        assert_eq!(t.result(&id, 10), ResultAnswer::Unknown(10));
        assert_eq!(t.next_expiry(), None);
    }

    #[test]
    fn the_requests_waiting_for_one_goal_are_bounded() {
        let mut t = Table::default();
        let id = GoalId::new_random();
        t.accept(id, stamp(1));
        for q in 0..RESULT_WAITERS as u32 {
            assert_eq!(t.result(&id, q), ResultAnswer::Waiting);
        }
        assert_eq!(t.result(&id, 99), ResultAnswer::Full(99));
        let waiting = t.end(&id, GoalEndStatus::Aborted, 1, Instant::now());
        assert_eq!(waiting, (0..RESULT_WAITERS as u32).collect::<Vec<_>>());
    }

    #[test]
    fn ended_goals_are_bounded_the_first_ended_going_first() {
        let (mut t, t0) = (Table::default(), Instant::now());
        let ids: Vec<GoalId> = (0..ENDED_KEPT + 5).map(|_| GoalId::new_random()).collect();
        for (i, id) in ids.iter().enumerate() {
            t.accept(*id, stamp(i as i64 + 1));
        }
        // A goal that has not ended is never dropped for the bound.
        let running = ids[0];
        for (i, id) in ids.iter().enumerate().skip(1) {
            let at = t0 + Duration::from_secs(i as u64);
            t.end(id, GoalEndStatus::Aborted, i as u32, at);
        }
        assert_eq!(t.len(), ENDED_KEPT + 1);
        assert!(t.contains(&running));
        for id in &ids[1..5] {
            assert!(!t.contains(id), "the first ended go first");
        }
        for id in &ids[5..] {
            assert!(t.contains(id));
        }
        assert_eq!(t.statuses().status_list.len(), ENDED_KEPT + 1);
    }

    #[test]
    fn cancel_follows_rcl() {
        let mut t = Table::default();
        let (a, b, c) = (
            GoalId::new_random(),
            GoalId::new_random(),
            GoalId::new_random(),
        );
        t.accept(a, stamp(10));
        t.accept(b, stamp(20));
        t.accept(c, stamp(30));
        t.end(&c, GoalEndStatus::Succeeded, 0, Instant::now());
        let by = |goal_id, stamp| GoalInfo { goal_id, stamp };
        let ids = |r: &CancelGoalResponse| {
            r.goals_canceling
                .iter()
                .map(|g| g.goal_id)
                .collect::<Vec<_>>()
        };
        // An ended goal by id: terminated; nothing changes.
        let r = t.cancel(&by(c, Time::ZERO));
        assert_eq!(r.return_code, CancelGoalResponseEnum::GoalTerminated);
        assert!(r.goals_canceling.is_empty());
        // By stamp: the goals accepted at or before it that have not ended.
        let r = t.cancel(&by(GoalId::ZERO, stamp(10)));
        assert_eq!(
            (r.return_code, ids(&r)),
            (CancelGoalResponseEnum::None, vec![a])
        );
        assert_eq!(r.goals_canceling[0].stamp, stamp(10));
        assert_eq!(status_of(&t, &a), Some(GoalStatusEnum::Canceling));
        assert_eq!(status_of(&t, &b), Some(GoalStatusEnum::Accepted));
        // By id: that goal; a canceling goal is listed again.
        let r = t.cancel(&by(b, Time::ZERO));
        assert_eq!(
            (r.return_code, ids(&r)),
            (CancelGoalResponseEnum::None, vec![b])
        );
        let r = t.cancel(&by(b, Time::ZERO));
        assert_eq!(ids(&r), vec![b]);
        // Both zero: every goal that has not ended.
        let r = t.cancel(&by(GoalId::ZERO, Time::ZERO));
        assert_eq!(
            (r.return_code, ids(&r)),
            (CancelGoalResponseEnum::None, vec![a, b])
        );
        assert_eq!(status_of(&t, &c), Some(GoalStatusEnum::Succeeded));
        // Stamp and id: the goals up to the stamp and that id; none at all is no error.
        let mut u = Table::default();
        let (d, e, f) = (
            GoalId::new_random(),
            GoalId::new_random(),
            GoalId::new_random(),
        );
        u.accept(d, stamp(10));
        u.accept(e, stamp(20));
        u.accept(f, stamp(30));
        let r = u.cancel(&by(f, stamp(10)));
        assert_eq!(ids(&r), vec![d, f]);
        let r = u.cancel(&by(GoalId::ZERO, stamp(5)));
        assert_eq!(
            (r.return_code, ids(&r)),
            (CancelGoalResponseEnum::None, vec![])
        );
    }

    #[test]
    fn a_cancel_request_is_read_back_whole() {
        let id = GoalId::new_random();
        let json = serde_json::json!({
            "goal_info": {
                "goal_id": { "uuid": id.uuid.as_bytes() },
                "stamp": { "sec": 1_700_000_000, "nanosec": 123_456_789 },
            }
        });
        let req: CancelGoalRequest = serde_json::from_value(json).unwrap();
        let info = cancel_target(&req).expect("readable");
        assert_eq!(info.goal_id, id);
        assert_eq!(info.stamp.to_nanos(), 1_700_000_000_123_456_789);
    }
}
