//! `~/<ch>/autotune` (`pwm_actuator_msgs/action/Autotune`) of each channel with feedback: the
//! action that runs the relay autotune (`core::heater::autotune`) and, with `apply`, sets the
//! gains it found as parameters.
//!
//! The run itself lives in the output thread's channel core, which alone knows when the line
//! was really on and stops the run on a heater fault, the e-stop, a deactivate or a disable.
//! The action's task sends the goal and a cancel through the request queue and reads the
//! core's reports (start, each cycle, the end) that the report thread files in the node state.
//! One run per channel at a time: a second goal is rejected while one runs.
//!
//! A refused goal (no reading yet, the channel not running, a target outside the limits, an
//! amplitude above `max_duty_pct`, ...) is accepted and then aborted, so the client gets the
//! reason in the result's `message`.

use crate::core::heater::autotune::{Goal, Outcome, Progress, Report, Stop};
use crate::engine::Input;
use crate::ros::inbound::heater::HeaterChannel;
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg::{AutotuneFeedback, AutotuneGoal, AutotuneResult, MSG_PACKAGE};
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use ros2_client::action::{AsyncActionServer, ExecutingGoalHandle, GoalEndStatus};
use ros2_client::ParameterValue;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::task::JoinHandle;

/// The rule that gives the gains, as the result names it.
pub const RULE: &str = "tyreus_luyben";
/// How often the task looks for the core's reports.
const POLL: Duration = Duration::from_millis(50);
/// How long the output thread has to answer a goal.
const START_WAIT: Duration = Duration::from_secs(2);
/// How long the result waits for its client to ask for it.
const RESULT_WAIT: Duration = Duration::from_secs(30);

type Server = AsyncActionServer<AutotuneGoal, AutotuneResult, AutotuneFeedback>;
type Executing = ExecutingGoalHandle<AutotuneGoal>;

/// The autotune action of each channel in `heaters`, and the tasks that serve them.
pub fn serve_autotune(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    heaters: &[HeaterChannel],
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    for h in heaters {
        let server = ep
            .services()
            .action_server::<AutotuneGoal, AutotuneResult, AutotuneFeedback>(
                &format!("~/{}/autotune", h.name),
                MSG_PACKAGE,
                "Autotune",
            )?;
        let server = AsyncActionServer::new(server);
        tasks.push(tokio::spawn(serve(
            server,
            Arc::clone(inputs),
            h.channel,
            h.name.clone(),
        )));
    }
    Ok(tasks)
}

async fn serve(server: Server, inputs: Arc<Inputs>, ch: usize, name: String) {
    loop {
        let handle = match server.receive_new_goal().await {
            Ok(h) => h,
            Err(e) => {
                warn!("{name}: autotune: unreadable goal: {e}");
                continue;
            }
        };
        let Some(goal) = server.get_new_goal(handle) else {
            continue;
        };
        let accepted = match server.accept_goal(handle).await {
            Ok(a) => a,
            Err(e) => {
                warn!("{name}: autotune: cannot accept the goal: {e:?}");
                continue;
            }
        };
        let exec = match server.start_executing_goal(accepted).await {
            Ok(x) => x,
            Err(e) => {
                warn!("{name}: autotune: cannot start the goal: {e:?}");
                continue;
            }
        };
        let (status, result) = execute(&server, &inputs, ch, &name, goal, exec).await;
        match tokio::time::timeout(
            RESULT_WAIT,
            server.send_result_response(exec, status, result),
        )
        .await
        {
            Ok(Ok(())) => {}
            Ok(Err(e)) => warn!("{name}: autotune: cannot send the result: {e:?}"),
            Err(_) => warn!(
                "{name}: autotune: the client did not ask for its result within {} s",
                RESULT_WAIT.as_secs()
            ),
        }
    }
}

/// A channel parameter's value as f64, if it is a double.
fn param(inputs: &Inputs, name: &str, key: &str) -> Option<f64> {
    inputs.with_params(|s| match s.get(&format!("{name}.{key}")) {
        Some(ParameterValue::Double(v)) => Some(*v),
        _ => None,
    })
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

async fn execute(
    server: &Server,
    inputs: &Inputs,
    ch: usize,
    name: &str,
    g: AutotuneGoal,
    exec: Executing,
) -> (GoalEndStatus, AutotuneResult) {
    let amplitude_pct = if g.amplitude_pct == 0.0 {
        param(inputs, name, "max_duty_pct").unwrap_or(100.0)
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
    let stale =
        Duration::from_secs_f64(param(inputs, name, "autotune_timeout_s").unwrap_or(1200.0) + 60.0);
    let ticket = inputs.state().reset_ticket();
    // Reports of an earlier run that nobody took.
    inputs.state().take_autotune(ch, 0);
    if let Err(e) = inputs.send(ch, Input::Autotune { ticket, goal }) {
        return ended(
            "refused",
            format!("{name}: the goal did not reach the output thread: {e}"),
        );
    }
    info!(
        "{name}: autotune to {} °C, relay {} %, noise band {} °C{}",
        goal.target_c,
        goal.amplitude_pct,
        goal.noise_band_c,
        if g.apply { ", apply" } else { "" }
    );
    let (mut started, mut canceling, mut last) = (false, false, Instant::now());
    loop {
        for report in inputs.state().take_autotune(ch, ticket) {
            last = Instant::now();
            match report {
                Report::Refused(why) => {
                    warn!("{name}: autotune refused: {why}");
                    return ended("refused", format!("{name}: refused: {why}"));
                }
                Report::Started => started = true,
                Report::Progress(p) => {
                    if let Err(e) = server.publish_feedback(exec, feedback(p)).await {
                        warn!("{name}: autotune: cannot publish feedback: {e:?}");
                    }
                }
                Report::Finished(o) => return finish(inputs, name, g.apply, canceling, o),
            }
        }
        if (!started && last.elapsed() > START_WAIT) || last.elapsed() > stale {
            let _ = inputs.send(ch, Input::AutotuneCancel(ticket));
            return ended(
                "lost",
                format!("{name}: no report from the output thread; the run was canceled"),
            );
        }
        tokio::select! {
            _ = tokio::time::sleep(POLL) => {}
            cancel = server.receive_cancel_request() => match cancel {
                Ok(c) => {
                    let mine = c.contains_goal(&exec.goal_id());
                    let ids = mine.then_some(exec.goal_id()).into_iter();
                    if let Err(e) = server.respond_to_cancel_requests(&c, ids).await {
                        warn!("{name}: autotune: cannot answer a cancel: {e}");
                    }
                    if mine && !canceling {
                        canceling = true;
                        info!("{name}: autotune cancel requested");
                        let _ = inputs.send(ch, Input::AutotuneCancel(ticket));
                    }
                }
                Err(e) => warn!("{name}: autotune: unreadable cancel request: {e}"),
            },
            other = server.receive_new_goal() => {
                if let Ok(h) = other {
                    warn!("{name}: autotune goal rejected: a run is under way");
                    let _ = server.reject_goal(h).await;
                }
            }
        }
    }
}

/// The result of a run that ended with `o`; with `apply` and gains, sets them as parameters.
fn finish(
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
                match inputs.set_params(items, "autotune") {
                    Ok(()) => r.applied = true,
                    Err(e) => r
                        .message
                        .push_str(&format!("; the gains were not applied: {e}")),
                }
            }
            info!(
                "{name}: autotune converged: Ku {:.4} %/°C, Tu {:.2} s; pid_kp {:.4} pid_ki {:.5} \
                 pid_kd {:.4}{}",
                e.ku,
                e.tu_s,
                g.kp,
                g.ki,
                g.kd,
                if r.applied { " (applied)" } else { "" }
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
