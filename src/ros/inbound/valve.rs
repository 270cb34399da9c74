//! The three-point valves' inputs: each valve is made in the output thread on its two channels'
//! lines, and `~/valve/<NAME>/position` (`std_msgs/Float64`, percent, 0 = closed) sets its
//! target. Positions go through the request queue like commands; the core refuses NaN and
//! infinities (the target in force stays) and clamps the rest to 0..100.

//!
//! End switches (`NAME.open_limit_line`, `NAME.close_limit_line`) are GPIO input lines,
//! requested at start-up ([`open_switches`]; a line that cannot be requested stops the node,
//! exit 2) and read by one thread per line ([`spawn_switch_readers`]): the level at start, then
//! every change, each sent as `Input::ValveSwitch` through the request queue.

use crate::core::valve::Dir;
use crate::core::ValveConfig;
use crate::engine::Input;
use crate::output::gpio_input::{InputError, InputLine, InputRequest};
use crate::ros::config::valve::{LimitLine, ValveLimits, ValveSpec};
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg;
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{info, warn};
use std::sync::Arc;
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
/// [`SWITCH_WAIT`]; the threads end with the process.
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
                start: Default::default(),
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
