//! The compact console line per edge (`pw01 ↑ t=12.000000s late=+23us duty=37.0% e1=0`),
//! rate-limited per channel so it stays readable at 200 Hz: at most `rate` lines per second and
//! channel, and one summary line for the edges not shown.
//!
//! Pure text formatting and counting; the caller decides where the lines go (the log) and
//! passes the times in.

use crate::core::{Level, Nanos};
use crate::output_thread::EdgeReport;

const WINDOW_NS: Nanos = 1_000_000_000;

#[derive(Debug, Clone, Copy, Default)]
struct Window {
    start_ns: Nanos,
    shown: u32,
    hidden: u64,
    max_late_ns: i64,
}

/// Rate-limited edge lines for every channel.
#[derive(Debug, Clone)]
pub struct EdgeLines {
    rate: u32,
    windows: Vec<Window>,
}

/// The line for one edge. `t_ns` is the time since the node started, `late_ns` the lateness.
pub fn edge_line(
    channel: &str,
    level: Level,
    t_ns: Nanos,
    late_ns: i64,
    duty_pct: f64,
    e1: bool,
) -> String {
    format!(
        "{channel} {} t={}.{:06}s late={} duty={duty_pct:.1}% e1={}",
        if level.is_high() { '↑' } else { '↓' },
        t_ns / 1_000_000_000,
        (t_ns % 1_000_000_000) / 1000,
        signed_us(late_ns),
        u8::from(e1)
    )
}

fn signed_us(ns: i64) -> String {
    let us = ns / 1000;
    if ns < 0 {
        format!("-{}us", us.unsigned_abs())
    } else {
        format!("+{us}us")
    }
}

impl EdgeLines {
    /// `rate` lines per second and channel at most (0 = no lines at all).
    pub fn new(channels: usize, rate: u32) -> EdgeLines {
        EdgeLines {
            rate,
            windows: vec![Window::default(); channels],
        }
    }

    /// Changes the rate (from the `edge_log_rate` parameter).
    pub fn set_rate(&mut self, rate: u32) {
        self.rate = rate;
    }

    fn summary(channel: &str, w: &Window) -> String {
        format!(
            "{channel}: {} more edge{} in the last second not shown (latest max late={})",
            w.hidden,
            if w.hidden == 1 { "" } else { "s" },
            signed_us(w.max_late_ns)
        )
    }

    /// The lines to print for edge `e` of channel `channel` (named `name`): a summary of the
    /// previous second if edges were held back, then the edge's own line if the rate allows.
    /// `start_ns` is the node's start on the monotonic clock.
    pub fn edge(
        &mut self,
        channel: usize,
        name: &str,
        e: &EdgeReport,
        start_ns: Nanos,
        duty_pct: f64,
        e1: bool,
    ) -> Vec<String> {
        let mut out = Vec::new();
        let rate = self.rate;
        let Some(w) = self.windows.get_mut(channel) else {
            return out;
        };
        if rate == 0 {
            return out;
        }
        let now = e.actual_ns;
        if now.saturating_sub(w.start_ns) >= WINDOW_NS || w.start_ns == 0 {
            if w.hidden > 0 {
                out.push(Self::summary(name, w));
            }
            *w = Window {
                start_ns: now.max(1),
                ..Window::default()
            };
        }
        let late = e.lateness_ns();
        if w.shown < rate {
            w.shown += 1;
            out.push(edge_line(
                name,
                e.level,
                now.saturating_sub(start_ns),
                late,
                duty_pct,
                e1,
            ));
        } else {
            w.max_late_ns = if w.hidden == 0 {
                late
            } else {
                w.max_late_ns.max(late)
            };
            w.hidden += 1;
        }
        out
    }

    /// When [`EdgeLines::flush`] has a summary to give next (the earliest window with held-back
    /// edges closes), monotonic ns; `None` while no edge is held back.
    pub fn next_flush(&self) -> Option<Nanos> {
        self.windows
            .iter()
            .filter(|w| w.hidden > 0)
            .map(|w| w.start_ns.saturating_add(WINDOW_NS))
            .min()
    }

    /// Summaries of channels whose held-back edges are older than a second at `now_ns`, so a
    /// burst is summarised even when no edge follows it. `names` gives the channel names.
    pub fn flush(&mut self, names: &[String], now_ns: Nanos) -> Vec<String> {
        let mut out = Vec::new();
        for (w, name) in self.windows.iter_mut().zip(names) {
            if w.hidden > 0 && now_ns.saturating_sub(w.start_ns) >= WINDOW_NS {
                out.push(Self::summary(name, w));
                *w = Window {
                    start_ns: now_ns.max(1),
                    ..Window::default()
                };
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn edge(level: Level, actual_ns: Nanos, late_ns: i64) -> EdgeReport {
        EdgeReport {
            channel: 0,
            level,
            seq: 1,
            scheduled_ns: (actual_ns as i64 - late_ns) as Nanos,
            actual_ns,
            wall_ns: 0,
        }
    }

    #[test]
    fn line_format() {
        assert_eq!(
            edge_line("pw01", Level::High, 12_000_000_000, 23_400, 37.0, false),
            "pw01 ↑ t=12.000000s late=+23us duty=37.0% e1=0"
        );
        assert_eq!(
            edge_line("pw02", Level::Low, 1_234_567_891, -2_000, 5.04, true),
            "pw02 ↓ t=1.234567s late=-2us duty=5.0% e1=1"
        );
    }

    #[test]
    fn rate_limit_and_summary() {
        let start = 1_000_000_000;
        let mut l = EdgeLines::new(1, 3);
        let names = vec!["pw01".to_string()];
        let mut printed = 0;
        // 200 Hz for one second: 3 lines, then silence.
        for i in 0..200u64 {
            let t = start + i * 5_000_000;
            printed += l
                .edge(
                    0,
                    "pw01",
                    &edge(Level::High, t, 1000 + i as i64),
                    start,
                    50.0,
                    false,
                )
                .len();
        }
        assert_eq!(printed, 3);
        // Not yet a second since the window opened: no summary.
        assert!(l.flush(&names, start + 900_000_000).is_empty());
        let s = l.flush(&names, start + 1_000_000_000);
        assert_eq!(
            s,
            vec!["pw01: 197 more edges in the last second not shown (latest max late=+1us)"]
        );
        // The next edge opens a new window and is shown.
        let next = l.edge(
            0,
            "pw01",
            &edge(Level::Low, start + 1_100_000_000, 0),
            start,
            50.0,
            false,
        );
        assert_eq!(next.len(), 1);
        assert!(next[0].starts_with("pw01 ↓ t=1.100000s"));
    }

    #[test]
    fn summary_on_next_window_when_not_flushed() {
        let mut l = EdgeLines::new(1, 1);
        let a = l.edge(0, "pw01", &edge(Level::High, 10, 0), 0, 1.0, false);
        let b = l.edge(0, "pw01", &edge(Level::Low, 20, 0), 0, 1.0, false);
        let c = l.edge(
            0,
            "pw01",
            &edge(Level::High, 10 + WINDOW_NS, 0),
            0,
            1.0,
            false,
        );
        assert_eq!((a.len(), b.len(), c.len()), (1, 0, 2));
        assert!(c[0].contains("1 more edge in the last second"));
    }

    #[test]
    fn rate_zero_prints_nothing() {
        let mut l = EdgeLines::new(1, 0);
        assert!(l
            .edge(0, "pw01", &edge(Level::High, 10, 0), 0, 1.0, false)
            .is_empty());
        assert!(l.flush(&["pw01".into()], 10 * WINDOW_NS).is_empty());
    }
}
