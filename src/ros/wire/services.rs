//! The one place a service of the node is created ([`ServiceMaker::serve`]): its name
//! resolved as a node's service name, its QoS, and the task that answers each request.

use crate::ros::config::args::Remap;
use crate::ros::config::names::{to_ros_name, NameKind, NodeIdentity};
use crate::ros::wire::endpoints::{create_err, EndpointError};
use futures::StreamExt;
use log::{debug, warn};
use ros2_client::{Message, Node, Server, ServiceMapping, ServiceTypeName};
use tokio::task::JoinHandle;

/// A service request type: a message a server task can own.
pub trait Request: Message + Clone + Send + Sync + 'static {}
impl<T: Message + Clone + Send + Sync + 'static> Request for T {}

/// A service response type: a message a server task can send.
pub trait Response: Message + Send + Sync + 'static {}
impl<T: Message + Send + Sync + 'static> Response for T {}

/// What a node's services are created with: the node, its identity and remapping rules.
pub struct ServiceMaker<'a> {
    /// The node.
    pub node: &'a mut Node,
    /// Its name and namespace.
    pub id: &'a NodeIdentity,
    /// The remapping rules.
    pub remaps: &'a [Remap],
}

impl ServiceMaker<'_> {
    /// Creates the service `name` (resolved as a node's service name, e.g. `~/reset_estop`)
    /// of type `package/type_name` and the task that answers each request with `handler`.
    pub fn serve<Req, Resp>(
        &mut self,
        name: &str,
        package: &str,
        type_name: &str,
        handler: impl Fn(Req) -> Resp + Send + 'static,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
    {
        let full = self.id.resolve(name, NameKind::Service, self.remaps)?;
        let qos = crate::ros::interface::qos::services();
        let server: Server<Req, Resp> = self
            .node
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
                        let resp = handler(req);
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
