//! A simulated three-point actuator, the "true" valve that the property tests and
//! `pwm_actuator_node sim-valve` drive with the node's real edges: its own travel times, a
//! start lag, a coast after the fall, play between motor and stem, hard end stops, end
//! switches that close near the ends, and faults a real one has (a stalled motor, a stuck
//! switch). Times are the edges' stamps, ns; positions percent of the stroke, 0 = closed.
//!
//! The motor position `m` runs over `0..=100 + backlash`; the stem follows it with the play:
//! opening moves the stem only once the motor is `backlash` ahead of it, closing once the motor
//! is back at it. The stops hold the stem within `0..=100` (the motor stalls against them).

/// What kind of actuator it is.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthParams {
    /// Travel times (open, close), ns.
    pub travel_ns: [f64; 2],
    /// From a line's rise until the motor moves, ns.
    pub lag_ns: f64,
    /// The motor runs on this long after a fall (if it was moving), ns.
    pub coast_ns: f64,
    /// Play between motor and stem, percent of the stroke.
    pub backlash_pct: f64,
    /// An end switch closes this close to its end, percent.
    pub switch_at_pct: f64,
}

/// The true valve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueValve {
    p: TruthParams,
    /// The motor's position at the last change, percent.
    motor: f64,
    /// The stem's position at the last change, percent.
    stem: f64,
    /// Which line is high (0 open, 1 close) and since when, ns.
    high: [Option<i64>; 2],
    /// The motor does not turn.
    pub stalled: bool,
    /// A switch stuck active (open, close), whatever the position.
    pub stuck: [bool; 2],
}

impl TrueValve {
    /// A valve whose stem is at `pos` percent, the play taken up towards closing.
    pub fn new(p: TruthParams, pos: f64) -> TrueValve {
        let pos = pos.clamp(0.0, 100.0);
        TrueValve {
            p,
            motor: pos,
            stem: pos,
            high: [None, None],
            stalled: false,
            stuck: [false; 2],
        }
    }

    /// The settings.
    pub fn params(&self) -> &TruthParams {
        &self.p
    }

    /// The motor displacement a line high from `since` to `t` gives, the coast after a fall
    /// (`fell`) included, percent.
    fn displacement(&self, i: usize, since: i64, t: i64, fell: bool) -> f64 {
        if self.stalled {
            return 0.0;
        }
        let ran = (t - since) as f64 - self.p.lag_ns;
        if ran <= 0.0 {
            return 0.0;
        }
        let ran = if fell { ran + self.p.coast_ns } else { ran };
        ran / self.p.travel_ns[i] * 100.0
    }

    /// The motor and stem after a motor displacement `delta` in direction `i` from
    /// (`motor`, `stem`).
    fn apply(&self, motor: f64, stem: f64, i: usize, delta: f64) -> (f64, f64) {
        let b = self.p.backlash_pct;
        if i == 0 {
            // The stem moves once the motor is `b` ahead of it; the stop holds it at 100.
            let m = (motor + delta).min(100.0 + b);
            (m, stem.max(m - b).min(100.0))
        } else {
            let m = (motor - delta).max(0.0);
            (m, stem.min(m).max(0.0))
        }
    }

    /// Line `i` (0 open, 1 close) went to `level` at `t` ns. A rise while the other line is
    /// high (never, from the node) is ignored: the motor would not turn.
    pub fn edge(&mut self, i: usize, level: bool, t: i64) {
        if i > 1 {
            return;
        }
        match (level, self.high[i]) {
            (true, None) if self.high[1 - i].is_none() => self.high[i] = Some(t),
            (false, Some(since)) => {
                let d = self.displacement(i, since, t, true);
                (self.motor, self.stem) = self.apply(self.motor, self.stem, i, d);
                self.high[i] = None;
            }
            _ => {}
        }
    }

    /// The stem's true position at `t` ns, percent.
    pub fn position(&self, t: i64) -> f64 {
        for i in 0..2 {
            if let Some(since) = self.high[i] {
                let d = self.displacement(i, since, t, false);
                return self.apply(self.motor, self.stem, i, d).1;
            }
        }
        self.stem
    }

    /// Whether a line is high.
    pub fn driving(&self) -> bool {
        self.high.iter().any(Option::is_some)
    }

    /// The end switches (open, close) at `t`: closed within `switch_at_pct` of their end, or
    /// stuck.
    pub fn switches(&self, t: i64) -> [bool; 2] {
        let p = self.position(t);
        [
            self.stuck[0] || p >= 100.0 - self.p.switch_at_pct,
            self.stuck[1] || p <= self.p.switch_at_pct,
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(lag: f64, coast: f64, b: f64) -> TruthParams {
        TruthParams {
            travel_ns: [1e9, 2e9],
            lag_ns: lag,
            coast_ns: coast,
            backlash_pct: b,
            switch_at_pct: 0.5,
        }
    }

    #[test]
    fn the_true_valve_integrates_its_lines_between_hard_stops() {
        let mut v = TrueValve::new(params(0.0, 0.0, 0.0), 50.0);
        v.edge(0, true, 0);
        assert!((v.position(250_000_000) - 75.0).abs() < 1e-9);
        v.edge(0, false, 1_000_000_000);
        assert_eq!(v.position(2_000_000_000), 100.0, "the open stop");
        assert_eq!(v.switches(2_000_000_000), [true, false]);
        v.edge(1, true, 3_000_000_000);
        v.edge(1, false, 4_000_000_000);
        assert!((v.position(5_000_000_000) - 50.0).abs() < 1e-9);
    }

    #[test]
    fn lag_coast_and_play_shape_each_drive() {
        // 100 ms lag, 20 ms coast: a 300 ms drive moves the motor 220 ms' worth.
        let mut v = TrueValve::new(params(1e8, 2e7, 2.0), 50.0);
        v.edge(0, true, 0);
        assert_eq!(v.position(50_000_000), 50.0, "within the lag");
        v.edge(0, false, 300_000_000);
        // 22 % of motor travel, the first 2 % taking up the play.
        assert!((v.position(400_000_000) - 70.0).abs() < 1e-9, "{v:?}");
        // Reversing: 2 % of play first, then the stem follows.
        v.edge(1, true, 1_000_000_000);
        v.edge(1, false, 1_280_000_000);
        // 200 ms of closing motor at 2 s: 10 %, 2 % of it play.
        assert!((v.position(2_000_000_000) - 62.0).abs() < 1e-9, "{v:?}");
        v.stalled = true;
        v.edge(0, true, 3_000_000_000);
        v.edge(0, false, 4_000_000_000);
        assert!((v.position(5_000_000_000) - 62.0).abs() < 1e-9);
    }
}
