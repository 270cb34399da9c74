//! The three-point valves' inputs: each valve is made in the output thread on its two channels'
//! lines, and `~/valve/<NAME>/position` (`std_msgs/Float64`, percent, 0 = closed) sets its
//! target. Positions go through the request queue like commands; the core refuses NaN and
//! infinities (the target in force stays) and clamps the rest to 0..100. A valve with
//! `NAME.feedback_topic` subscribes to it (`std_msgs/Float64`, percent, best effort so that
//! best-effort and reliable publishers both match); `~/valve/<NAME>/reset` (`std_srvs/Trigger`)
//! asks the output thread to clear a latched fault and answers with its verdict, which comes
//! back in the valve's next snapshot and, through the report side, on the request's own reply
//! path ([`ValveAnswers`]).

//!
//! End switches (`NAME.open_limit_line`, `NAME.close_limit_line`) are GPIO input lines,
//! requested at start-up ([`open_switches`]; a line that cannot be requested stops the node,
//! exit 2) and read by one thread per line ([`spawn_switch_readers`]): the level at start, then
//! every change, each sent as `Input::ValveSwitch` through the request queue.

use crate::core::valve::{Dir, Manual, ResetAnswer, ValveFault, ValveStart};
use crate::core::ValveConfig;
use crate::output::gpio_input::{InputError, InputLine, InputRequest};
use crate::output_thread::{Input, OutputThreadError};
use crate::ros::config::valve::{LimitLine, ValveLimits, ValveSpec};
use crate::ros::inbound::inputs::Inputs;
use crate::ros::inbound::replies::{ReplySlots, Tickets};
use crate::ros::interface::msg::{self, TriggerResponse};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::task::JoinHandle;

/// One requested end switch line.
#[derive(Debug)]
pub struct SwitchLine {
    /// The valve's index.
    pub valve: usize,
    /// The end it marks.
    pub dir: Dir,
    /// What it is, for the log (`valve mix close limit`).
    pub name: String,
    req: InputRequest,
    /// The logical level read when the line was requested.
    initial: bool,
}

/// Requests the end switch lines of the valves (`limits[k]` belongs to `valves[k]`), as
/// inputs with both edges and the valve's debounce and polarity.
pub fn open_switches(
    valves: &[ValveSpec],
    limits: &[ValveLimits],
) -> Result<Vec<SwitchLine>, InputError> {
    let mut out = Vec::new();
    for (k, (v, l)) in valves.iter().zip(limits).enumerate() {
        let each: [(Dir, &str, &Option<LimitLine>); 2] = [
            (Dir::Open, "open", &l.open),
            (Dir::Close, "close", &l.close),
        ];
        for (dir, end, line) in each {
            let Some(line) = line else { continue };
            let input = InputLine {
                name: format!("valve {} {end} limit", v.name),
                chip: line.chip.clone(),
                offset: line.offset,
                active_low: l.active_low,
            };
            let (req, initial) = InputRequest::open(&input, Duration::from_millis(l.debounce_ms))?;
            info!(
                "{}: line {} of {}, {}, debounce {} ms, {} now",
                input.name,
                line.offset,
                line.chip.display(),
                if l.active_low {
                    "active low"
                } else {
                    "active high"
                },
                l.debounce_ms,
                if initial { "active" } else { "inactive" }
            );
            out.push(SwitchLine {
                valve: k,
                dir,
                name: input.name,
                req,
                initial,
            });
        }
    }
    Ok(out)
}

/// How long a reader waits for an edge before it waits again, and how long it pauses after a
/// read error before it retries.
const SWITCH_WAIT: Duration = Duration::from_secs(1);

/// Starts one reader thread per switch line (after [`listen_valves`] made the valves): it sends
/// the level read at start, then each change. A read error is logged once and retried every
/// `SWITCH_WAIT` (1 s); the threads end with the process.
pub fn spawn_switch_readers(switches: Vec<SwitchLine>, inputs: &Arc<Inputs>) {
    for s in switches {
        let inputs = Arc::clone(inputs);
        let spawned = std::thread::Builder::new()
            .name("pwm-switch".into())
            .spawn(move || read_switch(s, &inputs));
        if let Err(e) = spawned {
            warn!("cannot start an end switch reader: {e}; the valve relies on its overrun");
        }
    }
}

fn read_switch(s: SwitchLine, inputs: &Inputs) {
    let send = |active: bool| {
        let _ = inputs.send(
            0,
            Input::ValveSwitch {
                valve: s.valve,
                dir: s.dir,
                active,
            },
        );
    };
    let mut last = s.initial;
    send(last);
    let mut failing = false;
    loop {
        let active = match s.req.next_edge(SWITCH_WAIT) {
            Ok(Some(active)) => active,
            Ok(None) => continue,
            Err(e) => {
                if !failing {
                    warn!("{}: cannot read the line: {e}; retrying", s.name);
                    failing = true;
                }
                std::thread::sleep(SWITCH_WAIT);
                // The level may have changed while the events could not be read.
                match s.req.level() {
                    Ok(level) => level,
                    Err(_) => continue,
                }
            }
        };
        failing = false;
        if active != last {
            last = active;
            info!("{}: {}", s.name, if active { "active" } else { "inactive" });
            send(active);
        }
    }
}

/// One valve to make: its channels, its settings, what it starts with, its feedback topic
/// (empty: none).
#[derive(Debug, Clone)]
pub struct ValveRun {
    /// Name and channels.
    pub spec: ValveSpec,
    /// Settings.
    pub config: ValveConfig,
    /// Restored position, wired switches, feedback.
    pub start: ValveStart,
    /// The `std_msgs/Float64` feedback topic, as configured (relative names resolve in the
    /// node's namespace, and remapping applies); empty for none.
    pub feedback_topic: String,
    /// The loop's process value topic, as configured; empty for none.
    pub process_topic: String,
    /// The process value is a `sensor_msgs/Temperature` (else a `std_msgs/Float64`).
    pub process_temperature: bool,
}

/// How long `~/valve/<NAME>/reset` waits for the output thread's answer.
pub const VALVE_RESET_WAIT: Duration = Duration::from_secs(1);

/// The answer to a valve reset: cleared or not, with the fault the same snapshot reported.
pub type ValveResetAnswer = (bool, Option<ValveFault>);

/// What the report side tells the valves' reset services: the fault each valve reported last
/// (for the service's message; the lock is held for a copy), and the answers to the resets,
/// each handed to its request's reply path ([`ReplySlots`]).
#[derive(Debug)]
pub struct ValveAnswers {
    faults: Box<[Mutex<Option<ValveFault>>]>,
    resets: ReplySlots<ValveResetAnswer>,
    tickets: Tickets,
}

impl ValveAnswers {
    /// Slots for `valves` valves.
    pub fn new(valves: usize) -> ValveAnswers {
        ValveAnswers {
            faults: (0..valves).map(|_| Mutex::new(None)).collect(),
            resets: ReplySlots::new(valves),
            tickets: Tickets::default(),
        }
    }

    /// Valve `k`'s snapshot came with `fault` latched and `reset` the last answer: the answer
    /// goes to the reset that waits for it, if one still does (a snapshot repeats the last
    /// answer; a repeat finds nobody waiting).
    pub fn note(&self, k: usize, fault: Option<ValveFault>, reset: Option<ResetAnswer>) {
        if let Some(slot) = self.faults.get(k) {
            *crate::output::panic_off::lock_ignore_poison(slot) = fault;
        }
        if let Some(a) = reset {
            self.resets.answer(k, a.ticket, (a.cleared, fault));
        }
    }

    /// The fault valve `k` has latched, as last reported.
    pub fn fault(&self, k: usize) -> Option<ValveFault> {
        *crate::output::panic_off::lock_ignore_poison(self.faults.get(k)?)
    }

    /// Files a reset's reply path for valve `k` under a fresh ticket, hands the ticket to
    /// `send` (the request to the output thread) and awaits the answer for up to
    /// [`VALVE_RESET_WAIT`]: `Ok(None)` when none came, `Err` when `send` failed.
    pub async fn ask(
        &self,
        k: usize,
        send: impl FnOnce(u32) -> Result<(), OutputThreadError>,
    ) -> Result<Option<ValveResetAnswer>, OutputThreadError> {
        let ticket = self.tickets.next();
        let reply = self.resets.expect(k, ticket);
        send(ticket)?;
        Ok(reply.within(VALVE_RESET_WAIT).await)
    }
}

/// Makes each valve of `valves` (numbered in order) in the output thread and listens on its
/// `~/valve/<NAME>/position`, its feedback topic and its `~/valve/<NAME>/reset`.
pub fn listen_valves(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    valves: &[ValveRun],
    answers: &Arc<ValveAnswers>,
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for (k, run) in valves.iter().enumerate() {
        let (v, config) = (&run.spec, &run.config);
        let p = config.params;
        info!(
            "valve {}: {} opens, {} closes; travel {} ms open, {} ms close, start lag {} ms, \
             backlash {} %",
            v.name,
            inputs.name(v.open),
            inputs.name(v.close),
            p.travel_open_ms,
            p.travel_close_ms,
            p.start_lag_ms,
            p.backlash_pct
        );
        let _ = inputs.send(
            v.open,
            Input::AddValve {
                close: v.close,
                config: *config,
                start: run.start,
            },
        );
        let to_thread = Arc::clone(inputs);
        let topic = format!("~/valve/{}/position", v.name);
        tasks.push(ep.listen(&topic, move |m: msg::Float64| {
            let _ = to_thread.send(
                0,
                Input::ValvePosition {
                    valve: k,
                    pct: m.data,
                },
            );
        })?);
        if !run.feedback_topic.is_empty() {
            info!(
                "valve {}: position feedback from {}",
                v.name, run.feedback_topic
            );
            let to_thread = Arc::clone(inputs);
            tasks.push(ep.listen_with(
                &run.feedback_topic,
                qos::sensor(),
                move |m: msg::Float64| {
                    let _ = to_thread.send(
                        0,
                        Input::ValveFeedback {
                            valve: k,
                            pct: m.data,
                        },
                    );
                },
            )?);
        }
        if !run.process_topic.is_empty() {
            info!(
                "valve {}: process value from {} ({})",
                v.name,
                run.process_topic,
                if run.process_temperature {
                    "sensor_msgs/Temperature"
                } else {
                    "std_msgs/Float64"
                }
            );
            if run.process_temperature {
                tasks.push(crate::ros::inbound::heater::listen_temperature(
                    ep,
                    &run.process_topic,
                    inputs,
                    0,
                    move |value, age| Input::ValveProcess {
                        valve: k,
                        value,
                        age,
                    },
                )?);
            } else {
                let to_thread = Arc::clone(inputs);
                tasks.push(ep.listen_with(
                    &run.process_topic,
                    qos::sensor(),
                    move |m: msg::Float64| {
                        // Unstamped: its age is not known, so only the timeout judges it.
                        let _ = to_thread.send(
                            0,
                            Input::ValveProcess {
                                valve: k,
                                value: m.data,
                                age: None,
                            },
                        );
                    },
                )?);
            }
        }
        let to_thread = Arc::clone(inputs);
        let topic = format!("~/valve/{}/setpoint", v.name);
        tasks.push(ep.listen(&topic, move |m: msg::Float64| {
            let _ = to_thread.send(
                0,
                Input::ValveSetpoint {
                    valve: k,
                    value: m.data,
                },
            );
        })?);
        let to_thread = Arc::clone(inputs);
        let topic = format!("~/valve/{}/manual", v.name);
        tasks.push(ep.listen(&topic, move |m: msg::StringMsg| {
            // A word that is none of the commands goes on too (its first 32 bytes): the valve
            // counts it with its refusals, and the report side logs it.
            let manual = m.data.trim().parse::<Manual>();
            let _ = to_thread.send(0, Input::ValveManual { valve: k, manual });
        })?);
        let (to_thread, a) = (Arc::clone(inputs), Arc::clone(answers));
        let name: Arc<str> = v.name.as_str().into();
        let reset = move |_: msg::EmptyRequest| {
            let (to_thread, a, name) = (Arc::clone(&to_thread), Arc::clone(&a), Arc::clone(&name));
            async move { reset(&to_thread, &a, k, &name).await }
        };
        let mut maker = ep.services();
        tasks.push(maker.serve_async(
            &format!("~/valve/{}/reset", v.name),
            "std_srvs",
            "Trigger",
            reset,
        )?);
    }
    Ok(tasks)
}

/// `~/valve/<NAME>/reset`: asks the output thread to clear valve `k`'s fault and answers with
/// its verdict (refused while an implausible end switch stays active).
async fn reset(inputs: &Inputs, answers: &ValveAnswers, k: usize, name: &str) -> TriggerResponse {
    let fault = answers.fault(k);
    let answer = answers
        .ask(k, |ticket| {
            inputs.send(0, Input::ValveReset { valve: k, ticket })
        })
        .await;
    reset_response(name, fault, answer)
}

/// The reset service's answer for valve `name`, which had `fault` latched when asked.
fn reset_response(
    name: &str,
    fault: Option<ValveFault>,
    answer: Result<Option<ValveResetAnswer>, OutputThreadError>,
) -> TriggerResponse {
    let refuse = |message: String| TriggerResponse {
        success: false,
        message,
    };
    let what = fault.map_or("", |f| f.name());
    let (cleared, now) = match answer {
        Err(e) => return refuse(format!("the reset did not reach the output thread: {e}")),
        Ok(None) => {
            return refuse(format!(
                "valve {name}: no answer from the output thread within {} ms; nothing changed \
                 that is known",
                VALVE_RESET_WAIT.as_millis()
            ))
        }
        Ok(Some(a)) => a,
    };
    match (cleared, fault) {
        (true, Some(_)) => {
            info!("valve {name}: {what} cleared by a reset");
            TriggerResponse {
                success: true,
                message: format!(
                    "valve {name}: {what} cleared; the valve is unreferenced and waits for a \
                     fresh position command"
                ),
            }
        }
        (true, None) => TriggerResponse {
            success: true,
            message: format!("valve {name}: no fault latched"),
        },
        (false, _) => {
            let f = now.or(fault);
            warn!("valve {name}: reset refused: the cause lasts");
            refuse(format!(
                "valve {name}: reset refused: {} lasts (an end switch is still active)",
                f.map_or("the fault", |f| f.name())
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const IMPLAUSIBLE: ValveFault = ValveFault::SwitchImplausible {
        switches: [true, true],
        low_pct: 10.0,
        high_pct: 20.0,
    };

    fn answer(ticket: u32, cleared: bool) -> Option<ResetAnswer> {
        Some(ResetAnswer { ticket, cleared })
    }

    // With tokio's clock paused, a wait that looked again every few ms would move the clock on;
    // an answer that wakes the request leaves it where it was.
    #[tokio::test(start_paused = true)]
    async fn the_snapshot_answer_comes_back_on_the_request_own_path_at_once() {
        let answers = Arc::new(ValveAnswers::new(2));
        answers.note(1, Some(IMPLAUSIBLE), None);
        let before = answers.fault(1);
        let start = tokio::time::Instant::now();
        let report_thread = Arc::clone(&answers);
        let got = answers
            .ask(1, move |ticket| {
                tokio::spawn(async move {
                    tokio::task::yield_now().await;
                    // A snapshot with another valve's answer, then this valve's.
                    report_thread.note(0, None, answer(ticket, true));
                    report_thread.note(1, None, answer(ticket, true));
                });
                Ok(())
            })
            .await;
        assert!(matches!(got, Ok(Some((true, None)))), "{got:?}");
        assert_eq!(start.elapsed(), Duration::ZERO);
        let r = reset_response("mix", before, got);
        assert!(r.success);
        assert_eq!(
            r.message,
            "valve mix: switch_implausible cleared; the valve is unreferenced and waits for a \
             fresh position command"
        );

        let report_thread = Arc::clone(&answers);
        let got = answers
            .ask(1, move |ticket| {
                tokio::spawn(async move {
                    tokio::task::yield_now().await;
                    report_thread.note(1, Some(IMPLAUSIBLE), answer(ticket, false));
                });
                Ok(())
            })
            .await;
        assert!(
            matches!(got, Ok(Some((false, Some(IMPLAUSIBLE))))),
            "{got:?}"
        );
        assert_eq!(start.elapsed(), Duration::ZERO);
        assert_eq!(
            reset_response("mix", None, got).message,
            "valve mix: reset refused: switch_implausible lasts (an end switch is still active)"
        );
    }

    #[tokio::test(start_paused = true)]
    async fn a_valve_reset_without_answer_gives_up_after_its_wait_and_its_late_answer_is_dropped() {
        let answers = ValveAnswers::new(1);
        let mut sent = None;
        let start = tokio::time::Instant::now();
        let got = answers
            .ask(0, |ticket| {
                sent = Some(ticket);
                Ok(())
            })
            .await;
        assert!(matches!(got, Ok(None)), "{got:?}");
        assert_eq!(start.elapsed(), VALVE_RESET_WAIT);
        let r = reset_response("mix", None, got);
        assert!(!r.success);
        assert_eq!(
            r.message,
            "valve mix: no answer from the output thread within 1000 ms; nothing changed that \
             is known"
        );
        // The late snapshot: its fault is kept, its answer dropped; the next reset waits for
        // its own.
        let late = sent.unwrap();
        answers.note(0, Some(IMPLAUSIBLE), answer(late, false));
        assert_eq!(answers.fault(0), Some(IMPLAUSIBLE));
        let got = answers
            .ask(0, |ticket| {
                answers.note(0, Some(IMPLAUSIBLE), answer(late, false));
                answers.note(0, None, answer(ticket, true));
                Ok(())
            })
            .await;
        assert!(matches!(got, Ok(Some((true, None)))), "{got:?}");
        let full = answers
            .ask(0, |_| Err(OutputThreadError::QueueFull { capacity: 256 }))
            .await;
        assert!(
            matches!(full, Err(OutputThreadError::QueueFull { capacity: 256 })),
            "{full:?}"
        );
        assert_eq!(
            reset_response("mix", None, full).message,
            "the reset did not reach the output thread: request queue full (256 entries); \
             request dropped"
        );
    }
}
