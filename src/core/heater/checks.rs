//! The heater checks that need a history: `not_heating` (Klipper's `verify_heater`) and
//! `stuck_on` (a rise while the line was held off). The range and sensor-timeout checks need
//! none and live with the channel's heater state.
//!
//! Pure state machines: the caller passes the instant, the reading and what the line did.

pub use super::super::config::heater::Runaway;
use super::super::Nanos;

/// Klipper's `verify_heater` state, ticked once a second (see
/// [`NotHeating::tick`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NotHeating {
    approaching: bool,
    starting: bool,
    last_target: f64,
    goal_temp: f64,
    goal_time: Nanos,
    error: f64,
}

impl Default for NotHeating {
    fn default() -> Self {
        NotHeating {
            approaching: false,
            starting: false,
            last_target: 0.0,
            goal_temp: 0.0,
            goal_time: Nanos::MAX,
            error: 0.0,
        }
    }
}

impl NotHeating {
    /// The error summed so far, °C·s.
    pub fn error(&self) -> f64 {
        self.error
    }

    /// Whether an approach to a new target is being watched.
    pub fn approaching(&self) -> bool {
        self.approaching
    }

    /// One tick at `now` with reading `temp` and `target` (°C; 0 or below: no target, as a
    /// heater switched off in Klipper). Returns true when the heater is not heating at the
    /// expected rate. Follows `klippy/extras/verify_heater.py` `check_event` step for step.
    pub fn tick(&mut self, now: Nanos, temp: f64, target: f64, p: &Runaway) -> bool {
        if temp >= target - p.hysteresis_c || target <= 0.0 {
            // Near the target (or none): the approach ends. Above the band the error is held,
            // not reset: a heater that overshot and then falls keeps what it had.
            self.approaching = false;
            self.starting = false;
            if temp <= target + p.hysteresis_c {
                self.error = 0.0;
            }
            self.last_target = target;
            return false;
        }
        self.error += (target - p.hysteresis_c) - temp;
        let mut fault = false;
        if !self.approaching {
            if target != self.last_target {
                // A new target: watch the approach; it must gain heating_gain within
                // check_gain_time, again and again.
                self.approaching = true;
                self.starting = true;
                self.goal_temp = temp + p.heating_gain_c;
                self.goal_time = now.saturating_add(p.gain_time);
            } else if self.error >= p.max_error {
                fault = true;
            }
        } else if temp >= self.goal_temp {
            // Gained: the error starts again and the goal is re-armed.
            self.starting = false;
            self.error = 0.0;
            self.goal_temp = temp + p.heating_gain_c;
            self.goal_time = now.saturating_add(p.gain_time);
        } else if now >= self.goal_time {
            // No longer approaching: the summed error decides from now on.
            self.approaching = false;
        } else if self.starting {
            // Right after a new target the temperature may still fall: the goal follows it.
            self.goal_temp = self.goal_temp.min(temp + p.heating_gain_c);
        }
        self.last_target = target;
        fault
    }
}

/// Readings kept for `stuck_on`'s window (decimated to about 1/16 of the window).
const STUCK_SLOTS: usize = 32;

/// The readings taken while the line was off, for `stuck_on`: a rise of more than
/// `stuck_on_rise_c` within `stuck_on_time_s` while the line has been held off the whole time.
/// A fixed ring: no allocation after construction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StuckOn {
    ring: [(Nanos, f64); STUCK_SLOTS],
    head: usize,
    len: usize,
}

impl Default for StuckOn {
    fn default() -> Self {
        StuckOn {
            ring: [(0, 0.0); STUCK_SLOTS],
            head: 0,
            len: 0,
        }
    }
}

/// What `stuck_on` found at a reading.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rise {
    /// The rise within the window, °C (the reading less the lowest one kept in the window).
    pub rise_c: f64,
    /// Whether the line has been off for the whole window.
    pub off_whole_window: bool,
}

impl StuckOn {
    /// Forgets every reading (the line went high, or the check was reconfigured).
    pub fn clear(&mut self) {
        self.len = 0;
    }

    fn get(&self, k: usize) -> (Nanos, f64) {
        self.ring[(self.head + k) % STUCK_SLOTS]
    }

    /// Takes a finite reading `temp` at `now`, with the line off since `off_since` (`None`:
    /// the line is high), over a window of `window` ns. Returns the rise within the window.
    pub fn reading(
        &mut self,
        now: Nanos,
        temp: f64,
        off_since: Option<Nanos>,
        window: Nanos,
    ) -> Rise {
        let Some(off_since) = off_since else {
            self.clear();
            return Rise {
                rise_c: 0.0,
                off_whole_window: false,
            };
        };
        let start = now.saturating_sub(window).max(off_since);
        // Drop what lies before the window or before the line went off.
        while self.len > 0 && self.get(0).0 < start {
            self.head = (self.head + 1) % STUCK_SLOTS;
            self.len -= 1;
        }
        let lowest = (0..self.len).map(|k| self.get(k).1).fold(temp, f64::min);
        let spacing = (window / (STUCK_SLOTS as Nanos / 2)).max(1);
        let newest = (self.len > 0).then(|| self.get(self.len - 1).0);
        if newest.is_none_or(|t| now >= t.saturating_add(spacing)) {
            if self.len == STUCK_SLOTS {
                self.head = (self.head + 1) % STUCK_SLOTS;
                self.len -= 1;
            }
            self.ring[(self.head + self.len) % STUCK_SLOTS] = (now, temp);
            self.len += 1;
        }
        Rise {
            rise_c: temp - lowest,
            off_whole_window: now.saturating_sub(off_since) >= window,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    fn klipper() -> Runaway {
        Runaway {
            hysteresis_c: 5.0,
            max_error: 120.0,
            gain_time: 20 * S,
            heating_gain_c: 2.0,
        }
    }

    #[test]
    fn a_new_target_starts_an_approach_that_must_gain() {
        let p = klipper();
        let mut v = NotHeating::default();
        // Heater at 20 °C, target 200: an approach starts, goal 22 within 20 s.
        assert!(!v.tick(0, 20.0, 200.0, &p));
        assert!(v.approaching());
        // Gains 2 °C every 10 s: never a fault, the error restarts at each gain.
        let mut temp = 20.0;
        for s in 1..=300 {
            temp += 0.2;
            assert!(!v.tick(s * S, temp, 200.0, &p), "tick {s}");
        }
        assert!(v.approaching());
    }

    #[test]
    fn a_cold_heater_trips_after_the_approach_and_max_error() {
        let p = klipper();
        let mut v = NotHeating::default();
        let mut tripped = None;
        for s in 0..100 {
            if v.tick(s * S, 20.0, 200.0, &p) {
                tripped = Some(s);
                break;
            }
        }
        // The approach runs out at 20 s; the error (175 °C per tick) then exceeds 120 at the
        // next tick.
        assert_eq!(tripped, Some(21));
    }

    #[test]
    fn the_error_is_held_above_the_band_and_reset_within_it() {
        let p = klipper();
        let mut v = NotHeating::default();
        v.tick(0, 100.0, 100.0, &p); // in the band: error 0, last target 100
        v.tick(S, 90.0, 100.0, &p); // below the band, same target: error 5
        assert_eq!(v.error(), 5.0);
        v.tick(2 * S, 110.0, 100.0, &p); // above the band: held
        assert_eq!(v.error(), 5.0);
        v.tick(3 * S, 100.0, 100.0, &p); // within: reset
        assert_eq!(v.error(), 0.0);
    }

    #[test]
    fn stuck_on_sees_a_rise_only_over_a_whole_window_off() {
        let mut s = StuckOn::default();
        let w = 10 * S;
        // The line went off at 0; the temperature rises 1 °C/s.
        for k in 0..=20u64 {
            let r = s.reading(k * S, 20.0 + k as f64, Some(0), w);
            assert_eq!(r.off_whole_window, k >= 10, "{k}");
            if k >= 10 {
                assert!((r.rise_c - 10.0).abs() < 1.0, "{k}: {r:?}");
            }
        }
        // The line goes high: everything is forgotten.
        let r = s.reading(21 * S, 41.0, None, w);
        assert_eq!(r.rise_c, 0.0);
        let r = s.reading(22 * S, 42.0, Some(21 * S + S / 2), w);
        assert_eq!((r.rise_c, r.off_whole_window), (0.0, false));
    }
}
