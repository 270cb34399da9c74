//! The latched emergency stop of the whole node: `~/estop` (std_msgs/Bool) latches it on
//! `true`, `~/reset_estop` (std_srvs/Trigger) clears it only while the last input is `false`,
//! and with `estop_timeout_ms` a missing `false` latches it too (a heartbeat e-stop, for a
//! wireless stop button whose silence must stop the machine).
//!
//! Latching drives every line inactive at once through the output thread; while latched,
//! commands, enables and parameters are taken and reported but the lines stay inactive; after
//! a reset every channel is disabled and runs again only on its next `enable=true` (the core's
//! [`Channel::set_estop`](crate::core::Channel::set_estop)).

use crate::clock;
use crate::core::Nanos;
use crate::output_thread::Input;
use crate::ros::inbound::inputs::Inputs;
use crate::ros::interface::msg::{self, TriggerResponse};
use crate::ros::wire::endpoints::{EndpointError, Endpoints};
use log::{error, info, warn};
use std::sync::Arc;
use tokio::sync::Mutex;
use tokio::task::JoinHandle;

/// Why the e-stop was latched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    /// `true` on `~/estop`.
    Input,
    /// No `false` on `~/estop` within `estop_timeout_ms`.
    Timeout,
}

/// The e-stop's state, shared by the `~/estop` callback, the reset service and the timeout
/// check. One lock orders the three, so a reset and an input never cross; it is tokio's, held
/// across the await of the output thread's acknowledgment, which holds no thread meanwhile.
///
/// Whether it is latched, and how often it latched, are published through the node state
/// (`Inputs::state`), which the diagnostics read.
pub struct EStop {
    state: Mutex<State>,
    /// `estop_timeout_ms` in ns; 0 = no timeout.
    timeout_ns: Nanos,
}

#[derive(Debug)]
struct State {
    latched: bool,
    /// The last value received on `~/estop` (`false` before any).
    asserted: bool,
    /// When the last `false` arrived (or when the node started), monotonic ns.
    last_release: Nanos,
}

impl EStop {
    /// Not latched; with a `timeout_ms` of 0 no timeout, else the first `false` is due within
    /// it from now.
    pub fn new(timeout_ms: u64) -> EStop {
        EStop {
            state: Mutex::new(State {
                latched: false,
                asserted: false,
                last_release: clock::monotonic_ns(),
            }),
            timeout_ns: timeout_ms.saturating_mul(1_000_000),
        }
    }

    /// How often the timeout should be checked (a tenth of it, 5..100 ms); `None` without one.
    pub fn timeout_check_period(&self) -> Option<std::time::Duration> {
        (self.timeout_ns > 0).then(|| {
            std::time::Duration::from_nanos((self.timeout_ns / 10).clamp(5_000_000, 100_000_000))
        })
    }

    /// A value on `~/estop`: `true` latches (once; repeats change nothing), `false` is
    /// remembered (it allows a reset and feeds the timeout) and never releases by itself.
    pub async fn input(&self, inputs: &Inputs, asserted: bool) {
        let mut s = self.state.lock().await;
        s.asserted = asserted;
        if asserted {
            self.latch(&mut s, inputs, Cause::Input).await;
        } else {
            s.last_release = clock::monotonic_ns();
        }
    }

    /// Latches when the timeout is set and no `false` came within it; returns whether it did.
    pub async fn check_timeout(&self, inputs: &Inputs, now: Nanos) -> bool {
        if self.timeout_ns == 0 {
            return false;
        }
        let mut s = self.state.lock().await;
        if s.latched || now.saturating_sub(s.last_release) < self.timeout_ns {
            return false;
        }
        self.latch(&mut s, inputs, Cause::Timeout).await;
        true
    }

    /// `~/reset_estop`: clears the latch only while the last input is `false` (and, with a
    /// timeout, a `false` is recent); every channel is then disabled.
    pub async fn reset(&self, inputs: &Inputs) -> TriggerResponse {
        let mut s = self.state.lock().await;
        let refuse = |message: &str| TriggerResponse {
            success: false,
            message: message.to_string(),
        };
        // The output thread latches it itself for a heater fault under
        // heater_fault_latches_estop: the slot says so.
        if !s.latched && !inputs.safety().estop_latched() {
            return TriggerResponse {
                success: true,
                message: "the e-stop is not latched".into(),
            };
        }
        if s.asserted {
            return refuse("the e-stop input is still asserted (last ~/estop was true)");
        }
        let now = clock::monotonic_ns();
        if self.timeout_ns > 0 && now.saturating_sub(s.last_release) >= self.timeout_ns {
            return refuse("no false on ~/estop within estop_timeout_ms: the stop is still open");
        }
        if let Err(e) = inputs.safety().take_async(Input::EStop(false)).await {
            // Latched again in the slot, so the thread and this state agree when it resumes.
            inputs.safety().store(Input::EStop(true));
            return refuse(&format!("the reset was not applied: {e}"));
        }
        s.latched = false;
        inputs.state().set_estop(false);
        for ch in 0..inputs.channels() {
            inputs.note_disabled(ch);
        }
        info!("e-stop reset: every channel is disabled; enable each channel to run it again");
        TriggerResponse {
            success: true,
            message: "e-stop reset; every channel is disabled until its next enable".into(),
        }
    }

    async fn latch(&self, s: &mut State, inputs: &Inputs, cause: Cause) {
        if s.latched {
            return;
        }
        s.latched = true;
        inputs.state().set_estop(true);
        let why = match cause {
            Cause::Input => "~/estop true".to_string(),
            Cause::Timeout => format!(
                "no false on ~/estop within {} ms",
                self.timeout_ns / 1_000_000
            ),
        };
        // Said only once the output thread has written the lines, or the emergency handle
        // has switched them off.
        match inputs.safety().take_async(Input::EStop(true)).await {
            Ok(took) => warn!(
                "e-stop latched ({why}): every output driven inactive ({} us after the input)",
                took.as_micros()
            ),
            Err(e) => error!(
                "e-stop latched ({why}), but {e}: every output switched off by the emergency \
                 handle"
            ),
        }
    }
}

/// `~/estop` (reliable, volatile: any publisher matches), `~/reset_estop` (std_srvs/Trigger)
/// and, with `estop_timeout_ms`, the task that latches when no `false` comes in time.
pub fn spawn(
    ep: &mut Endpoints<'_>,
    inputs: &Arc<Inputs>,
    estop: &Arc<EStop>,
) -> Result<Vec<JoinHandle<()>>, EndpointError> {
    let mut tasks = Vec::new();
    let (to_thread, e) = (Arc::clone(inputs), Arc::clone(estop));
    tasks.push(ep.listen_async("~/estop", move |m: msg::Bool| {
        let (to_thread, e) = (Arc::clone(&to_thread), Arc::clone(&e));
        async move { e.input(&to_thread, m.data).await }
    })?);
    let (to_thread, e) = (Arc::clone(inputs), Arc::clone(estop));
    let reset = move |_: msg::EmptyRequest| {
        let (to_thread, e) = (Arc::clone(&to_thread), Arc::clone(&e));
        async move { e.reset(&to_thread).await }
    };
    let mut maker = ep.services();
    tasks.push(maker.serve_async("~/reset_estop", "std_srvs", "Trigger", reset)?);
    if let Some(period) = estop.timeout_check_period() {
        let (to_thread, e) = (Arc::clone(inputs), Arc::clone(estop));
        tasks.push(tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tick.tick().await;
                e.check_timeout(&to_thread, clock::monotonic_ns()).await;
            }
        }));
    }
    Ok(tasks)
}
