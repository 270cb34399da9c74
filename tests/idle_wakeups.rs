//! An idle node's threads sleep until something is due: the report reader sleeps, never
//! spins, until its next deadline.

use pwm_actuator::core::ChannelParams;
use pwm_actuator::engine::{self, EngineOptions};
use pwm_actuator::output::SimOutput;
use std::time::Duration;

fn one_channel() -> Vec<pwm_actuator::core::ChannelConfig> {
    vec![ChannelParams::default().validate().unwrap()]
}

#[test]
fn a_reader_waiting_less_than_a_millisecond_sleeps_rather_than_spins() {
    // A wait shorter than the poll's millisecond resolution is rounded up, never down to 0:
    // a reader with a deadline 0.3 ms away sleeps once instead of spinning until it.
    let sim = SimOutput::new(vec!["pw01".into()], None).unwrap();
    let mut e = engine::spawn(one_channel(), sim, EngineOptions::default()).unwrap();
    std::thread::sleep(Duration::from_millis(100));
    e.reports.clear_wake();
    while e.reports.try_recv().is_some() {}
    for _ in 0..20 {
        let start = std::time::Instant::now();
        let woken = e.reports.wait(Duration::from_micros(300));
        assert!(!woken, "no report is coming");
        assert!(
            start.elapsed() >= Duration::from_micros(300),
            "returned after {:?}, before its deadline",
            start.elapsed()
        );
    }
    e.handle.shutdown().unwrap();
}
