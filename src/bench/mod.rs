//! `pwm_actuator_node bench`: edge lateness of the output thread against a tokio `sleep_until`
//! baseline, in one run, with the same channels, period, duty and simulated output.
//!
//! Both sides run the very same output thread and per-wake-up work (`engine::spawn_with`);
//! only the loop that puts the thread to sleep differs ([`baseline`] for tokio). Lateness is
//! the time the output write returned minus the time the core scheduled the edge, read from
//! the edge reports the ROS side would publish.
//!
//! Part of the binary, not of the library: nothing the node runs depends on it.

mod baseline;

use pwm_actuator::clock;
use pwm_actuator::core::{ChannelParams, Command, Nanos, NS_PER_MS};
use pwm_actuator::engine::{self, Engine, EngineOptions, Input, Report, Request};
use pwm_actuator::output::SimOutput;
use std::fmt::Write as _;
use std::time::Duration;

/// What to run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BenchOptions {
    /// Number of channels.
    pub channels: usize,
    /// Period of every channel, ms.
    pub period_ms: u64,
    /// Duty of every channel, percent.
    pub duty_percent: f64,
    /// Start offset between consecutive channels, ms (wrapped into the period).
    pub offset_ms: f64,
    /// Length of each side's run, s.
    pub seconds: f64,
    /// SCHED_FIFO priority for both sides' output threads, if any.
    pub rt_priority: Option<i32>,
    /// Print one JSON object instead of the table.
    pub json: bool,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            channels: 2,
            period_ms: 5,
            duty_percent: 37.0,
            offset_ms: 1.3,
            seconds: 10.0,
            rt_priority: None,
            json: false,
        }
    }
}

/// One side's figures.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Figures {
    /// Edges written.
    pub edges: usize,
    /// Edges written before their scheduled time.
    pub early: usize,
    /// Median lateness, µs.
    pub p50_us: f64,
    /// 99th percentile lateness, µs.
    pub p99_us: f64,
    /// 99.9th percentile lateness, µs.
    pub p999_us: f64,
    /// Largest lateness, µs.
    pub max_us: f64,
    /// Process CPU time over wall time, percent of one core.
    pub cpu_pct: f64,
    /// Peak resident set size during the run, KiB.
    pub rss_kb: u64,
    /// Host CPU steal during the run, percent of all CPU time (from /proc/stat).
    pub steal_pct: f64,
    /// Reports dropped because the reader lagged.
    pub dropped: u64,
}

const USAGE: &str = "usage: pwm_actuator_node bench [--channels N] [--period-ms MS] [--duty PCT] \
[--offset-ms MS] [--seconds S] [--rt-priority P] [--json]";

/// Parses the bench's arguments.
pub fn parse_args(args: &[String]) -> Result<BenchOptions, String> {
    let mut o = BenchOptions::default();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let mut value = |name: &str| {
            it.next()
                .ok_or_else(|| format!("{name} needs a value\n{USAGE}"))
                .cloned()
        };
        fn num<T: std::str::FromStr>(name: &str, v: &str) -> Result<T, String> {
            v.parse()
                .map_err(|_| format!("{name}: `{v}` is not a valid number\n{USAGE}"))
        }
        match a.as_str() {
            "--channels" => o.channels = num("--channels", &value("--channels")?)?,
            "--period-ms" => o.period_ms = num("--period-ms", &value("--period-ms")?)?,
            "--duty" => o.duty_percent = num("--duty", &value("--duty")?)?,
            "--offset-ms" => o.offset_ms = num("--offset-ms", &value("--offset-ms")?)?,
            "--seconds" => o.seconds = num("--seconds", &value("--seconds")?)?,
            "--rt-priority" => {
                o.rt_priority = Some(num("--rt-priority", &value("--rt-priority")?)?)
            }
            "--json" => o.json = true,
            "-h" | "--help" => return Err(USAGE.to_string()),
            other => return Err(format!("unknown bench option `{other}`\n{USAGE}")),
        }
    }
    if o.channels == 0 || o.channels > 256 {
        return Err(format!("--channels {} is outside 1..256", o.channels));
    }
    if !(o.seconds > 0.0 && o.seconds <= 3600.0) {
        return Err(format!("--seconds {} is outside (0, 3600]", o.seconds));
    }
    if !(0.0..=100.0).contains(&o.duty_percent) {
        return Err(format!("--duty {} is outside 0..100", o.duty_percent));
    }
    if !(o.offset_ms >= 0.0 && o.offset_ms.is_finite()) {
        return Err(format!("--offset-ms {} must be >= 0", o.offset_ms));
    }
    Ok(o)
}

/// Entry point of `pwm_actuator_node bench ARGS`; returns the process exit code.
pub fn main(args: &[String]) -> i32 {
    let opts = match parse_args(args) {
        Ok(o) => o,
        Err(e) => {
            eprintln!("{e}");
            return 2;
        }
    };
    let params = ChannelParams {
        period_ms: opts.period_ms,
        ..ChannelParams::default()
    };
    if let Err(e) = params.validate() {
        eprintln!("--period-ms: {e}");
        return 2;
    }
    if !opts.json {
        println!(
            "pwm_actuator bench: {} channels, period {} ms, duty {} %, offset {} ms, {} s per side, sim output{}",
            opts.channels,
            opts.period_ms,
            opts.duty_percent,
            opts.offset_ms,
            opts.seconds,
            opts.rt_priority
                .map(|p| format!(", SCHED_FIFO {p}"))
                .unwrap_or_default()
        );
    }
    let ours = match run_side(&opts, params, false) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("bench (timerfd thread): {e}");
            return 1;
        }
    };
    let baseline = match run_side(&opts, params, true) {
        Ok(f) => f,
        Err(e) => {
            eprintln!("bench (tokio baseline): {e}");
            return 1;
        }
    };
    let ratio = |b: f64, o: f64| if o > 0.0 { b / o } else { f64::INFINITY };
    let (r50, r99) = (
        ratio(baseline.p50_us, ours.p50_us),
        ratio(baseline.p99_us, ours.p99_us),
    );
    if opts.json {
        println!(
            "{{\"ours\": {}, \"baseline\": {}, \"ratio_p50\": {:.2}, \"ratio_p99\": {:.2}}}",
            json(&ours),
            json(&baseline),
            r50,
            r99
        );
    } else {
        println!("{}", table(&ours, &baseline));
        println!("ratio baseline/ours: p50 {r50:.1}x, p99 {r99:.1}x");
    }
    0
}

fn json(f: &Figures) -> String {
    format!(
        "{{\"p50_us\": {:.2}, \"p99_us\": {:.2}, \"p999_us\": {:.2}, \"max_us\": {:.2}, \
         \"early\": {}, \"edges\": {}, \"cpu_pct\": {:.2}, \"rss_kb\": {}, \"steal_pct\": {:.2}, \
         \"dropped\": {}}}",
        f.p50_us,
        f.p99_us,
        f.p999_us,
        f.max_us,
        f.early,
        f.edges,
        f.cpu_pct,
        f.rss_kb,
        f.steal_pct,
        f.dropped
    )
}

fn table(ours: &Figures, baseline: &Figures) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "{:<18} {:>7} {:>6} {:>9} {:>9} {:>9} {:>9} {:>6} {:>8} {:>6}",
        "",
        "edges",
        "early",
        "p50 us",
        "p99 us",
        "p99.9 us",
        "max us",
        "cpu %",
        "rss KiB",
        "steal%"
    );
    for (name, f) in [("ours (timerfd)", ours), ("baseline (tokio)", baseline)] {
        let _ = writeln!(
            s,
            "{:<18} {:>7} {:>6} {:>9.1} {:>9.1} {:>9.1} {:>9.1} {:>6.2} {:>8} {:>6.2}",
            name,
            f.edges,
            f.early,
            f.p50_us,
            f.p99_us,
            f.p999_us,
            f.max_us,
            f.cpu_pct,
            f.rss_kb,
            f.steal_pct
        );
    }
    s.trim_end().to_string()
}

/// Runs one side and measures it.
fn run_side(opts: &BenchOptions, params: ChannelParams, baseline: bool) -> Result<Figures, String> {
    let cfg = params.validate().map_err(|e| e.to_string())?;
    let names: Vec<String> = (1..=opts.channels).map(|i| format!("pw{i:02}")).collect();
    let output = SimOutput::new(names, None).map_err(|e| e.to_string())?;
    let engine_opts = EngineOptions {
        rt_priority: opts.rt_priority,
        queue_capacity: 16_384,
    };
    let configs = vec![cfg; opts.channels];
    reset_peak_rss();
    let Engine {
        mut requests,
        mut reports,
        handle,
    } = if baseline {
        baseline::spawn(configs, output, engine_opts)
    } else {
        engine::spawn(configs, output, engine_opts)
    }
    .map_err(|e| e.to_string())?;

    // The reader: what the ROS side does, minus publishing.
    let expected = (opts.seconds * 2000.0 / opts.period_ms as f64) as usize * opts.channels;
    let reader = std::thread::spawn(move || {
        let mut lateness: Vec<i64> = Vec::with_capacity(expected + 1024);
        reports.serve(
            || false,
            |r| {
                if let Report::Edge(e) = r {
                    lateness.push(e.lateness_ns());
                }
            },
            |_| {},
        );
        (lateness, reports.dropped())
    });

    let send = |requests: &mut engine::Requests, channel, input| {
        requests
            .send(Request { channel, input })
            .map_err(|e| e.to_string())
    };
    for ch in 0..opts.channels {
        send(
            &mut requests,
            ch,
            Input::Command(Command::Percent(opts.duty_percent)),
        )?;
    }
    // Stagger the channels' period starts by the offset, wrapped into the period.
    let period_ns = opts.period_ms * NS_PER_MS;
    let offset_ns = (opts.offset_ms * NS_PER_MS as f64) as Nanos;
    let t0 = clock::monotonic_ns() + 20 * NS_PER_MS;
    let mut order: Vec<(Nanos, usize)> = (0..opts.channels)
        .map(|ch| ((ch as Nanos * offset_ns) % period_ns.max(1), ch))
        .collect();
    order.sort_unstable();
    for (off, ch) in order {
        sleep_until(t0 + off);
        send(&mut requests, ch, Input::Enable(true))?;
    }
    // Measure a whole window after the last enable.
    let cpu0 = process_cpu_ns();
    let steal0 = read_steal();
    let wall0 = clock::monotonic_ns();
    sleep_until(wall0 + (opts.seconds * 1e9) as Nanos);
    let wall = clock::monotonic_ns() - wall0;
    let cpu = process_cpu_ns().saturating_sub(cpu0);
    let steal = match (steal0, read_steal()) {
        (Some((s0, t0)), Some((s1, t1))) if t1 > t0 => 100.0 * (s1 - s0) as f64 / (t1 - t0) as f64,
        _ => 0.0,
    };
    let rss_kb = peak_rss_kb();
    handle.shutdown().map_err(|e| e.to_string())?;
    drop(requests);
    let (mut lateness, dropped) = reader.join().map_err(|_| "reader thread panicked")?;
    // The shutdown edges are not scheduled by the core's timing: leave them out.
    lateness.truncate(lateness.len().saturating_sub(opts.channels));
    Ok(figures(&mut lateness, cpu, wall, rss_kb, steal, dropped))
}

fn figures(
    lateness: &mut [i64],
    cpu_ns: u64,
    wall_ns: u64,
    rss_kb: u64,
    steal_pct: f64,
    dropped: u64,
) -> Figures {
    lateness.sort_unstable();
    let pct = |p: f64| -> f64 {
        if lateness.is_empty() {
            return 0.0;
        }
        let i = ((p / 100.0) * (lateness.len() - 1) as f64).round() as usize;
        lateness[i.min(lateness.len() - 1)] as f64 / 1000.0
    };
    Figures {
        edges: lateness.len(),
        early: lateness.iter().filter(|l| **l < 0).count(),
        p50_us: pct(50.0),
        p99_us: pct(99.0),
        p999_us: pct(99.9),
        max_us: lateness.last().map_or(0.0, |m| *m as f64 / 1000.0),
        cpu_pct: if wall_ns > 0 {
            100.0 * cpu_ns as f64 / wall_ns as f64
        } else {
            0.0
        },
        rss_kb,
        steal_pct,
        dropped,
    }
}

fn sleep_until(t: Nanos) {
    let now = clock::monotonic_ns();
    if t > now {
        std::thread::sleep(Duration::from_nanos(t - now));
    }
}

/// User + system CPU time of the whole process, ns.
fn process_cpu_ns() -> u64 {
    use nix::time::{clock_gettime, ClockId};
    clock_gettime(ClockId::CLOCK_PROCESS_CPUTIME_ID)
        .map(|t| t.tv_sec() as u64 * 1_000_000_000 + t.tv_nsec() as u64)
        .unwrap_or(0)
}

/// Resets the kernel's peak-RSS mark for this process so each side reports its own peak.
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn peak_rss_kb() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1))
                .and_then(|v| v.parse().ok())
        })
        .unwrap_or(0)
}

/// (steal, total) jiffies from the aggregate line of /proc/stat.
fn read_steal() -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().next()?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    let steal = *v.get(7)?;
    Some((steal, v.iter().take(8).sum()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn defaults_are_the_issue_load() {
        let o = parse_args(&[]).unwrap();
        assert_eq!((o.channels, o.period_ms, o.duty_percent), (2, 5, 37.0));
        assert_eq!((o.offset_ms, o.seconds, o.json), (1.3, 10.0, false));
    }

    #[test]
    fn options_parse_and_bad_values_say_why() {
        let o = parse_args(&args("--channels 64 --period-ms 10 --seconds 2 --json")).unwrap();
        assert_eq!(
            (o.channels, o.period_ms, o.seconds, o.json),
            (64, 10, 2.0, true)
        );
        assert!(parse_args(&args("--channels x"))
            .unwrap_err()
            .contains("`x` is not a valid number"));
        assert!(parse_args(&args("--channels 0")).is_err());
        assert!(parse_args(&args("--bogus"))
            .unwrap_err()
            .contains("--bogus"));
        assert!(parse_args(&args("--seconds"))
            .unwrap_err()
            .contains("needs a value"));
    }

    #[test]
    fn percentiles_and_early_edges() {
        let mut l: Vec<i64> = (1..=1000).map(|i| i * 1000).collect();
        l[0] = -5000;
        let f = figures(&mut l, 50, 1000, 1, 0.0, 0);
        assert_eq!(f.edges, 1000);
        assert_eq!(f.early, 1);
        assert_eq!(f.max_us, 1000.0);
        assert_eq!(f.p50_us, 501.0);
        assert_eq!(f.cpu_pct, 5.0);
    }

    /// A short real run of both sides: every edge is reported and none is early. Bounds are
    /// loose on purpose; the figures themselves belong to the benchmark's printout.
    #[test]
    fn both_sides_run_and_report_every_edge() {
        let opts = BenchOptions {
            channels: 2,
            period_ms: 10,
            seconds: 0.5,
            ..BenchOptions::default()
        };
        let params = ChannelParams {
            period_ms: 10,
            ..ChannelParams::default()
        };
        for baseline in [false, true] {
            let f = run_side(&opts, params, baseline).unwrap();
            // 2 channels x 2 edges x 50 periods = 200, give or take the window's ends.
            assert!(
                f.edges >= 150 && f.edges <= 260,
                "{baseline}: {} edges",
                f.edges
            );
            assert_eq!(f.early, 0, "an absolute deadline is never written early");
            assert_eq!(f.dropped, 0);
        }
    }
}
