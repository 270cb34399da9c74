//! The PID of the heater loop, in percent of duty per °C, sampled at fixed instants.
//!
//! The shape of the PID that heater controllers run (Klipper's `ControlPID`, ESPHome's PID
//! climate): the derivative is taken on the measurement, not the error, so a setpoint step
//! gives no kick; it is smoothed by a first-order filter. The integral is kept in percent (its
//! contribution to the output), is held inside the output limits, and is not integrated further
//! while the output sits at a limit in the direction the error pushes (anti-windup). A change
//! of gains and the start of the loop are bumpless: the integral takes up the difference so the
//! output does not jump.
//!
//! Nothing here reads a clock; the caller passes the time since the last sample.

pub use super::super::config::heater::Gains;

/// What each term contributed at the last sample, and the output, all in percent
/// (pid-rs's habit: the terms are returned, not hidden).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Terms {
    /// Proportional term, %.
    pub p: f64,
    /// Integral term, %.
    pub i: f64,
    /// Derivative term (on the measurement), %.
    pub d: f64,
    /// The output, limited to the output limits, %.
    pub output: f64,
}

/// The loop's state (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pid {
    gains: Gains,
    /// The integral term, %.
    integral: f64,
    /// The filtered derivative term, %.
    d: f64,
    /// The measurement and setpoint of the last sample, °C.
    last: Option<(f64, f64)>,
    /// The next sample starts from this output, % (a bumpless start).
    start_from: Option<f64>,
    terms: Terms,
}

impl Pid {
    /// A loop with `gains` that has not run yet; its first sample starts from 0 %.
    pub fn new(gains: Gains) -> Pid {
        Pid {
            gains,
            integral: 0.0,
            d: 0.0,
            last: None,
            start_from: Some(0.0),
            terms: Terms::default(),
        }
    }

    /// The gains in force.
    pub fn gains(&self) -> Gains {
        self.gains
    }

    /// The terms of the last sample.
    pub fn terms(&self) -> Terms {
        self.terms
    }

    /// Makes the next sample start from `output` % (bumpless transfer): its integral is set so
    /// that, with the proportional term of that sample, the output is `output` as far as the
    /// limits and the integral's range allow. Used when the loop takes over from an open-loop
    /// duty. The derivative starts afresh.
    pub fn start_from(&mut self, output: f64) {
        self.start_from = Some(output);
        self.last = None;
        self.d = 0.0;
    }

    /// Moves the integral by `pct` (%): a feed-forward added to the output handing its value
    /// to the integral when it goes stale (or taking it back when it returns), so the output
    /// does not jump.
    pub fn shift_integral(&mut self, pct: f64) {
        if let Some(from) = self.start_from.as_mut() {
            *from += pct;
        } else {
            self.integral += pct;
            self.terms.i = self.integral;
        }
    }

    /// Takes new gains without a jump of the output: the derivative keeps its filtered slope
    /// (rescaled to the new gain) and the integral takes up what the new proportional term
    /// changes, so the output the old gains gave at the last sample is what the new ones give
    /// for that same sample, within `lo..=hi` %.
    pub fn set_gains(&mut self, gains: Gains, lo: f64, hi: f64) {
        if gains == self.gains {
            return;
        }
        self.d = if self.gains.kd != 0.0 {
            self.d * gains.kd / self.gains.kd
        } else {
            0.0
        };
        if let Some((measurement, setpoint)) = self.last {
            let p = gains.kp * (setpoint - measurement);
            self.integral = (self.terms.output - p - self.d).clamp(lo, hi);
        }
        self.gains = gains;
    }

    /// One sample on a new reading: the loop's output for `setpoint` and `measurement` (°C),
    /// `dt_s` seconds after the last sample, which read the previous reading `dt_s` before,
    /// limited to `lo..=hi` %. See [`Pid::sample`].
    pub fn step(&mut self, setpoint: f64, measurement: f64, dt_s: f64, lo: f64, hi: f64) -> Terms {
        self.sample(setpoint, measurement, Some(dt_s), dt_s, lo, hi)
    }

    /// One sample: the loop's output for `setpoint` and `measurement` (°C), `dt_s` seconds
    /// after the last sample, limited to `lo..=hi` % (the power limits the duty then goes
    /// through). `reading_dt_s` is the time between this measurement and the one the last
    /// sample used, `None` when it is the same reading: the derivative is taken between
    /// readings, not between samples, so a loop that samples faster than its sensor publishes
    /// sees neither a zero slope nor a spike. Both inputs must be finite; the caller refuses
    /// the rest.
    pub fn sample(
        &mut self,
        setpoint: f64,
        measurement: f64,
        reading_dt_s: Option<f64>,
        dt_s: f64,
        lo: f64,
        hi: f64,
    ) -> Terms {
        let g = self.gains;
        let error = setpoint - measurement;
        let p = g.kp * error;
        // Derivative on the measurement: a setpoint step changes P only.
        if let (Some((last, _)), Some(rdt)) = (self.last, reading_dt_s.filter(|t| *t > 0.0)) {
            let raw = -g.kd * (measurement - last) / rdt;
            let alpha = if g.d_filter_s > 0.0 {
                rdt / (g.d_filter_s + rdt)
            } else {
                1.0
            };
            self.d += alpha * (raw - self.d);
        }
        if let Some(from) = self.start_from.take() {
            self.integral = (from - p - self.d).clamp(lo, hi);
        } else {
            let candidate = self.integral + g.ki * error * dt_s;
            // Anti-windup: the integral goes up to what holds the output at its limit in the
            // direction the error pushes, never beyond, and a step that would cross the limit
            // ends at it (so the output reaches the limit rather than stopping short of it).
            let rest = p + self.d;
            if error > 0.0 && rest + candidate > hi {
                self.integral = self.integral.max((hi - rest).min(candidate));
            } else if error < 0.0 && rest + candidate < lo {
                self.integral = self.integral.min((lo - rest).max(candidate));
            } else {
                self.integral = candidate;
            }
            self.integral = self.integral.clamp(lo, hi);
        }
        self.last = Some((measurement, setpoint));
        let output = (p + self.integral + self.d).clamp(lo, hi);
        self.terms = Terms {
            p,
            i: self.integral,
            d: self.d,
            output,
        };
        self.terms
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gains(kp: f64, ki: f64, kd: f64) -> Gains {
        Gains {
            kp,
            ki,
            kd,
            d_filter_s: 0.0,
        }
    }

    #[test]
    fn a_setpoint_step_moves_p_only_no_derivative_kick() {
        let mut pid = Pid::new(gains(2.0, 0.0, 50.0));
        pid.step(50.0, 40.0, 1.0, 0.0, 100.0);
        let t = pid.step(50.0, 40.0, 1.0, 0.0, 100.0);
        assert_eq!((t.p, t.d), (20.0, 0.0));
        // The setpoint jumps by 10 °C, the measurement does not move: no derivative.
        let t = pid.step(60.0, 40.0, 1.0, 0.0, 100.0);
        assert_eq!((t.p, t.d), (40.0, 0.0));
        // The measurement rises by 1 °C in 1 s: D = -50 % per °C/s.
        let t = pid.step(60.0, 41.0, 1.0, 0.0, 100.0);
        assert_eq!(t.d, -50.0);
    }

    #[test]
    fn the_derivative_is_taken_between_readings_not_samples() {
        let mut pid = Pid::new(gains(0.0, 0.0, 10.0));
        pid.sample(0.0, 0.0, Some(1.0), 0.25, -100.0, 100.0);
        // A reading 1 s later, 1 °C up: -10 %.
        let t = pid.sample(0.0, 1.0, Some(1.0), 0.25, -100.0, 100.0);
        assert_eq!(t.d, -10.0);
        // Three samples on the same reading: the slope holds, no zero.
        for _ in 0..3 {
            let t = pid.sample(0.0, 1.0, None, 0.25, -100.0, 100.0);
            assert_eq!(t.d, -10.0);
        }
        // The next reading, 1 s after the last: the same slope, no spike.
        let t = pid.sample(0.0, 2.0, Some(1.0), 0.25, -100.0, 100.0);
        assert_eq!(t.d, -10.0);
    }

    #[test]
    fn the_derivative_filter_smooths() {
        let mut pid = Pid::new(Gains {
            d_filter_s: 3.0,
            ..gains(0.0, 0.0, 10.0)
        });
        pid.step(0.0, 0.0, 1.0, -100.0, 100.0);
        let t = pid.step(0.0, 1.0, 1.0, -100.0, 100.0);
        // alpha = 1 / (3 + 1): a quarter of the raw -10 %.
        assert!((t.d + 2.5).abs() < 1e-12, "{t:?}");
    }

    #[test]
    fn the_integral_does_not_wind_up_while_the_output_is_limited() {
        let mut pid = Pid::new(gains(1.0, 1.0, 0.0));
        // A large error for a long time: the output sits at 100 %.
        for _ in 0..1000 {
            let t = pid.step(200.0, 20.0, 1.0, 0.0, 100.0);
            assert_eq!(t.output, 100.0);
        }
        assert!(pid.terms().i <= 100.0);
        // The measurement crosses the setpoint: the output leaves the limit at once rather
        // than after unwinding 1000 s of integral.
        let t = pid.step(200.0, 201.0, 1.0, 0.0, 100.0);
        assert!(t.output < 100.0, "{t:?}");
        let mut steps = 0;
        while pid.step(200.0, 205.0, 1.0, 0.0, 100.0).output > 0.0 {
            steps += 1;
            assert!(steps < 30, "the integral wound up: {:?}", pid.terms());
        }
    }

    #[test]
    fn the_integral_is_held_at_a_lowered_limit() {
        let mut pid = Pid::new(gains(0.0, 1.0, 0.0));
        for _ in 0..100 {
            pid.step(60.0, 50.0, 1.0, 0.0, 40.0);
        }
        assert_eq!(pid.terms().output, 40.0);
        assert!(pid.terms().i <= 40.0);
    }

    #[test]
    fn a_gain_change_is_bumpless() {
        let mut pid = Pid::new(gains(3.0, 0.1, 20.0));
        let mut m = 55.0;
        for _ in 0..20 {
            pid.step(60.0, m, 1.0, 0.0, 100.0);
            m += 0.1;
        }
        let before = pid.terms().output;
        assert!(before > 0.0 && before < 100.0, "{before}");
        pid.set_gains(gains(6.0, 0.3, 40.0), 0.0, 100.0);
        // The same sample again with the new gains: the same output.
        let (p, d) = (6.0 * (60.0 - (m - 0.1)), pid.d);
        assert!((p + pid.integral + d - before).abs() < 1e-9);
        // The next sample moves from there, by what the process did, not by the gain change.
        let after = pid.step(60.0, m, 1.0, 0.0, 100.0).output;
        assert!(
            (after - before).abs() < 6.0 * 0.1 + 0.3 * 3.0 + 40.0 * 0.1,
            "{before} -> {after}"
        );
    }

    #[test]
    fn the_loop_starts_bumpless_from_an_open_loop_duty() {
        let mut pid = Pid::new(gains(2.0, 0.1, 5.0));
        pid.start_from(40.0);
        let t = pid.step(55.0, 50.0, 1.0, 0.0, 100.0);
        assert_eq!(t.output, 40.0);
        assert_eq!((t.p, t.i), (10.0, 30.0));
        // From 0 % with a large error: the integral cannot go below the limit, P acts at once.
        let mut pid = Pid::new(gains(2.0, 0.1, 5.0));
        let t = pid.step(100.0, 20.0, 1.0, 0.0, 100.0);
        assert_eq!((t.i, t.output), (0.0, 100.0));
    }
}
