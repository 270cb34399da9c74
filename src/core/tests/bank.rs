//! The node-level planner in virtual time: several channels driven the way the output thread
//! drives them (in channel order, [`Bank::before`] and [`Bank::after`] around each action),
//! every deadline processed exactly when due.

use super::harness::{high_spans, MS};
use crate::core::{
    Bank, Channel, ChannelParams, Command, Event, Level, Nanos, Phase, ShortPulse, NS_PER_MS,
};
use proptest::prelude::*;

/// Channels under one planner, with every edge and skip recorded per channel.
struct Rack {
    channels: Vec<Channel>,
    bank: Bank,
    now: Nanos,
    edges: Vec<Vec<(Nanos, Level)>>,
    skips: Vec<Vec<Nanos>>,
}

impl Rack {
    fn new(params: &[ChannelParams], bank: Bank) -> Rack {
        let n = params.len();
        let mut r = Rack {
            channels: params
                .iter()
                .map(|p| Channel::new(p.validate().expect("valid test parameters"), 0))
                .collect(),
            bank,
            now: 0,
            edges: vec![Vec::new(); n],
            skips: vec![Vec::new(); n],
        };
        for i in 0..n {
            r.bank.before(&mut r.channels, i, 0);
        }
        r
    }

    fn record(edges: &mut [Vec<(Nanos, Level)>], skips: &mut [Vec<Nanos>], i: usize, e: Event) {
        match e {
            Event::Edge { at, level } => edges[i].push((at, level)),
            Event::Skipped { at } => skips[i].push(at),
            _ => {}
        }
    }

    /// One action on channel `i` at the current instant, as the output thread does it.
    /// After an input, the planner always looks for waiting pulses; after a poll only if the
    /// channel gave a slot up, as the output thread does.
    fn act(&mut self, i: usize, f: impl FnOnce(&mut Channel, Nanos, &mut dyn FnMut(Event))) {
        self.act_as(i, true, f);
    }

    fn act_as(
        &mut self,
        i: usize,
        input: bool,
        f: impl FnOnce(&mut Channel, Nanos, &mut dyn FnMut(Event)),
    ) {
        let now = self.now;
        let held = self.channels[i].occupies();
        self.bank.before(&mut self.channels, i, now);
        let (edges, skips) = (&mut self.edges, &mut self.skips);
        f(&mut self.channels[i], now, &mut |e| {
            Rack::record(edges, skips, i, e)
        });
        if input || (held && !self.channels[i].occupies()) {
            self.bank.after(&mut self.channels, now, &mut |c, e| {
                Rack::record(edges, skips, c, e)
            });
        }
    }

    /// Sets the planner at the current instant, as the output thread does on a parameter
    /// change: every channel's place, a lowered limit at once, waiting pulses let start.
    fn set_bank(&mut self, bank: Bank) -> &mut Self {
        let now = self.now;
        self.bank = bank;
        for i in 0..self.channels.len() {
            self.bank.before(&mut self.channels, i, now);
        }
        let (edges, skips) = (&mut self.edges, &mut self.skips);
        self.bank.shed(&mut self.channels, now, &mut |c, e| {
            Rack::record(edges, skips, c, e)
        });
        self.bank.after(&mut self.channels, now, &mut |c, e| {
            Rack::record(edges, skips, c, e)
        });
        self
    }

    /// Runs every deadline up to and including `t`, each at its instant, channels in order.
    fn run_to(&mut self, t: Nanos) -> &mut Self {
        while let Some(d) = self.channels.iter().filter_map(Channel::poll_at).min() {
            if d > t {
                break;
            }
            self.now = d;
            for i in 0..self.channels.len() {
                if self.channels[i].poll_at().is_some_and(|p| p <= d) {
                    self.act_as(i, false, |ch, now, emit| ch.poll(now, emit));
                }
            }
        }
        self.now = t;
        self
    }

    fn at(&mut self, ms: u64) -> &mut Self {
        self.run_to(ms * MS)
    }

    fn enable(&mut self, i: usize, on: bool) -> &mut Self {
        self.act(i, |ch, now, emit| ch.set_enable(now, on, emit));
        self
    }

    fn duty(&mut self, i: usize, pct: f64) -> &mut Self {
        self.act(i, |ch, now, emit| {
            ch.command(now, Command::Percent(pct), emit)
        });
        self
    }

    /// Channel `i`'s high spans as (rise, fall) in ms, up to now.
    fn spans_ms(&self, i: usize) -> Vec<(f64, f64)> {
        high_spans(&self.edges[i], self.now)
            .into_iter()
            .map(|(a, b)| (a as f64 / MS as f64, b as f64 / MS as f64))
            .collect()
    }

    /// How many lines were high at once, at most, up to now.
    fn most_high(&self) -> usize {
        let mut changes: Vec<(Nanos, i32)> = Vec::new();
        for e in &self.edges {
            for (a, b) in high_spans(e, self.now) {
                changes.push((a, 1));
                changes.push((b, -1));
            }
        }
        // Falls before rises at the same instant: a line handing over to another is not two.
        changes.sort_by_key(|&(t, d)| (t, d));
        let (mut high, mut most) = (0i32, 0i32);
        for (_, d) in changes {
            high += d;
            most = most.max(high);
        }
        most as usize
    }
}

fn period(ms: u64) -> ChannelParams {
    ChannelParams {
        period_ms: ms,
        ..ChannelParams::default()
    }
}

const STAGGER: Bank = Bank {
    phase: Phase::Stagger,
    max_on: 0,
};

#[test]
fn sync_starts_every_channel_at_its_enable_together() {
    let mut r = Rack::new(&[period(1000), period(1000)], Bank::default());
    r.duty(0, 30.0)
        .duty(1, 40.0)
        .enable(0, true)
        .enable(1, true);
    r.at(2000);
    assert_eq!(r.spans_ms(0), [(0.0, 300.0), (1000.0, 1300.0)]);
    assert_eq!(r.spans_ms(1), [(0.0, 400.0), (1000.0, 1400.0)]);
    assert_eq!(r.most_high(), 2);
}

#[test]
fn stagger_lays_the_on_phases_end_to_end_on_a_shared_grid() {
    let mut r = Rack::new(&[period(1000), period(1000), period(1000)], STAGGER);
    r.duty(0, 20.0).duty(1, 30.0).duty(2, 40.0);
    // Enabled at different instants, they all start on the grid of whole periods.
    r.at(250)
        .enable(0, true)
        .at(600)
        .enable(1, true)
        .enable(2, true);
    r.at(3000);
    assert_eq!(r.spans_ms(0), [(1000.0, 1200.0), (2000.0, 2200.0)]);
    assert_eq!(r.spans_ms(1), [(1200.0, 1500.0), (2200.0, 2500.0)]);
    assert_eq!(r.spans_ms(2), [(1500.0, 1900.0), (2500.0, 2900.0)]);
    assert_eq!(r.most_high(), 1);
    let s = r.channels[1].status(r.now);
    assert!(s.protections.stagger, "reported: {:?}", s.protections);
}

#[test]
fn stagger_follows_duty_changes_period_by_period() {
    let mut r = Rack::new(&[period(1000), period(1000)], STAGGER);
    r.duty(0, 50.0)
        .duty(1, 50.0)
        .enable(0, true)
        .enable(1, true);
    // 000: a command takes effect at the next period start; the second channel moves with the
    // first one's new on time.
    r.at(1500).duty(0, 10.0).at(2000).duty(0, 0.0).at(3500);
    assert_eq!(
        r.spans_ms(0),
        [(0.0, 500.0), (1000.0, 1500.0), (2000.0, 2100.0)]
    );
    assert_eq!(
        r.spans_ms(1),
        [
            (500.0, 1000.0),
            (1500.0, 2000.0),
            (2100.0, 2600.0),
            (3000.0, 3500.0)
        ]
    );
    assert_eq!(r.most_high(), 1);
}

#[test]
fn stagger_groups_channels_by_period() {
    let mut r = Rack::new(&[period(1000), period(500), period(1000)], STAGGER);
    r.duty(0, 40.0).duty(1, 40.0).duty(2, 40.0);
    r.enable(0, true).enable(1, true).enable(2, true).at(1000);
    // pw02 runs alone on its 500 ms grid; pw03 follows pw01.
    assert_eq!(r.spans_ms(1), [(0.0, 200.0), (500.0, 700.0)]);
    assert_eq!(r.spans_ms(2), [(400.0, 800.0)]);
}

#[test]
fn with_duties_above_100_percent_a_pulse_that_cannot_fit_is_skipped_with_e1() {
    // 70 % + 60 %: pw02 is placed to end with the period (400..1000) but pw01 is on until 700;
    // its line would overlap, so it waits, cannot fit, and is skipped, E1 saying so.
    let mut r = Rack::new(&[period(1000), period(1000)], STAGGER);
    r.duty(0, 70.0)
        .duty(1, 60.0)
        .enable(0, true)
        .enable(1, true);
    r.at(2000);
    assert_eq!(r.spans_ms(0), [(0.0, 700.0), (1000.0, 1700.0)]);
    assert!(r.spans_ms(1).is_empty(), "{:?}", r.spans_ms(1));
    assert_eq!(r.skips[1], [400 * MS, 1400 * MS]);
    assert!(r.channels[1].status(r.now).e1);
    // 70 % + 30 % fits exactly, with no wait and no E1.
    let mut r = Rack::new(&[period(1000), period(1000)], STAGGER);
    r.duty(0, 70.0)
        .duty(1, 30.0)
        .enable(0, true)
        .enable(1, true);
    r.at(2000);
    assert_eq!(r.spans_ms(1), [(700.0, 1000.0), (1700.0, 2000.0)]);
    let s = r.channels[1].status(r.now);
    assert!(!s.e1 && !s.protections.delayed, "{:?}", s.protections);
}

#[test]
fn an_extended_period_spans_whole_periods_of_the_grid_and_keeps_its_duty() {
    // 7 % of 200 ms is 14 ms, below the 30 ms minimum: extend wants 428.6 ms; on the stagger
    // grid it takes three whole periods, 600 ms, with 7 % of it on (42 ms).
    let ext = ChannelParams {
        period_ms: 200,
        min_on_ms: 30,
        short_pulse: Some(ShortPulse::Extend),
        ..ChannelParams::default()
    };
    let mut r = Rack::new(&[period(200), ext], STAGGER);
    r.duty(0, 20.0)
        .duty(1, 7.0)
        .enable(0, true)
        .enable(1, true)
        .at(1800);
    assert_eq!(r.spans_ms(0).len(), 9);
    assert_eq!(
        r.spans_ms(1),
        [(40.0, 82.0), (640.0, 682.0), (1240.0, 1282.0)],
        "after pw01's 40 ms, every third period of the grid"
    );
    assert_eq!(r.most_high(), 1);
}

fn limit(max_on: usize) -> Bank {
    Bank {
        phase: Phase::Sync,
        max_on,
    }
}

#[test]
fn a_pulse_without_a_slot_waits_and_keeps_its_length_and_its_period() {
    let mut r = Rack::new(&[period(1000), period(1000)], limit(1));
    r.duty(0, 40.0)
        .duty(1, 40.0)
        .enable(0, true)
        .enable(1, true)
        .at(3000);
    assert_eq!(
        r.spans_ms(0),
        [(0.0, 400.0), (1000.0, 1400.0), (2000.0, 2400.0)]
    );
    assert_eq!(
        r.spans_ms(1),
        [(400.0, 800.0), (1400.0, 1800.0), (2400.0, 2800.0)],
        "delayed by the other's pulse, each period still 1000 ms with 400 ms on"
    );
    assert_eq!(r.most_high(), 1);
    assert!(r.skips.iter().all(Vec::is_empty));
    let s = r.channels[1].status(r.now);
    assert!(s.protections.delayed, "{:?}", s.protections);
    assert_eq!(s.skipped_pulses, 0);
    assert!(!s.e1, "the duty is delivered");
}

#[test]
fn a_pulse_that_cannot_fit_its_period_is_skipped_and_reported() {
    let mut r = Rack::new(&[period(1000), period(1000)], limit(1));
    r.duty(0, 60.0)
        .duty(1, 60.0)
        .enable(0, true)
        .enable(1, true)
        .at(2000);
    assert_eq!(r.spans_ms(0), [(0.0, 600.0), (1000.0, 1600.0)]);
    assert!(r.spans_ms(1).is_empty(), "{:?}", r.spans_ms(1));
    // The latest start that fits 600 ms in the period [0, 1000) is 400 ms.
    assert_eq!(r.skips[1], [400 * MS, 1400 * MS]);
    let s = r.channels[1].status(r.now);
    assert_eq!(s.skipped_pulses, 2);
    assert!(s.e1 && s.protections.delayed, "not delivered: E1");
}

#[test]
fn the_slot_goes_to_the_pulse_that_waited_longest() {
    let mut r = Rack::new(&[period(1000), period(1000), period(1000)], limit(1));
    r.duty(0, 30.0).duty(1, 30.0).duty(2, 30.0);
    r.enable(0, true)
        .at(100)
        .enable(2, true)
        .at(200)
        .enable(1, true)
        .at(1000);
    assert_eq!(r.spans_ms(0), [(0.0, 300.0)]);
    assert_eq!(r.spans_ms(2), [(300.0, 600.0)], "waited since 100 ms");
    assert_eq!(r.spans_ms(1), [(600.0, 900.0)], "waited since 200 ms");
}

#[test]
fn the_minimum_break_still_holds_after_a_delayed_pulse() {
    // min off 300 ms: pw02's delayed pulse ends at 900, its next rise waits until 1200 even
    // though its period starts at 1000 and a slot is free.
    let p = ChannelParams {
        period_ms: 1000,
        min_on_ms: 100,
        min_off_ms: Some(300),
        short_pulse: Some(ShortPulse::Suppress),
        ..ChannelParams::default()
    };
    let mut r = Rack::new(&[p, p], limit(1));
    r.duty(0, 50.0)
        .duty(1, 40.0)
        .enable(0, true)
        .enable(1, true)
        .at(900);
    r.duty(0, 0.0).at(2000);
    assert_eq!(r.spans_ms(1)[..2], [(500.0, 900.0), (1200.0, 1400.0)]);
}

proptest! {
    /// Under stagger, with the duties summing to at most 100 % at every instant, no two on
    /// phases of channels of equal period overlap, whatever the enables and commands do.
    #[test]
    fn no_overlap_under_stagger_when_the_duties_sum_to_at_most_100(
        n in 2usize..6,
        period_ms in prop::sample::select(vec![200u64, 1000, 1500]),
        steps in prop::collection::vec(
            (0u64..3000, prop::collection::vec(0u32..=100, 6), prop::collection::vec(any::<bool>(), 6)),
            1..12,
        ),
    ) {
        let mut r = Rack::new(&vec![period(period_ms); n], STAGGER);
        let mut t = 0;
        for (dt, weights, enables) in &steps {
            // Duties in whole ms of the period, scaled to sum to at most 100 %.
            let total: u32 = weights[..n].iter().sum::<u32>().max(100);
            for i in 0..n {
                let on_ms = u64::from(weights[i]) * period_ms / u64::from(total);
                r.duty(i, on_ms as f64 * 100.0 / period_ms as f64);
                r.enable(i, enables[i]);
            }
            t += dt * NS_PER_MS / 10;
            r.run_to(t);
        }
        r.run_to(t + 3 * period_ms * MS);
        prop_assert!(r.most_high() <= 1, "{:?}", (0..n).map(|i| r.spans_ms(i)).collect::<Vec<_>>());
    }

    /// Under stagger no two lines of a group are ever on together, whatever the duties (above
    /// 100 % in sum too), apply_at, minima, enables and commands do: a pulse waits or is
    /// skipped instead.
    #[test]
    fn no_two_lines_of_a_stagger_group_are_ever_on_together(
        chans in prop::collection::vec(
            (
                0u32..=100,
                0u64..120,
                prop::sample::select(vec![ApplyAt::NextPeriod, ApplyAt::NextStep, ApplyAt::Immediate]),
                prop::sample::select(vec![ShortPulse::Stretch, ShortPulse::Suppress, ShortPulse::Extend]),
            ),
            2..6,
        ),
        ops in prop::collection::vec((0u64..1500, 0usize..6, 0u32..=100, any::<bool>()), 0..30),
    ) {
        let params: Vec<ChannelParams> = chans
            .iter()
            .map(|&(_, min_on_ms, apply_at, policy)| ChannelParams {
                period_ms: 500,
                min_on_ms,
                apply_at: Some(apply_at),
                short_pulse: Some(policy),
                ..ChannelParams::default()
            })
            .collect();
        let mut r = Rack::new(&params, STAGGER);
        for (i, &(pct, ..)) in chans.iter().enumerate() {
            r.duty(i, f64::from(pct)).enable(i, true);
        }
        let mut t = 0;
        for &(dt, i, pct, on) in &ops {
            t += dt * MS;
            r.run_to(t);
            let i = i % chans.len();
            r.duty(i, f64::from(pct)).enable(i, on);
        }
        r.run_to(t + 3000 * MS);
        prop_assert!(r.most_high() <= 1, "{:?}", overlaps(&r));
    }

    /// Never more than `max_simultaneous_on` lines high, whatever the periods, minima, duties,
    /// enables and phase.
    #[test]
    fn never_more_lines_high_than_max_simultaneous_on(
        max_on in 1usize..4,
        stagger in any::<bool>(),
        chans in prop::collection::vec((prop::sample::select(vec![100u64, 250, 1000]), 0u64..80, 0u32..=100, prop::sample::select(vec![ShortPulse::Stretch, ShortPulse::Suppress, ShortPulse::Extend])), 2..7),
        ops in prop::collection::vec((0u64..2000, 0usize..7, 0u32..=100, any::<bool>()), 0..30),
    ) {
        let params: Vec<ChannelParams> = chans
            .iter()
            .map(|&(period_ms, min_on_ms, _, policy)| ChannelParams {
                period_ms,
                min_on_ms,
                short_pulse: Some(policy),
                ..ChannelParams::default()
            })
            .collect();
        let phase = if stagger { Phase::Stagger } else { Phase::Sync };
        let mut r = Rack::new(&params, Bank { phase, max_on });
        for (i, &(_, _, pct, _)) in chans.iter().enumerate() {
            r.duty(i, f64::from(pct)).enable(i, true);
        }
        let mut t = 0;
        for &(dt, i, pct, on) in &ops {
            t += dt * MS;
            r.run_to(t);
            let i = i % chans.len();
            r.duty(i, f64::from(pct)).enable(i, on);
        }
        r.run_to(t + 3000 * MS);
        prop_assert!(r.most_high() <= max_on);
    }
}

// ---- Review: scenarios that break the planner's promises ----

use crate::core::ApplyAt;

/// Every pair of overlapping high spans (channel a, channel b, from ms, to ms) up to now.
fn overlaps(r: &Rack) -> Vec<(usize, usize, f64, f64)> {
    let n = r.channels.len();
    let mut out = Vec::new();
    for a in 0..n {
        for b in a + 1..n {
            for &(a0, a1) in &r.spans_ms(a) {
                for &(b0, b1) in &r.spans_ms(b) {
                    let (s, e) = (a0.max(b0), a1.min(b1));
                    if s < e {
                        out.push((a, b, s, e));
                    }
                }
            }
        }
    }
    out
}

/// Under `next_step`: pw01, pw02, pw03 at 20 % each share the stagger grid (pw01 on
/// 0..200, pw02 placed at 200, pw03 placed at 400). At 100 ms pw02's command goes to 50 %
/// (the duties now sum to 90 %). pw03 was placed behind pw02's old on time (400 ms), but
/// pw02's on phase keeps the length it was placed with (the new command takes effect with
/// the next period), so no two on phases of the group overlap.
#[test]
fn a_next_step_command_during_the_lead_keeps_the_placed_length() {
    let p = ChannelParams {
        apply_at: Some(ApplyAt::NextStep),
        ..period(1000)
    };
    let mut r = Rack::new(&[p, p, p], STAGGER);
    r.duty(0, 20.0).duty(1, 20.0).duty(2, 20.0);
    r.enable(0, true).enable(1, true).enable(2, true);
    r.at(100).duty(1, 50.0).at(1000);
    assert!(overlaps(&r).is_empty(), "overlaps: {:?}", overlaps(&r));
}

/// Under `immediate`: pw01 (tcont-like immediate) 20 %, pw02 40 % on the stagger grid:
/// pw01 on 0..200, pw02 on 200..600. At 100 ms pw01's command goes to 50 % (sum 90 %): its
/// running on step is re-timed to 500 ms (003), and pw02, placed at 200 ms, waits for it.
#[test]
fn an_immediate_command_lengthening_a_pulse_makes_the_next_of_the_group_wait() {
    let p = ChannelParams {
        apply_at: Some(ApplyAt::Immediate),
        ..period(1000)
    };
    let mut r = Rack::new(&[p, p], STAGGER);
    r.duty(0, 20.0).duty(1, 40.0);
    r.enable(0, true).enable(1, true);
    r.at(100).duty(0, 50.0).at(1000);
    assert!(overlaps(&r).is_empty(), "overlaps: {:?}", overlaps(&r));
}

/// `extend` at a high duty: pw01 93 % of 200 ms with min off 30 ms (the 14 ms
/// break is too short: extend grows the period, on the grid to 600 ms, 558 ms on); pw02 5 %
/// (10 ms). Duties sum to 98 %, yet pw01's on phase spans three grid periods: pw02 waits
/// for it (and is skipped, E1, where it cannot fit) instead of overlapping it.
#[test]
fn an_extended_phase_across_grid_periods_makes_the_group_wait() {
    let ext = ChannelParams {
        period_ms: 200,
        min_off_ms: Some(30),
        short_pulse: Some(ShortPulse::Extend),
        ..ChannelParams::default()
    };
    let mut r = Rack::new(&[ext, period(200)], STAGGER);
    r.duty(0, 93.0)
        .duty(1, 5.0)
        .enable(0, true)
        .enable(1, true)
        .at(1200);
    assert!(
        overlaps(&r).is_empty(),
        "spans {:?} {:?}",
        r.spans_ms(0),
        r.spans_ms(1)
    );
}

/// The line guard: pw01 50 %, pw02 20 % (min on 200 ms, min off 500 ms), pw03 20 %
/// (no minima), period 1000 ms, stagger. Period 1: pw01 1000..1500, pw02 1500..1700, pw03
/// 1700..1900. pw01 drops to 10 % from period 2: after it pw02 could start at 2100, but its
/// break since 1700 must last 500 ms, so it is placed at 2200 (on until 2400), and pw03 after
/// it: the line is where the layout says.
#[test]
fn a_rise_held_for_the_minimum_break_is_placed_where_the_line_will_be() {
    let guarded = ChannelParams {
        min_on_ms: 200,
        min_off_ms: Some(500),
        ..period(1000)
    };
    let mut r = Rack::new(&[period(1000), guarded, period(1000)], STAGGER);
    r.duty(0, 50.0).duty(1, 20.0).duty(2, 20.0);
    r.enable(0, true).enable(1, true).enable(2, true);
    r.at(1500).duty(0, 10.0).at(3000);
    assert!(overlaps(&r).is_empty(), "overlaps: {:?}", overlaps(&r));
}

/// A slot limit of 2 and a channel of another period: pw01 (period 200, 50 %) and
/// pw02 (period 2000, 10 %) hold both slots at 0, so pw03 (period 1000, 30 %, placed at 0)
/// waits until pw01 falls at 100 and runs 100..400. pw04 (period 1000, 30 %) was placed at
/// pw03's planned end, 300; a slot is free then, but pw03 of its group is still on: pw04
/// waits for it.
#[test]
fn a_phase_delayed_for_a_slot_holds_back_the_next_of_its_group() {
    let mut r = Rack::new(
        &[period(200), period(2000), period(1000), period(1000)],
        Bank {
            phase: Phase::Stagger,
            max_on: 2,
        },
    );
    r.duty(0, 50.0).duty(1, 10.0).duty(2, 30.0).duty(3, 30.0);
    for i in 0..4 {
        r.enable(i, true);
    }
    r.at(1000);
    let same_period: Vec<_> = overlaps(&r)
        .into_iter()
        .filter(|o| o.0 == 2 && o.1 == 3)
        .collect();
    assert!(
        same_period.is_empty(),
        "pw03 {:?} pw04 {:?}",
        r.spans_ms(2),
        r.spans_ms(3)
    );
}

/// `max_simultaneous_on` is lowered at runtime: three lines at 60 % are high
/// together under no limit; at 100 ms the limit becomes 1 (a parameter change, which the
/// worker applies with `set_bank`): the two latest-started pulses give their slots up at
/// once (their minimum on time has passed), with E1.
#[test]
fn lowering_max_simultaneous_on_takes_the_latest_slots_back_at_once() {
    let mut r = Rack::new(&[period(1000), period(1000), period(1000)], limit(0));
    r.duty(0, 60.0).duty(1, 60.0).duty(2, 60.0);
    r.enable(0, true).enable(1, true).enable(2, true);
    r.at(100);
    r.set_bank(limit(1));
    let from = r.edges.iter().map(Vec::len).collect::<Vec<_>>();
    r.at(2000);
    let high_after = (0..3)
        .filter(|&i| {
            r.edges[i][..from[i]]
                .last()
                .is_some_and(|e| e.1 == Level::High)
        })
        .filter(|&i| {
            r.edges[i][from[i]..]
                .first()
                .is_some_and(|e| e.0 > 100 * MS)
        })
        .count();
    assert!(
        high_after <= 1,
        "{high_after} lines stay high after the limit became 1"
    );
}

/// A waiting pulse whose length grows: pw01 60 % holds the slot (0..600); pw02 (immediate)
/// 30 % waits, latest start 700. At 100 ms pw02's command goes to 60 % (003): the wait is
/// re-timed for 600 ms, latest start 400, so when pw01 falls at 600 the pulse no longer fits
/// its period and was skipped; no pulse runs past its period's end.
#[test]
fn a_waiting_pulse_that_grows_is_retimed_and_stays_in_its_period() {
    let imm = ChannelParams {
        apply_at: Some(ApplyAt::Immediate),
        ..period(1000)
    };
    let mut r = Rack::new(&[period(1000), imm], limit(1));
    r.duty(0, 60.0)
        .duty(1, 30.0)
        .enable(0, true)
        .enable(1, true);
    r.at(100).duty(1, 60.0).at(2000);
    assert!(
        r.spans_ms(1)
            .iter()
            .all(|&(a, b)| (a / 1000.0).floor() == ((b - 1e-9) / 1000.0).floor()),
        "pw02 {:?}, pw01 {:?}, skips {:?}",
        r.spans_ms(1),
        r.spans_ms(0),
        r.skips
    );
}

/// A late wake-up, as the worker handles it: one poll at 750 ms of every channel due, in
/// channel order, the slot freed by a deadline handed over at that deadline's instant.
/// pw01 70 % holds the slot (0..700); pw02 40 % waits, latest start 600. Woken at 750, the
/// worker polls pw01 first: its fall at 700 frees the slot, and `after(700)` may not grant it to
/// pw02, whose wait ended at 600 but was not processed yet: it is skipped at 600 instead of
/// starting at 700 and running past its period's end.
#[test]
fn a_late_wake_up_skips_a_wait_that_expired_before_the_slot_freed() {
    let mut r = Rack::new(&[period(1000), period(1000)], limit(1));
    r.duty(0, 70.0)
        .duty(1, 40.0)
        .enable(0, true)
        .enable(1, true);
    r.at(500);
    // One late wake-up at 750 ms, the worker's way.
    let now = 750 * MS;
    r.now = now;
    for i in 0..2 {
        if let Some(due) = r.channels[i].poll_at().filter(|d| *d <= now) {
            r.bank.before(&mut r.channels, i, now);
            let (edges, skips) = (&mut r.edges, &mut r.skips);
            r.channels[i].poll(now, &mut |e| Rack::record(edges, skips, i, e));
            r.bank.after(&mut r.channels, due, &mut |c, e| {
                Rack::record(edges, skips, c, e)
            });
        }
    }
    r.at(2000);
    assert_eq!(
        r.skips[1].first(),
        Some(&(600 * MS)),
        "pw02 {:?}, pw01 {:?}, skips {:?}",
        r.spans_ms(1),
        r.spans_ms(0),
        r.skips
    );
}

/// The time base under the planner: staggered or limited to one line on, every
/// edge lies on the tick grid, every pulse is whole ticks, and the lines still never overlap.
#[test]
fn the_planner_keeps_every_edge_on_the_tick_grid() {
    // 60 Hz half cycles: 8 333 300 ns; 1000 ms is 120 ticks (999.996 ms).
    let ticked = |ms: u64| ChannelParams {
        time_base_ms: 8.3333,
        ..period(ms)
    };
    let tick = 8_333_300;
    for bank in [STAGGER, limit(1)] {
        let mut r = Rack::new(&[ticked(1000), ticked(1000), ticked(1000)], bank);
        r.duty(0, 23.0).duty(1, 31.0).duty(2, 17.0);
        r.at(250)
            .enable(0, true)
            .at(603)
            .enable(1, true)
            .enable(2, true);
        r.at(1777).duty(1, 12.5).at(8000);
        for (i, edges) in r.edges.iter().enumerate() {
            assert!(!edges.is_empty());
            assert!(
                edges.iter().all(|(t, _)| t % tick == 0),
                "{bank:?} channel {i}: {edges:?}"
            );
        }
        assert_eq!(r.most_high(), 1, "{bank:?}");
        // 23 % of 120 ticks is 27.6: 28, 27, 28, 28, 27, ... (the last pulse still runs).
        let on: Vec<Nanos> = high_spans(&r.edges[0], 8000 * MS - 1)
            .iter()
            .map(|(a, b)| b - a)
            .collect();
        assert!(
            on[..on.len() - 1]
                .iter()
                .all(|t| *t == 27 * tick || *t == 28 * tick),
            "{bank:?}: {on:?}"
        );
    }
}
