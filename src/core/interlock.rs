//! Split-range pairs (001's "Hot/Cold or Split Range case"): two channels driven from one signed
//! command, whose lines are never high together.
//!
//! Sans-IO like the channel: [`Interlocks::sync`] is called by whoever drives the channels after
//! each action on one of them, and engages or releases the partner's interlock from the real
//! levels of the lines. It never reads a clock and never writes an output.

use super::{Channel, Command, Event, Level, Nanos};

/// Why a pair is refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum PairError {
    /// A channel index beyond the channels configured.
    #[error("no channel with index {0}")]
    NoSuchChannel(usize),
    /// Both ends of the pair are the same channel.
    #[error("channel {0} cannot be paired with itself")]
    SelfPair(usize),
    /// A channel already belongs to another pair.
    #[error("channel {0} is already in a split-range pair")]
    AlreadyPaired(usize),
}

/// The partner of every channel that belongs to a pair.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Interlocks {
    partner: Vec<Option<usize>>,
}

impl Interlocks {
    /// No pairs among `channels` channels.
    pub fn new(channels: usize) -> Interlocks {
        Interlocks {
            partner: vec![None; channels],
        }
    }

    /// Pairs channels `a` and `b`: from now on their lines are never high together.
    pub fn pair(&mut self, a: usize, b: usize) -> Result<(), PairError> {
        for c in [a, b] {
            match self.partner.get(c) {
                None => return Err(PairError::NoSuchChannel(c)),
                Some(Some(_)) => return Err(PairError::AlreadyPaired(c)),
                Some(None) => {}
            }
        }
        if a == b {
            return Err(PairError::SelfPair(a));
        }
        self.partner[a] = Some(b);
        self.partner[b] = Some(a);
        Ok(())
    }

    /// The partner of channel `i`, if it is in a pair.
    pub fn partner(&self, i: usize) -> Option<usize> {
        self.partner.get(i).copied().flatten()
    }

    /// After channel `i` acted at `now`: each of the pair is interlocked exactly while the
    /// other's line is high. Releasing one may let its held rise through at once; its events go
    /// to `emit` with the channel index.
    pub fn sync(
        &self,
        channels: &mut [Channel],
        i: usize,
        now: Nanos,
        emit: &mut dyn FnMut(usize, Event),
    ) {
        let Some(p) = self.partner(i) else { return };
        if p >= channels.len() || i >= channels.len() {
            return;
        }
        let high = |c: &Channel| c.level() == Level::High;
        // The partner first: released, it may go high at once, and then `i` must stay locked.
        // Then `i` from the partner's level as it now is, and the partner once more in case
        // `i` itself went high on release.
        let i_high = high(&channels[i]);
        channels[p].set_interlock(now, i_high, &mut |e| emit(p, e));
        let p_high = high(&channels[p]);
        channels[i].set_interlock(now, p_high, &mut |e| emit(i, e));
        let i_high = high(&channels[i]);
        channels[p].set_interlock(now, i_high, &mut |e| emit(p, e));
    }
}

/// The duties a signed split-range command gives its pair, as (hot, cold) commands in percent:
/// positive drives the hot channel, negative the cold one, the other is held at 0; within the
/// dead band (`deadband_pct`, percent around 0) both are 0. NaN and infinities pass through to
/// the hot side's own refusal, so the last valid command stays in force.
pub fn split_command(signed_pct: f64, deadband_pct: f64) -> (Command, Command) {
    if !signed_pct.is_finite() {
        return (Command::Percent(signed_pct), Command::Percent(signed_pct));
    }
    let band = deadband_pct.abs();
    if signed_pct > band {
        (Command::Percent(signed_pct), Command::Percent(0.0))
    } else if signed_pct < -band {
        (Command::Percent(0.0), Command::Percent(-signed_pct))
    } else {
        (Command::Percent(0.0), Command::Percent(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::{ChannelParams, NS_PER_MS};

    const MS: Nanos = NS_PER_MS;

    fn cfg(period_ms: u64, min_on_ms: u64) -> crate::core::ChannelConfig {
        ChannelParams {
            period_ms,
            min_on_ms,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap()
    }

    /// Two channels in a pair, driven in virtual time; every edge logged as (ms, channel, high).
    struct Pair {
        ch: Vec<Channel>,
        locks: Interlocks,
        now: Nanos,
        log: Vec<(Nanos, usize, bool)>,
    }

    impl Pair {
        fn new(a: crate::core::ChannelConfig, b: crate::core::ChannelConfig) -> Pair {
            let mut locks = Interlocks::new(2);
            locks.pair(0, 1).unwrap();
            Pair {
                ch: vec![Channel::new(a, 0), Channel::new(b, 0)],
                locks,
                now: 0,
                log: Vec::new(),
            }
        }

        fn act(&mut self, i: usize, f: impl FnOnce(&mut Channel, Nanos, &mut dyn FnMut(Event))) {
            let now = self.now;
            let log = &mut self.log;
            let mut note = |c: usize, e: Event| {
                if let Event::Edge { level, .. } = e {
                    log.push((now / MS, c, level.is_high()));
                }
            };
            f(&mut self.ch[i], now, &mut |e| note(i, e));
            self.locks.sync(&mut self.ch, i, now, &mut note);
        }

        fn run_to(&mut self, t: Nanos) {
            loop {
                let next = (0..2)
                    .filter_map(|i| self.ch[i].poll_at().map(|d| (d, i)))
                    .min();
                match next {
                    Some((d, i)) if d <= t => {
                        self.now = d;
                        self.act(i, |c, now, emit| c.poll(now, emit));
                    }
                    _ => break,
                }
            }
            self.now = t;
        }

        fn split(&mut self, pct: f64) {
            let (hot, cold) = split_command(pct, 0.0);
            self.act(0, |c, now, emit| c.command(now, hot, emit));
            self.act(1, |c, now, emit| c.command(now, cold, emit));
        }

        fn never_both_high(&self) {
            let mut high = [false; 2];
            for (t, c, h) in &self.log {
                high[*c] = *h;
                assert!(!(high[0] && high[1]), "both high at {t} ms: {:?}", self.log);
            }
        }
    }

    #[test]
    fn split_command_drives_one_side_only_001() {
        let p = |c: Command| c.raw();
        let (h, c) = split_command(40.0, 0.0);
        assert_eq!((p(h), p(c)), (40.0, 0.0));
        let (h, c) = split_command(-25.0, 0.0);
        assert_eq!((p(h), p(c)), (0.0, 25.0));
        let (h, c) = split_command(1.5, 2.0);
        assert_eq!((p(h), p(c)), (0.0, 0.0), "inside the dead band");
        let (h, c) = split_command(-2.0, 2.0);
        assert_eq!((p(h), p(c)), (0.0, 0.0), "the band's edge is inside");
        let (h, _) = split_command(f64::NAN, 0.0);
        assert!(h.raw().is_nan(), "refused by the channel itself");
    }

    #[test]
    fn pairs_are_checked() {
        let mut l = Interlocks::new(3);
        assert_eq!(l.pair(0, 0), Err(PairError::SelfPair(0)));
        assert_eq!(l.pair(0, 3), Err(PairError::NoSuchChannel(3)));
        l.pair(0, 1).unwrap();
        assert_eq!(l.pair(2, 1), Err(PairError::AlreadyPaired(1)));
        assert_eq!(
            (l.partner(0), l.partner(1), l.partner(2)),
            (Some(1), Some(0), None)
        );
    }

    #[test]
    fn a_sign_change_never_overlaps_and_waits_for_the_partner_001() {
        // Hot at 60 % of 1 s (next_period: its running pulse completes); at 100 ms the command
        // goes to -50 %. Cold (immediate) would start its pulse at once, but its line stays low
        // until hot's pulse has ended at 600 ms.
        let tcont = ChannelParams {
            period_ms: 1000,
            profile: crate::core::Profile::TcontCp,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        let mut p = Pair::new(cfg(1000, 0), tcont);
        p.split(60.0);
        p.act(0, |c, now, emit| c.set_enable(now, true, emit));
        p.act(1, |c, now, emit| c.set_enable(now, true, emit));
        p.run_to(100 * MS);
        p.split(-50.0);
        p.run_to(3000 * MS);
        p.never_both_high();
        assert_eq!(p.log[..3], [(0, 0, true), (600, 0, false), (600, 1, true)]);
    }

    #[test]
    fn the_starting_side_waits_out_its_own_minimum_break_001() {
        // Both tcont_cp (immediate). Cold (min on/off 300 ms) runs 40 % and falls at 400 ms;
        // hot (min 100 ms) then runs 100 %. At 450 ms the command turns to -100 %: hot ends its
        // pulse at its minimum (500 ms), and cold rises only at 700 ms, after its own minimum
        // break since its fall at 400 ms.
        let tcont = |min_on_ms| {
            ChannelParams {
                period_ms: 1000,
                min_on_ms,
                profile: crate::core::Profile::TcontCp,
                ..ChannelParams::default()
            }
            .validate()
            .unwrap()
        };
        let mut p = Pair::new(tcont(100), tcont(300));
        p.split(-40.0);
        p.act(1, |c, now, emit| c.set_enable(now, true, emit));
        p.run_to(400 * MS);
        p.split(100.0);
        p.act(0, |c, now, emit| c.set_enable(now, true, emit));
        p.run_to(450 * MS);
        p.split(-100.0);
        p.run_to(2000 * MS);
        p.never_both_high();
        assert_eq!(
            p.log,
            [
                (0, 1, true),
                (400, 1, false),
                (400, 0, true),
                (500, 0, false),
                (700, 1, true)
            ]
        );
    }

    mod props {
        use super::*;
        use crate::core::{ApplyAt, OutputKind, Profile};
        use proptest::prelude::*;

        fn arb_cfg() -> impl Strategy<Value = crate::core::ChannelConfig> {
            let transistor = (5u64..400, prop_oneof![Just(0u64), 0u64..200])
                .prop_map(|(p, m)| (OutputKind::Transistor, p, m));
            let relay = (100u64..400, prop_oneof![Just(0u64), 50u64..200])
                .prop_map(|(p, m)| (OutputKind::Relay, p, m));
            (
                prop_oneof![3 => transistor, 1 => relay],
                prop::sample::select(Profile::ALL.to_vec()),
                prop::option::of(prop::sample::select(vec![
                    ApplyAt::NextPeriod,
                    ApplyAt::NextStep,
                    ApplyAt::Immediate,
                ])),
            )
                .prop_map(
                    |((output_kind, period_ms, min_on_ms), profile, apply_at)| {
                        let params = ChannelParams {
                            period_ms,
                            min_on_ms,
                            profile,
                            output_kind,
                            apply_at,
                            ..ChannelParams::default()
                        };
                        match params.validate() {
                            Ok(c) => c,
                            Err(e) => unreachable!("generated parameters are valid: {e}"),
                        }
                    },
                )
        }

        #[derive(Debug, Clone)]
        enum Op {
            Split(f64),
            Enable(usize, bool),
            Own(usize, f64),
        }

        fn arb_op() -> impl Strategy<Value = Op> {
            prop_oneof![
                4 => (-120.0..120.0f64).prop_map(Op::Split),
                2 => (0usize..2, any::<bool>()).prop_map(|(i, on)| Op::Enable(i, on)),
                1 => (0usize..2, 0.0..100.0f64).prop_map(|(i, d)| Op::Own(i, d)),
            ]
        }

        proptest! {
            /// 001's split range: whatever the commands, enables and each side's own duty
            /// topic do, the two lines of a pair are never high together, and no interlocked
            /// rise is lost for ever (the last level follows the last command).
            #[test]
            fn the_two_lines_of_a_pair_are_never_high_together(
                hot in arb_cfg(),
                cold in arb_cfg(),
                ops in prop::collection::vec(((0u64..600_000).prop_map(|us| us * 1000), arb_op()), 1..40),
            ) {
                let mut p = Pair::new(hot, cold);
                for (dt, op) in ops {
                    let t = p.now + dt;
                    p.run_to(t);
                    match op {
                        Op::Split(pct) => p.split(pct),
                        Op::Enable(i, on) => p.act(i, |c, now, emit| c.set_enable(now, on, emit)),
                        Op::Own(i, d) => p.act(i, |c, now, emit| c.command(now, Command::Percent(d), emit)),
                    }
                }
                let t = p.now + 3000 * MS;
                p.run_to(t);
                let mut high = [false; 2];
                for (t, c, h) in &p.log {
                    high[*c] = *h;
                    prop_assert!(!(high[0] && high[1]), "both high at {} ms", t);
                }
            }
        }
    }
}
