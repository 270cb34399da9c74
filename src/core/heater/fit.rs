//! The heater's model fitted to a run's record: the readings and the line's real on time,
//! kept in bins of one width, and the model whose sensor follows them best.
//!
//! The model is the one [`super::model`] runs and the MPC predicts with: first order plus dead
//! time with a lagging sensor, `dT/dt = (ambient + gain·u(t − L) − T)/tau`,
//! `dS/dt = (T − S)/tau_s`. For a given `tau`, `tau_s` and `L` the sensor's response is linear
//! in the ambient, the gain and the starting temperature, which least squares give exactly;
//! the three that remain are searched (a compass search over `ln tau`, the apparent dead time
//! `L + tau_s` and the sensor's share `tau_s/(L + tau_s)` of it, which keeps the two lags that
//! trade against each other on one axis).
//!
//! Bounded work: the record is a fixed array ([`BINS`] bins; two neighbours merge, the width
//! doubling, when a run outgrows them), one evaluation of the fit is one pass over it (a few
//! tens of floating-point operations per bin, two sub-steps of the exact solution each), and
//! the search runs a given number of evaluations per call, at most [`MAX_EVALS`] in all, so a
//! caller on the output thread spreads it over several readings. No allocation.

use super::super::Nanos;
use super::ModelParams;

/// Bins of the record: the approach's, then the relay's.
pub const BINS: usize = 512;
/// Bins the approach keeps (the rest are the relay's).
const APPROACH_BINS: usize = 128;
/// The relay's bins.
pub const RELAY_BINS: usize = BINS - APPROACH_BINS;
/// The first width of a bin, ns.
pub const FIRST_WIDTH: Nanos = 100_000_000;
/// The approach's bins widen by this factor each: fine where a step's response bends (its
/// dead time and its sensor's lag), coarse along the slow curve after it, 1000 s in all (a
/// longer approach widens its last bin).
const GROWTH: f64 = 1.05;
/// Most evaluations a fit takes.
pub const MAX_EVALS: u32 = 600;

/// The record of a run: per bin the readings' sum, count and mean instant, and the line's on
/// time, ns. The approach (until [`Trace::split`]) has bins that widen from its start; the
/// relay's are of one width, which doubles (two neighbours merging) when the run outgrows
/// them, so a long approach leaves the relay's cycles their own resolution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Trace {
    t0: Nanos,
    /// The approach's bin edges from the start, ns (the last bin runs to the split).
    edges: [Nanos; APPROACH_BINS],
    /// The relay's start (once split), its bins' width and how many are in use.
    relay_t0: Option<Nanos>,
    width: Nanos,
    relay_len: usize,
    /// The relay's bins start once this instant has passed (the end of the approach's
    /// running bin).
    split_at: Option<Nanos>,
    y: [f64; BINS],
    n: [u32; BINS],
    /// The readings' summed offsets from their bin's start, s, and their squares, s².
    dt: [f64; BINS],
    dt2: [f64; BINS],
    /// The line's on time in the bin, ns, and its moment about the bin's start, ns·s.
    e: [f64; BINS],
    m: [f64; BINS],
    /// The last instant recorded and the line's cumulative on time then.
    last: (Nanos, Nanos),
    /// The line's duty before the run, %.
    before_pct: f64,
    started: bool,
    frozen: bool,
}

impl Trace {
    /// An empty record; `before_pct` is the line's duty before its first instant (the input
    /// the heater had then, which reaches the sensor a dead time later).
    pub fn new(before_pct: f64) -> Trace {
        let mut edges = [0; APPROACH_BINS];
        let (mut at, mut w) = (0.0, FIRST_WIDTH as f64);
        for e in edges.iter_mut() {
            *e = at as Nanos;
            at += w;
            w *= GROWTH;
        }
        Trace {
            t0: 0,
            edges,
            relay_t0: None,
            width: FIRST_WIDTH,
            relay_len: 0,
            split_at: None,
            y: [0.0; BINS],
            n: [0; BINS],
            dt: [0.0; BINS],
            dt2: [0.0; BINS],
            e: [0.0; BINS],
            m: [0.0; BINS],
            last: (0, 0),
            before_pct: if before_pct.is_finite() {
                before_pct.clamp(0.0, 100.0)
            } else {
                0.0
            },
            started: false,
            frozen: false,
        }
    }

    /// The relay's bins' width now, ns.
    pub fn width(&self) -> Nanos {
        self.width
    }

    /// The approach ends at `now` (after its reading there): the relay's bins start, and the
    /// approach's running bin ends here.
    pub fn split(&mut self, now: Nanos) {
        if self.started && self.split_at.is_none() && now >= self.last.0 {
            self.split_at = Some(now);
        }
    }

    /// Nothing more is recorded (the fit runs on what there is).
    pub fn freeze(&mut self) {
        self.frozen = true;
    }

    /// The approach's bin holding `t` (the last one holds everything after its edge).
    fn approach_bin(&self, t: Nanos) -> usize {
        let off = t.saturating_sub(self.t0);
        self.edges.partition_point(|e| *e <= off).saturating_sub(1)
    }

    /// Merges the relay's bins pairwise, doubling their width.
    fn merge(&mut self) {
        let w = self.width as f64 / 1e9;
        let first = APPROACH_BINS;
        let half = (BINS - first) / 2;
        for j in 0..half {
            let (o, a, b) = (first + j, first + 2 * j, first + 2 * j + 1);
            let (y, dt) = (
                self.y[a] + self.y[b],
                self.dt[a] + self.dt[b] + self.n[b] as f64 * w,
            );
            // Σ(x + w)² = Σx² + 2wΣx + n·w² for the second bin's offsets.
            let dt2 = self.dt2[a] + self.dt2[b] + 2.0 * w * self.dt[b] + self.n[b] as f64 * w * w;
            let (n, e) = (self.n[a] + self.n[b], self.e[a] + self.e[b]);
            let m = self.m[a] + self.m[b] + self.e[b] * w;
            self.y[o] = y;
            self.dt[o] = dt;
            self.dt2[o] = dt2;
            self.n[o] = n;
            self.e[o] = e;
            self.m[o] = m;
        }
        let rest = first + half..BINS;
        self.y[rest.clone()].fill(0.0);
        self.dt[rest.clone()].fill(0.0);
        self.dt2[rest.clone()].fill(0.0);
        self.n[rest.clone()].fill(0);
        self.e[rest.clone()].fill(0.0);
        self.m[rest].fill(0.0);
        self.width = self.width.saturating_mul(2);
        self.relay_len = self.relay_len.div_ceil(2);
    }

    /// The array index of the bin holding `t` (at least the record's start), growing the
    /// relay's bins as needed.
    fn bin(&mut self, t: Nanos) -> usize {
        match self.relay_t0 {
            Some(r0) if t >= r0 => {
                let mut k = ((t - r0) / self.width) as usize;
                while k >= BINS - APPROACH_BINS {
                    self.merge();
                    k = ((t - r0) / self.width) as usize;
                }
                self.relay_len = self.relay_len.max(k + 1);
                APPROACH_BINS + k
            }
            _ => self.approach_bin(t),
        }
    }

    /// The start and width of the bin at array index `i`, ns.
    fn span(&self, i: usize) -> (Nanos, Nanos) {
        if i >= APPROACH_BINS {
            let r0 = self.relay_t0.unwrap_or(self.t0);
            (r0 + (i - APPROACH_BINS) as Nanos * self.width, self.width)
        } else {
            let start = self.t0 + self.edges[i];
            let end = match (self.edges.get(i + 1), self.relay_t0) {
                (Some(e), Some(r0)) => (self.t0 + e).min(r0),
                (Some(e), None) => self.t0 + e,
                (None, Some(r0)) => r0,
                (None, None) => self.last.0.max(start),
            };
            (start, end.saturating_sub(start))
        }
    }

    /// A reading `celsius` at `now` with the line's cumulative on time `on_total` (ns). The
    /// on time since the last one is spread evenly over the time between them.
    pub fn record(&mut self, now: Nanos, celsius: f64, on_total: Nanos) {
        if !celsius.is_finite() || self.frozen {
            return;
        }
        if !self.started {
            self.started = true;
            self.t0 = now;
            self.last = (now, on_total);
        }
        if now < self.last.0 {
            return;
        }
        if let Some(at) = self
            .split_at
            .filter(|t| now > *t && self.relay_t0.is_none())
        {
            self.relay_t0 = Some(at);
        }
        let (t1, e1) = self.last;
        let energy = on_total.saturating_sub(e1) as f64;
        if now > t1 && energy > 0.0 {
            let span = (now - t1) as f64;
            let mut t = t1;
            while t < now {
                let i = self.bin(t);
                let (start, width) = self.span(i);
                let end = if width == 0 || i == APPROACH_BINS - 1 && self.relay_t0.is_none() {
                    now
                } else {
                    (start + width).min(now)
                };
                let end = end.max(t + 1);
                let part = energy * (end.min(now) - t) as f64 / span;
                self.e[i] += part;
                // Spread evenly: its centroid is the middle of the stretch.
                self.m[i] += part * ((t - start) + (end.min(now) - start)) as f64 / 2e9;
                t = end;
            }
        }
        let i = self.bin(now);
        let (start, _) = self.span(i);
        let x = (now - start) as f64 / 1e9;
        self.y[i] += celsius;
        self.n[i] += 1;
        self.dt[i] += x;
        self.dt2[i] += x * x;
        self.last = (now, on_total);
    }

    /// How many complete bins hold readings.
    fn bins_with_readings(&self) -> usize {
        self.bins_counted(0.0)
    }

    /// How many complete bins hold readings and start at least `skip_s` after the record's
    /// start.
    fn bins_counted(&self, skip_s: f64) -> usize {
        let (a, r) = self.complete();
        let counted = |i: &usize| {
            let (start, width) = self.span(*i);
            self.n[*i] > 0 && width > 0 && (start - self.t0) as f64 / 1e9 >= skip_s
        };
        (0..a).filter(counted).count() + (APPROACH_BINS..APPROACH_BINS + r).filter(counted).count()
    }

    /// Whether a reading was recorded.
    pub fn started(&self) -> bool {
        self.started
    }

    /// How long the record runs, ns (0 before its first reading).
    pub fn length(&self) -> Nanos {
        self.last.0.saturating_sub(self.t0)
    }

    /// The complete bins, in time order: the approach's (all of them once the relay's
    /// started), then the relay's but its running one.
    fn complete(&self) -> (usize, usize) {
        match self.relay_t0 {
            Some(r0) => {
                let approach = self.approach_bin(r0.saturating_sub(1)) + 1;
                let relay = ((self.last.0.saturating_sub(r0)) / self.width) as usize;
                (approach, relay.min(self.relay_len))
            }
            None => (self.approach_bin(self.last.0), 0),
        }
    }

    /// The line's duty on the piece of the record holding `t` (s from the record's start),
    /// and where that piece ends (s): a bin whose on time is all or nothing, or one full-power
    /// pulse of the bin's on time around its centroid (the switch of a relay inside the bin,
    /// where it was), or before the record `before_pct` up to its start.
    fn input(&self, t: f64, bins: (usize, usize)) -> (f64, f64) {
        if t < 0.0 {
            return (self.before_pct, 0.0);
        }
        let at = self.t0 + (t * 1e9) as Nanos;
        let i = match self.relay_t0 {
            Some(r0) if at >= r0 => {
                let k = ((at - r0) / self.width) as usize;
                if k >= bins.1 {
                    // Past the complete bins (a lag of zero reaching the running one).
                    return (self.before_pct, f64::INFINITY);
                }
                APPROACH_BINS + k
            }
            _ => {
                let k = self.approach_bin(at);
                if k >= bins.0 {
                    return (self.before_pct, f64::INFINITY);
                }
                k
            }
        };
        let (start, width) = self.span(i);
        let a = (start - self.t0) as f64 / 1e9;
        let w = width as f64 / 1e9;
        let on = (self.e[i] / 1e9).clamp(0.0, w);
        if on <= 1e-6 * w || on >= w * (1.0 - 1e-6) {
            return (on / w.max(1e-12) * 100.0, a + w);
        }
        let c = self.m[i] / self.e[i];
        let p0 = a + (c - on / 2.0).clamp(0.0, w - on);
        let p1 = p0 + on;
        if t < p0 {
            (0.0, p0)
        } else if t < p1 {
            (100.0, p1)
        } else {
            (0.0, a + w)
        }
    }

    /// The least-squares fit for `tau`, `tau_s` and `dead` (s): the sum of squared errors over
    /// the readings and `(ambient, start − ambient, gain)`; `None` when it is singular.
    pub fn evaluate(&self, tau: f64, tau_s: f64, dead: f64) -> Option<(f64, [f64; 3])> {
        self.evaluate_with(tau, tau_s, dead, 0.0, None, &mut |_, _, _| {})
    }

    /// [`Trace::evaluate`] with the bins that start within `skip_s` of the record's start
    /// run through but not counted (a record that starts in the middle of a relay, where the
    /// input of the last dead time and the sensor's lag behind the block are not known, counts
    /// once they have passed), and the gain `gain` (°C/%) held where given.
    pub fn evaluate_after(
        &self,
        tau: f64,
        tau_s: f64,
        dead: f64,
        skip_s: f64,
        gain: Option<f64>,
    ) -> Option<(f64, [f64; 3])> {
        self.evaluate_with(tau, tau_s, dead, skip_s, gain, &mut |_, _, _| {})
    }

    /// [`Trace::evaluate`], telling `each` every bin's index, reading and regressors.
    fn evaluate_with(
        &self,
        tau: f64,
        tau_s: f64,
        dead: f64,
        skip_s: f64,
        gain: Option<f64>,
        each: &mut dyn FnMut(usize, f64, [f64; 3]),
    ) -> Option<(f64, [f64; 3])> {
        let bins = self.complete();
        if bins.0 + bins.1 < 8 || tau <= 0.0 || dead < 0.0 || tau_s < 0.0 {
            return None;
        }
        let step = |h: f64| {
            let a = (-h / tau).exp();
            if tau_s <= 1e-9 {
                return (a, 0.0, a);
            }
            let b = (-h / tau_s).exp();
            let beta = if (tau - tau_s).abs() > 1e-9 * tau {
                tau / (tau - tau_s) * (a - b)
            } else {
                h / tau * a
            };
            (a, b, beta)
        };
        // The steps of the exact solution, for the two lengths a uniform stretch repeats.
        let mut cache = [(f64::NAN, (0.0, 0.0, 0.0)); 2];
        let mut coef = |h: f64| {
            for c in &cache {
                if c.0 == h {
                    return c.1;
                }
            }
            let v = step(h);
            cache.swap(0, 1);
            cache[0] = (h, v);
            v
        };
        let advance = |(t, s): (f64, f64), c: f64, (a, b, beta): (f64, f64, f64)| {
            (c + (t - c) * a, c + (t - c) * beta + (s - c) * b)
        };
        // The free response from 1 °C and the response to the input, sensor and block.
        let (mut free, mut forced) = ((1.0, 1.0), (0.0, 0.0));
        let mut mm = [[0.0f64; 3]; 3];
        let mut v = [0.0f64; 3];
        let mut yy = 0.0;
        let indices = (0..bins.0).chain(APPROACH_BINS..APPROACH_BINS + bins.1);
        for i in indices {
            let (start, width) = self.span(i);
            let (ts, w) = ((start - self.t0) as f64 / 1e9, width as f64 / 1e9);
            let te = ts + w;
            // The input that reaches the block over the bin: from a dead time earlier, in
            // pieces of constant duty; the middle of the bin is always a piece's end.
            let (free0, forced0) = (free.1, forced.1);
            let tm = ts + w / 2.0;
            let (mut t, mut mid) = (ts, (free.1, forced.1));
            while t < te - 1e-12 {
                let (u, end) = self.input(t - dead, bins);
                let stop = if t < tm - 1e-12 { tm } else { te };
                let until = (end + dead).min(stop).max(t + 1e-9);
                let c = coef(until - t);
                free = advance(free, 0.0, c);
                forced = advance(forced, u, c);
                if (until - tm).abs() <= 1e-12 {
                    mid = (free.1, forced.1);
                }
                t = until;
            }
            let n = self.n[i];
            if n == 0 || ts < skip_s || w <= 0.0 {
                continue;
            }
            let nf = n as f64;
            let (x1, x2) = (self.dt[i] / nf, self.dt2[i] / nf);
            // The sensor's mean over the readings' instants, from the parabola through the
            // bin's start, middle and end.
            let mean = |a: f64, m: f64, b: f64| {
                let c = 2.0 * (a - 2.0 * m + b) / (w * w);
                let slope = (b - a) / w - c * w;
                a + slope * x1 + c * x2
            };
            let mut r = [
                1.0,
                mean(free0, mid.0, free.1),
                mean(forced0, mid.1, forced.1),
            ];
            let mut y = self.y[i] / nf;
            if let Some(g) = gain {
                // The gain's part is known: what is left of the reading, without its regressor.
                y -= g * r[2];
                r[2] = 0.0;
            }
            each(i, y, r);
            for a in 0..3 {
                v[a] += nf * r[a] * y;
                for b in 0..3 {
                    mm[a][b] += nf * r[a] * r[b];
                }
            }
            yy += nf * y * y;
        }
        if gain.is_some() {
            mm[2][2] = mm[0][0].max(1.0);
        }
        let mut theta = solve3(mm, v)?;
        if let Some(g) = gain {
            theta[2] = g;
        }
        let sse = yy - (theta[0] * v[0] + theta[1] * v[1] + theta[2] * v[2]);
        Some((sse.max(0.0), theta))
    }
}

/// Solves the 3×3 system `m·x = v` by elimination with partial pivoting.
pub(crate) fn solve3(mut m: [[f64; 3]; 3], mut v: [f64; 3]) -> Option<[f64; 3]> {
    let scale = m.iter().flatten().fold(0.0f64, |a, x| a.max(x.abs()));
    if scale <= 0.0 || scale.is_nan() {
        return None;
    }
    for c in 0..3 {
        let p = (c..3).max_by(|&a, &b| m[a][c].abs().total_cmp(&m[b][c].abs()))?;
        if m[p][c].abs() < 1e-13 * scale {
            return None;
        }
        m.swap(c, p);
        v.swap(c, p);
        for r in c + 1..3 {
            let k = m[r][c] / m[c][c];
            let pivot = m[c];
            for (x, p) in m[r].iter_mut().zip(pivot).skip(c) {
                *x -= k * p;
            }
            v[r] -= k * v[c];
        }
    }
    let mut x = [0.0; 3];
    for c in (0..3).rev() {
        let s: f64 = (c + 1..3).map(|j| m[c][j] * x[j]).sum();
        x[c] = (v[c] - s) / m[c][c];
    }
    x.iter().all(|x| x.is_finite()).then_some(x)
}

/// A point of the search: `ln tau`, the apparent dead time `L + tau_s` (s), and the sensor's
/// share `tau_s / (L + tau_s)`.
type Point = [f64; 3];

fn lags(q: &Point) -> (f64, f64, f64) {
    let tau = q[0].exp();
    let d = q[1].max(0.0);
    let rho = q[2].clamp(0.0, 1.0);
    (tau, d * rho, d * (1.0 - rho))
}

/// The search (see the module documentation): resumable, a given number of evaluations at a
/// time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit {
    q: Point,
    best: f64,
    steps: [f64; 3],
    /// The next direction to try (0..6), and the sweep's count without an improvement.
    dir: usize,
    failed: usize,
    evals: u32,
    done: bool,
}

impl Fit {
    /// A search from `tau` (s) and the apparent dead time `dead` (s), the sensor's share of
    /// it starting at a half.
    pub fn new(tau: f64, dead: f64) -> Fit {
        let tau = tau.clamp(0.5, 1e5);
        let dead = dead.clamp(0.0, super::MAX_MODEL_DEAD_TIME_S);
        Fit {
            q: [tau.ln(), dead, 0.5],
            best: f64::INFINITY,
            steps: [0.3, 0.3 * dead.max(0.5), 0.25],
            dir: 0,
            failed: 0,
            evals: 0,
            done: false,
        }
    }

    /// Whether the search has ended.
    pub fn done(&self) -> bool {
        self.done
    }

    /// Evaluations so far.
    pub fn evals(&self) -> u32 {
        self.evals
    }

    fn eval(&mut self, trace: &Trace, q: &Point) -> f64 {
        self.evals += 1;
        let (tau, tau_s, dead) = lags(q);
        match trace.evaluate(tau, tau_s, dead) {
            Some((sse, th)) if th[2] > 0.0 => sse,
            _ => f64::INFINITY,
        }
    }

    /// Runs up to `budget` evaluations on `trace`; returns whether the search has ended.
    pub fn run(&mut self, trace: &Trace, budget: u32) -> bool {
        let mut left = budget;
        if self.best == f64::INFINITY && !self.done && left > 0 {
            let q = self.q;
            self.best = self.eval(trace, &q);
            left -= 1;
        }
        while left > 0 && !self.done {
            let i = self.dir / 2;
            let sign = if self.dir.is_multiple_of(2) {
                1.0
            } else {
                -1.0
            };
            let mut q = self.q;
            q[i] += sign * self.steps[i];
            let valid = q[1] >= 0.0 && (0.0..=1.0).contains(&q[2]) && q[0] < 1e5f64.ln();
            let f = if valid {
                left -= 1;
                self.eval(trace, &q)
            } else {
                f64::INFINITY
            };
            if f < self.best {
                self.best = f;
                self.q = q;
                self.failed = 0;
                // Keep going the way that paid.
            } else {
                self.dir = (self.dir + 1) % 6;
                self.failed += 1;
                if self.failed >= 6 {
                    self.failed = 0;
                    for s in &mut self.steps {
                        *s *= 0.5;
                    }
                }
            }
            let fine = self.steps[0] < 1e-3
                && self.steps[1] < 1e-3 * self.q[1].max(0.1)
                && self.steps[2] < 2e-3;
            if fine || self.evals >= MAX_EVALS {
                self.done = true;
            }
        }
        self.done
    }

    /// The standard error of the dead time at the search's point, s, with the other
    /// parameters held: from the sum of squares' curvature `c` along the split of the apparent
    /// dead time (the two lags' sum held) and the readings' noise `σ²` the residual gives,
    /// `√(2σ²/c)`. The split shows only in how each relay corner rounds off, so this is what
    /// the noise leaves of it; infinite where the curvature gives none.
    pub fn dead_time_se(&self, trace: &Trace) -> Option<f64> {
        let (tau, tau_s, dead) = lags(&self.q);
        let sum = tau_s + dead;
        let h = (0.05 * sum).max(1e-3);
        // Three points along the split within 0..=sum.
        let l0 = dead.clamp(h, (sum - h).max(h));
        let at = |l: f64| trace.evaluate(tau, (sum - l).max(0.0), l.max(0.0));
        let (f0, _) = at(l0 - h)?;
        let (f1, _) = at(l0)?;
        let (f2, _) = at(l0 + h)?;
        let c = (f0 + f2 - 2.0 * f1) / (h * h);
        // The bins' means carry the readings' noise over their counts: the weighted sum of
        // squares is σ² times the bins less the six parameters.
        let bins = trace.bins_with_readings();
        if bins <= 6 {
            return None;
        }
        let var = f1 / (bins - 6) as f64;
        Some(if c > 0.0 {
            (2.0 * var / c).sqrt()
        } else {
            f64::INFINITY
        })
    }

    /// The model at the search's point, when it is a heater's: a positive gain, and the
    /// values within their parameters' ranges.
    pub fn model(&self, trace: &Trace) -> Option<ModelParams> {
        let (tau, tau_s, dead) = lags(&self.q);
        let (_, th) = trace.evaluate(tau, tau_s, dead)?;
        let m = ModelParams {
            gain_c_per_pct: th[2],
            tau_s: tau,
            dead_time_s: dead,
            ambient_c: th[0],
            sensor_tau_s: tau_s,
        };
        let sane = m.gain_c_per_pct > 0.0
            && m.gain_c_per_pct <= super::MAX_MODEL_GAIN
            && (0.1..=super::MAX_TIME_S).contains(&tau)
            && dead <= super::MAX_MODEL_DEAD_TIME_S
            && tau_s <= super::MAX_MODEL_DEAD_TIME_S
            && (super::MIN_TEMP_C..=super::MAX_TEMP_C).contains(&m.ambient_c);
        sane.then_some(m)
    }
}

/// Points of the profile along the sensor's share of the apparent dead time: 0, 1/32, .., 1.
pub const SHARES: usize = 33;
/// Apparent dead times the profile tries at each share: the fit's, and that less and more
/// [`SUM_STEP`] of it.
const SUMS: usize = 3;
/// See [`SUMS`].
const SUM_STEP: f64 = 0.1;
/// A record that starts in the middle of a relay counts after this many of the largest
/// apparent dead time the profile tries (the input of the last dead time has passed, and the
/// sensor's lag behind the block has decayed to under 1 %).
const SKIP_SUMS: f64 = 6.0;

/// The split of the apparent dead time between the dead time and the sensor's lag, told from
/// several records of one relay: each record (a window of its cycles) is fitted at the same
/// grid of splits and apparent dead times, the time constant held at the fit's, the linear
/// parts (ambient, start, gain) its own; the sums of squares add up over the windows, and the
/// least of the sum is the fit over all of them. Only the grid's sums are kept, so the record
/// stays one window long however long the relay goes on, and each window keeps its bins fine.
///
/// Along the apparent dead time a parabola through its three points gives the least at each
/// share (the profile); along the share a parabola through the least point and its neighbours
/// gives the dead time, and its curvature with the noise the residual gives its standard
/// error, as in [`Fit::dead_time_se`] but with the apparent dead time free.
///
/// Bounded work: `SHARES × 3` evaluations per window, a given number per call.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    tau: f64,
    sum: f64,
    gain: f64,
    /// The window under evaluation holds the gain.
    hold: bool,
    /// The sums of squares over the windows so far, by share and apparent dead time.
    sse: [[f64; SUMS]; SHARES],
    /// The bins counted, and the windows.
    bins: usize,
    windows: u32,
    /// The window under evaluation: the next point, its bins' skip, and its sums.
    next: usize,
    skip_s: f64,
    part: [[f64; SUMS]; SHARES],
    failed: bool,
}

/// The split a [`Profile`] gives: the dead time and the sensor's lag, s, and the dead time's
/// standard error, s (infinite where the profile shows no least).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Split {
    /// The dead time, s.
    pub dead_time_s: f64,
    /// The sensor's time constant, s.
    pub sensor_tau_s: f64,
    /// The dead time's standard error, s.
    pub dead_time_se_s: f64,
}

impl Profile {
    /// A profile around the time constant `tau` (s), the apparent dead time `sum` (s, the
    /// dead time and the sensor's lag together) and the gain `gain` (°C/%) of a fit.
    pub fn new(tau: f64, sum: f64, gain: f64) -> Profile {
        Profile {
            tau,
            sum: sum.max(1e-3),
            gain,
            hold: false,
            sse: [[0.0; SUMS]; SHARES],
            bins: 0,
            windows: 0,
            next: SHARES * SUMS,
            skip_s: 0.0,
            part: [[0.0; SUMS]; SHARES],
            failed: false,
        }
    }

    /// The time a record that starts in the middle of the relay runs before its bins count,
    /// s (see `SKIP_SUMS`).
    pub fn skip_s(&self) -> f64 {
        SKIP_SUMS * self.sum * (1.0 + SUM_STEP)
    }

    /// Windows added so far.
    pub fn windows(&self) -> u32 {
        self.windows
    }

    fn point(&self, k: usize, j: usize) -> (f64, f64) {
        let sum = self.sum * (1.0 + (j as f64 - 1.0) * SUM_STEP);
        let share = k as f64 / (SHARES - 1) as f64;
        (sum * share, sum * (1.0 - share))
    }

    /// Starts the evaluation of the run's record from its start (the approach, which fixes
    /// the gain, and the first cycles): all of it counts, its gain its own.
    pub fn begin_run(&mut self) {
        self.next = 0;
        self.skip_s = 0.0;
        self.hold = false;
        self.failed = false;
    }

    /// Starts the evaluation of a window recorded in the middle of the relay: its bins within
    /// [`Profile::skip_s`] of its start are not counted, and the gain is the fit's. (Around
    /// one temperature the gain trades against the sensor's lag: both lower the swing the
    /// sensor shows. The approach fixes it.)
    pub fn begin_window(&mut self) {
        self.next = 0;
        self.skip_s = self.skip_s();
        self.hold = true;
        self.failed = false;
    }

    /// Whether a window's evaluation is under way.
    pub fn evaluating(&self) -> bool {
        self.next < SHARES * SUMS
    }

    /// Runs up to `budget` evaluations of the window `trace`; returns whether the window is
    /// done. A window the model cannot be fitted to (too few bins, a singular system) is
    /// left out.
    pub fn run(&mut self, trace: &Trace, budget: u32) -> bool {
        let mut left = budget;
        while left > 0 && self.evaluating() {
            let (k, j) = (self.next / SUMS, self.next % SUMS);
            let (tau_s, dead) = self.point(k, j);
            let gain = self.hold.then_some(self.gain);
            match trace.evaluate_after(self.tau, tau_s, dead, self.skip_s, gain) {
                Some((sse, _)) if sse.is_finite() && !self.failed => self.part[k][j] = sse,
                _ => self.failed = true,
            }
            self.next += 1;
            left -= 1;
        }
        if self.evaluating() {
            return false;
        }
        if !self.failed {
            for (acc, part) in self.sse.iter_mut().zip(&self.part) {
                for (a, p) in acc.iter_mut().zip(part) {
                    *a += p;
                }
            }
            self.bins += trace.bins_counted(self.skip_s);
            self.windows += 1;
        }
        self.failed = false;
        true
    }

    /// The split the windows so far give; `None` before the first.
    pub fn split(&self) -> Option<Split> {
        if self.windows == 0 {
            return None;
        }
        let h = self.sum * SUM_STEP;
        // Per share, the least over the apparent dead time: (least, apparent dead time).
        let mut least = [(0.0, 0.0); SHARES];
        for (k, q) in self.sse.iter().enumerate() {
            let c = q[0] - 2.0 * q[1] + q[2];
            let (best, at) = if c > 0.0 {
                let x = (-(q[2] - q[0]) / (2.0 * c)).clamp(-2.0, 2.0);
                (q[1] + x * (q[2] - q[0]) / 2.0 + x * x * c / 2.0, x)
            } else {
                let j = (0..SUMS)
                    .min_by(|a, b| q[*a].total_cmp(&q[*b]))
                    .unwrap_or(1);
                (q[j], j as f64 - 1.0)
            };
            least[k] = (best, self.sum + at * h);
        }
        let k = (0..SHARES).min_by(|a, b| least[*a].0.total_cmp(&least[*b].0))?;
        // The parabola through the least point and its neighbours (the edge's own at an edge).
        let m = k.clamp(1, SHARES - 2);
        let (p0, p1, p2) = (least[m - 1].0, least[m].0, least[m + 1].0);
        let step = 1.0 / (SHARES - 1) as f64;
        let curv = (p0 - 2.0 * p1 + p2) / (step * step);
        let x = if curv > 0.0 {
            (-(p2 - p0) / (2.0 * (p0 - 2.0 * p1 + p2))).clamp(-1.0, 1.0)
        } else {
            k as f64 - m as f64
        };
        let x = if k == m { x } else { k as f64 - m as f64 };
        let share = ((m as f64 + x) * step).clamp(0.0, 1.0);
        // The apparent dead time along the profile, linear between its points.
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let sum = if x >= 0.0 {
            lerp(least[m].1, least[m + 1].1, x)
        } else {
            lerp(least[m].1, least[m - 1].1, -x)
        };
        let (tau_s, dead) = (sum * share, sum * (1.0 - share));
        // The dead time against the share along the profile: dL/dshare.
        let dead_at = |i: usize| least[i].1 * (1.0 - i as f64 * step);
        let slope = (dead_at(m + 1) - dead_at(m - 1)) / (2.0 * step);
        let p_min = p1.min(least[k].0);
        let dof = self.bins as f64 - 3.0 * self.windows as f64 - 2.0;
        let se = if curv > 0.0 && dof > 0.0 {
            let var = p_min.max(0.0) / dof;
            slope.abs() * (2.0 * var / curv).sqrt()
        } else {
            f64::INFINITY
        };
        Some(Split {
            dead_time_s: dead,
            sensor_tau_s: tau_s,
            dead_time_se_s: se,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::plant::{Plant, PlantParams};
    use super::*;

    const MS: Nanos = 1_000_000;
    const S: Nanos = 1_000_000_000;

    /// A relay run on `p` (0..100 %, band ±`band` around `target`), readings every 250 ms, the
    /// line switching at whole seconds (a 1 s period), until `cycles` switch-ons after the
    /// approach: the record.
    fn relay_cycles(p: PlantParams, target: f64, band: f64, cycles: u32, seed: u64) -> Trace {
        let mut plant = Plant::new(p, 0, seed);
        let mut trace = Trace::new(0.0);
        let (mut on, mut want, mut on_total, mut since, mut ons) = (false, true, 0u64, 0u64, 0);
        for k in 0.. {
            let t = k * 250 * MS;
            if t.is_multiple_of(S) && want != on {
                if on {
                    on_total += t - since;
                } else {
                    since = t;
                }
                on = want;
                plant.line(t, on);
            }
            let total = on_total + if on { t - since } else { 0 };
            let c = plant.reading(t).unwrap();
            trace.record(t, c, total);
            if c > target + band && want {
                want = false;
                trace.split(t);
            } else if c < target - band && !want {
                want = true;
                ons += 1;
                if ons > cycles {
                    break;
                }
            }
        }
        trace
    }

    #[test]
    #[ignore]
    fn explore_snr() {
        let mut g = 0x1234_5678_9abc_def1u64;
        let mut unit = || {
            g ^= g >> 12;
            g ^= g << 25;
            g ^= g >> 27;
            (g.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..40 {
            let rate = 0.3 + 0.4 * unit();
            let tau = 30.0 + 570.0 * unit();
            let dead = 0.5 + 2.5 * unit();
            let lag = 0.5 + 2.5 * unit();
            let noise = 0.02 + 0.18 * unit();
            let p = PlantParams {
                rate_c_per_s: rate,
                tau_s: tau,
                dead_time_s: dead,
                ambient_c: 20.0,
                noise_c: noise,
                sensor_tau_s: lag,
            };
            let target = 20.0 + 0.4 * rate * tau;
            let trace = relay_cycles(p, target, (1.1 * noise).max(0.2), 6, 7);
            let mut fit = Fit::new(tau * 1.3, (dead + lag) * 0.8);
            while !fit.run(&trace, 16) {}
            let m = fit.model(&trace).unwrap();
            let snr = rate * dead.min(lag) / noise;
            println!(
                "snr {snr:6.2} r {rate:.2} tau {tau:4.0} L {dead:.2} lag {lag:.2} n {noise:.2}: gain {:+5.1} % tau {:+5.1} % L {:+6.1} % lag {:+6.1} % sum {:+5.1} % evals {}",
                (m.gain_c_per_pct / (rate * tau / 100.0) - 1.0) * 100.0,
                (m.tau_s / tau - 1.0) * 100.0,
                (m.dead_time_s / dead - 1.0) * 100.0,
                (m.sensor_tau_s / lag - 1.0) * 100.0,
                ((m.dead_time_s + m.sensor_tau_s) / (dead + lag) - 1.0) * 100.0,
                fit.evals()
            );
        }
    }

    /// How well a relay run tells the dead time from the sensor's lag against its length, on
    /// the slowest, noisiest heater of the sizing range (0.3 °C/s, `L` 0.5 s behind a 1 s
    /// sensor, ±0.2 °C of noise; its corners about 0.7 times the noise): over 16 noise seeds,
    /// the dead time's spread, worst error, and the standard error the fit gives (its rms
    /// ratio to the true error near 1 when the standard error is honest). `CYCLES=5,10,20,40`.
    #[test]
    #[ignore]
    fn explore_dead_time_against_cycles() {
        let p = PlantParams {
            rate_c_per_s: 0.3,
            tau_s: 600.0,
            dead_time_s: 0.5,
            ambient_c: 20.0,
            noise_c: 0.2,
            sensor_tau_s: 1.0,
        };
        let cycles: Vec<u32> = std::env::var("CYCLES")
            .ok()
            .map(|s| s.split(',').filter_map(|x| x.parse().ok()).collect())
            .unwrap_or(vec![5, 10, 20, 40]);
        for &cycles in &cycles {
            let (mut ls, mut ses, mut zs) = (Vec::new(), Vec::new(), Vec::new());
            let mut width = 0;
            for seed in (1..=31u64).step_by(2) {
                let trace = relay_cycles(p, 92.0, 0.22, cycles, seed);
                width = trace.width() / MS;
                let mut fit = Fit::new(600.0 * 1.2, 1.2);
                while !fit.run(&trace, 16) {}
                let m = fit.model(&trace).unwrap();
                let se = fit.dead_time_se(&trace).unwrap();
                ls.push(m.dead_time_s);
                ses.push(se);
                zs.push((m.dead_time_s - p.dead_time_s) / se);
            }
            let n = ls.len() as f64;
            let mean = ls.iter().sum::<f64>() / n;
            let sd = (ls.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
            let worst = ls
                .iter()
                .map(|l| (l / p.dead_time_s - 1.0).abs() * 100.0)
                .fold(0.0, f64::max);
            let se = ses.iter().sum::<f64>() / n;
            let z = (zs.iter().map(|z| z * z).sum::<f64>() / n).sqrt();
            println!(
                "{cycles:3} cycles (bins {width} ms): L mean {mean:.3} s, sd {sd:.3} s, worst \
                 {worst:.1} %; standard error given {se:.3} s, error/se rms {z:.2}"
            );
        }
    }

    /// A relay run as [`relay_cycles`] of `cycles` switch-ons after the approach, recorded in
    /// the run's record, then in `windows` records of `window_s` each started afresh in the
    /// middle of the relay (their first reading starts their relay bins), with a gap of a
    /// second between them: the records.
    fn relay_windows(
        p: PlantParams,
        target: f64,
        band: f64,
        cycles: u32,
        window_s: u64,
        windows: usize,
    ) -> Vec<Trace> {
        let mut plant = Plant::new(p, 0, 1);
        let mut traces = vec![Trace::new(0.0)];
        let (mut on, mut want, mut on_total, mut since, mut ons) = (false, true, 0u64, 0u64, 0);
        let mut next: Option<Nanos> = None;
        for k in 0.. {
            let t = k * 250 * MS;
            if t.is_multiple_of(S) && want != on {
                if on {
                    on_total += t - since;
                } else {
                    since = t;
                }
                on = want;
                plant.line(t, on);
            }
            let total = on_total + if on { t - since } else { 0 };
            let c = plant.reading(t).unwrap();
            if next.is_some_and(|at| t >= at) {
                if traces.len() > windows {
                    break;
                }
                traces.push(Trace::new(0.0));
                let trace = traces.last_mut().unwrap();
                trace.record(t, c, total);
                trace.split(t);
                next = Some(t + window_s * S + S);
            } else if next.is_none_or(|at| t + S < at) {
                traces.last_mut().unwrap().record(t, c, total);
            }
            if c > target + band && want {
                want = false;
                if ons == 0 {
                    traces[0].split(t);
                }
            } else if c < target - band && !want {
                want = true;
                ons += 1;
                if ons == cycles + 1 {
                    next = Some(t + S);
                }
            }
        }
        traces
    }

    /// The profile over windows of a noise-free relay finds the plant's split from a fit's
    /// apparent dead time 5 % off: the run's record with its own gain, then records started
    /// in the middle of the relay with the gain held and their start skipped. Each window
    /// alone tells it too, and the windows' sums add up.
    #[test]
    fn the_profile_over_windows_finds_the_split() {
        let p = PlantParams {
            rate_c_per_s: 1.0,
            tau_s: 60.0,
            dead_time_s: 2.0,
            ambient_c: 20.0,
            noise_c: 0.0,
            sensor_tau_s: 1.0,
        };
        let traces = relay_windows(p, 44.0, 0.3, 4, 60, 3);
        assert_eq!(traces.len(), 4);
        let mut all = Profile::new(60.0, 3.15, 0.6);
        for (i, t) in traces.iter().enumerate() {
            if i == 0 {
                all.begin_run();
            } else {
                all.begin_window();
            }
            let mut calls = 0;
            while !all.run(t, 8) {
                calls += 1;
            }
            assert_eq!(calls, (SHARES * SUMS).div_ceil(8) - 1);
            assert_eq!(all.windows(), i as u32 + 1, "window {i} was left out");
            let s = all.split().unwrap();
            println!("{} windows: {s:?}", i + 1);
            assert!((s.dead_time_s - 2.0).abs() < 0.03, "{s:?}");
            assert!((s.sensor_tau_s - 1.0).abs() < 0.03, "{s:?}");
            // The windows alone, each.
            let mut one = Profile::new(60.0, 3.15, 0.6);
            if i == 0 {
                one.begin_run();
            } else {
                one.begin_window();
            }
            while !one.run(t, 64) {}
            let s = one.split().unwrap();
            assert!((s.dead_time_s - 2.0).abs() < 0.03, "window {i}: {s:?}");
        }
        // A window too short to count after its skip is left out.
        let mut short = Trace::new(0.0);
        short.record(0, 44.0, 0);
        short.split(0);
        for k in 1..20 {
            short.record(k * 250 * MS, 44.0, 0);
        }
        all.begin_window();
        while !all.run(&short, 64) {}
        assert_eq!(all.windows(), 4);
    }

    /// On a noise-free record the true model fits exactly: the sum of squares vanishes, the
    /// linear parts come out exact, and the search from a point well off finds the plant.
    #[test]
    fn the_fit_finds_the_plant_on_a_clean_record() {
        let p = PlantParams {
            rate_c_per_s: 1.0,
            tau_s: 60.0,
            dead_time_s: 2.0,
            ambient_c: 20.0,
            noise_c: 0.0,
            sensor_tau_s: 1.0,
        };
        let trace = relay_cycles(p, 44.0, 0.3, 6, 1);
        let (sse, th) = trace.evaluate(60.0, 1.0, 2.0).unwrap();
        assert!(sse < 1e-2, "{sse}");
        assert!(
            (th[0] - 20.0).abs() < 0.01 && (th[2] - 0.6).abs() < 1e-3,
            "{th:?}"
        );
        // Another lag split with the same sum fits clearly worse.
        assert!(trace.evaluate(60.0, 0.0, 3.0).unwrap().0 > 100.0 * sse.max(1e-4));
        let mut fit = Fit::new(90.0, 2.0);
        let mut rounds = 0;
        while !fit.run(&trace, 8) {
            rounds += 1;
        }
        let m = fit.model(&trace).unwrap();
        println!("{m:?} after {} evaluations in {rounds} rounds", fit.evals());
        assert!(fit.evals() <= MAX_EVALS);
        assert!((m.gain_c_per_pct / 0.6 - 1.0).abs() < 0.01, "{m:?}");
        assert!((m.tau_s / 60.0 - 1.0).abs() < 0.01, "{m:?}");
        assert!((m.dead_time_s - 2.0).abs() < 0.02, "{m:?}");
        assert!((m.sensor_tau_s - 1.0).abs() < 0.02, "{m:?}");
        assert!((m.ambient_c - 20.0).abs() < 0.1, "{m:?}");
    }

    /// A record's bins stay bounded whatever the run's length: a relay of an hour merges
    /// the relay's bins, the approach's last bin takes what outlasts its widening bins.
    #[test]
    fn a_long_run_stays_within_the_bins() {
        let p = PlantParams {
            rate_c_per_s: 0.1,
            tau_s: 3000.0,
            dead_time_s: 30.0,
            ambient_c: 20.0,
            noise_c: 0.05,
            sensor_tau_s: 10.0,
        };
        let trace = relay_cycles(p, 50.0, 0.3, 8, 1);
        assert!(trace.width() > FIRST_WIDTH);
        let (a, r) = trace.complete();
        assert!(a <= APPROACH_BINS && r <= BINS - APPROACH_BINS, "{a} {r}");
        let mut fit = Fit::new(3000.0, 40.0);
        while !fit.run(&trace, 50) {}
        let m = fit.model(&trace).unwrap();
        assert!((m.dead_time_s + m.sensor_tau_s - 40.0).abs() < 4.0, "{m:?}");
    }
}
