//! `pwm_actuator_node sim-valve`: a simulated three-point valve actuator as its own process and
//! ROS participant (part of the binary only).
//!
//! It listens to the `~/<ch>/edges` of a valve's two channels (the node's real edges, stamped
//! with the time each write returned) and moves a true position with its own travel times —
//! which may differ from the ones the node is configured with — between hard end stops, and
//! publishes it as `std_msgs/Float64` (percent, 0 = closed) at a fixed rate. With `--record` it
//! writes every edge and every published position to a CSV file (`t_s,kind,value`, wall-clock
//! seconds; kind `open`, `close` or `true`) for the picture of docs/valve.md.

use crate::sim_ros::{self, make_topic};
use clap::{ArgAction, Args, FromArgMatches};
use futures::StreamExt;
use pwm_actuator::clock;
use pwm_actuator::ros::interface::msg::{self, RosMessage};
use ros2_client::qos::History;
use ros2_client::QosProfile;
use std::io::Write;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Options of `pwm_actuator_node sim-valve`.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct SimValveOptions {
    /// The node whose channels drive the valve
    #[arg(long, value_name = "NODE", default_value = "/pwm_actuator")]
    pub node: String,
    /// The channel whose line drives the valve open
    #[arg(long, value_name = "CH", default_value = "pw01")]
    pub open: String,
    /// The channel whose line drives the valve closed
    #[arg(long, value_name = "CH", default_value = "pw02")]
    pub close: String,
    /// The true travel time from closed to open, ms, 100..3600000
    #[arg(long, value_name = "MS", default_value_t = 60_000.0)]
    pub travel_open_ms: f64,
    /// The true travel time from open to closed, ms, 100..3600000
    #[arg(long, value_name = "MS", default_value_t = 60_000.0)]
    pub travel_close_ms: f64,
    /// Where the valve starts, percent 0..100 (unknown to the node)
    #[arg(long, value_name = "PCT", default_value_t = 37.0)]
    pub start_pct: f64,
    /// The topic the true position is published on (std_msgs/Float64, percent)
    #[arg(long, value_name = "TOPIC", default_value = "/sim_valve/position")]
    pub topic: String,
    /// Positions published per second, 0.1..1000
    #[arg(long, value_name = "HZ", default_value_t = 20.0)]
    pub rate_hz: f64,
    /// Write every edge and published position to this CSV file
    #[arg(long, value_name = "FILE.csv")]
    pub record: Option<PathBuf>,
    /// Stop after this many seconds (0: run until interrupted)
    #[arg(long, value_name = "S", default_value_t = 0.0)]
    pub duration: f64,
}

/// The `sim-valve` subcommand, for the whole command line.
pub fn command() -> clap::Command {
    SimValveOptions::augment_args(clap::Command::new("sim-valve"))
        .about(
            "A simulated three-point valve actuator driven by two channels' ~/<ch>/edges, with \
             its own travel times and hard end stops, publishing its true position \
             (std_msgs/Float64, %). Its own ROS participant (node sim_valve).",
        )
        .disable_help_flag(true)
        .arg(
            clap::Arg::new("help")
                .short('h')
                .long("help")
                .action(ArgAction::Help)
                .help("Print help"),
        )
}

/// Parses the subcommand's matches.
pub fn options(m: &clap::ArgMatches) -> Result<SimValveOptions, clap::Error> {
    SimValveOptions::from_arg_matches(m)
}

/// Why the options are refused.
fn check(o: &SimValveOptions) -> Result<(), String> {
    let within = |name: &str, v: f64, lo: f64, hi: f64| {
        if (lo..=hi).contains(&v) {
            Ok(())
        } else {
            Err(format!("--{name} {v} is outside {lo}..{hi}"))
        }
    };
    within("travel-open-ms", o.travel_open_ms, 100.0, 3_600_000.0)?;
    within("travel-close-ms", o.travel_close_ms, 100.0, 3_600_000.0)?;
    within("start-pct", o.start_pct, 0.0, 100.0)?;
    within("rate-hz", o.rate_hz, 0.1, 1000.0)?;
    within("duration", o.duration, 0.0, 1e7)
}

/// The true actuator: a position between hard end stops, moved by each line's high time at the
/// true travel times. Times are the edges' stamps (ns).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrueValve {
    /// True travel times (open, close), ns.
    travel: [f64; 2],
    /// Position at the last fall, percent.
    pos: f64,
    /// Which line is high (0 open, 1 close) and since when.
    high: [Option<i64>; 2],
}

impl TrueValve {
    /// A valve at `pos` percent with true travel times `open_ms`, `close_ms`.
    pub fn new(pos: f64, open_ms: f64, close_ms: f64) -> TrueValve {
        TrueValve {
            travel: [open_ms * 1e6, close_ms * 1e6],
            pos: pos.clamp(0.0, 100.0),
            high: [None, None],
        }
    }

    /// Line `i` (0 open, 1 close) went to `level` at `t` ns.
    pub fn edge(&mut self, i: usize, level: bool, t: i64) {
        if i > 1 {
            return;
        }
        match (level, self.high[i]) {
            (true, None) => self.high[i] = Some(t),
            (false, Some(since)) => {
                self.pos = self.moved(i, since, t);
                self.high[i] = None;
            }
            _ => {}
        }
    }

    fn moved(&self, i: usize, since: i64, t: i64) -> f64 {
        let sign = if i == 0 { 1.0 } else { -1.0 };
        let ran = (t - since).max(0) as f64;
        // Hard end stops: the motor runs on against them, the position stays.
        (self.pos + sign * ran / self.travel[i] * 100.0).clamp(0.0, 100.0)
    }

    /// The true position at `t` ns, percent. Both lines high (never, from the node) count as
    /// no motion: the motor would not turn.
    pub fn position(&self, t: i64) -> f64 {
        match self.high {
            [Some(s), None] => self.moved(0, s, t),
            [None, Some(s)] => self.moved(1, s, t),
            _ => self.pos,
        }
    }
}

/// Runs the simulated valve; returns the exit status (0 done, 1 ROS error, 2 bad options).
pub fn run(o: SimValveOptions) -> i32 {
    if let Err(e) = check(&o) {
        eprintln!("sim-valve: {e}");
        return 2;
    }
    sim_ros::block_on("sim-valve", serve(o))
}

/// The CSV record, if asked for.
struct Record(Option<std::io::BufWriter<std::fs::File>>);

impl Record {
    fn line(&mut self, t: f64, kind: &str, value: f64) {
        if let Some(w) = self.0.as_mut() {
            let _ = writeln!(w, "{t:.6},{kind},{value:.4}");
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

async fn serve(o: SimValveOptions) -> Result<(), String> {
    let mut node = sim_ros::start_node("sim_valve")?;
    let reliable = QosProfile::publisher_default().history(History::KeepLast { depth: 100 });
    let valve = Arc::new(Mutex::new(TrueValve::new(
        o.start_pct,
        o.travel_open_ms,
        o.travel_close_ms,
    )));
    let start_wall = clock::wall_ns();
    // Wall-clock seconds, as the node's messages are stamped, so a record and a ROS recording
    // line up.
    let secs = |t: i64| t as f64 / 1e9;
    let record = Arc::new(Mutex::new(Record(match &o.record {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).map_err(|e| format!("{}: {e}", p.display()))?,
        )),
        None => None,
    })));
    for (i, ch) in [&o.open, &o.close].into_iter().enumerate() {
        let topic = format!("{}/{}/edges", o.node.trim_end_matches('/'), ch);
        let t = make_topic(&node, &topic, msg::OutputEdge::type_name(), &reliable)?;
        let edges = node
            .create_subscription::<msg::OutputEdge>(&t, Some(reliable.clone()))
            .map_err(|e| format!("subscription {topic}: {e}"))?;
        let (valve, record) = (Arc::clone(&valve), Arc::clone(&record));
        tokio::spawn(async move {
            let stream = edges.async_stream();
            futures::pin_mut!(stream);
            while let Some(Ok((e, _))) = stream.next().await {
                let t = e.stamp.to_nanos();
                lock(&valve).edge(i, e.level, t);
                let kind = if i == 0 { "open" } else { "close" };
                lock(&record).line(secs(t), kind, f64::from(u8::from(e.level)));
            }
        });
    }
    let out_t = make_topic(&node, &o.topic, msg::Float64::type_name(), &reliable)?;
    let publisher = node
        .create_publisher::<msg::Float64>(&out_t, Some(reliable.clone()))
        .map_err(|e| format!("publisher {}: {e}", o.topic))?;
    eprintln!(
        "sim-valve: true travel {} ms open, {} ms close, from {} %; edges from {}/{{{},{}}}/edges, \
         position on {} at {} Hz",
        o.travel_open_ms, o.travel_close_ms, o.start_pct, o.node, o.open, o.close, o.topic, o.rate_hz
    );
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / o.rate_hz));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let end = (o.duration > 0.0).then(|| start_wall + (o.duration * 1e9) as i64);
    let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
        .map_err(|e| format!("SIGTERM: {e}"))?;
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = tokio::signal::ctrl_c() => break,
            _ = term.recv() => break,
        }
        let now = clock::wall_ns();
        if end.is_some_and(|e| now >= e) {
            break;
        }
        let pos = lock(&valve).position(now);
        lock(&record).line(secs(now), "true", pos);
        let _ = publisher.publish(msg::Float64 { data: pos });
    }
    if let Some(w) = lock(&record).0.as_mut() {
        let _ = w.flush();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_true_valve_integrates_its_lines_between_hard_stops() {
        let mut v = TrueValve::new(50.0, 1000.0, 2000.0);
        v.edge(0, true, 0);
        assert!((v.position(250_000_000) - 75.0).abs() < 1e-9);
        v.edge(0, false, 1_000_000_000);
        assert_eq!(v.position(2_000_000_000), 100.0, "the open stop");
        v.edge(1, true, 3_000_000_000);
        v.edge(1, false, 4_000_000_000);
        assert!((v.position(5_000_000_000) - 50.0).abs() < 1e-9);
        let m = command()
            .try_get_matches_from(["sim-valve", "--travel-open-ms", "10"])
            .unwrap();
        assert!(check(&options(&m).unwrap())
            .unwrap_err()
            .contains("travel-open-ms"));
    }
}
