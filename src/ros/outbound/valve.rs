//! Output thread → ROS for the three-point valves: `~/valve/<NAME>/state` on every snapshot the
//! output thread sends, and one `/diagnostics` status per valve — ERROR while both end switches
//! are active (a wiring or switch fault: nothing drives either way), WARN while unreferenced, when
//! the uncertainty of the estimate exceeds `NAME.max_uncertainty_pct`, or after a command
//! timeout; OK otherwise; STALE before the first snapshot.

use crate::clock;
use crate::core::valve::{Activity, Motion};
use crate::core::ValveStatus;
use crate::ros::interface::msg::{self, DiagnosticStatus, KeyValue};
use crate::ros::interface::qos;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{debug, info};
use ros2_client::builtin_interfaces::Time;
use ros2_client::Publisher;

/// One valve on the report side: its publisher, what its diagnostics judge by, its last
/// snapshot.
pub struct ValveOut {
    name: String,
    /// The channels of its lines, `pw01/pw02` (open/close), for the diagnostics' hardware id.
    lines: String,
    state: Publisher<msg::ValveState>,
    last: Option<ValveStatus>,
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
            });
        }
        Ok(out)
    }

    /// A snapshot came: it is published, and kept for the diagnostics.
    pub fn on_status(&mut self, status: ValveStatus) {
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
        self.last = Some(status);
        if let Err(e) = self.state.publish(state_msg(&self.name, &status)) {
            debug!("valve {}: cannot publish state: {e}", self.name);
        }
    }

    /// The valve's `/diagnostics` status.
    pub fn to_status(&self, node_name: &str) -> DiagnosticStatus {
        diagnostic(node_name, &self.name, &self.lines, self.last.as_ref())
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
        recalibration_due: s.recalibration_due,
        timed_out: s.timed_out,
        estop: s.estop,
        open_switch: s.switches[0],
        close_switch: s.switches[1],
        moves: s.moves,
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
    let (level, message) = if s.switches == [true, true] {
        (
            DiagnosticStatus::ERROR,
            "both end switches active: a wiring or switch fault; no drive either way until one \
             releases"
                .to_string(),
        )
    } else if !s.referenced {
        (
            DiagnosticStatus::WARN,
            "unreferenced: the position is not known".to_string(),
        )
    } else if s.uncertainty_pct > s.max_uncertainty_pct {
        (
            DiagnosticStatus::WARN,
            format!(
                "uncertainty {:.1} % above max_uncertainty_pct {} %",
                s.uncertainty_pct, s.max_uncertainty_pct
            ),
        )
    } else if s.timed_out {
        (
            DiagnosticStatus::WARN,
            "no position command within command_timeout_ms".to_string(),
        )
    } else {
        (DiagnosticStatus::OK, "ok".to_string())
    };
    let kv = |key: &str, value: String| KeyValue {
        key: key.into(),
        value,
    };
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
            kv("recalibration_due", s.recalibration_due.to_string()),
            kv("moves", s.moves.to_string()),
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        }
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
            ..unref
        };
        assert_eq!(d(Some(&both)).level, DiagnosticStatus::ERROR);
        assert!(d(Some(&both))
            .message
            .starts_with("both end switches active"));
        let m = state_msg("mix", &ok);
        assert_eq!(
            (m.motion.as_str(), m.run_since_reference_s),
            ("stopped", 30.0)
        );
    }
}
