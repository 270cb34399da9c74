//! Output thread → ROS for the three-point valves: `~/valve/<NAME>/state` on every snapshot the
//! output thread sends, the valve's state file (`state_dir`), the answers to
//! `~/valve/<NAME>/reset`, and one `/diagnostics` status per valve — ERROR while a fault is
//! latched (`motor_stalled`, `switch_implausible`, `travel_mismatch`, with its figures), WARN
//! while unreferenced, when the uncertainty of the estimate exceeds `NAME.max_uncertainty_pct`,
//! while the position feedback is silent, after a command timeout, while the valve's loop holds
//! for want of a fresh process value or has driven the valve to its safe position (with the
//! reading's age and the timeouts), and in manual mode; OK otherwise; STALE before the first
//! snapshot. Inputs the valve refused are counted by it and logged here (rate-limited per
//! place, as every warning).

use crate::clock;
use crate::core::valve::{
    Activity, Control, Dir, LoopState, Manual, Motion, StallCause, ValveFault, ValveRefusal,
};
use crate::core::{ValveConfig, ValveStatus, NS_PER_MS};
use crate::ros::config::logging::escape_controls;
use crate::ros::config::valve_state::{write_state, Stamp, StateRecord, STATE_MARGIN_PCT};
use crate::ros::inbound::valve::ValveAnswers;
use crate::ros::interface::msg::{self, DiagnosticStatus, KeyValue};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use crate::ros::wire::mw::Publisher;
use log::{debug, error, info, warn};
use ros2_client::builtin_interfaces::Time;
use std::path::PathBuf;
use std::sync::Arc;

/// While the valve moves its state file is written at most this often, ns (and at every start
/// and stop of a move).
pub const STATE_WRITE_MOVING: i64 = 1_000_000_000;

/// At rest the state file is written afresh this often, so that what a restart after a kill
/// adds to the bounds stays bounded, ns.
pub const STATE_WRITE_RESTING: i64 = 30_000_000_000;

/// How long a report may be on its way from the output thread, counted when a record of the
/// last snapshot is written afresh, ns.
pub const REPORT_WAY: i64 = 1_000_000_000;

/// One valve's state file and when it was last written.
struct StateFile {
    dir: PathBuf,
    config: ValveConfig,
    /// The last record written, its wall time, and whether the valve was moving then.
    last: Option<(StateRecord, i64, bool)>,
    failing: bool,
}

impl StateFile {
    /// Writes the record of `status` if due: the first, at a move's start and stop and when the
    /// lines are held or released, every
    /// [`STATE_WRITE_MOVING`] while moving, at rest once the bounds leave the recorded ones
    /// widened by [`STATE_MARGIN_PCT`] (at most that often; the restore widens them as much),
    /// and every [`STATE_WRITE_RESTING`] at rest.
    fn update(&mut self, name: &str, status: &ValveStatus, stamp: Stamp) {
        let rec = StateRecord::of(&self.config, status, stamp);
        let now = stamp.wall_ns;
        let moving = status.motion != Motion::Stopped;
        let due = match &self.last {
            None => true,
            Some((last, at, was_moving)) => {
                let age = now - at;
                // At rest a record still holds while the bounds stay within its own, widened by
                // a margin: a noisy feedback does not rewrite the file at every sample.
                let [_, lo, hi] = rec.motor;
                let [_, was_lo, was_hi] = last.motor;
                let held = lo >= was_lo - STATE_MARGIN_PCT
                    && hi <= was_hi + STATE_MARGIN_PCT
                    && rec.lines_held == last.lines_held;
                let quiet = !moving && held;
                // A move's start and stop, and the lines held or released (a stop of the node,
                // the e-stop, a fault), are written at once.
                *was_moving != moving
                    || rec.lines_held != last.lines_held
                    || (!quiet && age >= STATE_WRITE_MOVING)
                    || age >= STATE_WRITE_RESTING
            }
        };
        if !due {
            return;
        }
        match write_state(&self.dir, name, &rec.encode(name)) {
            Ok(()) => {
                if self.failing {
                    info!("valve {name}: state file written again");
                }
                self.failing = false;
                self.last = Some((rec, now, moving));
            }
            Err(e) => {
                if !self.failing {
                    error!(
                        "valve {name}: cannot write its state file in {}: {e}; a restart will \
                         not find the position",
                        self.dir.display()
                    );
                }
                self.failing = true;
            }
        }
    }
}

/// One valve on the report side: its publisher, what its diagnostics judge by, its last
/// snapshot.
pub struct ValveOut {
    name: String,
    /// The channels of its lines, `pw01/pw02` (open/close), for the diagnostics' hardware id.
    lines: String,
    state: Publisher<msg::ValveState>,
    last: Option<ValveStatus>,
    file: Option<StateFile>,
    /// Its index, and where the answers to its resets go.
    answers: Option<(usize, Arc<ValveAnswers>)>,
}

impl ValveOut {
    /// The publisher of `~/valve/<name>/state` for each valve, `(name, open channel name, close
    /// channel name)` in the order the valves were made.
    pub fn create(
        ep: &mut Endpoints<'_>,
        valves: &[(String, String, String)],
    ) -> Result<Vec<ValveOut>, EndpointError> {
        let mut out = Vec::with_capacity(valves.len());
        for (name, open, close) in valves {
            out.push(ValveOut {
                name: name.clone(),
                lines: format!("{open}/{close}"),
                state: ep.publisher(&format!("~/valve/{name}/state"), qos::status())?,
                last: None,
                file: None,
                answers: None,
            });
        }
        Ok(out)
    }

    /// Keeps this valve's state file in `dir` (its settings `config`).
    pub fn keep_state(&mut self, dir: PathBuf, config: ValveConfig) {
        self.file = Some(StateFile {
            dir,
            config,
            last: None,
            failing: false,
        });
    }

    /// Files the answers to this valve's (number `index`) resets in `answers`.
    pub fn answer_to(&mut self, index: usize, answers: Arc<ValveAnswers>) {
        self.answers = Some((index, answers));
    }

    /// Once a second: the state file written afresh at rest (see [`STATE_WRITE_RESTING`]). The
    /// last snapshot still holds but for a change whose report is on its way: the record is
    /// stamped [`REPORT_WAY`] earlier, so a restore counts that too.
    pub fn periodic(&mut self) {
        if let (Some(f), Some(s)) = (self.file.as_mut(), self.last.as_ref()) {
            f.update(&self.name, s, Stamp::now().earlier(REPORT_WAY));
        }
    }

    /// A snapshot taken at monotonic `at_ns` came: it is published, kept for the diagnostics,
    /// written to the state file (stamped with the wall-clock time it was taken).
    pub fn on_status(&mut self, status: ValveStatus, at_ns: crate::core::Nanos) {
        let before = self.last.and_then(|s| s.fault);
        if status.fault.is_some() && before.is_none() {
            if let Some(f) = &status.fault {
                error!("valve {}: {}", self.name, fault_text(&self.name, f));
            }
        }
        if let Some((k, a)) = &self.answers {
            a.note(*k, status.fault, status.reset);
        }
        if let Some(f) = self.file.as_mut() {
            let since = clock::monotonic_ns().saturating_sub(at_ns);
            f.update(&self.name, &status, Stamp::now().earlier(since as i64));
        }
        let was = self.last.map(|s| (s.referenced, s.switches));
        if was.is_some_and(|w| w != (status.referenced, status.switches)) {
            // Rare (a reference, an end switch): worth a line on the console.
            info!(
                "valve {}: position {:.1} %, {}, switches open {} close {}",
                self.name,
                status.position_pct,
                if status.referenced {
                    "referenced"
                } else {
                    "unreferenced"
                },
                on_off(status.switches[0]),
                on_off(status.switches[1])
            );
        }
        let before = self.last.map_or(0, |s| s.refused.total());
        let refused = status.refused.total().saturating_sub(before);
        if let (true, Some(r)) = (refused > 0, status.last_refusal) {
            // Counted by the valve; logged here, where the log is rate-limited per place.
            let more = if refused > 1 {
                format!(" ({refused} refused since the last report)")
            } else {
                String::new()
            };
            warn!(
                "valve {}: {}{more}",
                self.name,
                refusal_text(&self.name, &r)
            );
        }
        self.last = Some(status);
        if let Err(e) = self.state.publish(state_msg(&self.name, &status)) {
            debug!("valve {}: cannot publish state: {e}", self.name);
        }
    }

    /// The valve's `/diagnostics` status.
    pub fn to_status(&self, node_name: &str) -> DiagnosticStatus {
        diagnostic(node_name, &self.name, &self.lines, self.last.as_ref())
    }

    /// The level of the valve's `/diagnostics` status ([`DiagnosticStatus::OK`] ...), as
    /// [`ValveOut::to_status`] gives it.
    pub fn level(&self) -> u8 {
        diagnostic("", &self.name, &self.lines, self.last.as_ref()).level
    }
}

fn on_off(active: bool) -> &'static str {
    if active {
        "active"
    } else {
        "inactive"
    }
}

/// The `ValveState` message of `status`.
pub fn state_msg(name: &str, s: &ValveStatus) -> msg::ValveState {
    msg::ValveState {
        stamp: Time::from_nanos(clock::wall_ns()),
        name: name.to_string(),
        position_pct: s.position_pct,
        target_pct: s.target_pct,
        motion: motion_name(s.motion).into(),
        activity: activity_name(s.activity).into(),
        referenced: s.referenced,
        run_since_reference_s: s.run_since_reference as f64 / 1e9,
        uncertainty_pct: s.uncertainty_pct,
        position_low_pct: s.low_pct,
        position_high_pct: s.high_pct,
        restored: s.restored,
        recalibration_due: s.recalibration_due,
        timed_out: s.timed_out,
        estop: s.estop,
        open_switch: s.switches[0],
        close_switch: s.switches[1],
        fault: s.fault.map_or("", |f| f.name()).to_string(),
        feedback_pct: s.feedback_pct,
        moves: s.moves,
        control: s.control.control.as_str().into(),
        loop_state: s.control.state.as_str().into(),
        manual: s.control.manual.map_or("", |m| m.as_str()).into(),
        setpoint: s.control.setpoint,
        process_value: s.control.process_value,
        process_age_s: s.control.process_age.map_or(f64::NAN, |a| a as f64 / 1e9),
        stale_readings: s.control.stale.0,
        position_commands_refused: s.refused.position,
        setpoints_refused: s.refused.setpoint,
        process_values_refused: s.refused.process_value,
        manual_refused: s.refused.manual,
        starts: s.starts,
        starts_last_hour: s.starts_last_hour,
        max_starts_per_h: s.max_starts_per_h,
    }
}

fn drive_name(d: Dir) -> &'static str {
    match d {
        Dir::Open => "opening",
        Dir::Close => "closing",
    }
}

fn end_name(d: Dir) -> &'static str {
    match d {
        Dir::Open => "open",
        Dir::Close => "close",
    }
}

/// What a latched fault means, with its figures, for `/diagnostics` and the log.
pub fn fault_text(name: &str, f: &ValveFault) -> String {
    let reset = format!("lines off until ~/valve/{name}/reset");
    match *f {
        ValveFault::MotorStalled {
            cause: StallCause::NoEndSwitch(d),
            drive_ms,
            expected_pct,
            ..
        } => format!(
            "motor_stalled: the end move {} ran its whole drive ({drive_ms:.0} ms after the start \
             lag, enough for {expected_pct:.1} % at the slowest travel) and the {} end switch \
             did not report; {reset}",
            drive_name(d),
            end_name(d)
        ),
        ValveFault::MotorStalled {
            cause: StallCause::NoFeedbackMotion(d),
            drive_ms,
            moved_pct,
            expected_pct,
        } => format!(
            "motor_stalled: {drive_ms:.0} ms of drive {} after the start lag moved the feedback \
             {moved_pct:.2} %, where a healthy valve moves at least {expected_pct:.1} %; {reset}",
            drive_name(d)
        ),
        ValveFault::SwitchImplausible {
            switches,
            low_pct,
            high_pct,
        } => format!(
            "switch_implausible: end switches open {} close {} while the valve can only be \
             within {low_pct:.1}..{high_pct:.1} %; {reset} once both switches release",
            on_off(switches[0]),
            on_off(switches[1])
        ),
        ValveFault::TravelMismatch {
            dir,
            measured_ms,
            configured_ms,
        } => format!(
            "travel_mismatch: the {} travel time measured {:.0}..{:.0} ms, configured {:.0} ms \
             (more than 10 % off); {reset}",
            end_name(dir),
            measured_ms[0],
            measured_ms[1],
            configured_ms
        ),
    }
}

fn motion_name(m: Motion) -> &'static str {
    match m {
        Motion::Stopped => "stopped",
        Motion::Opening => "opening",
        Motion::Closing => "closing",
    }
}

fn activity_name(a: Activity) -> &'static str {
    match a {
        Activity::Tracking => "tracking",
        Activity::Referencing => "referencing",
        Activity::Recalibrating => "recalibrating",
        Activity::Exercising => "exercising",
    }
}

/// The diagnostics status of valve `name` (`<node>: valve <name>`).
pub fn diagnostic(
    node_name: &str,
    name: &str,
    lines: &str,
    last: Option<&ValveStatus>,
) -> DiagnosticStatus {
    let full = format!("{node_name}: valve {name}");
    let Some(s) = last else {
        return DiagnosticStatus {
            level: DiagnosticStatus::STALE,
            name: full,
            message: "no report from the output thread yet".into(),
            hardware_id: lines.into(),
            values: Vec::new(),
        };
    };
    let c = &s.control;
    let (level, message) = if let Some(f) = &s.fault {
        (DiagnosticStatus::ERROR, fault_text(name, f))
    } else {
        // What the valve knows first, then what its loop does, then manual mode: each says
        // why it warns; several at once are all given.
        let mut warns: Vec<String> = Vec::new();
        if !s.referenced {
            warns.push("unreferenced: the position is not known".into());
        } else if s.uncertainty_pct > s.max_uncertainty_pct {
            warns.push(format!(
                "uncertainty {:.1} % above max_uncertainty_pct {} %",
                s.uncertainty_pct, s.max_uncertainty_pct
            ));
        } else if s.feedback_silent {
            warns.push(
                "position feedback silent: the position counts on the drive times alone".into(),
            );
        }
        if s.timed_out {
            warns.push(if c.control == Control::Pid {
                "no setpoint within command_timeout_ms: on_timeout acted".into()
            } else {
                "no position command within command_timeout_ms".into()
            });
        }
        if let Some(w) = loop_warning(s) {
            warns.push(w);
        }
        if let Some(m) = c.manual {
            warns.push(manual_text(name, m, s.target_pct));
        }
        if warns.is_empty() {
            let ok = if c.state == LoopState::Waiting {
                format!("ok; the loop waits for a setpoint on ~/valve/{name}/setpoint")
            } else {
                "ok".to_string()
            };
            (DiagnosticStatus::OK, ok)
        } else {
            (DiagnosticStatus::WARN, warns.join("; "))
        }
    };
    let kv = |key: &str, value: String| KeyValue {
        key: key.into(),
        value,
    };
    let secs = |ns: Option<crate::core::Nanos>| ns.map_or(f64::NAN, |a| a as f64 / 1e9);
    DiagnosticStatus {
        level,
        name: full,
        message,
        hardware_id: lines.into(),
        values: vec![
            kv("position_pct", format!("{:.2}", s.position_pct)),
            kv("target_pct", format!("{:.2}", s.target_pct)),
            kv("motion", motion_name(s.motion).into()),
            kv("activity", activity_name(s.activity).into()),
            kv("referenced", s.referenced.to_string()),
            kv(
                "run_since_reference_s",
                format!("{:.1}", s.run_since_reference as f64 / 1e9),
            ),
            kv("uncertainty_pct", format!("{:.2}", s.uncertainty_pct)),
            kv("position_low_pct", format!("{:.2}", s.low_pct)),
            kv("position_high_pct", format!("{:.2}", s.high_pct)),
            kv("restored", s.restored.to_string()),
            kv("recalibration_due", s.recalibration_due.to_string()),
            kv("fault", s.fault.map_or("", |f| f.name()).to_string()),
            kv("feedback_pct", format!("{:.2}", s.feedback_pct)),
            kv(
                "measured_travel_ms",
                format!(
                    "{:.0}/{:.0}",
                    s.measured_travel_ms[0], s.measured_travel_ms[1]
                ),
            ),
            kv(
                "measured_start_lag_ms",
                format!("{:.0}/{:.0}", s.measured_lag_ms[0], s.measured_lag_ms[1]),
            ),
            kv("open_switch", s.switches[0].to_string()),
            kv("close_switch", s.switches[1].to_string()),
            kv("moves", s.moves.to_string()),
            kv("starts", s.starts.to_string()),
            kv("starts_last_hour", s.starts_last_hour.to_string()),
            kv("max_starts_per_h", s.max_starts_per_h.to_string()),
            kv(
                "deadband_in_force_pct",
                format!("{:.2}", s.deadband_in_force_pct),
            ),
            kv("control", c.control.as_str().into()),
            kv("loop_output", c.output.as_str().into()),
            kv("loop_state", c.state.as_str().into()),
            kv("manual", c.manual.map_or("", |m| m.as_str()).into()),
            kv("setpoint", format!("{}", c.setpoint)),
            kv("process_value", format!("{}", c.process_value)),
            kv("process_age_s", format!("{:.2}", secs(c.process_age))),
            kv("process_timeout_ms", (c.timeout / NS_PER_MS).to_string()),
            kv("stale_readings", c.stale.0.to_string()),
            kv("position_commands_refused", s.refused.position.to_string()),
            kv("setpoints_refused", s.refused.setpoint.to_string()),
            kv(
                "process_values_refused",
                s.refused.process_value.to_string(),
            ),
            kv("manual_refused", s.refused.manual.to_string()),
            kv(
                "last_refusal",
                s.last_refusal
                    .map_or(String::new(), |r| refusal_text(name, &r)),
            ),
        ],
    }
}

/// Why the loop makes the valve warn, with its figures: it holds for want of a fresh process
/// value, or it drove the valve to its safe position.
fn loop_warning(s: &ValveStatus) -> Option<String> {
    let c = &s.control;
    let timeout_ms = c.timeout / NS_PER_MS;
    let age = match c.process_age {
        Some(a) => format!("the last fresh reading is {:.1} s old", a as f64 / 1e9),
        None => "no fresh reading since the loop started".to_string(),
    };
    match c.state {
        LoopState::Holding => Some(format!(
            "process value stale: {age} (process_timeout_ms {timeout_ms}): the loop stopped and \
             the valve holds at {:.1} %{}",
            s.position_pct,
            c.safe.map_or(String::new(), |p| format!(
                "; after safe_after_ms {} it goes to safe_position_pct {p} %",
                c.safe_after / NS_PER_MS
            ))
        )),
        LoopState::Safe => Some(format!(
            "safe position: {age} (process_timeout_ms {timeout_ms}, then safe_after_ms {}): \
             the loop stopped and the valve is driven to safe_position_pct {} %, at {:.1} % now",
            c.safe_after / NS_PER_MS,
            c.safe.unwrap_or(f64::NAN),
            s.position_pct
        )),
        _ => None,
    }
}

/// Manual mode, for the diagnostics' message.
fn manual_text(name: &str, m: Manual, target_pct: f64) -> String {
    let what = match m {
        Manual::Position(_) => format!("position {target_pct:.1} %"),
        m => m.as_str().to_string(),
    };
    format!(
        "manual mode: {what}; the loop and the position commands are set aside until auto on \
         ~/valve/{name}/manual"
    )
}

/// A refusal for the log and the diagnostics: control characters in an echoed word escaped.
fn refusal_text(name: &str, r: &ValveRefusal) -> String {
    let text = r
        .to_string()
        .replace("~/valve/NAME/", &format!("~/valve/{name}/"));
    escape_controls(&text).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::valve::ControlStatus;

    fn status() -> ValveStatus {
        ValveStatus {
            position_pct: 40.0,
            low_pct: 36.0,
            high_pct: 45.0,
            motor: [40.5, 37.0, 45.0],
            restored: false,
            fault: None,
            reset: None,
            feedback_pct: f64::NAN,
            feedback_silent: false,
            measured_travel_ms: [f64::NAN; 2],
            measured_lag_ms: [f64::NAN; 2],
            target_pct: 40.0,
            motion: Motion::Stopped,
            activity: Activity::Tracking,
            referenced: true,
            run_since_reference: 30_000_000_000,
            uncertainty_pct: 5.0,
            max_uncertainty_pct: 10.0,
            recalibration_due: false,
            timed_out: false,
            estop: false,
            live: true,
            switches: [false; 2],
            moves: 3,
            starts: 3,
            starts_last_hour: 3,
            max_starts_per_h: 0,
            deadband_in_force_pct: 0.5,
            control: ControlStatus::default(),
            refused: Default::default(),
            last_refusal: None,
        }
    }

    /// The state file follows a move and a stop of the node at once, and is not rewritten at
    /// rest while the bounds stay within the record and its margin.
    #[test]
    fn the_state_file_follows_moves_and_the_stop_at_once() {
        use crate::ros::config::valve_state::read_state;
        let dir = std::env::temp_dir().join(format!("pwm-valve-out-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let config = crate::core::ValveParams::default().validate().unwrap();
        let mut f = StateFile {
            dir: dir.clone(),
            config,
            last: None,
            failing: false,
        };
        let t0 = Stamp::now();
        let at = |ms: i64| Stamp {
            wall_ns: t0.wall_ns + ms * 1_000_000,
            boot_ns: t0.boot_ns + ms * 1_000_000,
            ..t0
        };
        let read = || read_state(&dir, "mix").unwrap().unwrap();
        let rest = status();
        f.update("mix", &rest, at(0));
        assert_eq!(read().stamp, at(0), "the first record");
        let moving = ValveStatus {
            motion: Motion::Opening,
            motor: [41.0, 37.0, 46.0],
            ..rest
        };
        f.update("mix", &moving, at(100));
        assert_eq!(read().stamp, at(100), "a move's start at once");
        f.update("mix", &moving, at(600));
        assert_eq!(read().stamp, at(100), "not twice within a second");
        f.update("mix", &moving, at(1_200));
        assert_eq!(read().stamp, at(1_200), "once a second while moving");
        let held = ValveStatus {
            live: false,
            ..rest
        };
        f.update("mix", &rest, at(1_300));
        f.update("mix", &held, at(1_400));
        let r = read();
        assert!(
            r.lines_held && r.stamp == at(1_400),
            "the stop at once: {r:?}"
        );
        // At rest, bounds within the record's and the margin: no rewrite.
        let noisy = ValveStatus {
            motor: [40.7, 36.6, 45.4],
            ..held
        };
        f.update("mix", &noisy, at(1_500));
        f.update("mix", &noisy, at(3_500));
        assert_eq!(read().stamp, at(1_400));
        f.update("mix", &noisy, at(1_400 + STATE_WRITE_RESTING / 1_000_000));
        assert_ne!(read().stamp, at(1_400), "written afresh at rest");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn diagnostics_warn_while_unreferenced_or_too_uncertain() {
        let d = |s: Option<&ValveStatus>| diagnostic("n", "mix", "pw01/pw02", s);
        assert_eq!(d(None).level, DiagnosticStatus::STALE);
        let ok = status();
        assert_eq!(d(Some(&ok)).level, DiagnosticStatus::OK);
        assert_eq!(d(Some(&ok)).name, "n: valve mix");
        let unref = ValveStatus {
            referenced: false,
            ..ok
        };
        assert_eq!(d(Some(&unref)).level, DiagnosticStatus::WARN);
        assert!(d(Some(&unref)).message.contains("unreferenced"));
        let vague = ValveStatus {
            uncertainty_pct: 12.0,
            ..ok
        };
        assert!(d(Some(&vague))
            .message
            .contains("above max_uncertainty_pct"));
        let one = ValveStatus {
            switches: [false, true],
            ..ok
        };
        assert_eq!(
            d(Some(&one)).level,
            DiagnosticStatus::OK,
            "at the closed end"
        );
        let both = ValveStatus {
            switches: [true, true],
            fault: Some(ValveFault::SwitchImplausible {
                switches: [true, true],
                low_pct: 0.0,
                high_pct: 100.0,
            }),
            ..unref
        };
        assert_eq!(d(Some(&both)).level, DiagnosticStatus::ERROR);
        let m = d(Some(&both)).message;
        assert!(
            m.starts_with("switch_implausible: end switches open active close active")
                && m.contains("~/valve/mix/reset"),
            "{m}"
        );
        let stalled = ValveStatus {
            fault: Some(ValveFault::MotorStalled {
                cause: StallCause::NoFeedbackMotion(Dir::Open),
                drive_ms: 612.0,
                moved_pct: 0.04,
                expected_pct: 4.0,
            }),
            ..ok
        };
        let m = d(Some(&stalled)).message;
        assert_eq!(d(Some(&stalled)).level, DiagnosticStatus::ERROR);
        assert!(
            m.starts_with("motor_stalled: 612 ms of drive opening") && m.contains("0.04 %"),
            "{m}"
        );
        let silent = ValveStatus {
            feedback_silent: true,
            ..ok
        };
        assert_eq!(d(Some(&silent)).level, DiagnosticStatus::WARN);
        let m = state_msg("mix", &ok);
        assert_eq!(
            (m.motion.as_str(), m.run_since_reference_s),
            ("stopped", 30.0)
        );
    }

    /// The loop's state on the topic and on /diagnostics: a WARN with the reading's age and
    /// the timeout while it holds, with the safe position once it went there, in manual mode;
    /// the counts of what was refused.
    #[test]
    fn the_loop_holding_safe_or_manual_warns_with_its_figures() {
        use crate::core::valve::{Control, LoopOutput, Refused};
        let d = |s: &ValveStatus| diagnostic("n", "mix", "pw01/pw02", Some(s));
        let value = |s: &DiagnosticStatus, key: &str| {
            s.values
                .iter()
                .find(|kv| kv.key == key)
                .map(|kv| kv.value.clone())
                .unwrap_or_else(|| panic!("no {key}"))
        };
        let running = ValveStatus {
            control: ControlStatus {
                control: Control::Pid,
                output: LoopOutput::Step,
                state: LoopState::Running,
                setpoint: 45.0,
                process_value: 44.5,
                process_age: Some(200_000_000),
                timeout: 1_000_000_000,
                safe: Some(20.0),
                safe_after: 500_000_000,
                ..ControlStatus::default()
            },
            ..status()
        };
        let r = d(&running);
        assert_eq!((r.level, r.message.as_str()), (DiagnosticStatus::OK, "ok"));
        assert_eq!(value(&r, "loop_state"), "running");
        assert_eq!(value(&r, "process_age_s"), "0.20");

        let holding = ValveStatus {
            control: ControlStatus {
                state: LoopState::Holding,
                process_age: Some(1_340_000_000),
                stale: (3, 5_000_000_000),
                ..running.control
            },
            ..running
        };
        let h = d(&holding);
        assert_eq!(h.level, DiagnosticStatus::WARN);
        assert!(
            h.message.starts_with(
                "process value stale: the last fresh reading is 1.3 s old (process_timeout_ms \
                 1000): the loop stopped and the valve holds at 40.0 %; after safe_after_ms 500 \
                 it goes to safe_position_pct 20 %"
            ),
            "{}",
            h.message
        );
        assert_eq!(value(&h, "stale_readings"), "3");
        let never = ValveStatus {
            control: ControlStatus {
                process_age: None,
                process_value: f64::NAN,
                ..holding.control
            },
            ..holding
        };
        assert!(d(&never)
            .message
            .contains("no fresh reading since the loop started"));

        let safe = ValveStatus {
            control: ControlStatus {
                state: LoopState::Safe,
                process_age: Some(1_600_000_000),
                ..holding.control
            },
            position_pct: 31.0,
            ..holding
        };
        let m = d(&safe).message;
        assert_eq!(d(&safe).level, DiagnosticStatus::WARN);
        assert!(
            m.contains("1.6 s old (process_timeout_ms 1000, then safe_after_ms 500)")
                && m.contains("driven to safe_position_pct 20 %, at 31.0 % now"),
            "{m}"
        );

        let bad = "wide\nopen".parse::<Manual>().unwrap_err();
        let manual = ValveStatus {
            control: ControlStatus {
                state: LoopState::Manual,
                manual: Some(Manual::Position(35.0)),
                ..running.control
            },
            target_pct: 35.0,
            refused: Refused {
                position: 1,
                setpoint: 2,
                process_value: 3,
                manual: 4,
            },
            last_refusal: Some(ValveRefusal::BadManual(bad)),
            ..running
        };
        let g = d(&manual);
        assert_eq!(g.level, DiagnosticStatus::WARN);
        assert!(
            g.message
                .starts_with("manual mode: position 35.0 %; the loop and the position commands")
                && g.message.ends_with("until auto on ~/valve/mix/manual"),
            "{}",
            g.message
        );
        assert_eq!(
            value(&g, "last_refusal"),
            "manual command refused: manual `wide\\nopen` is none of auto, open, close, stop \
             or a position in percent"
        );
        assert_eq!(
            [
                "position_commands_refused",
                "setpoints_refused",
                "process_values_refused",
                "manual_refused"
            ]
            .map(|k| value(&g, k)),
            ["1", "2", "3", "4"]
        );
        let waiting = ValveStatus {
            control: ControlStatus {
                state: LoopState::Waiting,
                ..running.control
            },
            ..running
        };
        assert_eq!(
            d(&waiting).message,
            "ok; the loop waits for a setpoint on ~/valve/mix/setpoint"
        );
        let timed_out = ValveStatus {
            timed_out: true,
            control: ControlStatus {
                state: LoopState::TimedOut,
                ..running.control
            },
            ..running
        };
        assert_eq!(
            d(&timed_out).message,
            "no setpoint within command_timeout_ms: on_timeout acted"
        );
        // Several reasons at once are all given.
        let both = ValveStatus {
            referenced: false,
            ..holding
        };
        let b = d(&both).message;
        assert!(
            b.starts_with("unreferenced") && b.contains("; process value stale"),
            "{b}"
        );
    }

    /// The loop's state, the manual command, the process value and the refusals on the state
    /// topic; a refusal's echoed word escaped.
    #[test]
    fn the_state_carries_the_loop_and_the_refusals() {
        use crate::core::valve::{Control, LoopOutput, LoopState, Manual, Refused};
        let running = ValveStatus {
            control: ControlStatus {
                control: Control::Pid,
                output: LoopOutput::Step,
                state: LoopState::Running,
                setpoint: 45.0,
                process_value: 44.5,
                process_age: Some(200_000_000),
                stale: (3, 5_000_000_000),
                ..ControlStatus::default()
            },
            ..status()
        };
        let m = state_msg("mix", &running);
        assert_eq!(
            (m.control.as_str(), m.loop_state.as_str(), m.manual.as_str()),
            ("pid", "running", "")
        );
        assert_eq!(
            (
                m.setpoint,
                m.process_value,
                m.process_age_s,
                m.stale_readings
            ),
            (45.0, 44.5, 0.2, 3)
        );
        let never = ValveStatus {
            control: ControlStatus {
                process_age: None,
                process_value: f64::NAN,
                ..running.control
            },
            ..running
        };
        assert!(state_msg("mix", &never).process_age_s.is_nan());
        let bad = "wide\nopen".parse::<Manual>().unwrap_err();
        let manual = ValveStatus {
            control: ControlStatus {
                state: LoopState::Manual,
                manual: Some(Manual::Position(35.0)),
                ..running.control
            },
            refused: Refused {
                position: 1,
                setpoint: 2,
                process_value: 3,
                manual: 4,
            },
            ..running
        };
        let m = state_msg("mix", &manual);
        assert_eq!(
            (m.loop_state.as_str(), m.manual.as_str()),
            ("manual", "position")
        );
        assert_eq!(
            (
                m.position_commands_refused,
                m.setpoints_refused,
                m.process_values_refused,
                m.manual_refused
            ),
            (1, 2, 3, 4)
        );
        assert_eq!(
            refusal_text("mix", &ValveRefusal::BadManual(bad)),
            "manual command refused: manual `wide\\nopen` is none of auto, open, close, stop \
             or a position in percent"
        );
        assert!(refusal_text("mix", &ValveRefusal::PositionInManual).contains("~/valve/mix/manual"));
    }
}
