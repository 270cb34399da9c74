//! The node's endpoints, created with its identity and remapping rules: topics, publishers,
//! subscriptions with the task that hands each received message to a callback, and services
//! with the task that answers each request ([`ServiceMaker::serve`], the one place a service
//! is created).

use crate::ros::config::args::Remap;
use crate::ros::config::names::{to_ros_name, NameError, NameKind, NodeIdentity};
use crate::ros::interface::msg::RosMessage;
use crate::ros::interface::qos;
use crate::ros::wire::action::ActionEndpoints;
use crate::ros::wire::mw::Publisher;
use futures::StreamExt;
use log::{debug, warn};
use ros2_client::{
    Message, Node, QosProfile, Server, ServiceMapping, ServiceTypeName, Subscription,
};
use tokio::task::JoinHandle;

/// Why an endpoint (a topic, publisher, subscription or service) of the node cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum EndpointError {
    /// Its name does not resolve (e.g. a bad remap).
    #[error(transparent)]
    Name(#[from] NameError),
    /// Zenoh refused to create it.
    #[cfg(feature = "zenoh")]
    #[error("ROS on Zenoh: cannot create {what}: {why}")]
    Zenoh {
        /// What: `publisher /pwm_actuator/pw01/edges`, ...
        what: String,
        /// Why.
        why: String,
    },
    /// DDS refused to create it.
    #[error("ROS: cannot create {what}")]
    Create {
        /// What: `topic /pwm_actuator/pw01/duty`, `service /pwm_actuator/reset_estop`, ...
        what: String,
        /// Why (ros2-client's error).
        #[source]
        source: ros2_client::CreateError,
    },
}

/// Maps a creation error of ros2-client to [`EndpointError::Create`] naming `what`.
pub(crate) fn create_err(
    what: impl Into<String>,
) -> impl FnOnce(ros2_client::CreateError) -> EndpointError {
    let what = what.into();
    move |source| EndpointError::Create { what, source }
}

/// Resolves a topic name of this node.
pub(crate) fn topic(
    node: &Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    type_name: ros2_client::MessageTypeName,
    qos: &QosProfile,
) -> Result<(String, rustdds::Topic), EndpointError> {
    let full = id.resolve(name, NameKind::Topic, remaps)?;
    let t = node
        .create_topic(&to_ros_name(&full)?, type_name, qos)
        .map_err(create_err(format!("topic {full}")))?;
    Ok((full, t))
}

pub(crate) fn publisher<M: RosMessage>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    qos: QosProfile,
) -> Result<Publisher<M>, EndpointError> {
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("publishing {full}");
    node.create_publisher(&t, Some(qos))
        .map(Publisher::Dds)
        .map_err(create_err(format!("publisher {full}")))
}

pub(crate) fn subscription<M: RosMessage + 'static>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
) -> Result<(String, Subscription<M>), EndpointError> {
    subscription_with(node, id, remaps, name, qos::commands())
}

/// A subscription to `name` with `qos`.
pub(crate) fn subscription_with<M: RosMessage + 'static>(
    node: &mut Node,
    id: &NodeIdentity,
    remaps: &[Remap],
    name: &str,
    qos: QosProfile,
) -> Result<(String, Subscription<M>), EndpointError> {
    let (full, t) = topic(node, id, remaps, name, M::type_name(), &qos)?;
    debug!("subscribing {full}");
    let s = node
        .create_subscription(&t, Some(qos))
        .map_err(create_err(format!("subscription {full}")))?;
    Ok((full, s))
}

/// Runs `on_msg` for every message of `sub`, until the task is aborted: [`listen_async`]'s loop
/// with a callback that is done when it returns.
pub(crate) fn listen<M, F>(full: String, sub: Subscription<M>, mut on_msg: F) -> JoinHandle<()>
where
    M: Message + Send + Sync + 'static,
    F: FnMut(M) + Send + 'static,
{
    listen_async(full, sub, move |m| {
        on_msg(m);
        std::future::ready(())
    })
}

/// Runs `on_msg` for every message of `sub`, awaiting each before taking the next (in order),
/// until the task is aborted: for a callback that awaits an answer of the output thread.
pub(crate) fn listen_async<M, F, Fut>(
    full: String,
    sub: Subscription<M>,
    mut on_msg: F,
) -> JoinHandle<()>
where
    M: Message + Send + Sync + 'static,
    F: FnMut(M) -> Fut + Send + 'static,
    Fut: std::future::Future<Output = ()> + Send,
{
    tokio::spawn(async move {
        let stream = sub.async_stream();
        futures::pin_mut!(stream);
        while let Some(r) = stream.next().await {
            match r {
                Ok((m, _info)) => on_msg(m).await,
                Err(e) => warn!("{full}: unreadable message: {e}"),
            }
        }
    })
}

/// The middleware the node's endpoints are made on: its DDS node, or its Zenoh session.
pub enum Mw<'a> {
    /// DDS: the ros2-client node.
    Dds(&'a mut Node),
    /// Zenoh: the session with the node's token, and the type hashes its keys carry.
    #[cfg(feature = "zenoh")]
    Zenoh(&'a crate::ros::wire::zenoh_session::ZenohNode),
}

impl Mw<'_> {
    /// The same middleware for a shorter borrow.
    pub fn reborrow(&mut self) -> Mw<'_> {
        match self {
            Mw::Dds(node) => Mw::Dds(node),
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => Mw::Zenoh(z),
        }
    }
}

/// Keeps a Zenoh endpoint (and its own task) until the returned task is aborted, as a DDS
/// endpoint lives in the task that listens on it.
#[cfg(feature = "zenoh")]
fn hold<T: Send + 'static>(endpoint: T) -> JoinHandle<()> {
    tokio::spawn(async move {
        let _endpoint = endpoint;
        std::future::pending::<()>().await
    })
}

/// A Zenoh endpoint's error as an [`EndpointError`] naming `what`.
#[cfg(feature = "zenoh")]
fn zenoh_err<E: std::fmt::Display>(what: String) -> impl FnOnce(E) -> EndpointError {
    move |e| EndpointError::Zenoh {
        what,
        why: e.to_string(),
    }
}

/// What every endpoint of the node is made with: the middleware, the node's identity and the
/// remapping rules. Each owner of a group of endpoints (a channel's topics, the e-stop, the
/// lifecycle, the parameter services, the reporter's publishers) makes them through this.
pub struct Endpoints<'a> {
    /// The middleware.
    pub mw: Mw<'a>,
    /// Its name and namespace.
    pub id: &'a NodeIdentity,
    /// The remapping rules.
    pub remaps: &'a [Remap],
}

impl Endpoints<'_> {
    /// A publisher of `name` (resolved as a node's topic name) with `qos`.
    pub fn publisher<M: RosMessage>(
        &mut self,
        name: &str,
        qos: QosProfile,
    ) -> Result<Publisher<M>, EndpointError> {
        match &mut self.mw {
            Mw::Dds(node) => publisher(node, self.id, self.remaps, name, qos),
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => {
                let full = self.id.resolve(name, NameKind::Topic, self.remaps)?;
                debug!("publishing {full} on Zenoh");
                crate::ros::wire::zenoh_pub::ZenohPublisher::new(&z.session, &full, qos, &z.hashes)
                    .map(Publisher::Zenoh)
                    .map_err(zenoh_err(format!("publisher {full}")))
            }
        }
    }

    /// A subscription of `name` with the commands' QoS, and the task that runs `on_msg` for
    /// every message until it is aborted.
    pub fn listen<M, F>(&mut self, name: &str, on_msg: F) -> Result<JoinHandle<()>, EndpointError>
    where
        M: RosMessage + Send + Sync + 'static,
        F: FnMut(M) + Send + 'static,
    {
        self.listen_with(name, qos::commands(), on_msg)
    }

    /// As [`Endpoints::listen`], but `on_msg` is async and awaited before the next message is
    /// taken: for a callback that awaits the output thread's acknowledgment of a safety input
    /// and must not hold an async worker meanwhile.
    pub fn listen_async<M, F, Fut>(
        &mut self,
        name: &str,
        on_msg: F,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        M: RosMessage + Send + Sync + 'static,
        F: FnMut(M) -> Fut + Send + 'static,
        Fut: std::future::Future<Output = ()> + Send,
    {
        match &mut self.mw {
            Mw::Dds(node) => {
                let (full, sub) = subscription::<M>(node, self.id, self.remaps, name)?;
                Ok(listen_async(full, sub, on_msg))
            }
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => {
                let full = self.id.resolve(name, NameKind::Topic, self.remaps)?;
                debug!("subscribing {full} on Zenoh");
                crate::ros::wire::zenoh_sub::ZenohSubscription::listen_async(
                    &z.session,
                    &full,
                    qos::commands(),
                    &z.hashes,
                    on_msg,
                )
                .map(hold)
                .map_err(zenoh_err(format!("subscription {full}")))
            }
        }
    }

    /// Subscribes to `name` with `qos` (a sensor's best effort) and hands each message to
    /// `on_msg` in a task.
    pub fn listen_with<M, F>(
        &mut self,
        name: &str,
        qos: QosProfile,
        on_msg: F,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        M: RosMessage + Send + Sync + 'static,
        F: FnMut(M) + Send + 'static,
    {
        match &mut self.mw {
            Mw::Dds(node) => {
                let (full, sub) = subscription_with::<M>(node, self.id, self.remaps, name, qos)?;
                Ok(listen(full, sub, on_msg))
            }
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => {
                let full = self.id.resolve(name, NameKind::Topic, self.remaps)?;
                debug!("subscribing {full} on Zenoh");
                crate::ros::wire::zenoh_sub::ZenohSubscription::listen(
                    &z.session, &full, qos, &z.hashes, on_msg,
                )
                .map(hold)
                .map_err(zenoh_err(format!("subscription {full}")))
            }
        }
    }

    /// The resolved name of the topic `name` (a node's topic name, remapped as the node's
    /// endpoints are), e.g. `~/pw01/edges` → `/pwm_actuator/pw01/edges`.
    pub fn topic_name(&self, name: &str) -> Result<String, EndpointError> {
        Ok(self.id.resolve(name, NameKind::Topic, self.remaps)?)
    }

    /// The service maker over the same node, identity and rules.
    pub fn services(&mut self) -> ServiceMaker<'_> {
        ServiceMaker {
            mw: self.mw.reborrow(),
            id: self.id,
            remaps: self.remaps,
        }
    }
}

/// A service request type: a message a server task can own.
pub trait Request: Message + Clone + Send + Sync + 'static {}
impl<T: Message + Clone + Send + Sync + 'static> Request for T {}

/// A service response type: a message a server task can send.
pub trait Response: Message + Send + Sync + 'static {}
impl<T: Message + Send + Sync + 'static> Response for T {}

/// What a node's services are created with: the middleware, the node's identity and remapping
/// rules.
pub struct ServiceMaker<'a> {
    /// The middleware.
    pub mw: Mw<'a>,
    /// Its name and namespace.
    pub id: &'a NodeIdentity,
    /// The remapping rules.
    pub remaps: &'a [Remap],
}

impl ServiceMaker<'_> {
    /// Creates the action server `name` (resolved as a node's service name, e.g.
    /// `~/pw01/autotune`) of type `package/action/type_name`, with ROS 2's default QoS for
    /// actions.
    pub fn action_server<G, R, F>(
        &mut self,
        name: &str,
        package: &str,
        type_name: &str,
    ) -> Result<ActionEndpoints<G, R, F>, EndpointError>
    where
        G: Message + Clone + 'static,
        R: Message + Clone + 'static,
        F: Message + 'static,
    {
        let full = self.id.resolve(name, NameKind::Service, self.remaps)?;
        debug!("action {full}");
        match &mut self.mw {
            Mw::Dds(node) => node
                .create_action_server(
                    ServiceMapping::Enhanced,
                    &to_ros_name(&full)?,
                    &ros2_client::ActionTypeName::new(package, type_name),
                    crate::ros::interface::qos::action_server(),
                )
                .map(|ep| ActionEndpoints::Dds(Box::new(ep)))
                .map_err(create_err(format!("action {full}"))),
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => crate::ros::wire::action::zenoh_action::ZenohActionEndpoints::new(
                &z.session,
                &full,
                &format!("{package}/action/{type_name}"),
                crate::ros::interface::qos::action_server(),
                &z.hashes,
            )
            .map(|z| ActionEndpoints::Zenoh(Box::new(z)))
            .map_err(zenoh_err(format!("action {full}"))),
        }
    }

    /// Creates the service `name` (resolved as a node's service name, e.g. `~/reset_estop`)
    /// of type `package/type_name` and the task that answers each request with `handler`, one
    /// request at a time, in order. The handler runs on tokio's blocking pool: it may block (the
    /// lifecycle's transitions wait there for the output thread to take the hold of the lines,
    /// up to `SAFETY_TAKE_BOUND`, 250 ms) without holding an async worker that every other
    /// endpoint shares. A handler that waits for an answer of the output thread (a reply or a
    /// safety input's acknowledgment) can be async instead ([`ServiceMaker::serve_async`]).
    pub fn serve<Req, Resp>(
        &mut self,
        name: &str,
        package: &str,
        type_name: &str,
        handler: impl Fn(Req) -> Resp + Send + Sync + 'static,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
    {
        let handler = std::sync::Arc::new(handler);
        self.serve_with(name, package, type_name, move |req| {
            let h = std::sync::Arc::clone(&handler);
            async move { tokio::task::spawn_blocking(move || h(req)).await }
        })
    }

    /// As [`ServiceMaker::serve`], but `handler` is async and runs in the service's task: it
    /// awaits the answer it needs (its own reply path, with its timeout) and holds no thread
    /// meanwhile. It must not block.
    pub fn serve_async<Req, Resp, F, Fut>(
        &mut self,
        name: &str,
        package: &str,
        type_name: &str,
        handler: F,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
        F: Fn(Req) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Resp> + Send + 'static,
    {
        self.serve_with(name, package, type_name, move |req| {
            let answer = handler(req);
            async move { Ok(answer.await) }
        })
    }

    /// The service `name` and its task, answering each request with what `handler`'s future
    /// gives (a handler that failed is logged and its request left unanswered).
    fn serve_with<Req, Resp, F, Fut>(
        &mut self,
        name: &str,
        package: &str,
        type_name: &str,
        handler: F,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
        F: Fn(Req) -> Fut + Send + Sync + 'static,
        Fut: std::future::Future<Output = Result<Resp, tokio::task::JoinError>> + Send + 'static,
    {
        let full = self.id.resolve(name, NameKind::Service, self.remaps)?;
        let qos = crate::ros::interface::qos::services();
        // One arm without the `zenoh` feature.
        #[allow(clippy::infallible_destructuring_match)]
        let node = match &mut self.mw {
            Mw::Dds(node) => node,
            #[cfg(feature = "zenoh")]
            Mw::Zenoh(z) => {
                debug!("service {full} on Zenoh");
                return crate::ros::wire::zenoh_srv::ZenohService::<Req, Resp>::serve_with(
                    &z.session,
                    &full,
                    &format!("{package}/srv/{type_name}"),
                    qos,
                    &z.hashes,
                    handler,
                )
                .map(hold)
                .map_err(zenoh_err(format!("service {full}")));
            }
        };
        let server: Server<Req, Resp> = node
            .create_server(
                ServiceMapping::Enhanced,
                &to_ros_name(&full)?,
                &ServiceTypeName::new(package, type_name),
                qos.clone(),
                qos,
            )
            .map_err(create_err(format!("service {full}")))?;
        Ok(tokio::spawn(async move {
            let stream = server.receive_request_stream();
            futures::pin_mut!(stream);
            while let Some(r) = stream.next().await {
                match r {
                    Ok((id, req)) => {
                        debug!("{full}: request");
                        let resp = match handler(req).await {
                            Ok(resp) => resp,
                            Err(e) => {
                                warn!("{full}: the request's handler failed: {e}");
                                continue;
                            }
                        };
                        if let Err(e) = server.async_send_response(id, resp).await {
                            warn!("{full}: cannot send the response: {e}");
                        }
                    }
                    Err(e) => warn!("{full}: unreadable request: {e}"),
                }
            }
        }))
    }
}
