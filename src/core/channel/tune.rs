//! The autotune inside the channel: the relay's duty takes the path of a duty command (limits,
//! protections, minimum times, the line's promises), the heater checks stay armed with the
//! run's target as `not_heating`'s, and anything that stops the channel — a heater fault, the
//! e-stop, the lines held, a disable, the watchdog, a change of `control` or feedback — ends
//! the run with the reason. Every end commands 0 %: the line stays off until told otherwise.

use super::super::command::Command;
use super::super::heater::autotune::{
    Autotune, Goal, GoalRefusal, Outcome, Report, Rule, Stop, TuneSizing,
};
use super::super::heater::{sizing, Control, Gains, HeaterParams, DEFAULT_FEEDBACK_TIMEOUT_MS};
use super::super::NS_PER_MS;
use super::{Channel, Event, Nanos};

impl Channel {
    /// Whether an autotune runs, and its target (°C).
    pub fn autotune_target(&self) -> Option<f64> {
        self.heat.autotune.as_ref().map(|(_, a)| a.goal().target_c)
    }

    /// Starts an autotune of `goal` at `now`, answered with [`Event::Autotune`] and `ticket`:
    /// refused unless the channel has feedback and a reading, runs (enabled, no e-stop, lines
    /// live), has no heater fault latched and no other run, and the goal is within the
    /// channel's limits (target within `temp_min_c..=temp_max_c`, amplitude within
    /// `max_duty_pct`), and a fresh reading came. The target must lie `autotune_margin_c`
    /// below `temp_max_c`, which must be set.
    pub fn start_autotune(
        &mut self,
        now: Nanos,
        ticket: u32,
        goal: Goal,
        emit: &mut dyn FnMut(Event),
    ) {
        let p = self.cfg.heater.params;
        let refusal = if !p.feedback {
            Some(GoalRefusal::NoFeedback)
        } else if !p.temp_max_set() {
            Some(GoalRefusal::NoTempMax)
        } else if self.heat.fault.is_some() {
            Some(GoalRefusal::Fault)
        } else if !self.enabled || self.estop || !self.live {
            Some(GoalRefusal::NotRunning)
        } else if self.heat.autotune.is_some() {
            Some(GoalRefusal::Busy)
        } else {
            // Marlin's M303 keeps its target 15 °C below the heater's maximum: the relay
            // overshoots it.
            goal.check(
                p.temp_min_c,
                p.temp_max_c - p.autotune_margin_c,
                self.cfg.max_duty * 100.0,
            )
            .err()
        };
        // Only a fresh reading starts a run (the feedback timeout, or its default when the
        // timeout is off under open).
        let fresh = match self.cfg.heater.feedback_timeout {
            0 => DEFAULT_FEEDBACK_TIMEOUT_MS * NS_PER_MS,
            t => t,
        };
        let reading = self
            .heat
            .reading
            .filter(|(c, at)| c.is_finite() && now.saturating_sub(*at) < fresh)
            .map(|(c, _)| c);
        let refusal = refusal.or(reading.is_none().then_some(GoalRefusal::NoReading));
        if let Some(r) = refusal {
            emit(Event::Autotune {
                ticket,
                report: Report::Refused(r),
            });
            return;
        }
        // The duty the heater had before the run: what the line delivered over the last
        // duty window, else the duty in force.
        let on_now = self.on_total(now);
        let before = self
            .heat
            .delivered
            .duty(now.saturating_sub(self.duty_window()), now, on_now)
            .unwrap_or(self.cfg.limit_duty(self.band.accepted()))
            * 100.0;
        let run = Autotune::new(
            goal,
            self.cfg.heater.autotune,
            now,
            reading.unwrap_or(goal.target_c),
            self.cfg.period,
            before,
        );
        self.heat.autotune = Some((ticket, run));
        self.watchdog.feed(now);
        emit(Event::Autotune {
            ticket,
            report: Report::Started,
        });
        emit(Event::Autotune {
            ticket,
            report: Report::Progress(run.progress()),
        });
        // The goal counts as a command: it feeds the watchdog and clears a trip.
        self.take_command(now, Command::Percent(run.output_pct()), true, emit);
    }

    /// Cancels the run with `ticket` at `now` (another ticket is ignored).
    pub fn cancel_autotune(&mut self, now: Nanos, ticket: u32, emit: &mut dyn FnMut(Event)) {
        if self
            .heat
            .autotune
            .as_ref()
            .is_some_and(|(t, _)| *t == ticket)
        {
            self.finish_autotune(now, Stop::Canceled, emit);
        }
    }

    /// A reading (finite, in range) at `now` while a run goes: moves the relay; readings
    /// feed the watchdog while the run sets the duty.
    pub(super) fn autotune_reading(
        &mut self,
        now: Nanos,
        celsius: f64,
        emit: &mut dyn FnMut(Event),
    ) {
        let on_total = self.on_total(now);
        let Some((ticket, run)) = self.heat.autotune.as_mut() else {
            return;
        };
        let ticket = *ticket;
        self.watchdog.feed(now);
        let (before, out) = (run.progress(), run.output_pct());
        let stop = run.reading_delivered(now, celsius, on_total);
        let (progress, output) = (run.progress(), run.output_pct());
        if progress != before {
            emit(Event::Autotune {
                ticket,
                report: Report::Progress(progress),
            });
        }
        if let Some(stop) = stop {
            self.finish_autotune(now, stop, emit);
            return;
        }
        if output != out {
            self.take_command(now, Command::Percent(output), false, emit);
        }
    }

    /// The run's timeout, checked at `not_heating`'s tick.
    pub(super) fn autotune_tick(&mut self, now: Nanos, emit: &mut dyn FnMut(Event)) {
        let stop = self
            .heat
            .autotune
            .as_mut()
            .and_then(|(_, run)| run.tick(now));
        if let Some(stop) = stop {
            self.finish_autotune(now, stop, emit);
        }
    }

    /// Ends a run, if one goes, for `stop` at `now`.
    pub(super) fn finish_autotune(&mut self, now: Nanos, stop: Stop, emit: &mut dyn FnMut(Event)) {
        let Some((ticket, run)) = self.heat.autotune.as_ref() else {
            return;
        };
        let (ticket, progress) = (*ticket, run.progress());
        let estimate = run.estimate().filter(|_| stop == Stop::Converged);
        self.heat.autotune = None;
        let gains = estimate.map(|e| Rule::TyreusLuyben.gains(e.ku, e.tu_s));
        let sizing = gains.map(|g| self.tune_sizing(g));
        if self.loop_on() {
            // The loop holds 0 % until a new setpoint.
            self.heat.setpoint = None;
            self.heat.pid.start_from(0.0);
            self.heat.last_sample = None;
        }
        self.take_command(now, Command::Percent(0.0), false, emit);
        emit(Event::Autotune {
            ticket,
            report: Report::Finished(Outcome {
                stop,
                progress,
                estimate,
                gains,
                sizing,
            }),
        });
    }

    /// TCONT_CP's sizing rules (003) for `gains` with the channel's period and minima.
    fn tune_sizing(&self, gains: Gains) -> TuneSizing {
        let ms = |ns: Nanos| ns as f64 / super::super::NS_PER_MS as f64;
        let h = HeaterParams {
            control: Control::Pid,
            pid_kp: gains.kp,
            pid_ki: gains.ki,
            ..self.cfg.heater.params
        };
        let (period, min_on, min_off) = (
            ms(self.cfg.period),
            ms(self.cfg.min_on),
            ms(self.cfg.min_off),
        );
        let mut rules = sizing(&h, period, min_on, min_off);
        let broken = [rules.next(), rules.next(), rules.next()];
        let ti_ms = if gains.ki > 0.0 {
            gains.kp / gains.ki * 1000.0
        } else {
            f64::INFINITY
        };
        TuneSizing {
            period_ok: period <= ti_ms / 5.0,
            min_times_ok: min_on <= 0.1 * period && min_off <= 0.1 * period,
            recommended_period_ms: (ti_ms / 5.0)
                .floor()
                .min(super::super::config::MAX_PERIOD_MS as f64)
                as u64,
            broken,
        }
    }
}
