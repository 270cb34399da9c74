//! The six standard parameter services (`~/get_parameters`, `~/get_parameter_types`,
//! `~/set_parameters`, `~/set_parameters_atomically`, `~/list_parameters`,
//! `~/describe_parameters`), served from the node's own parameter store.
//!
//! ros2-client 0.12.1 can serve parameters itself, but its `describe_parameters` answers every
//! name with "(description missing, not implemented)" and no range, its validator sees one
//! value at a time (so `set_parameters_atomically` cannot check `min_on_ms <= period_ms`
//! across the values), and it refuses any type change. So the node turns those services off
//! (`NodeOptions::start_parameter_services(false)`) and offers the same six services, with the
//! same names, types and QoS, here. Handlers only read the store or call
//! [`Inputs::set_params`]; they never block.

use crate::ros::inbound::inputs::{ChangeError, Inputs};
use crate::ros::wire::endpoints::{EndpointError, Endpoints, ServiceMaker};
use crate::ros::wire::endpoints::{Request, Response};
use ros2_client::parameters::raw;
use ros2_client::rcl_interfaces::{
    DescribeParametersRequest, DescribeParametersResponse, GetParameterTypesRequest,
    GetParameterTypesResponse, GetParametersRequest, GetParametersResponse, ListParametersRequest,
    ListParametersResponse, ListParametersResult, SetParametersAtomicallyResponse,
    SetParametersRequest, SetParametersResponse,
};
use ros2_client::ParameterValue;
use std::sync::Arc;
use tokio::task::JoinHandle;

fn get(inputs: &Inputs, req: GetParametersRequest) -> GetParametersResponse {
    inputs.with_params(|s| GetParametersResponse {
        values: req
            .names
            .iter()
            .map(|n| s.get(n).unwrap_or(ParameterValue::NotSet).into())
            .collect(),
    })
}

fn get_types(inputs: &Inputs, req: GetParameterTypesRequest) -> GetParameterTypesResponse {
    inputs.with_params(|s| GetParameterTypesResponse {
        values: req
            .names
            .iter()
            .map(|n| {
                s.descriptor(n)
                    .map_or(raw::ParameterType::NOT_SET, |d| d.ptype.raw())
            })
            .collect(),
    })
}

fn list(inputs: &Inputs, req: ListParametersRequest) -> ListParametersResponse {
    let (names, prefixes) = inputs.with_params(|s| s.list(&req.prefixes, req.depth));
    ListParametersResponse {
        result: ListParametersResult { names, prefixes },
    }
}

fn describe(inputs: &Inputs, req: DescribeParametersRequest) -> DescribeParametersResponse {
    inputs.with_params(|s| DescribeParametersResponse {
        values: req
            .names
            .iter()
            .map(|n| match s.descriptor(n) {
                Some(d) => d.to_raw(),
                None => raw::ParameterDescriptor {
                    name: n.clone(),
                    r#type: raw::ParameterType::NOT_SET,
                    description: "not declared".into(),
                    additional_constraints: String::new(),
                    read_only: true,
                    dynamic_typing: false,
                    floating_point_range: vec![],
                    integer_range: vec![],
                },
            })
            .collect(),
    })
}

/// The answer to one change: its refusal's text is the `reason` ROS clients see.
fn result(r: Result<(), ChangeError>) -> raw::SetParametersResult {
    match r {
        Ok(()) => raw::SetParametersResult {
            successful: true,
            reason: String::new(),
        },
        Err(e) => raw::SetParametersResult {
            successful: false,
            reason: e.to_string(),
        },
    }
}

fn items(req: SetParametersRequest) -> Vec<(String, ParameterValue)> {
    req.parameter
        .into_iter()
        .map(|p| (p.name, ParameterValue::from(p.value)))
        .collect()
}

/// `set_parameters`: each parameter on its own, in order, as rclcpp does.
async fn set(inputs: Arc<Inputs>, req: SetParametersRequest) -> SetParametersResponse {
    let mut results = Vec::new();
    for item in items(req) {
        results.push(result(
            inputs.set_params(vec![item], "set_parameters").await,
        ));
    }
    SetParametersResponse { results }
}

/// `set_parameters_atomically`: all or nothing.
async fn set_atomically(
    inputs: Arc<Inputs>,
    req: SetParametersRequest,
) -> SetParametersAtomicallyResponse {
    SetParametersAtomicallyResponse {
        result: result(
            inputs
                .set_params(items(req), "set_parameters_atomically")
                .await,
        ),
    }
}

/// What every parameter service of the node is created with.
struct Servers<'a> {
    maker: ServiceMaker<'a>,
    inputs: &'a Arc<Inputs>,
}

impl Servers<'_> {
    /// Creates the service `~/<base>` of `rcl_interfaces/<type_name>` and the task that
    /// answers each request with `handler`.
    fn spawn<Req, Resp>(
        &mut self,
        base: &'static str,
        type_name: &'static str,
        handler: fn(&Inputs, Req) -> Resp,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
    {
        let inputs = Arc::clone(self.inputs);
        self.maker.serve(
            &format!("~/{base}"),
            "rcl_interfaces",
            type_name,
            move |req| handler(&inputs, req),
        )
    }
}

impl Servers<'_> {
    /// As [`Servers::spawn`], with an async `handler` that runs in the service's task (a
    /// change awaits the output thread's acknowledgment of a new planner there).
    fn spawn_async<Req, Resp, Fut>(
        &mut self,
        base: &'static str,
        type_name: &'static str,
        handler: fn(Arc<Inputs>, Req) -> Fut,
    ) -> Result<JoinHandle<()>, EndpointError>
    where
        Req: Request,
        Resp: Response,
        Fut: std::future::Future<Output = Resp> + Send + 'static,
    {
        let inputs = Arc::clone(self.inputs);
        self.maker.serve_async(
            &format!("~/{base}"),
            "rcl_interfaces",
            type_name,
            move |req| handler(Arc::clone(&inputs), req),
        )
    }
}

/// Creates the six parameter services and the tasks serving them.
pub fn spawn(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut s = Servers {
        maker: ep.services(),
        inputs,
    };
    Ok(vec![
        s.spawn("get_parameters", "GetParameters", get)?,
        s.spawn("get_parameter_types", "GetParameterTypes", get_types)?,
        s.spawn_async("set_parameters", "SetParameters", set)?,
        s.spawn_async(
            "set_parameters_atomically",
            "SetParametersAtomically",
            set_atomically,
        )?,
        s.spawn("list_parameters", "ListParameters", list)?,
        s.spawn("describe_parameters", "DescribeParameters", describe)?,
    ])
}
