//! `~/<ch>/autotune` (`pwm_actuator_msgs/action/Autotune`) of each channel with feedback: the
//! action that runs the relay autotune (`core::heater::autotune`) and, with `apply`, sets the
//! gains it found as parameters.
//!
//! The run itself lives in the output thread's channel core, which alone knows when the line
//! was really on and stops the run on a heater fault, the e-stop, a deactivate or a disable.
//! The action's task sends the goal and a cancel through the request queue and takes the
//! core's reports (start, each cycle, the end) from the channel's mailbox
//! ([`Mailbox`](super::replies::Mailbox)), where the report thread files them and wakes it: it
//! sleeps until a report is filed, a request comes or a run's time to report is over.
//!
//! The action server ([`ActionServer`]) answers every request as it comes and never waits for
//! a client: one run per channel at a time, so a goal that comes while a run goes is rejected
//! at once (the reason in the log); a goal that comes while none does is accepted at once and
//! sent to the output thread, which starts it within [`START_BY`] of its acceptance or never
//! (it drops a goal it takes later). Results are kept as the server says (15 minutes, 16 ended
//! goals).
//!
//! A refused goal (no reading yet, the channel not running, a target outside the limits, an
//! amplitude above `max_duty_pct`, ...) is accepted and then aborted, so the client gets the
//! reason in the result's `message`.

use crate::clock::monotonic_ns;
use crate::core::heater::autotune::{Goal, Outcome, Progress, Report, Stop};
use crate::output_thread::Input;
use crate::ros::config::params::ChannelValues;
use crate::ros::inbound::heater::HeaterChannel;
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg::{AutotuneFeedback, AutotuneGoal, AutotuneResult, MSG_PACKAGE};
use crate::ros::wire::action::{ActionServer, Event, GoalRequest};
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use ros2_client::action::{GoalEndStatus, GoalId};
use ros2_client::ParameterValue;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;

/// The rule that gives the gains, as the result names it.
pub const RULE: &str = "tyreus_luyben";
/// How soon the task tries again to send a cancel that did not reach the output thread's
/// queue (it was full).
const CANCEL_RETRY: Duration = Duration::from_millis(50);
/// The latest a run starts after its goal was accepted: the output thread drops a goal it
/// takes later.
pub const START_BY: Duration = Duration::from_secs(1);
/// How long the task waits for the output thread's first answer to a goal before it ends the
/// goal as `lost` (longer than [`START_BY`]: by then the run can no longer start).
const START_WAIT: Duration = Duration::from_secs(2);

type Server = ActionServer<AutotuneGoal, AutotuneResult, AutotuneFeedback>;

/// The autotune action of each channel in `heaters`, and the tasks that serve them.
pub fn serve_autotune(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    heaters: &[HeaterChannel],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for h in heaters {
        let endpoints = ep
            .services()
            .action_server::<AutotuneGoal, AutotuneResult, AutotuneFeedback>(
                &format!("~/{}/autotune", h.name),
                MSG_PACKAGE,
                "Autotune",
            )?;
        let server = ActionServer::new(format!("{}: autotune", h.name), endpoints);
        tasks.push(tokio::spawn(serve(
            server,
            Arc::clone(inputs),
            h.channel,
            h.name.clone(),
        )));
    }
    Ok(tasks)
}

/// The run under way: its goal, the output thread's ticket, and what the task knows of it.
struct Run {
    id: GoalId,
    ticket: u32,
    apply: bool,
    started: bool,
    canceling: bool,
    /// Whether the cancel reached the output thread's queue (tried again every
    /// [`CANCEL_RETRY`]).
    cancel_sent: bool,
    /// When the last report came (or the goal was sent).
    last: Instant,
    /// No report for this long: the run is taken as lost.
    stale: Duration,
}

impl Run {
    /// When the task must look at the run without a report: when it is lost if none comes
    /// by then, or sooner to send a cancel again.
    fn wake_at(&self) -> Instant {
        let lost = self.last + if self.started { self.stale } else { START_WAIT };
        if self.canceling && !self.cancel_sent {
            lost.min(Instant::now() + CANCEL_RETRY)
        } else {
            lost
        }
    }
}

async fn serve(mut server: Server, inputs: Arc<Inputs>, ch: usize, name: String) {
    let mut run: Option<Run> = None;
    let mut expire_at: Option<Instant> = None;
    let mailbox = inputs.state().autotunes();
    loop {
        let wake = run
            .as_ref()
            .map(Run::wake_at)
            .into_iter()
            .chain(expire_at)
            .min();
        let timer = async {
            match wake {
                Some(t) => tokio::time::sleep_until(t.into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            event = server.next() => match event {
                Some(Event::Goal(g)) => match &run {
                    Some(r) => server.reject(g, &format!("a run is under way (goal {:?})", r.id)),
                    None => run = start(&mut server, &inputs, ch, &name, g),
                },
                Some(Event::Cancel(ids)) => {
                    if let Some(r) = run.as_mut().filter(|r| ids.contains(&r.id) && !r.canceling) {
                        r.canceling = true;
                        info!("{name}: autotune cancel requested");
                        r.cancel_sent = inputs.send(ch, Input::AutotuneCancel(r.ticket)).is_ok();
                    }
                }
                None => {}
            },
            // A report was filed (the report thread woke the task), or the run's time to
            // report is over.
            () = mailbox.filed(ch), if run.is_some() => {}
            () = timer => {}
        }
        if let Some(r) = run.as_mut() {
            if let Some((status, result)) = progress(&server, &inputs, ch, &name, r).await {
                server.end(&r.id, status, result);
                run = None;
            }
        }
        expire_at = server.expire();
    }
}

/// A value read from channel `ch`'s settings.
fn param<T>(inputs: &Inputs, ch: usize, read: impl FnOnce(&ChannelValues) -> T) -> Option<T> {
    inputs.with_params(|s| s.channel(ch).map(read))
}

fn ended(stop: &str, message: String) -> (GoalEndStatus, AutotuneResult) {
    (
        GoalEndStatus::Aborted,
        AutotuneResult {
            stop: stop.into(),
            message,
            ..AutotuneResult::default()
        },
    )
}

fn feedback(p: Progress) -> AutotuneFeedback {
    AutotuneFeedback {
        phase: p.phase.as_str().into(),
        cycles: p.cycles,
        amplitude_c: p.amplitude_c,
        period_s: p.period_s,
    }
}

/// Accepts the goal and sends it to the output thread; `None` when it ended at once (it did
/// not reach the thread).
fn start(
    server: &mut Server,
    inputs: &Inputs,
    ch: usize,
    name: &str,
    g: GoalRequest<AutotuneGoal>,
) -> Option<Run> {
    let (id, g) = server.accept(g);
    server.execute(&id);
    let amplitude_pct = if g.amplitude_pct == 0.0 {
        param(inputs, ch, |c| c.max_duty_pct).unwrap_or(100.0)
    } else {
        g.amplitude_pct
    };
    let goal = Goal {
        target_c: g.target_c,
        amplitude_pct,
        noise_band_c: g.noise_band_c,
    };
    // A report of the core never comes later than the run's timeout after the last one; a
    // minute more, and the run is taken as lost (its end dropped by a full report queue).
    let stale = Duration::from_secs_f64(
        param(inputs, ch, |c| c.autotune_timeout_s).unwrap_or(1200.0) + 60.0,
    );
    let ticket = inputs.state().ticket();
    // Reports of an earlier run that nobody took.
    inputs.state().autotunes().take(ch, 0);
    let start_by = monotonic_ns() + START_BY.as_nanos() as u64;
    if let Err(e) = inputs.send(
        ch,
        Input::Autotune {
            ticket,
            goal,
            start_by,
        },
    ) {
        let (status, result) = ended(
            "refused",
            format!("{name}: the goal did not reach the output thread: {e}"),
        );
        server.end(&id, status, result);
        return None;
    }
    info!(
        "{name}: autotune to {} °C, relay {} %, noise band {} °C{}",
        goal.target_c,
        goal.amplitude_pct,
        goal.noise_band_c,
        if g.apply { ", apply" } else { "" }
    );
    Some(Run {
        id,
        ticket,
        apply: g.apply,
        started: false,
        canceling: false,
        cancel_sent: false,
        last: Instant::now(),
        stale,
    })
}

/// Takes the core's reports of the run: publishes its feedback, and returns how it ended once
/// it has.
async fn progress(
    server: &Server,
    inputs: &Inputs,
    ch: usize,
    name: &str,
    run: &mut Run,
) -> Option<(GoalEndStatus, AutotuneResult)> {
    if run.canceling && !run.cancel_sent {
        run.cancel_sent = inputs.send(ch, Input::AutotuneCancel(run.ticket)).is_ok();
    }
    for report in inputs.state().autotunes().take(ch, run.ticket) {
        run.last = Instant::now();
        match report {
            Report::Refused(why) => {
                warn!("{name}: autotune refused: {why}");
                return Some(ended("refused", format!("{name}: refused: {why}")));
            }
            Report::Started => run.started = true,
            Report::Progress(p) => server.feedback(run.id, feedback(p)),
            Report::Finished(o) => {
                return Some(finish(inputs, name, run.apply, run.canceling, o).await)
            }
        }
    }
    let quiet = run.last.elapsed();
    if (!run.started && quiet >= START_WAIT) || quiet >= run.stale {
        let _ = inputs.send(ch, Input::AutotuneCancel(run.ticket));
        let why = if run.started {
            format!("no report from the output thread for {} s", quiet.as_secs())
        } else {
            format!(
                "the output thread did not start the run within {} s",
                START_WAIT.as_secs()
            )
        };
        return Some(ended(
            "lost",
            format!("{name}: {why}; the run was canceled"),
        ));
    }
    None
}

/// The result of a run that ended with `o`; with `apply` and gains, sets them as parameters.
async fn finish(
    inputs: &Inputs,
    name: &str,
    apply: bool,
    canceling: bool,
    o: Outcome,
) -> (GoalEndStatus, AutotuneResult) {
    let mut r = AutotuneResult {
        stop: o.stop.name().into(),
        message: format!("{name}: {}", o.stop),
        cycles: o.progress.cycles,
        ..AutotuneResult::default()
    };
    let status = match (o.stop, o.estimate, o.gains) {
        (Stop::Converged, Some(e), Some(g)) => {
            r.converged = true;
            r.ku = e.ku;
            r.tu_s = e.tu_s;
            r.pid_kp = g.kp;
            r.pid_ki = g.ki;
            r.pid_kd = g.kd;
            r.pid_d_filter_s = g.d_filter_s;
            r.rule = RULE.into();
            r.delivered_on_pct = e.delivered_on_pct;
            if let Some(m) = e.model {
                r.model_identified = true;
                r.model_gain_c_per_pct = m.gain_c_per_pct;
                r.model_tau_s = m.tau_s;
                r.model_dead_time_s = m.dead_time_s;
                r.model_ambient_c = m.ambient_c;
                r.model_sensor_tau_s = m.sensor_tau_s;
            }
            if let Some(summary) = e.model_summary() {
                r.message.push_str(&format!("; {summary}"));
            }
            if let Some(s) = o.sizing {
                r.period_ok = s.period_ok;
                r.min_times_ok = s.min_times_ok;
                r.recommended_period_ms = s.recommended_period_ms.min(u32::MAX as u64) as u32;
                r.sizing = s.broken.iter().flatten().map(|b| b.to_string()).collect();
            }
            if apply {
                let model = e.model.map(|m| {
                    [
                        ("model_gain_c_per_pct", m.gain_c_per_pct),
                        ("model_tau_s", m.tau_s),
                        ("model_dead_time_s", m.dead_time_s),
                        ("model_ambient_c", m.ambient_c),
                        ("model_sensor_tau_s", m.sensor_tau_s),
                    ]
                });
                let items = [
                    ("pid_kp", g.kp),
                    ("pid_ki", g.ki),
                    ("pid_kd", g.kd),
                    ("pid_d_filter_s", g.d_filter_s),
                ]
                .into_iter()
                .chain(model.into_iter().flatten())
                .map(|(k, v)| (format!("{name}.{k}"), ParameterValue::Double(v)))
                .collect();
                match inputs.set_params(items, "autotune").await {
                    Ok(()) => r.applied = true,
                    Err(e) => r
                        .message
                        .push_str(&format!("; the gains were not applied: {e}")),
                }
            }
            info!(
                "{name}: autotune converged: Ku {:.4} %/°C, Tu {:.2} s; pid_kp {:.4} pid_ki {:.5} \
                 pid_kd {:.4}{}{}",
                e.ku,
                e.tu_s,
                g.kp,
                g.ki,
                g.kd,
                if r.applied { " (applied)" } else { "" },
                e.model_summary()
                    .map(|s| format!("; {s}"))
                    .unwrap_or_default()
            );
            if canceling {
                GoalEndStatus::Canceled
            } else {
                GoalEndStatus::Succeeded
            }
        }
        (Stop::Canceled, ..) => GoalEndStatus::Canceled,
        _ if canceling => GoalEndStatus::Canceled,
        _ => GoalEndStatus::Aborted,
    };
    (status, r)
}
