//! The heater loop inside the channel (issue 22): readings and setpoints as inputs, the PID
//! sampled as a channel deadline whose duty takes the path of a duty command, and the heater
//! checks, which latch a fault that drives the line low at once and keeps it low, as the
//! e-stop does for one channel. `stuck_on` reads the line as really written (its guard), so
//! "held off the whole time" is exact.

use super::super::command::Command;
use super::super::heater::{
    Control, HeaterConfig, HeaterFault, HeaterStatus, Refusal, ResetRefusal, StuckOn, CHECK_TICK,
};
use super::{Channel, Event, Level, Nanos};

impl Channel {
    /// Whether the loop sets the duty (`control` `pid`).
    pub(super) fn pid_on(&self) -> bool {
        self.cfg.heater.params.control == Control::Pid
    }

    /// The latched heater fault, if any.
    pub fn heater_fault(&self) -> Option<HeaterFault> {
        self.heat.fault
    }

    /// The PID's sample, ns: as configured, or the period (1 s with no period).
    fn sample(&self) -> Nanos {
        match (self.cfg.heater.sample, self.cfg.period) {
            (0, 0) => CHECK_TICK,
            (0, p) => p,
            (s, _) => s,
        }
    }

    /// The output limits the loop works within, % (the power limits its duty goes through).
    fn pid_limits(&self) -> (f64, f64) {
        let lo = if self.cfg.zero_means_zero {
            0.0
        } else {
            self.cfg.min_duty * 100.0
        };
        (lo, self.cfg.max_duty * 100.0)
    }

    /// When `sensor_timeout` trips: enabled, feedback with a timeout, no fault latched.
    fn sensor_deadline(&self) -> Option<Nanos> {
        let h = &self.cfg.heater;
        (h.params.feedback && h.feedback_timeout > 0 && self.enabled && self.heat.fault.is_none())
            .then(|| {
                self.heat
                    .reading
                    .map_or(self.heat.expected_since, |(_, at)| at)
                    .saturating_add(h.feedback_timeout)
            })
    }

    /// The heater's next deadline: `sensor_timeout`, the next `not_heating` tick, the next
    /// PID sample.
    pub(super) fn heat_deadline(&self) -> Option<Nanos> {
        [
            self.sensor_deadline(),
            self.heat.next_tick,
            self.heat.next_sample,
        ]
        .into_iter()
        .flatten()
        .min()
    }

    /// Handles a heater deadline falling at `t`, if one does; returns whether one did.
    pub(super) fn heat_due(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) -> bool {
        if self.sensor_deadline() == Some(t) {
            self.latch_heater_fault(t, self.silence(t), emit);
            return true;
        }
        if self.heat.next_tick == Some(t) {
            self.heat.next_tick = Some(t.saturating_add(CHECK_TICK));
            self.not_heating_tick(t, emit);
            return true;
        }
        if self.heat.next_sample == Some(t) {
            self.pid_sample(t, emit);
            return true;
        }
        false
    }

    fn silence(&self, now: Nanos) -> HeaterFault {
        let since = self
            .heat
            .reading
            .map_or(self.heat.expected_since, |(_, at)| at);
        HeaterFault::SensorTimeout {
            silent_ms: now.saturating_sub(since) / super::super::NS_PER_MS,
            timeout_ms: self.cfg.heater.params.feedback_timeout_ms,
        }
    }

    /// Before a rising enable at `now`: a sensor already silent for its timeout latches
    /// `sensor_timeout` and the enable is not taken (returns false); under `pid` the loop
    /// takes a sample first, so the first period runs the loop's duty.
    pub(super) fn heat_before_enable(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) -> bool {
        let h = &self.cfg.heater;
        if h.params.feedback && h.feedback_timeout > 0 && self.heat.fault.is_none() {
            let since = self
                .heat
                .reading
                .map_or(self.heat.expected_since, |(_, at)| at);
            if now.saturating_sub(since) >= h.feedback_timeout {
                self.latch_heater_fault(now, self.silence(now), emit);
                return false;
            }
        }
        if self.pid_on() && self.heat.fault.is_none() {
            self.pid_sample(now, emit);
        }
        true
    }

    /// One PID sample at `t`: the loop's duty for the latest reading goes the way of a duty
    /// command. Without a setpoint or a reading the duty in force stays. The loop is frozen
    /// while the watchdog has tripped.
    fn pid_sample(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let sample = self.sample();
        self.heat.next_sample = Some(t.saturating_add(sample));
        if self.watchdog_tripped || self.heat.fault.is_some() || self.heat.autotune.is_some() {
            return;
        }
        let (Some((setpoint, _)), Some((reading, _))) = (self.heat.setpoint, self.heat.reading)
        else {
            return;
        };
        if !reading.is_finite() {
            return;
        }
        // The time since the last sample; after a pause (disabled) the nominal sample, so the
        // integral does not take the pause in one step.
        let dt = match self.heat.last_sample {
            Some(last) if t.saturating_sub(last) <= 2 * sample => t.saturating_sub(last),
            _ => sample,
        };
        self.heat.last_sample = Some(t);
        let (lo, hi) = self.pid_limits();
        let out = self
            .heat
            .pid
            .step(setpoint, reading, dt as f64 / 1e9, lo, hi)
            .output;
        self.take_command(t, Command::Percent(out), false, emit);
    }

    /// `not_heating`'s tick at `t` (Klipper's `verify_heater`, once a second): the target is
    /// the setpoint while the loop runs (under `pid`, enabled, no fault), else none.
    fn not_heating_tick(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let Some((temp, _)) = self.heat.reading.filter(|(c, _)| c.is_finite()) else {
            return;
        };
        self.autotune_tick(t, emit);
        let runs = self.pid_on() && self.enabled && self.heat.fault.is_none();
        let target = match (self.autotune_target(), self.heat.setpoint) {
            // An autotune's target is the check's while it runs.
            (Some(target), _) => target,
            (None, Some((sp, _))) if runs => sp,
            _ => 0.0,
        };
        let runaway = self.cfg.heater.runaway;
        if self.heat.not_heating.tick(t, temp, target, &runaway) {
            let fault = HeaterFault::NotHeating {
                celsius: temp,
                target_c: target,
                error: self.heat.not_heating.error(),
                max_error: runaway.max_error,
            };
            self.latch_heater_fault(t, fault, emit);
        }
    }

    /// When the line has been off since (creation counts as a fall), or `None` while high.
    fn off_since(&self) -> Option<Nanos> {
        match self.line.level {
            Level::High => None,
            Level::Low => Some(self.line.since.unwrap_or(self.heat.expected_since)),
        }
    }

    fn out_of_range(&self, celsius: f64) -> Option<HeaterFault> {
        let p = &self.cfg.heater.params;
        let inside = celsius.is_finite() && celsius >= p.temp_min_c && celsius <= p.temp_max_c;
        (!inside).then_some(HeaterFault::OutOfRange {
            celsius,
            min_c: p.temp_min_c,
            max_c: p.temp_max_c,
        })
    }

    /// A temperature reading `celsius` (°C) at `now`. Ignored without feedback configured.
    /// NaN, infinities and readings outside `temp_min_c..=temp_max_c` latch
    /// `temperature_out_of_range`; a rise while the line has been off for `stuck_on_time_s`
    /// latches `stuck_on`. Under `pid` it feeds the watchdog together with the setpoint.
    pub fn feedback(&mut self, now: Nanos, celsius: f64, emit: &mut dyn FnMut(Event)) {
        let p = self.cfg.heater.params;
        if !p.feedback {
            return;
        }
        self.heat.reading = Some((celsius, now));
        if let Some(fault) = self.out_of_range(celsius) {
            self.latch_heater_fault(now, fault, emit);
            return;
        }
        if p.stuck_on_rise_c > 0.0 {
            let off = self.off_since();
            let window = self.cfg.heater.stuck_window;
            let rise = self.heat.stuck.reading(now, celsius, off, window);
            self.heat.rise = rise;
            if rise.off_whole_window && rise.rise_c > p.stuck_on_rise_c {
                let fault = HeaterFault::StuckOn {
                    rise_c: rise.rise_c,
                    limit_c: p.stuck_on_rise_c,
                    window_s: p.stuck_on_time_s,
                };
                self.latch_heater_fault(now, fault, emit);
                return;
            }
        }
        self.autotune_reading(now, celsius, emit);
        self.feed_watchdog(now, emit);
    }

    /// A setpoint (°C) at `now`, under `pid`; refused under `open`, when not finite, or
    /// outside `temp_min_c..=temp_max_c`.
    pub fn set_setpoint(&mut self, now: Nanos, celsius: f64, emit: &mut dyn FnMut(Event)) {
        let p = self.cfg.heater.params;
        let refusal = if !self.pid_on() {
            Some(Refusal::SetpointUnderOpen)
        } else if self.heat.autotune.is_some() {
            Some(Refusal::Autotuning)
        } else if !celsius.is_finite() {
            Some(Refusal::SetpointNotFinite(celsius))
        } else if celsius < p.temp_min_c || celsius > p.temp_max_c {
            Some(Refusal::SetpointOutOfRange {
                value: celsius,
                min_c: p.temp_min_c,
                max_c: p.temp_max_c,
            })
        } else {
            None
        };
        if let Some(r) = refusal {
            emit(Event::Refused(r));
            return;
        }
        self.heat.setpoint = Some((celsius, now));
        self.feed_watchdog(now, emit);
    }

    /// Under `pid` the watchdog watches the setpoint and the feedback: it counts from the
    /// older of the two, and recovers once both are fresh.
    fn feed_watchdog(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        if !self.pid_on() {
            return;
        }
        let (Some((_, sp)), Some((_, rd))) = (self.heat.setpoint, self.heat.reading) else {
            return;
        };
        let fed = sp.min(rd);
        self.last_command_at = self.last_command_at.max(fed);
        let fresh =
            self.cfg.command_timeout == 0 || now < fed.saturating_add(self.cfg.command_timeout);
        if self.watchdog_tripped && fresh {
            self.watchdog_tripped = false;
            self.fault_until = None;
            emit(Event::Watchdog { tripped: false });
            // The loop takes over from where it stands (the line was off).
            self.heat.pid.start_from(0.0);
            self.heat.last_sample = None;
            if self.enabled {
                self.pid_sample(now, emit);
            }
        }
    }

    /// Latches `fault` at `now`: the line goes low at once and stays low, the channel is
    /// disabled (as the e-stop does for one channel). A fault already latched is kept.
    fn latch_heater_fault(&mut self, now: Nanos, fault: HeaterFault, emit: &mut dyn FnMut(Event)) {
        if self.heat.fault.is_some() {
            return;
        }
        self.finish_autotune(
            now,
            crate::core::heater::autotune::Stop::HeaterFault(fault),
            emit,
        );
        self.heat.fault = Some(fault);
        self.heat.next_sample = None;
        self.fault_until = None;
        emit(Event::HeaterFault(fault));
        self.set_enable(now, false, emit);
        self.force_low(now, emit);
    }

    /// Whether the condition of `fault` holds at `now`: the figures it has now if so.
    fn condition(&self, now: Nanos, fault: HeaterFault) -> Option<HeaterFault> {
        let h = &self.cfg.heater;
        match fault {
            HeaterFault::OutOfRange { .. } => match self.heat.reading {
                Some((c, _)) => self.out_of_range(c),
                None => Some(fault),
            },
            HeaterFault::SensorTimeout { .. } => {
                let since = self
                    .heat
                    .reading
                    .map_or(self.heat.expected_since, |(_, at)| at);
                (h.feedback_timeout > 0 && now.saturating_sub(since) >= h.feedback_timeout)
                    .then(|| self.silence(now))
            }
            // The check would go on summing error: the reading is below the setpoint less the
            // hysteresis (a setpoint of 0 or below is no target, as in Klipper).
            HeaterFault::NotHeating { max_error, .. } => {
                let (Some((sp, _)), Some((temp, _))) = (self.heat.setpoint, self.heat.reading)
                else {
                    return None;
                };
                (sp > 0.0 && (temp < sp - h.runaway.hysteresis_c || temp.is_nan())).then_some(
                    HeaterFault::NotHeating {
                        celsius: temp,
                        target_c: sp,
                        error: self.heat.not_heating.error(),
                        max_error,
                    },
                )
            }
            HeaterFault::StuckOn {
                limit_c, window_s, ..
            } => {
                let r = self.heat.rise;
                (r.off_whole_window && r.rise_c > h.params.stuck_on_rise_c).then_some(
                    HeaterFault::StuckOn {
                        rise_c: r.rise_c,
                        limit_c,
                        window_s,
                    },
                )
            }
        }
    }

    /// Clears the latched heater fault at `now` once its condition is gone; the answer comes
    /// as [`Event::FaultReset`] with `ticket`. The channel stays disabled until its next
    /// enable, as after an e-stop reset, and the checks start afresh.
    pub fn reset_heater_fault(&mut self, now: Nanos, ticket: u32, emit: &mut dyn FnMut(Event)) {
        let result = match self.heat.fault {
            None => Err(ResetRefusal::NoFault),
            Some(f) => match self.condition(now, f) {
                Some(lasts) => Err(ResetRefusal::Lasts(lasts)),
                None => Ok(()),
            },
        };
        if result.is_ok() {
            self.set_enable(now, false, emit);
            self.line.held = None;
            self.level = self.line.level;
            self.heat.fault = None;
            self.heat.not_heating = Default::default();
            self.heat.pid.start_from(self.accepted * 100.0);
            self.heat.last_sample = None;
            // The silence counts from now: the reset was allowed on a fresh reading.
            self.heat.expected_since = now;
        }
        emit(Event::FaultReset { ticket, result });
    }

    /// New heater settings at `now`, in force at once: a gain change is bumpless, a switch
    /// from `open` to `pid` starts the loop from the duty in force, one back to `open` keeps
    /// the loop's last duty until a command.
    pub(super) fn heat_config(
        &mut self,
        now: Nanos,
        new: HeaterConfig,
        emit: &mut dyn FnMut(Event),
    ) {
        let old = self.cfg.heater;
        if old == new {
            return;
        }
        if old.params.control != new.params.control || old.params.feedback != new.params.feedback {
            self.finish_autotune(now, crate::core::heater::autotune::Stop::Reconfigured, emit);
        }
        self.cfg.heater = new;
        self.cfg.params.heater = new.params;
        let (lo, hi) = self.pid_limits();
        match (old.params.control, new.params.control) {
            (Control::Open, Control::Pid) => {
                self.heat.pid = super::super::heater::Pid::new(new.gains);
                self.heat
                    .pid
                    .start_from(self.cfg.limit_duty(self.accepted) * 100.0);
                self.heat.last_sample = None;
                self.heat.setpoint = None;
                if self.enabled && self.heat.fault.is_none() {
                    self.heat.next_sample = Some(now);
                }
            }
            (Control::Pid, Control::Open) => {
                self.heat.next_sample = None;
                self.heat.setpoint = None;
                // The loop's last duty stays in force until a command; the watchdog counts
                // commands from now.
                self.last_command_at = now;
            }
            _ => self.heat.pid.set_gains(new.gains, lo, hi),
        }
        if old.sample != new.sample && self.heat.next_sample.is_some() {
            let from = self.heat.last_sample.unwrap_or(now);
            self.heat.next_sample = Some(from.saturating_add(self.sample()).max(now));
        }
        if old.stuck_window != new.stuck_window || new.params.stuck_on_rise_c == 0.0 {
            self.heat.stuck = StuckOn::default();
        }
        if !old.params.feedback && new.params.feedback {
            self.heat.expected_since = now;
            self.heat.next_tick = Some(now.saturating_add(CHECK_TICK));
        }
    }

    /// The heater's report at `now`.
    pub(super) fn heater_status(&self, now: Nanos) -> HeaterStatus {
        HeaterStatus {
            feedback: self.cfg.heater.params.feedback,
            pid: self.pid_on(),
            reading: self.heat.reading,
            setpoint: self.heat.setpoint.map(|(c, _)| c),
            terms: self.heat.pid.terms(),
            fault: self.heat.fault,
            fault_lasts: self
                .heat
                .fault
                .is_some_and(|f| self.condition(now, f).is_some()),
            runaway_error: self.heat.not_heating.error(),
            sizing: {
                let ms = |ns: Nanos| ns as f64 / super::super::NS_PER_MS as f64;
                let mut rules = super::super::heater::sizing(
                    &self.cfg.heater.params,
                    ms(self.cfg.period),
                    ms(self.cfg.min_on),
                    ms(self.cfg.min_off),
                );
                [rules.next(), rules.next(), rules.next()]
            },
        }
    }
}
