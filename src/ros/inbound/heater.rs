//! The heater loop's inputs, for each channel with a `feedback_topic`: the
//! temperature subscription (`sensor_msgs/Temperature`, best effort, so best-effort sensor
//! publishers and reliable ones both match), `~/<ch>/setpoint` (`std_msgs/Float64`, °C) and
//! `~/<ch>/reset_fault` (`std_srvs/Trigger`).
//!
//! Readings and setpoints go to the output thread through the request queue, like commands:
//! one dropped or late is what `sensor_timeout` is there to catch. A reset is decided by the
//! core, which alone knows whether the fault's condition is gone; the service awaits its
//! answer on the request's own reply path ([`replies`](super::replies)), which the report
//! thread completes with the core's `FaultReset` event.

use crate::core::heater::ResetRefusal;
use crate::output_thread::{Input, OutputThreadError};
use crate::ros::inbound::inputs::Inputs;
use crate::ros::inbound::node_state::NodeState;
use crate::ros::interface::msg::{self, TriggerResponse};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use std::sync::Arc;
use std::time::Duration;
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
        let name: Arc<str> = h.name.as_str().into();
        let reset = move |_: msg::EmptyRequest| {
            let (to_thread, name) = (Arc::clone(&to_thread), Arc::clone(&name));
            async move { reset(&to_thread, ch, &name).await }
        };
        let mut maker = ep.services();
        tasks.push(maker.serve_async(
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
async fn reset(inputs: &Inputs, channel: usize, name: &str) -> TriggerResponse {
    let answer = ask_reset(inputs.state(), channel, |ticket| {
        inputs.send(channel, Input::ResetFault(ticket))
    })
    .await;
    match answer {
        ResetOutcome::Cleared => inputs.note_disabled(channel),
        ResetOutcome::NoAnswer => {
            warn!("{name}: no answer to the heater fault reset within {RESET_WAIT:?}")
        }
        ResetOutcome::Refused(_) | ResetOutcome::NotSent(_) => {}
    }
    answer.response(name)
}

/// How a heater fault reset ended.
#[derive(Debug)]
enum ResetOutcome {
    /// The fault is cleared (or there was none).
    Cleared,
    /// The core refused it.
    Refused(ResetRefusal),
    /// The request did not reach the output thread.
    NotSent(OutputThreadError),
    /// No answer within [`RESET_WAIT`].
    NoAnswer,
}

/// Files the reset's reply path under a fresh ticket, hands the ticket to `send` (the request
/// to the output thread) and awaits the answer for up to [`RESET_WAIT`].
async fn ask_reset(
    state: &NodeState,
    channel: usize,
    send: impl FnOnce(u32) -> Result<(), OutputThreadError>,
) -> ResetOutcome {
    let ticket = state.ticket();
    let reply = state.resets().expect(channel, ticket);
    if let Err(e) = send(ticket) {
        return ResetOutcome::NotSent(e);
    }
    match reply.within(RESET_WAIT).await {
        Some(Ok(())) => ResetOutcome::Cleared,
        Some(Err(reason)) => ResetOutcome::Refused(reason),
        None => ResetOutcome::NoAnswer,
    }
}

impl ResetOutcome {
    /// The service's answer for channel `name`.
    fn response(&self, name: &str) -> TriggerResponse {
        let refuse = |message: String| TriggerResponse {
            success: false,
            message,
        };
        match self {
            ResetOutcome::Cleared => TriggerResponse {
                success: true,
                message: format!(
                    "{name}: heater fault cleared; the channel is disabled until its next enable"
                ),
            },
            ResetOutcome::Refused(reason) => refuse(format!("{name}: reset refused: {reason}")),
            ResetOutcome::NotSent(e) => {
                refuse(format!("the reset did not reach the output thread: {e}"))
            }
            ResetOutcome::NoAnswer => refuse(format!(
                "{name}: no answer from the output thread within {} ms; nothing changed that \
                 is known",
                RESET_WAIT.as_millis()
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // With tokio's clock paused, a wait that looked again every few ms would move the clock on;
    // an answer that wakes the request leaves it where it was.
    #[tokio::test(start_paused = true)]
    async fn the_core_answer_comes_back_on_the_request_own_path_at_once() {
        let state = Arc::new(NodeState::new(2));
        let start = tokio::time::Instant::now();
        let report_thread = Arc::clone(&state);
        let cleared = ask_reset(&state, 1, move |ticket| {
            // The report thread, taking the core's `FaultReset` event once the service waits.
            tokio::spawn(async move {
                tokio::task::yield_now().await;
                report_thread.resets().answer(1, ticket, Ok(()))
            });
            Ok(())
        })
        .await;
        assert!(matches!(cleared, ResetOutcome::Cleared), "{cleared:?}");
        assert_eq!(start.elapsed(), Duration::ZERO);
        let r = cleared.response("pw02");
        assert!(r.success);
        assert_eq!(
            r.message,
            "pw02: heater fault cleared; the channel is disabled until its next enable"
        );

        let report_thread = Arc::clone(&state);
        let refused = ask_reset(&state, 0, move |ticket| {
            let why = ResetRefusal::NoFault;
            tokio::spawn(async move {
                tokio::task::yield_now().await;
                report_thread.resets().answer(0, ticket, Err(why))
            });
            Ok(())
        })
        .await;
        assert!(
            matches!(refused, ResetOutcome::Refused(ResetRefusal::NoFault)),
            "{refused:?}"
        );
        assert_eq!(start.elapsed(), Duration::ZERO);
        let r = refused.response("pw01");
        assert!(!r.success);
        assert_eq!(r.message, "pw01: reset refused: no heater fault is latched");
    }

    #[tokio::test(start_paused = true)]
    async fn a_reset_without_answer_gives_up_after_its_wait_and_its_late_answer_is_dropped() {
        let state = NodeState::new(1);
        let mut sent = None;
        let start = tokio::time::Instant::now();
        let outcome = ask_reset(&state, 0, |ticket| {
            sent = Some(ticket);
            Ok(())
        })
        .await;
        assert!(matches!(outcome, ResetOutcome::NoAnswer), "{outcome:?}");
        assert_eq!(start.elapsed(), RESET_WAIT);
        let r = outcome.response("pw01");
        assert!(!r.success);
        assert_eq!(
            r.message,
            "pw01: no answer from the output thread within 1000 ms; nothing changed that is known"
        );
        // The core's answer, late: nobody waits, nothing breaks, the next reset is unaffected.
        let late = sent.unwrap();
        assert!(!state.resets().answer(0, late, Ok(())));
        let next = ask_reset(&state, 0, |ticket| {
            assert!(!state.resets().answer(0, late, Ok(())));
            assert!(state.resets().answer(0, ticket, Ok(())));
            Ok(())
        })
        .await;
        assert!(matches!(next, ResetOutcome::Cleared), "{next:?}");
    }

    #[tokio::test(start_paused = true)]
    async fn a_reset_that_does_not_reach_the_output_thread_is_refused_at_once() {
        let state = NodeState::new(1);
        let outcome = ask_reset(&state, 0, |_| {
            Err(OutputThreadError::QueueFull { capacity: 256 })
        })
        .await;
        assert_eq!(
            outcome.response("pw01").message,
            "the reset did not reach the output thread: request queue full (256 entries); request \
             dropped"
        );
    }
}
