//! The heater loop inside the channel: readings and setpoints as inputs, the PID sampled as a
//! channel deadline whose duty takes the path of a duty command, and the heater checks, which
//! latch a fault that drives the line low at once and keeps it low, as the e-stop does for one
//! channel. Only fresh readings count: one that stopped coming, or whose stamp says it is old
//! or from the future, moves nothing. `stuck_on`, `sensor_stuck` and the thermal model read
//! the line as really written (its guard and the real write times), so "held off the whole
//! time" and "the duty delivered" are exact.

use super::super::command::Command;
use super::super::heater::{
    delivered_span, Control, Delivered, HeaterConfig, HeaterFault, HeaterStatus, Model, Mpc,
    Refusal, ResetRefusal, StuckOn, CHECK_TICK, DEFAULT_FEEDBACK_TIMEOUT_MS, MAX_FEEDFORWARD_PCT,
};
use super::super::NS_PER_MS;
use super::watchdog::Watchdog;
use super::{Channel, Event, Level, Nanos};

/// How long the readings must be steady after a `sensor_jump` before a reset is taken, ns.
const JUMP_CALM: Nanos = 10_000_000_000;

impl Channel {
    /// Whether the PID sets the duty (`control` `pid`).
    pub(super) fn pid_on(&self) -> bool {
        self.cfg.heater.params.control == Control::Pid
    }

    /// Whether a loop sets the duty (`control` `pid` or `mpc`).
    pub(super) fn loop_on(&self) -> bool {
        self.cfg.heater.params.control.closed()
    }

    /// Whether the model-predictive loop sets the duty (`control` `mpc`).
    fn mpc_on(&self) -> bool {
        self.cfg.heater.params.control == Control::Mpc
    }

    /// The loop's target at `now`: the setpoint, or on its way there from where the ramp
    /// stood at `setpoint_ramp_c_per_s`; never above the setpoint ceiling in force.
    pub(super) fn loop_target(&self, now: Nanos) -> Option<f64> {
        let (sp, _) = self.heat.setpoint?;
        let rate = self.cfg.heater.params.setpoint_ramp_c_per_s;
        let t = match self.heat.ramp {
            Some((from, at)) if rate > 0.0 => {
                let reach = rate * now.saturating_sub(at) as f64 / 1e9;
                if sp >= from {
                    (from + reach).min(sp)
                } else {
                    (from - reach).max(sp)
                }
            }
            _ => sp,
        };
        Some(t.min(self.cfg.heater.params.setpoint_ceiling()))
    }

    /// The last reading if it is fresh at `now`.
    fn fresh_reading(&self, now: Nanos) -> Option<f64> {
        let timeout = self.feedback_timeout();
        self.heat
            .reading
            .filter(|(c, at)| c.is_finite() && (timeout == 0 || now.saturating_sub(*at) < timeout))
            .map(|(c, _)| c)
    }

    /// The ramp starts again at `now` from the present reading (an enable, a reset): the
    /// heater may have cooled meanwhile.
    fn restart_ramp(&mut self, now: Nanos) {
        self.heat.ramp = self.fresh_reading(now).map(|c| (c, now));
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

    /// The line's on time so far, ns: the finished high phases and the running one, as
    /// really written.
    pub(super) fn on_total(&self, t: Nanos) -> Nanos {
        let running = match (self.line.level, self.line.since) {
            (Level::High, Some(since)) => t.saturating_sub(since.max(self.heat.on_counted_to)),
            _ => 0,
        };
        self.heat.on_closed.saturating_add(running)
    }

    /// A high phase of the line from `since` ended at `at` (or a fall reached the line only
    /// at `at`, `since` being when it was scheduled): the heater got that on time.
    pub(super) fn heat_on_time(&mut self, since: Nanos, at: Nanos) {
        // A late batch counts a fall up to its wake-up, and the late fall again from its
        // schedule: what is counted already is not counted twice.
        let from = since.max(self.heat.on_counted_to);
        if at > from {
            self.heat.on_closed = self.heat.on_closed.saturating_add(at - from);
            self.heat.on_counted_to = at;
        }
    }

    /// The timeout readings are held to, ns: `feedback_timeout_ms`, and while an autotune runs
    /// with it at 0 (possible under `open`), its default.
    fn feedback_timeout(&self) -> Nanos {
        match self.cfg.heater.feedback_timeout {
            0 if self.heat.autotune.is_some() => DEFAULT_FEEDBACK_TIMEOUT_MS * NS_PER_MS,
            t => t,
        }
    }

    /// When the last fresh reading came (creation, a reset or a new feedback setting before
    /// the first).
    fn fresh_since(&self) -> Nanos {
        self.heat
            .reading
            .map_or(self.heat.expected_since, |(_, at)| at)
    }

    /// When `sensor_timeout` trips: enabled, feedback with a timeout, no fault latched.
    fn sensor_deadline(&self) -> Option<Nanos> {
        let timeout = self.feedback_timeout();
        (self.cfg.heater.params.feedback
            && timeout > 0
            && self.enabled
            && self.heat.fault.is_none())
        .then(|| self.fresh_since().saturating_add(timeout))
    }

    /// The checks that watch the loop act: enabled, no fault latched, and the loop or an
    /// autotune sets the duty, or a duty command does (the heater is driven either way).
    fn heater_driven(&self) -> bool {
        self.enabled && self.heat.fault.is_none()
    }

    /// The stretch the delivered duty is averaged over, ns: a PWM period (or the PID's sample
    /// when longer), at least a second.
    pub(super) fn duty_window(&self) -> Nanos {
        self.cfg.period.max(self.sample()).max(CHECK_TICK)
    }

    /// The heater's next deadline: `sensor_timeout`, the next `not_heating` tick, the next
    /// PID sample.
    pub(super) fn heat_deadline(&self) -> Option<Nanos> {
        super::earliest(&[
            self.sensor_deadline(),
            self.heat.next_tick,
            self.heat.next_sample,
        ])
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
        HeaterFault::SensorTimeout {
            silent_ms: now.saturating_sub(self.fresh_since()) / NS_PER_MS,
            timeout_ms: self.feedback_timeout() / NS_PER_MS,
        }
    }

    /// Before a rising enable at `now`: a sensor already silent for its timeout latches
    /// `sensor_timeout` and the enable is not taken (returns false); under `pid` the loop
    /// takes a sample first, so the first period runs the loop's duty.
    pub(super) fn heat_before_enable(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) -> bool {
        let timeout = self.feedback_timeout();
        if self.cfg.heater.params.feedback
            && timeout > 0
            && self.heat.fault.is_none()
            && now.saturating_sub(self.fresh_since()) >= timeout
        {
            self.latch_heater_fault(now, self.silence(now), emit);
            return false;
        }
        // The stuck check starts afresh with the run, and a ramp from where the heater is.
        self.heat.still.clear();
        self.restart_ramp(now);
        if self.loop_on() && self.heat.fault.is_none() {
            self.pid_sample(now, emit);
        }
        true
    }

    /// One sample of the loop at `t` (the PID's, or the model-predictive loop's): its duty for
    /// the latest reading and the target goes the way of a duty command. Without a setpoint
    /// or a reading the duty in force stays. The loop is frozen while the watchdog has
    /// tripped.
    fn pid_sample(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        let sample = self.sample();
        self.heat.next_sample = Some(t.saturating_add(sample));
        self.refresh_inputs(t);
        if self.watchdog.tripped() || self.heat.fault.is_some() || self.heat.autotune.is_some() {
            self.mpc_period(t);
            return;
        }
        let (Some(setpoint), Some((reading, read_at))) = (self.loop_target(t), self.heat.reading)
        else {
            return;
        };
        if !reading.is_finite() || t.saturating_sub(read_at) >= self.feedback_timeout().max(1) {
            return;
        }
        if self.mpc_on() {
            let (lo, hi) = self.pid_limits();
            let on = self.on_total(t);
            let start = self.heat.mpc_start.take();
            let Some(m) = self.heat.mpc.as_mut() else {
                return;
            };
            if let Some(from) = start {
                m.start_from(t, on, setpoint, from);
            }
            let out = m.sample(t, on, setpoint, lo, hi).output;
            self.take_command(t, Command::Percent(out), false, emit);
            self.mpc_period(t);
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
        // The derivative moves on a new reading only, over the time between the readings.
        let reading_dt = match self.heat.sampled_reading_at {
            Some(prev) if prev == read_at => None,
            Some(prev) => Some(read_at.saturating_sub(prev) as f64 / 1e9),
            None => Some(dt as f64 / 1e9),
        };
        self.heat.sampled_reading_at = Some(read_at);
        // The feed-forward is added to the PID's output: the PID works within the limits
        // less it.
        let ff = self.heat.ff_used;
        let out = self
            .heat
            .pid
            .sample(
                setpoint,
                reading,
                reading_dt,
                dt as f64 / 1e9,
                lo - ff,
                hi - ff,
            )
            .output
            + ff;
        self.take_command(t, Command::Percent(out.clamp(lo, hi)), false, emit);
        self.mpc_period(t);
    }

    /// A sample at `t` begins a period for the model-predictive loop's estimate: the duty
    /// the line is to deliver from here (the one in force while the channel runs, else 0).
    fn mpc_period(&mut self, t: Nanos) {
        let runs = self.enabled && !self.estop && self.live && !self.watchdog.tripped();
        let duty = if runs && self.heat.fault.is_none() {
            self.cfg.limit_duty(self.band.accepted()) * 100.0
        } else {
            0.0
        };
        let on = self.on_total(t);
        if let Some(m) = self.heat.mpc.as_mut() {
            m.period(t, on, duty);
        }
    }

    /// The feed-forward and the ambient in force at `now`: a configured input older than its
    /// timeout is stale and ignored. A feed-forward that goes stale hands its value to the
    /// loop's own estimate (the PID's integral, the disturbance the model-predictive loop
    /// estimates) and one that becomes fresh takes its value back from it, so neither moves
    /// the duty; a new value while fresh does.
    fn refresh_inputs(&mut self, now: Nanos) {
        let h = &self.cfg.heater;
        let p = &h.params;
        let fresh = |v: Option<(f64, Nanos)>, timeout: Nanos| {
            v.filter(|(_, at)| timeout == 0 || now.saturating_sub(*at) < timeout)
                .map(|(x, _)| x)
        };
        let ff = fresh(self.heat.ff_in, h.feedforward_timeout).filter(|_| p.feedforward);
        let ff_stale = p.feedforward && ff.is_none();
        let ff = ff.unwrap_or(0.0);
        if ff_stale != self.heat.ff_stale {
            let hand = if ff_stale { self.heat.ff_used } else { -ff };
            self.heat.pid.shift_integral(hand);
            if let Some(m) = self.heat.mpc.as_mut() {
                m.shift_disturbance(hand);
            }
        }
        self.heat.ff_used = ff;
        self.heat.ff_stale = ff_stale;
        let ambient = fresh(self.heat.ambient_in, h.ambient_timeout).filter(|_| p.ambient);
        self.heat.ambient_stale = p.ambient && ambient.is_none();
        let ambient = ambient.unwrap_or(p.model.ambient_c);
        let on = self.on_total(now);
        if let Some(m) = self.heat.mpc.as_mut() {
            if m.ambient() != ambient || m.feedforward() != ff {
                m.set_inputs(now, on, ambient, ff);
            }
        }
        if let Some(m) = self.heat.model.as_mut() {
            if m.started() && (m.ambient() != ambient || m.feedforward() != ff) {
                m.set_inputs(now, on, ambient, ff);
            }
        }
    }

    /// A feed-forward at `now`: the disturbance it announces, % of full power (a fan's duty
    /// through the share of the heater's power it takes). Refused unless finite and within
    /// ±100 %; ignored without `feedforward_topic`.
    pub fn feedforward(&mut self, now: Nanos, pct: f64, emit: &mut dyn FnMut(Event)) {
        if !self.cfg.heater.params.feedforward {
            return;
        }
        if !(pct.is_finite() && pct.abs() <= MAX_FEEDFORWARD_PCT) {
            emit(Event::Refused(Refusal::Feedforward(pct)));
            return;
        }
        self.heat.ff_in = Some((pct, now));
        self.refresh_inputs(now);
    }

    /// An ambient reading `celsius` arriving at `now`, `age` ns after its stamp (`None`:
    /// unstamped): the ambient the model's loss is computed against while fresh. Refused
    /// unless finite and between absolute zero and `temp_max_c`; ignored without
    /// `ambient_topic`.
    pub fn ambient_reading(
        &mut self,
        now: Nanos,
        celsius: f64,
        age: Option<i64>,
        emit: &mut dyn FnMut(Event),
    ) {
        let p = self.cfg.heater.params;
        if !p.ambient {
            return;
        }
        let (min_c, max_c) = (super::super::heater::MIN_TEMP_C, p.temp_max_c);
        if !(celsius.is_finite() && celsius >= min_c && celsius <= max_c) {
            emit(Event::Refused(Refusal::Ambient {
                value: celsius,
                min_c,
                max_c,
            }));
            return;
        }
        // Stamped in the future beyond the skew allowed: counted from its arrival.
        let at = match age {
            Some(a) if a > 0 => now.saturating_sub(a as Nanos),
            _ => now,
        };
        self.heat.ambient_in = Some((celsius, at));
        self.refresh_inputs(now);
    }

    /// `not_heating`'s tick at `t` (Klipper's `verify_heater`, once a second): the target is
    /// the setpoint while the loop runs (under `pid`, enabled, no fault), else none.
    fn not_heating_tick(&mut self, t: Nanos, emit: &mut dyn FnMut(Event)) {
        self.autotune_tick(t, emit);
        self.refresh_inputs(t);
        let timeout = self.feedback_timeout();
        let Some((temp, _)) = self
            .heat
            .reading
            .filter(|(c, at)| c.is_finite() && (timeout == 0 || t.saturating_sub(*at) < timeout))
        else {
            return;
        };
        let runs = self.loop_on() && self.enabled && self.heat.fault.is_none();
        // The ramped target is the check's, the setpoint what makes an approach new.
        let (target, goal) = match (self.autotune_target(), self.heat.setpoint) {
            // An autotune's target is the check's while it runs.
            (Some(target), _) => (target, target),
            (None, Some((sp, _))) if runs => (self.loop_target(t).unwrap_or(sp), sp),
            _ => (0.0, 0.0),
        };
        let runaway = self.cfg.heater.runaway;
        if self
            .heat
            .not_heating
            .tick_ramped(t, temp, target, goal, &runaway)
        {
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

    /// A temperature reading `celsius` (°C) at `now`, unstamped (its arrival is its time).
    /// See [`Channel::feedback_stamped`].
    pub fn feedback(&mut self, now: Nanos, celsius: f64, emit: &mut dyn FnMut(Event)) {
        self.feedback_stamped(now, celsius, None, emit);
    }

    /// A temperature reading `celsius` (°C) arriving at `now`, `age` ns after its stamp
    /// (`None`: unstamped; negative: stamped in the future). Ignored without feedback
    /// configured. A stamp older than the feedback timeout or further ahead than
    /// `feedback_max_skew_ms` makes the reading stale: counted, and used by nothing. A fresh
    /// reading goes through the checks: NaN, infinities and readings outside
    /// `temp_min_c..=temp_max_c` latch `temperature_out_of_range`; a rise while the line has
    /// been off for `stuck_on_time_s` latches `stuck_on`; a jump faster than the heater can
    /// latches `sensor_jump`; a reading standing still while the delivered power moves
    /// latches `sensor_stuck`; one that leaves the thermal model latches `model_deviation`.
    /// Under `pid` it feeds the watchdog together with the setpoint.
    pub fn feedback_stamped(
        &mut self,
        now: Nanos,
        celsius: f64,
        age: Option<i64>,
        emit: &mut dyn FnMut(Event),
    ) {
        let p = self.cfg.heater.params;
        if !p.feedback {
            return;
        }
        if let Some(age) = age {
            let timeout = self.feedback_timeout();
            let too_old = timeout > 0 && age > 0 && age as u64 >= timeout;
            let ahead = age < 0 && age.unsigned_abs() > self.cfg.heater.max_skew;
            if too_old || ahead {
                self.heat.stale = (self.heat.stale.0.saturating_add(1), age);
                self.heat.stale_now = true;
                return;
            }
        }
        self.heat.stale_now = false;
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
        let on_now = self.on_total(now);
        self.heat.delivered.record(now, on_now);
        if let Some(jump) = self
            .heat
            .leap
            .reading(now, celsius, p.sensor_max_rate_c_per_s)
        {
            self.heat.last_jump_at = Some(now);
            let fault = HeaterFault::SensorJump {
                change_c: jump.change_c,
                within_s: jump.within_s,
                max_rate: p.sensor_max_rate_c_per_s,
            };
            self.latch_heater_fault(now, fault, emit);
            return;
        }
        if let Some(fault) = self.model_reading(now, on_now, celsius) {
            self.latch_heater_fault(now, fault, emit);
            return;
        }
        if let Some(m) = self.heat.mpc.as_mut() {
            m.reading(now, on_now, celsius);
        }
        if self.heater_driven() {
            let delivered = self.heat.delivered;
            let limits = self.cfg.heater.stuck;
            // During an autotune's cycles the power that holds the heater is the relay's
            // mean, not the half cycle's.
            let reference = self
                .heat
                .autotune
                .as_ref()
                .and_then(|(_, a)| a.mean_power());
            if let Some(still) = self.heat.still.reading(
                now,
                celsius,
                &limits,
                self.cfg.period,
                &delivered,
                on_now,
                reference,
            ) {
                let fault = HeaterFault::SensorStuck {
                    celsius: still.celsius,
                    still_s: still.still_s,
                    swing_s: still.swing_s,
                    limit_s: p.sensor_stuck_energy_s,
                    full: still.full,
                };
                self.latch_heater_fault(now, fault, emit);
                return;
            }
        } else {
            self.heat.still.clear();
        }
        let limits = self.cfg.heater.stuck;
        // The loop (or an autotune) has asked for full power for the check's time.
        let full = self.heater_driven()
            && (self.loop_on() || self.heat.autotune.is_some())
            && self
                .heat
                .delivered
                .duty(now.saturating_sub(limits.no_rise), now, on_now)
                .is_some_and(|d| d >= super::super::heater::checks::FULL_POWER * limits.full);
        if let Some(flat) =
            self.heat
                .flat
                .reading(now, celsius, limits.no_rise, limits.band_c, full)
        {
            let fault = HeaterFault::NoRise {
                start_c: flat.start_c,
                now_c: flat.now_c,
                full_s: flat.full_s,
            };
            self.latch_heater_fault(now, fault, emit);
            return;
        }
        self.autotune_reading(now, celsius, emit);
        self.feed_watchdog(now, emit);
    }

    /// The thermal model at a fresh reading: its prediction, and `model_deviation` once the
    /// residual has stayed beyond the tolerance for the check's time.
    fn model_reading(&mut self, now: Nanos, on_now: Nanos, celsius: f64) -> Option<HeaterFault> {
        let m = self.heat.model.as_mut()?;
        let pr = m.reading(now, on_now, celsius);
        self.heat.prediction = Some(pr);
        let p = &self.cfg.heater.params;
        if pr.residual_c.abs() <= p.model_tolerance_c {
            self.heat.deviating_since = None;
            return None;
        }
        let since = *self.heat.deviating_since.get_or_insert(now);
        (now.saturating_sub(since) >= self.cfg.heater.model_time).then_some(
            HeaterFault::ModelDeviation {
                celsius,
                predicted_c: pr.predicted_c,
                tolerance_c: p.model_tolerance_c,
                time_s: p.model_time_s,
            },
        )
    }

    /// A setpoint (°C) at `now`, under `pid` or `mpc`; refused under `open`, when not
    /// finite, or outside `temp_min_c..=temp_max_c`. With `setpoint_ramp_c_per_s` the loop's
    /// target moves to it from where it stood (from the present reading at the first).
    pub fn set_setpoint(&mut self, now: Nanos, celsius: f64, emit: &mut dyn FnMut(Event)) {
        let p = self.cfg.heater.params;
        let refusal = if !self.loop_on() {
            Some(Refusal::SetpointUnderOpen)
        } else if self.heat.autotune.is_some() {
            Some(Refusal::Autotuning)
        } else if !celsius.is_finite() {
            Some(Refusal::SetpointNotFinite(celsius))
        } else if celsius < p.temp_min_c || celsius > p.setpoint_ceiling() {
            Some(Refusal::SetpointOutOfRange {
                value: celsius,
                min_c: p.temp_min_c,
                max_c: p.setpoint_ceiling(),
            })
        } else {
            None
        };
        if let Some(r) = refusal {
            emit(Event::Refused(r));
            return;
        }
        let from = self.loop_target(now).or_else(|| self.fresh_reading(now));
        self.heat.ramp = from.map(|c| (c, now));
        self.heat.setpoint = Some((celsius, now));
        self.heat.lowered_from = None;
        self.feed_watchdog(now, emit);
    }

    /// Under `pid` the watchdog watches the setpoint and the feedback: it counts from the
    /// older of the two, and recovers once both are fresh.
    fn feed_watchdog(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        if !self.loop_on() {
            return;
        }
        let (Some((_, sp)), Some((_, rd))) = (self.heat.setpoint, self.heat.reading) else {
            return;
        };
        let fed = sp.min(rd);
        self.watchdog.feed_no_earlier(fed);
        let fresh = Watchdog::fresh(now, fed, self.cfg.command_timeout);
        if self.watchdog.tripped() && fresh {
            self.watchdog.rearm();
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
        self.watchdog.end_fault_value();
        emit(Event::HeaterFault(fault));
        self.set_enable(now, false, emit);
        self.force_low(now, emit);
        // Nothing of the duty before the fault survives it: after the reset and the next
        // enable, the loop starts from 0 % and the present reading; open loop waits for a
        // new command.
        self.take_command(now, Command::Percent(0.0), false, emit);
        self.heat.pid.start_from(0.0);
        self.heat.last_sample = None;
        self.heat.sampled_reading_at = None;
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
                let timeout = self.feedback_timeout();
                (timeout > 0 && now.saturating_sub(self.fresh_since()) >= timeout)
                    .then(|| self.silence(now))
            }
            // The reading must have moved since: still the frozen value, the fault lasts.
            HeaterFault::SensorStuck { celsius, .. } => match self.heat.reading {
                Some((c, _)) if (c - celsius).abs() <= h.stuck.band_c => Some(fault),
                None => Some(fault),
                _ => None,
            },
            // With the line off nothing shows whether the heater heats again: as for
            // not_heating, the condition lasts while the setpoint would drive it hard again
            // (above the reading by more than the hysteresis); lower the setpoint to reset.
            HeaterFault::NoRise { full_s, .. } => {
                let (Some((sp, _)), Some((temp, _))) = (self.heat.setpoint, self.heat.reading)
                else {
                    return None;
                };
                (sp > 0.0 && temp < sp - h.runaway.hysteresis_c).then_some(HeaterFault::NoRise {
                    start_c: temp,
                    now_c: temp,
                    full_s,
                })
            }
            // The readings must have been steady (no jump) for the last 10 s.
            HeaterFault::SensorJump { .. } => self
                .heat
                .last_jump_at
                .is_some_and(|t| now.saturating_sub(t) < JUMP_CALM)
                .then_some(fault),
            // The residual must be back within the tolerance.
            HeaterFault::ModelDeviation {
                tolerance_c,
                time_s,
                ..
            } => match (self.heat.prediction, self.heat.reading) {
                (Some(pr), Some((c, _))) if pr.residual_c.abs() > tolerance_c => {
                    Some(HeaterFault::ModelDeviation {
                        celsius: c,
                        predicted_c: pr.predicted_c,
                        tolerance_c,
                        time_s,
                    })
                }
                _ => None,
            },
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
            // The loop starts afresh from 0 % and the readings to come (bumpless from 0).
            self.heat.pid.start_from(0.0);
            self.heat.last_sample = None;
            self.heat.sampled_reading_at = None;
            self.heat.still.clear();
            self.heat.deviating_since = None;
            if let (Some(m), Some((c, _))) = (self.heat.model.as_mut(), self.heat.reading) {
                let on = self.heat.on_closed;
                m.restart(now, on, c);
            }
            // The model-predictive loop starts from the present reading, its estimate of the
            // disturbance forgotten.
            if let (Some(m), Some((c, _))) = (self.heat.mpc.as_mut(), self.heat.reading) {
                let on = self.heat.on_closed;
                m.restart(now, on, c);
            }
            self.heat.mpc_start = None;
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
        let in_force = self.cfg.limit_duty(self.band.accepted()) * 100.0;
        match (old.params.control, new.params.control) {
            (Control::Open, Control::Pid) => {
                self.heat.pid = super::super::heater::Pid::new(new.gains);
                self.heat.pid.start_from(in_force - self.heat.ff_used);
                self.heat.last_sample = None;
                self.heat.setpoint = None;
                if self.enabled && self.heat.fault.is_none() {
                    self.heat.next_sample = Some(now);
                }
            }
            (Control::Open, Control::Mpc) => {
                self.heat.mpc_start = Some(in_force);
                self.heat.setpoint = None;
                if self.enabled && self.heat.fault.is_none() {
                    self.heat.next_sample = Some(now);
                }
            }
            (Control::Pid | Control::Mpc, Control::Open) => {
                self.heat.next_sample = None;
                self.heat.setpoint = None;
                // Open loop heats on commands only: 0 % until the first one. The watchdog
                // counts commands from now.
                self.take_command(now, Command::Percent(0.0), false, emit);
                self.watchdog.feed(now);
            }
            // Between the loops the setpoint stays, and the new loop starts from the duty the
            // old one left.
            (Control::Pid, Control::Mpc) => self.heat.mpc_start = Some(in_force),
            (Control::Mpc, Control::Pid) => {
                self.heat.pid = super::super::heater::Pid::new(new.gains);
                self.heat.pid.start_from(in_force - self.heat.ff_used);
                self.heat.last_sample = None;
                self.heat.sampled_reading_at = None;
            }
            _ => self.heat.pid.set_gains(new.gains, lo, hi),
        }
        // A lowered temp_max_c takes the setpoint in force down with it: the loop never aims
        // above the ceiling in force.
        if let Some((sp, at)) = self.heat.setpoint {
            let ceiling = new.params.setpoint_ceiling();
            if sp > ceiling {
                self.heat.setpoint = Some((ceiling.max(new.params.temp_min_c), at));
                self.heat.lowered_from = Some(sp);
            }
        }
        if old.params.model != new.params.model {
            self.heat.model = new
                .params
                .model
                .is_set()
                .then(|| Model::new(new.params.model));
            self.heat.prediction = None;
            self.heat.deviating_since = None;
            // A new model: the model-predictive loop starts again from the present reading,
            // and under mpc bumpless from the duty in force.
            let on = self.on_total(now);
            let reading = self.fresh_reading(now);
            self.heat.mpc = new.params.model.is_set().then(|| {
                let mut m = Mpc::new(new.params.model);
                if let Some(c) = reading {
                    m.restart(now, on, c);
                }
                m
            });
            if self.mpc_on() {
                self.heat.mpc_start = Some(in_force);
            }
            self.refresh_inputs(now);
        }
        if old.stuck != new.stuck || old.sample != new.sample {
            self.heat.still.clear();
            self.heat.flat = super::super::heater::NoRise::new(new.stuck.no_rise);
            self.heat.delivered = Delivered::new(delivered_span(&new, self.duty_window()));
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
        let p = &self.cfg.heater.params;
        HeaterStatus {
            feedback: p.feedback,
            pid: self.pid_on(),
            control: p.control,
            target: self.loop_target(now),
            mpc: self
                .heat
                .mpc
                .as_ref()
                .filter(|_| self.mpc_on())
                .map(|m| m.terms()),
            model_params: p.model.is_set().then_some(p.model),
            feedforward_pct: self.heat.ff_used,
            feedforward_stale: self.heat.ff_stale,
            ambient_c: (p.ambient || p.model.is_set()).then(|| {
                self.heat
                    .mpc
                    .as_ref()
                    .map_or(p.model.ambient_c, |m| m.ambient())
            }),
            ambient_stale: self.heat.ambient_stale,
            reading: self.heat.reading,
            setpoint: self.heat.setpoint.map(|(c, _)| c),
            terms: self.heat.pid.terms(),
            fault: self.heat.fault,
            fault_lasts: self
                .heat
                .fault
                .is_some_and(|f| self.condition(now, f).is_some()),
            runaway_error: self.heat.not_heating.error(),
            model: self.heat.prediction,
            stale: self.heat.stale,
            stale_now: self.heat.stale_now,
            setpoint_lowered_from: self.heat.lowered_from,
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
