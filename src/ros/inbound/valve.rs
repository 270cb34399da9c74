//! The three-point valves' inputs: each valve is made in the output thread on its two channels'
//! lines, and `~/valve/<NAME>/position` (`std_msgs/Float64`, percent, 0 = closed) sets its
//! target. Positions go through the request queue like commands; the core refuses NaN and
//! infinities (the target in force stays) and clamps the rest to 0..100.

use crate::core::ValveConfig;
use crate::engine::Input;
use crate::ros::config::valve::ValveSpec;
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::info;
use std::sync::Arc;
use tokio::task::JoinHandle;

/// Makes each valve of `valves` (numbered in order) in the output thread and listens on its
/// `~/valve/<NAME>/position`.
pub fn listen_valves(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    valves: &[(ValveSpec, ValveConfig)],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for (k, (v, config)) in valves.iter().enumerate() {
        let p = config.params;
        info!(
            "valve {}: {} opens, {} closes; travel {} ms open, {} ms close",
            v.name,
            inputs.name(v.open),
            inputs.name(v.close),
            p.travel_open_ms,
            p.travel_close_ms
        );
        let _ = inputs.send(
            v.open,
            Input::AddValve {
                close: v.close,
                config: *config,
            },
        );
        let b = Arc::clone(inputs);
        let topic = format!("~/valve/{}/position", v.name);
        tasks.push(ep.listen(&topic, move |m: msg::Float64| {
            let _ = b.send(
                0,
                Input::ValvePosition {
                    valve: k,
                    pct: m.data,
                },
            );
        })?);
    }
    Ok(tasks)
}
