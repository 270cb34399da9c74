//! The command-rate check of one channel, as diagnostic_updater's `FrequencyStatus` does it:
//! a ring of the command count and the time at each of the last `window` diagnostics runs (one
//! a second); each run measures `events / elapsed` against the oldest entry and replaces it.
//!
//! Levels and messages are the convention's, word for word, so an aggregator or a person who
//! knows `FrequencyStatus` reads them as usual:
//! - no command in the window: ERROR `No events recorded.`;
//! - below `min * (1 - tolerance)`: WARN `Frequency too low.`;
//! - above `max * (1 + tolerance)`: WARN `Frequency too high.`;
//! - otherwise OK `Desired frequency met`.
//!
//! With both bounds 0 the rate is measured and shown but not judged (OK, `Not checked`), so
//! the status is there whatever the settings and an aggregator never sees it go stale.
//!
//! Pure: counts and times (monotonic ns) are passed in; nothing here reads a clock.

use crate::core::Nanos;
use crate::ros::inbound::node_state::RateSettings;
use crate::ros::interface::msg::DiagnosticStatus;
use crate::ros::outbound::decimal::Fixed;
use crate::ros::outbound::diagnostics::key_values;

/// The summary when neither bound is set.
pub const NOT_CHECKED: &str =
    "Not checked (expected_command_hz_min and expected_command_hz_max are 0)";

/// One channel's rate check (see the module documentation).
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyStatus {
    /// (count, monotonic ns) at each of the last `window` runs; the oldest at `next`.
    ring: Vec<(u64, Nanos)>,
    next: usize,
}

/// What one run measured and concluded.
#[derive(Debug, Clone, PartialEq)]
pub struct FrequencyReport {
    /// `DiagnosticStatus` level.
    pub level: u8,
    /// The summary.
    pub message: &'static str,
    /// Commands in the window.
    pub events: u64,
    /// Commands since start-up.
    pub total: u64,
    /// Length of the window, s.
    pub window_s: f64,
    /// Measured rate, Hz.
    pub hz: f64,
    /// The settings it was judged by.
    pub settings: RateSettings,
}

impl FrequencyStatus {
    /// A check over `window` runs (at least 1), starting empty at monotonic `now` with the
    /// command count at `count` (diagnostic_updater's `clear()`).
    pub fn new(window: usize, count: u64, now: Nanos) -> FrequencyStatus {
        FrequencyStatus {
            ring: vec![(count, now); window.max(1)],
            next: 0,
        }
    }

    /// The number of runs in the window.
    pub fn window(&self) -> usize {
        self.ring.len()
    }

    /// The same check over a new number of runs: it starts empty at the latest run, as
    /// diagnostic_updater's `clear()` would have then, so the next run measures from it.
    pub fn resized(&self, window: usize) -> FrequencyStatus {
        let latest = self.ring[(self.next + self.ring.len() - 1) % self.ring.len()];
        FrequencyStatus::new(window, latest.0, latest.1)
    }

    /// One diagnostics run at `now` with `count` commands since start-up, judged by `s` (its
    /// window is the caller's business: a new window needs a new `FrequencyStatus`).
    pub fn run(&mut self, count: u64, now: Nanos, s: RateSettings) -> FrequencyReport {
        let (then_count, then) = self.ring[self.next];
        let events = count.saturating_sub(then_count);
        let window_s = now.saturating_sub(then) as f64 / 1e9;
        // The runs are a second apart; a zero-length window (two runs at one instant) has no
        // rate rather than an infinite one.
        let hz = if window_s > 0.0 {
            events as f64 / window_s
        } else {
            0.0
        };
        self.ring[self.next] = (count, now);
        self.next = (self.next + 1) % self.ring.len();
        let max = if s.max_hz > 0.0 {
            s.max_hz
        } else {
            f64::INFINITY
        };
        let (level, message) = if !s.checked() {
            (DiagnosticStatus::OK, NOT_CHECKED)
        } else if events == 0 {
            (DiagnosticStatus::ERROR, "No events recorded.")
        } else if hz < s.min_hz * (1.0 - s.tolerance) {
            (DiagnosticStatus::WARN, "Frequency too low.")
        } else if hz > max * (1.0 + s.tolerance) {
            (DiagnosticStatus::WARN, "Frequency too high.")
        } else {
            (DiagnosticStatus::OK, "Desired frequency met")
        };
        FrequencyReport {
            level,
            message,
            events,
            total: count,
            window_s,
            hz,
            settings: s,
        }
    }
}

impl FrequencyReport {
    /// What is shown before the first run: OK, `Starting`, nothing measured yet; `total`
    /// commands so far.
    pub fn starting(total: u64, settings: RateSettings) -> FrequencyReport {
        FrequencyReport {
            level: DiagnosticStatus::OK,
            message: "Starting: the first measurement comes after a second",
            events: 0,
            total,
            window_s: 0.0,
            hz: 0.0,
            settings,
        }
    }

    /// The report as a status named `name` for `hardware_id`, with the convention's keys
    /// (`Events in window`, `Events since startup`, `Duration of window (s)`, `Actual frequency
    /// (Hz)`, and the target or acceptable bounds that apply).
    pub fn to_status(&self, name: String, hardware_id: &str) -> DiagnosticStatus {
        let s = &self.settings;
        let mut kv = vec![
            ("Events in window", self.events.to_string()),
            ("Events since startup", self.total.to_string()),
            (
                "Duration of window (s)",
                Fixed(self.window_s, 6).to_string(),
            ),
            ("Actual frequency (Hz)", Fixed(self.hz, 6).to_string()),
        ];
        // As FrequencyStatus: a target when both bounds are the same, then each bound that
        // exists, widened by the tolerance.
        if s.min_hz == s.max_hz && s.min_hz > 0.0 {
            kv.push(("Target frequency (Hz)", Fixed(s.min_hz, 6).to_string()));
        }
        if s.min_hz > 0.0 {
            kv.push((
                "Minimum acceptable frequency (Hz)",
                Fixed(s.min_hz * (1.0 - s.tolerance), 6).to_string(),
            ));
        }
        if s.max_hz > 0.0 {
            kv.push((
                "Maximum acceptable frequency (Hz)",
                Fixed(s.max_hz * (1.0 + s.tolerance), 6).to_string(),
            ));
        }
        kv.push(("Window (diagnostics runs)", s.window.to_string()));
        kv.push(("Tolerance", format!("{}", s.tolerance)));
        DiagnosticStatus {
            level: self.level,
            name,
            message: self.message.to_string(),
            hardware_id: hardware_id.to_string(),
            values: key_values(kv),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    fn settings(min_hz: f64, max_hz: f64) -> RateSettings {
        RateSettings {
            min_hz,
            max_hz,
            ..RateSettings::default()
        }
    }

    fn kv<'a>(d: &'a DiagnosticStatus, key: &str) -> Option<&'a str> {
        d.values
            .iter()
            .find(|k| k.key == key)
            .map(|k| k.value.as_str())
    }

    #[test]
    fn commands_at_10_hz_then_none_go_ok_low_then_no_events() {
        // Commands at 10 Hz for 10 s with a 5 Hz minimum, then none; a run every second.
        let s = settings(5.0, 0.0);
        let mut f = FrequencyStatus::new(5, 0, 0);
        let mut count = 0;
        let mut seen = Vec::new();
        for second in 1..=16 {
            if second <= 10 {
                count += 10;
            }
            let r = f.run(count, second * S, s);
            seen.push((second, r.level, r.message, r.events));
        }
        // The window holds the last five runs: after the first five, events / 5 s.
        assert_eq!(seen[0], (1, 0, "Desired frequency met", 10));
        assert_eq!(seen[9], (10, 0, "Desired frequency met", 50));
        // Stopped after 10 s: 40, 30, 20, 10 events in 5 s (8, 6, 4, 2 Hz): 4 Hz is below
        // 5 * 0.9 = 4.5 Hz.
        let after: Vec<_> = seen[10..].iter().map(|(_, l, m, e)| (*l, *m, *e)).collect();
        assert_eq!(
            after,
            [
                (0, "Desired frequency met", 40),
                (0, "Desired frequency met", 30),
                (1, "Frequency too low.", 20),
                (1, "Frequency too low.", 10),
                (2, "No events recorded.", 0),
                (2, "No events recorded.", 0),
            ]
        );
    }

    #[test]
    fn the_window_runs_from_the_start_until_it_is_full() {
        let mut f = FrequencyStatus::new(3, 7, 10 * S);
        let r = f.run(9, 11 * S, settings(1.0, 0.0));
        assert_eq!((r.events, r.total, r.window_s, r.hz), (2, 9, 1.0, 2.0));
        let r = f.run(11, 12 * S, settings(1.0, 0.0));
        assert_eq!((r.events, r.window_s), (4, 2.0));
        let r = f.run(11, 13 * S, settings(1.0, 0.0));
        assert_eq!((r.events, r.window_s), (4, 3.0));
        // Full: now against the run at 11 s.
        let r = f.run(12, 14 * S, settings(1.0, 0.0));
        assert_eq!((r.events, r.window_s), (3, 3.0));
        assert_eq!(f.window(), 3);
    }

    #[test]
    fn too_high_and_the_tolerance() {
        let mut f = FrequencyStatus::new(1, 0, 0);
        // 11 Hz against a 10 Hz maximum with 10 % tolerance: met (11 is not above 11).
        assert_eq!(f.run(11, S, settings(0.0, 10.0)).level, 0);
        let r = f.run(23, 2 * S, settings(0.0, 10.0));
        assert_eq!((r.level, r.message), (1, "Frequency too high."));
        // Without tolerance 10.5 Hz is too high already.
        let exact = RateSettings {
            tolerance: 0.0,
            ..settings(10.0, 10.0)
        };
        let mut f = FrequencyStatus::new(1, 0, 0);
        let r = f.run(21, 2 * S, exact);
        assert_eq!(r.message, "Frequency too high.");
        let d = r.to_status("n: pw01 command frequency".into(), "sim");
        assert_eq!(kv(&d, "Target frequency (Hz)"), Some("10.000000"));
        assert_eq!(
            kv(&d, "Minimum acceptable frequency (Hz)"),
            Some("10.000000")
        );
        assert_eq!(
            kv(&d, "Maximum acceptable frequency (Hz)"),
            Some("10.000000")
        );
        assert_eq!(kv(&d, "Actual frequency (Hz)"), Some("10.500000"));
        assert_eq!(kv(&d, "Duration of window (s)"), Some("2.000000"));
        assert_eq!(d.hardware_id, "sim");
    }

    #[test]
    fn unchecked_is_measured_but_ok() {
        let mut f = FrequencyStatus::new(5, 0, 0);
        let r = f.run(0, S, settings(0.0, 0.0));
        assert_eq!((r.level, r.message), (0, NOT_CHECKED));
        let d = r.to_status("n: pw01 command frequency".into(), "sim");
        assert_eq!(kv(&d, "Events in window"), Some("0"));
        assert_eq!(kv(&d, "Actual frequency (Hz)"), Some("0.000000"));
        assert_eq!(kv(&d, "Target frequency (Hz)"), None);
        assert_eq!(kv(&d, "Minimum acceptable frequency (Hz)"), None);
        assert_eq!(kv(&d, "Maximum acceptable frequency (Hz)"), None);
        // Only a maximum: no events is an error, as the convention has it.
        let r = f.run(0, 2 * S, settings(0.0, 50.0));
        assert_eq!((r.level, r.message), (2, "No events recorded."));
        let d = r.to_status("x".into(), "sim");
        assert_eq!(kv(&d, "Minimum acceptable frequency (Hz)"), None);
        assert_eq!(
            kv(&d, "Maximum acceptable frequency (Hz)"),
            Some("55.000000")
        );
    }

    #[test]
    fn a_new_window_starts_at_the_latest_run() {
        let s = settings(1.0, 0.0);
        let mut f = FrequencyStatus::new(5, 0, 0);
        f.run(10, S, s);
        f.run(20, 2 * S, s);
        let mut g = f.resized(2);
        assert_eq!(g.window(), 2);
        let r = g.run(25, 3 * S, s);
        assert_eq!((r.events, r.window_s), (5, 1.0));
        let r = g.run(30, 4 * S, s);
        assert_eq!((r.events, r.window_s), (10, 2.0));
        let r = g.run(30, 5 * S, s);
        assert_eq!((r.events, r.window_s), (5, 2.0));
    }

    #[test]
    fn two_runs_at_one_instant_have_no_rate() {
        let mut f = FrequencyStatus::new(1, 0, 5);
        let r = f.run(3, 5, settings(1.0, 0.0));
        assert_eq!((r.events, r.hz), (3, 0.0));
        assert_eq!(r.message, "Frequency too low.");
    }
}
