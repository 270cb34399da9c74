//! The heater loop's inputs, for each channel with a `feedback_topic`: the
//! temperature subscription (`sensor_msgs/Temperature`, best effort, so best-effort sensor
//! publishers and reliable ones both match), `~/<ch>/setpoint` (`std_msgs/Float64`, °C) and
//! `~/<ch>/reset_fault` (`std_srvs/Trigger`).
//!
//! Readings and setpoints go to the output thread through the request queue, like commands:
//! one dropped or late is what `sensor_timeout` is there to catch. A reset is decided by the
//! core, which alone knows whether the fault's condition is gone; the service waits for its
//! answer, which the report thread files in the node state.

use crate::output_thread::Input;
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg::{self, TriggerResponse};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;

/// How long `~/<ch>/reset_fault` waits for the output thread's answer.
pub const RESET_WAIT: Duration = Duration::from_secs(1);

/// A channel with a heater loop: its index, its name and its feedback topic.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HeaterChannel {
    /// Channel index.
    pub channel: usize,
    /// `pw01`, ...
    pub name: String,
    /// The `sensor_msgs/Temperature` topic, as configured (relative names resolve in the
    /// node's namespace, and remapping applies).
    pub feedback_topic: String,
    /// The feed-forward topic (`std_msgs/Float64`, % of full power), empty for none.
    pub feedforward_topic: String,
    /// The ambient topic (`sensor_msgs/Temperature`, °C), empty for none.
    pub ambient_topic: String,
}

/// The feedback subscription, `~/<ch>/setpoint` and `~/<ch>/reset_fault` of each channel in
/// `heaters`, and the tasks that hand them to `inputs`.
pub fn listen_heaters(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    heaters: &[HeaterChannel],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for h in heaters {
        let ch = h.channel;
        info!("{}: temperature feedback from {}", h.name, h.feedback_topic);
        tasks.push(listen_temperature(
            ep,
            &h.feedback_topic,
            inputs,
            ch,
            |celsius, age| Input::Feedback { celsius, age },
        )?);
        if !h.feedforward_topic.is_empty() {
            info!("{}: feed-forward from {}", h.name, h.feedforward_topic);
            let to_thread = Arc::clone(inputs);
            tasks.push(ep.listen(&h.feedforward_topic, move |m: msg::Float64| {
                let _ = to_thread.send(ch, Input::Feedforward(m.data));
            })?);
        }
        if !h.ambient_topic.is_empty() {
            info!("{}: ambient temperature from {}", h.name, h.ambient_topic);
            tasks.push(listen_temperature(
                ep,
                &h.ambient_topic,
                inputs,
                ch,
                |celsius, age| Input::Ambient { celsius, age },
            )?);
        }
        let to_thread = Arc::clone(inputs);
        tasks.push(
            ep.listen(&format!("~/{}/setpoint", h.name), move |m: msg::Float64| {
                let _ = to_thread.send(ch, Input::Setpoint(m.data));
            })?,
        );
        let to_thread = Arc::clone(inputs);
        let name = h.name.clone();
        let reset = move |_: msg::EmptyRequest| reset(&to_thread, ch, &name);
        let mut maker = ep.services();
        tasks.push(maker.serve(
            &format!("~/{}/reset_fault", h.name),
            "std_srvs",
            "Trigger",
            reset,
        )?);
    }
    Ok(tasks)
}

/// Subscribes `topic` (`sensor_msgs/Temperature`, sensor QoS) and hands each reading to
/// channel `ch` as `input(°C, arrival less stamp in ns)`.
pub(crate) fn listen_temperature(
    ep: &mut Endpoints<'_>,
    topic: &str,
    inputs: &Arc<Inputs>,
    ch: usize,
    input: impl Fn(f64, Option<i64>) -> Input + Send + Sync + 'static,
) -> Result<JoinHandle<()>, EndpointError> {
    let to_thread = Arc::clone(inputs);
    ep.listen_with(topic, qos::sensor(), move |m: msg::Temperature| {
        let _ = to_thread.send(
            ch,
            input(m.temperature, stamp_age(&m.header, crate::clock::wall_ns())),
        );
    })
}

/// How long after its stamp a reading arrived at `now_wall` (ns since the Unix epoch), ns;
/// `None` for an unstamped reading (a zero stamp, as a message left at its defaults has).
pub(crate) fn stamp_age(header: &msg::Header, now_wall: i64) -> Option<i64> {
    let stamp = header.stamp.to_nanos();
    (stamp != 0).then(|| now_wall.saturating_sub(stamp))
}

/// `~/<ch>/reset_fault`: asks the output thread to clear the channel's heater fault and
/// answers with its verdict (refused with the reason while the condition lasts).
fn reset(inputs: &Inputs, channel: usize, name: &str) -> TriggerResponse {
    let refuse = |message: String| TriggerResponse {
        success: false,
        message,
    };
    let ticket = inputs.state().reset_ticket();
    if let Err(e) = inputs.send(channel, Input::ResetFault(ticket)) {
        return refuse(format!("the reset did not reach the output thread: {e}"));
    }
    let start = Instant::now();
    loop {
        if let Some(answer) = inputs.state().reset_answer(channel, ticket) {
            return match answer {
                Ok(()) => {
                    inputs.note_disabled(channel);
                    TriggerResponse {
                        success: true,
                        message: format!(
                            "{name}: heater fault cleared; the channel is disabled until its \
                             next enable"
                        ),
                    }
                }
                Err(reason) => refuse(format!("{name}: reset refused: {reason}")),
            };
        }
        if start.elapsed() >= RESET_WAIT {
            warn!("{name}: no answer to the heater fault reset within {RESET_WAIT:?}");
            return refuse(format!(
                "{name}: no answer from the output thread within {} ms; nothing changed \
                 that is known",
                RESET_WAIT.as_millis()
            ));
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}
