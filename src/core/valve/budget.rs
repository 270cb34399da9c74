//! The motor's budget of starts (`max_starts_per_h`): actuator data sheets give a duty class in
//! starts per hour (IEC 60034-1 duty S4), and a motor started more often than that overheats
//! and wears its gear and contacts. The valve counts every rise of a line as a start.
//!
//! Two rules keep the budget, and the valve's dead band, minimum pulse and accumulation are how
//! they act (Schneider `SERVO`: a move held back is accumulated, not lost):
//!
//! - **Pacing**: a bucket of tokens, refilled at `max_starts_per_h` an hour and holding a
//!   tenth of it; a start that tracks a target (position commands, the loop) needs a token,
//!   and while fewer than half the bucket are left the dead band in force widens in
//!   proportion (twice as wide at a quarter, ...), so small corrections wait and add up while
//!   large ones still go.
//! - **The hour**: no tracking start is made while the last 61 minutes (counted per minute,
//!   the minute under way included) already hold `max_starts_per_h` starts, so no window of
//!   an hour ever holds more.
//!
//! Starts the valve cannot defer — the reference at start, the exercise stroke, the end move
//! of a command timeout or of the loop's safe position, manual moves — are made at once,
//! counted, and take a token if one is left.

use crate::core::Nanos;

/// One minute, ns.
const MINUTE: Nanos = 60_000_000_000;

/// Minutes counted for the hour: the one under way and the 60 before it cover every window
/// of an hour that ends now.
const MINUTES: usize = 61;

/// How far the dead band in force may widen, times the configured one.
pub const MAX_DEADBAND_FACTOR: f64 = 20.0;

/// The start budget of one valve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Budget {
    /// Starts an hour; 0 = no budget.
    per_h: u64,
    /// Tokens left, 0..=capacity.
    tokens: f64,
    /// When the tokens were last refilled, ns.
    refilled_at: Nanos,
    /// Starts per minute, indexed by the minute's number modulo [`MINUTES`], and which minute
    /// each slot holds.
    counts: [u32; MINUTES],
    minute_of: [u64; MINUTES],
    /// Every start since the valve was made.
    total: u64,
}

impl Budget {
    /// A budget of `per_h` starts an hour (0: none) at `now`, its bucket full.
    pub fn new(per_h: u64, now: Nanos) -> Budget {
        let mut b = Budget {
            per_h,
            tokens: 0.0,
            refilled_at: now,
            counts: [0; MINUTES],
            minute_of: [u64::MAX; MINUTES],
            total: 0,
        };
        b.tokens = b.capacity();
        b
    }

    /// A new rate at `now`; the starts counted stay, the bucket keeps its share.
    pub fn set_rate(&mut self, per_h: u64, now: Nanos) {
        if per_h == self.per_h {
            return;
        }
        self.refill(now);
        let share = if self.capacity() > 0.0 {
            self.tokens / self.capacity()
        } else {
            1.0
        };
        self.per_h = per_h;
        self.tokens = share * self.capacity();
    }

    /// Starts an hour; 0 = none.
    pub fn per_h(&self) -> u64 {
        self.per_h
    }

    /// The bucket's size: a tenth of the hour's starts, at least one.
    fn capacity(&self) -> f64 {
        if self.per_h == 0 {
            0.0
        } else {
            (self.per_h as f64 / 10.0).max(1.0)
        }
    }

    /// Tokens added per ns.
    fn rate(&self) -> f64 {
        self.per_h as f64 / 3.6e12
    }

    fn refill(&mut self, now: Nanos) {
        if now > self.refilled_at {
            let add = (now - self.refilled_at) as f64 * self.rate();
            self.tokens = (self.tokens + add).min(self.capacity());
            self.refilled_at = now;
        }
    }

    /// Tokens at `now`.
    pub fn tokens(&self, now: Nanos) -> f64 {
        let add = now.saturating_sub(self.refilled_at) as f64 * self.rate();
        (self.tokens + add).min(self.capacity())
    }

    /// Starts within the minute under way and the 60 before it at `now`.
    pub fn last_hour(&self, now: Nanos) -> u64 {
        let m = now / MINUTE;
        let first = m.saturating_sub(MINUTES as u64 - 1);
        self.counts
            .iter()
            .zip(&self.minute_of)
            .filter(|(_, &of)| of != u64::MAX && of >= first && of <= m)
            .map(|(&c, _)| u64::from(c))
            .sum()
    }

    /// Every start counted.
    pub fn total(&self) -> u64 {
        self.total
    }

    /// Whether a start that tracks a target may be made at `now`.
    pub fn allows(&self, now: Nanos) -> bool {
        self.per_h == 0 || (self.tokens(now) >= 1.0 && self.last_hour(now) < self.per_h)
    }

    /// How many times the configured dead band is in force at `now`: 1 while at least half
    /// the bucket is left, then in proportion to what is missing, at most
    /// [`MAX_DEADBAND_FACTOR`].
    pub fn deadband_factor(&self, now: Nanos) -> f64 {
        if self.per_h == 0 {
            return 1.0;
        }
        let half = self.capacity() / 2.0;
        let t = self.tokens(now);
        if t >= half {
            1.0
        } else {
            (half / t.max(half / MAX_DEADBAND_FACTOR)).min(MAX_DEADBAND_FACTOR)
        }
    }

    /// When a token (and the dead band it narrows) next comes back, if the budget is on and
    /// the bucket is not full.
    pub fn next_token_at(&self, now: Nanos) -> Option<Nanos> {
        if self.per_h == 0 {
            return None;
        }
        let t = self.tokens(now);
        if t >= self.capacity() {
            return None;
        }
        let missing = (t.floor() + 1.0 - t).max(1e-9);
        let wait = (missing / self.rate()).ceil() as Nanos;
        // A full hour's window may hold it back longer: then the minute that frees it.
        let window = if self.last_hour(now) >= self.per_h {
            (now / MINUTE + 1) * MINUTE
        } else {
            0
        };
        Some(now.saturating_add(wait.max(1)).max(window))
    }

    /// A start at `now`: counted, and a token taken if one is left.
    pub fn start(&mut self, now: Nanos) {
        self.refill(now);
        self.tokens = (self.tokens - 1.0).max(0.0);
        self.total += 1;
        let m = now / MINUTE;
        let i = (m % MINUTES as u64) as usize;
        if self.minute_of[i] != m {
            self.minute_of[i] = m;
            self.counts[i] = 0;
        }
        self.counts[i] = self.counts[i].saturating_add(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Nanos = 1_000_000_000;

    #[test]
    fn no_budget_allows_every_start_and_counts_them() {
        let mut b = Budget::new(0, 0);
        for k in 0..1000 {
            assert!(b.allows(k * S / 10));
            b.start(k * S / 10);
        }
        assert_eq!(b.total(), 1000);
        assert_eq!(b.last_hour(100 * S), 1000);
        assert_eq!(b.deadband_factor(0), 1.0);
        assert_eq!(b.next_token_at(0), None);
    }

    /// Greedy starts, as often as allowed, for ten hours: no window of an hour holds more than
    /// the budget, and the long run takes nearly all of it.
    #[test]
    fn no_hour_holds_more_starts_than_the_budget() {
        for per_h in [1, 7, 60, 120, 1200] {
            let mut b = Budget::new(per_h, 0);
            let mut starts = Vec::new();
            let mut t = 0;
            while t < 10 * 3600 * S {
                if b.allows(t) {
                    b.start(t);
                    starts.push(t);
                }
                t += S / 4;
            }
            let mut most = 0;
            for (i, &s) in starts.iter().enumerate() {
                let n = starts[i..]
                    .iter()
                    .take_while(|&&x| x < s + 3600 * S)
                    .count();
                most = most.max(n);
            }
            assert!(
                most as u64 <= per_h,
                "{per_h}: {most} starts within an hour"
            );
            // Pacing: the first ten minutes hold at most a tenth of the budget (at least one)
            // and what a sixth of the hour refills.
            let early = starts.iter().take_while(|&&x| x < 600 * S).count() as f64;
            let cap = (per_h as f64 / 10.0).max(1.0);
            assert!(
                early <= cap.floor() + per_h as f64 / 6.0 + 1.0,
                "{per_h}: {early}"
            );
            let per_hour = starts.len() as f64 / 10.0;
            assert!(
                per_hour >= 0.9 * per_h as f64,
                "{per_h}: {per_hour} an hour"
            );
        }
    }

    #[test]
    fn the_dead_band_widens_as_the_bucket_empties() {
        let mut b = Budget::new(120, 0);
        // Capacity 12: the factor stays 1 down to 6 tokens.
        for _ in 0..6 {
            b.start(0);
        }
        assert_eq!(b.deadband_factor(0), 1.0);
        b.start(0);
        b.start(0);
        b.start(0);
        // 3 tokens: twice the dead band.
        assert!((b.deadband_factor(0) - 2.0).abs() < 1e-9);
        // Refilled at 120 an hour: three more tokens in 90 s.
        assert!((b.deadband_factor(90 * S) - 1.0).abs() < 1e-9);
        b.start(0);
        b.start(0);
        b.start(0);
        assert_eq!(b.deadband_factor(0), MAX_DEADBAND_FACTOR);
        assert!(!b.allows(0));
        let next = b.next_token_at(0).expect("refilling");
        assert_eq!(next, 30 * S);
        assert!(b.allows(next));
    }

    #[test]
    fn starts_that_cannot_wait_are_counted_and_take_what_is_left() {
        let mut b = Budget::new(10, 0);
        for _ in 0..5 {
            b.start(S);
        }
        assert_eq!(b.total(), 5);
        assert_eq!(b.tokens(S), 0.0);
        assert!(!b.allows(S));
        assert_eq!(b.last_hour(S), 5);
        // An hour and a minute later the minutes have passed.
        assert_eq!(b.last_hour(3661 * S + S), 0);
    }
}
