//! The channels' next deadlines, kept in order, so that a wake-up costs in proportion to the
//! channels it acts on, not to all of them.
//!
//! A channel's [`Channel::poll_at`] is read again only after something may have changed it: the
//! worker marks a channel whenever it acts on it (a poll, a request, a step of the interlock or
//! the planner, a write), and the marked ones are read before the order is next looked at. One
//! deadline can change with no action on its channel: a rise held back is named by `poll_at`
//! only while the board of the node's lines allows it, and the board changes with every other
//! line. A channel holding a rise is therefore not kept in the order but read at every look.
//!
//! Nothing here allocates after construction.

use crate::core::{Channel, Nanos};

/// A set of channel indices, walked in ascending order: one bit a channel.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Marks {
    words: Vec<u64>,
    /// Number of channels, the bits above it are never set.
    len: usize,
}

impl Marks {
    /// An empty set for `len` channels.
    pub(crate) fn new(len: usize) -> Marks {
        Marks {
            words: vec![0; len.div_ceil(64)],
            len,
        }
    }

    /// Adds channel `i` (ignored at or above the number of channels).
    pub(crate) fn set(&mut self, i: usize) {
        if i < self.len {
            self.words[i / 64] |= 1 << (i % 64);
        }
    }

    /// Removes channel `i`.
    pub(crate) fn unset(&mut self, i: usize) {
        if i < self.len {
            self.words[i / 64] &= !(1 << (i % 64));
        }
    }

    /// Whether channel `i` is in the set.
    #[cfg(test)]
    pub(crate) fn contains(&self, i: usize) -> bool {
        i < self.len && self.words[i / 64] & (1 << (i % 64)) != 0
    }

    /// Adds every channel.
    pub(crate) fn set_all(&mut self) {
        self.words.fill(!0);
        if !self.len.is_multiple_of(64) {
            if let Some(last) = self.words.last_mut() {
                *last = (1 << (self.len % 64)) - 1;
            }
        }
    }

    /// Empties the set.
    pub(crate) fn clear(&mut self) {
        self.words.fill(0);
    }

    /// Whether the set is empty.
    pub(crate) fn is_empty(&self) -> bool {
        self.words.iter().all(|w| *w == 0)
    }

    /// Adds every channel of `other` (a set for as many channels).
    pub(crate) fn add(&mut self, other: &Marks) {
        for (w, o) in self.words.iter_mut().zip(&other.words) {
            *w |= o;
        }
    }

    /// The lowest channel in the set at or above `from`.
    pub(crate) fn first_from(&self, from: usize) -> Option<usize> {
        let mut w = from / 64;
        let mut bits = *self.words.get(w)? & (!0 << (from % 64));
        loop {
            if bits != 0 {
                return Some(w * 64 + bits.trailing_zeros() as usize);
            }
            w += 1;
            bits = *self.words.get(w)?;
        }
    }
}

/// Not in the heap.
const OUT: usize = usize::MAX;

/// Channels with a deadline as a binary min-heap on (deadline, channel), each channel's place
/// in it kept, so that a changed deadline moves its channel in O(log n) and the heap never holds
/// more than one entry a channel.
#[derive(Debug, Clone)]
struct Order {
    heap: Vec<(Nanos, usize)>,
    place: Vec<usize>,
}

impl Order {
    fn new(len: usize) -> Order {
        Order {
            heap: Vec::with_capacity(len),
            place: vec![OUT; len],
        }
    }

    /// The earliest (deadline, channel).
    fn first(&self) -> Option<(Nanos, usize)> {
        self.heap.first().copied()
    }

    /// Puts channel `i` at deadline `at` (`None`: out of the order).
    fn put(&mut self, i: usize, at: Option<Nanos>) {
        let Some(&p) = self.place.get(i) else {
            return;
        };
        match (p, at) {
            (OUT, None) => {}
            (OUT, Some(t)) => {
                self.heap.push((t, i));
                self.place[i] = self.heap.len() - 1;
                self.up(self.heap.len() - 1);
            }
            (p, None) => self.remove_at(p),
            (p, Some(t)) => {
                if self.heap[p].0 != t {
                    self.heap[p].0 = t;
                    let p = self.up(p);
                    self.down(p);
                }
            }
        }
    }

    fn remove_at(&mut self, p: usize) {
        let last = self.heap.len() - 1;
        self.swap(p, last);
        let (_, i) = self.heap.pop().expect("p is in the heap");
        self.place[i] = OUT;
        if p < self.heap.len() {
            let p = self.up(p);
            self.down(p);
        }
    }

    fn swap(&mut self, a: usize, b: usize) {
        self.heap.swap(a, b);
        self.place[self.heap[a].1] = a;
        self.place[self.heap[b].1] = b;
    }

    /// Moves the entry at `p` up to its place; returns where it ended.
    fn up(&mut self, mut p: usize) -> usize {
        while p > 0 {
            let parent = (p - 1) / 2;
            if self.heap[parent] <= self.heap[p] {
                break;
            }
            self.swap(p, parent);
            p = parent;
        }
        p
    }

    /// Moves the entry at `p` down to its place.
    fn down(&mut self, mut p: usize) {
        loop {
            let (l, r) = (2 * p + 1, 2 * p + 2);
            let mut least = p;
            if l < self.heap.len() && self.heap[l] < self.heap[least] {
                least = l;
            }
            if r < self.heap.len() && self.heap[r] < self.heap[least] {
                least = r;
            }
            if least == p {
                return;
            }
            self.swap(p, least);
            p = least;
        }
    }
}

/// Every channel's next deadline: the channels kept in order, the ones to read again, and the
/// ones holding a rise (read at every look).
#[derive(Debug, Clone)]
pub(crate) struct Deadlines {
    order: Order,
    /// Acted on since their deadline was last read.
    stale: Marks,
    /// Holding a rise back at their last read: not in `order`, read at every look.
    held: Marks,
}

impl Deadlines {
    /// The deadlines of `channels` as they are now.
    pub(crate) fn new(channels: &[Channel]) -> Deadlines {
        let n = channels.len();
        let mut d = Deadlines {
            order: Order::new(n),
            stale: Marks::new(n),
            held: Marks::new(n),
        };
        d.stale.set_all();
        d.refresh(channels);
        d
    }

    /// Channel `i` was, or may have been, acted on: its deadline is read again.
    pub(crate) fn mark(&mut self, i: usize) {
        self.stale.set(i);
    }

    /// Every channel may have been acted on.
    pub(crate) fn mark_all(&mut self) {
        self.stale.set_all();
    }

    /// The channels marked since the last [`Deadlines::refresh`].
    pub(crate) fn stale(&self) -> &Marks {
        &self.stale
    }

    /// Reads the deadline of every channel marked since the last call.
    pub(crate) fn refresh(&mut self, channels: &[Channel]) {
        let mut from = 0;
        while let Some(i) = self.stale.first_from(from) {
            from = i + 1;
            let Some(ch) = channels.get(i) else { break };
            if ch.holds_rise() {
                self.held.set(i);
                self.order.put(i, None);
            } else {
                self.held.unset(i);
                self.order.put(i, ch.poll_at());
            }
        }
        self.stale.clear();
    }

    /// The earliest deadline of any of `channels` (the ones these deadlines were read from), ns.
    /// Every channel acted on must have been read again since ([`Deadlines::refresh`]).
    pub(crate) fn first(&self, channels: &[Channel]) -> Option<Nanos> {
        debug_assert!(
            self.stale.is_empty(),
            "a channel acted on was not read again"
        );
        let mut first = self.order.first().map(|(t, _)| t);
        let mut from = 0;
        while let Some(i) = self.held.first_from(from) {
            from = i + 1;
            if let Some(t) = channels.get(i).and_then(Channel::poll_at) {
                first = Some(first.map_or(t, |f| f.min(t)));
            }
        }
        first
    }

    /// Adds to `due` every channel whose deadline may have come at `now`: those in order up to
    /// `now` (taken out of it and marked, as acting on them changes their deadline), those
    /// holding a rise and those marked since the last read.
    pub(crate) fn take_due(&mut self, now: Nanos, due: &mut Marks) {
        while let Some((t, i)) = self.order.first() {
            if t > now {
                break;
            }
            self.order.put(i, None);
            self.stale.set(i);
        }
        due.add(&self.stale);
        due.add(&self.held);
    }

    /// Adds to `set` every channel that may hold a rise back: those holding one at their last
    /// read and those acted on since.
    pub(crate) fn add_may_hold_rise(&self, set: &mut Marks) {
        set.add(&self.held);
        set.add(&self.stale);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn marks_walk_in_order_across_words() {
        let mut m = Marks::new(130);
        for i in [129, 0, 64, 63, 5, 200] {
            m.set(i);
        }
        let mut seen = Vec::new();
        let mut from = 0;
        while let Some(i) = m.first_from(from) {
            seen.push(i);
            from = i + 1;
        }
        assert_eq!(seen, [0, 5, 63, 64, 129], "200 is beyond the channels");
        m.unset(64);
        assert_eq!(m.first_from(64), Some(129));
        assert_eq!(m.first_from(130), None);
        assert_eq!(m.first_from(1000), None);
        m.clear();
        assert!(m.is_empty());
        m.set_all();
        assert!((0..130).all(|i| m.contains(i)));
        assert!(!m.contains(130));
        assert_eq!(m.first_from(129), Some(129));
        let mut whole = Marks::new(128);
        whole.set_all();
        assert_eq!(whole.first_from(127), Some(127));
    }

    #[test]
    fn a_rise_the_board_holds_back_is_read_at_every_look() {
        use crate::core::{ChannelParams, Command, Level, LineBoard};
        let cfg = ChannelParams {
            period_ms: 100,
            ..ChannelParams::default()
        }
        .validate()
        .unwrap();
        let board = LineBoard::new(2);
        board.pair(0, 1);
        let mut ch = vec![Channel::new(cfg, 0), Channel::new(cfg, 0)];
        for (i, c) in ch.iter_mut().enumerate() {
            c.seat_on(&board, i);
        }
        // Line 1 high, as another wake-up's write left it.
        board.set(1, Level::High);
        ch[0].command(0, Command::Percent(50.0), &mut |_| {});
        ch[0].set_enable(0, true, &mut |_| {});
        assert!(ch[0].holds_rise(), "line 1 is high: line 0 may not rise");
        let d = Deadlines::new(&ch);
        let refused = d.first(&ch);
        assert_eq!(refused, ch[0].poll_at());
        // The other line goes low: nothing acts on channel 0, yet its rise is due now.
        board.set(1, Level::Low);
        let allowed = d.first(&ch);
        assert_eq!(allowed, ch[0].poll_at());
        assert!(allowed < refused, "{allowed:?} vs {refused:?}");
    }

    proptest! {
        /// Whatever sequence of deadlines the channels are given, the order's first entry is the
        /// earliest (deadline, channel), and every channel is in it exactly when it has one.
        #[test]
        fn the_order_always_starts_at_the_earliest_deadline(
            n in 1usize..70,
            puts in proptest::collection::vec((0usize..70, proptest::option::of(0u64..50)), 0..300),
        ) {
            let mut order = Order::new(n);
            let mut model: Vec<Option<Nanos>> = vec![None; n];
            for (i, at) in puts {
                let i = i % n;
                order.put(i, at);
                model[i] = at;
                let expect = (0..n).filter_map(|k| model[k].map(|t| (t, k))).min();
                prop_assert_eq!(order.first(), expect);
                prop_assert_eq!(order.heap.len(), model.iter().flatten().count());
                for (p, &(t, k)) in order.heap.iter().enumerate() {
                    prop_assert_eq!(order.place[k], p);
                    prop_assert_eq!(model[k], Some(t));
                }
            }
        }
    }
}
