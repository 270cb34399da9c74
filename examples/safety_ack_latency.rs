//! Measures how long a safety input's acknowledgment takes to come back from an idle output
//! thread (one channel, a sink that accepts every write), three ways:
//!
//! - `polled`: the slot's counter looked at every 50 µs with a thread sleep (the wait the safety
//!   path used before it had an acknowledgment eventfd), for comparison;
//! - `take`: [`SafetyPath::take`], a plain thread sleeping in `ppoll` on the eventfd;
//! - `take_async`: [`SafetyPath::take_async`] awaited on a current-thread tokio runtime.
//!
//! Each round stores a new planner (`max_simultaneous_on` 1, then 2, ...) and waits for it, after
//! 2 ms with nothing to do (the thread asleep). Prints, per way, the percentiles in µs of the
//! time from the input's store (which wakes the thread) to the caller's return with the
//! acknowledgment.
//!
//! ```sh
//! cargo run --release --example safety_ack_latency -- 1000
//! ```

use pwm_actuator::core::{Bank, ChannelParams, Phase};
use pwm_actuator::output::{EmergencyOff, LineChange, Output};
use pwm_actuator::output_thread::{self, Input, OutputThreadOptions, SafetyPath};
use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A sink that accepts every write.
struct Sink;

struct NoOff;
impl EmergencyOff for NoOff {
    fn all_inactive(&self) {}
}

impl Output for Sink {
    type Error = Infallible;
    fn line_count(&self) -> usize {
        1
    }
    fn set_levels(&mut self, _: &[LineChange]) -> Result<(), Infallible> {
        Ok(())
    }
    fn set_all_inactive(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(NoOff)
    }
}

/// The planner of round `k`.
fn bank(k: usize) -> Input {
    Input::Bank(Bank {
        phase: Phase::Sync,
        max_on: 1 + k % 2,
    })
}

/// The former wait: the counter looked at every 50 µs.
fn polled(safety: &SafetyPath, input: Input) {
    let request = safety.store(input);
    let start = Instant::now();
    while !safety.taken(request) {
        assert!(start.elapsed() < Duration::from_secs(1), "not taken");
        std::thread::sleep(Duration::from_micros(50));
    }
}

fn report(way: &str, mut took: Vec<Duration>) {
    took.sort_unstable();
    let at = |q: f64| took[((took.len() - 1) as f64 * q).round() as usize].as_secs_f64() * 1e6;
    println!(
        "{way:<11} median {:>7.1} µs  p90 {:>7.1}  p99 {:>7.1}  max {:>7.1}",
        at(0.5),
        at(0.9),
        at(0.99),
        at(1.0),
    );
}

fn main() {
    let rounds: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(1000);
    let cfg = ChannelParams::default()
        .validate()
        .expect("default channel");
    let thread = output_thread::spawn(vec![cfg], Sink, OutputThreadOptions::default())
        .expect("output thread");
    let safety = thread.requests.safety();
    let idle = || std::thread::sleep(Duration::from_millis(2));
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    println!("{rounds} acknowledgments each, from an idle output thread:");

    let run = |way: &str, take: &mut dyn FnMut(Input)| {
        let mut took = Vec::with_capacity(rounds);
        for k in 0..rounds {
            idle();
            let start = Instant::now();
            take(bank(k));
            took.push(start.elapsed());
        }
        report(way, took);
    };
    run("polled", &mut |input| polled(&safety, input));
    run("take", &mut |input| {
        safety.take(input).expect("taken");
    });
    run("take_async", &mut |input| {
        rt.block_on(safety.take_async(input)).expect("taken");
    });
    thread.handle.shutdown().expect("clean stop");
}
