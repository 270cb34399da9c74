//! Fault injection for exit-path tests, switched on only by the `PWM_ACTUATOR_FAULT`
//! environment variable:
//!
//! - `panic-after-ms=N`: a thread of the node panics N ms after start-up;
//! - `fail-write-after=N`: the output's writes fail after N successful ones;
//! - `hang-write-after-ms=N`: the first write N ms after start-up never returns (a driver stuck
//!   in the kernel), so the output thread hangs while the rest of the process runs.
//!
//! Both exist so that "every output ends inactive" can be shown on the real binary, not only
//! argued. Nothing here is active unless the variable is set.

use super::{EmergencyOff, ErrorKind, LineChange, Output, OutputError};
use std::sync::Arc;

/// The environment variable that selects a fault.
pub const FAULT_ENV: &str = "PWM_ACTUATOR_FAULT";

/// A fault to inject.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// Panic in a separate thread after this many ms.
    PanicAfterMs(u64),
    /// Fail every output write after this many successful writes.
    FailWriteAfter(u64),
    /// The first output write this many ms after start-up never returns.
    HangWriteAfterMs(u64),
}

impl Fault {
    /// Reads [`FAULT_ENV`]; `Ok(None)` when unset, `Err` with the reason when malformed.
    pub fn from_env() -> Result<Option<Fault>, FaultSpecError> {
        match std::env::var(FAULT_ENV) {
            Err(_) => Ok(None),
            Ok(v) => Fault::parse(&v).map(Some),
        }
    }

    /// Parses `panic-after-ms=N`, `fail-write-after=N` or `hang-write-after-ms=N`.
    pub fn parse(s: &str) -> Result<Fault, FaultSpecError> {
        let bad = || FaultSpecError {
            value: s.chars().take(64).collect(),
        };
        let (kind, n) = s.split_once('=').ok_or_else(bad)?;
        let n: u64 = n.trim().parse().map_err(|_| bad())?;
        match kind.trim() {
            "panic-after-ms" => Ok(Fault::PanicAfterMs(n)),
            "fail-write-after" => Ok(Fault::FailWriteAfter(n)),
            "hang-write-after-ms" => Ok(Fault::HangWriteAfterMs(n)),
            _ => Err(bad()),
        }
    }
}

/// A malformed [`FAULT_ENV`] value.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "{FAULT_ENV}=`{value}`: expected panic-after-ms=N, fail-write-after=N or \
     hang-write-after-ms=N"
)]
pub struct FaultSpecError {
    /// The value given (its first 64 characters).
    pub value: String,
}

/// The error of an injected write failure.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "injected output write failure{} after {after} writes ({FAULT_ENV})",
    line.map(|l| format!(" on line {l}")).unwrap_or_default()
)]
pub struct InjectedFailure {
    /// Successful writes before the failures began.
    pub after: u64,
    /// The line whose writes fail, if only one line's do.
    pub line: Option<usize>,
}

/// Wraps an output so that its writes fail after a number of successful ones.
pub struct FailingOutput<O: Output> {
    inner: O,
    writes_left: u64,
    after: u64,
    line: Option<usize>,
}

impl<O: Output> FailingOutput<O> {
    /// Wraps `inner`; writes fail after `after` successful calls to `set_levels`.
    pub fn new(inner: O, after: u64) -> Self {
        FailingOutput {
            inner,
            writes_left: after,
            after,
            line: None,
        }
    }

    /// Counts and fails only the writes that change `line` (index among the output's lines);
    /// the others always go through.
    pub fn on_line(self, line: usize) -> Self {
        FailingOutput {
            line: Some(line),
            ..self
        }
    }
}

impl<O: Output> Output for FailingOutput<O> {
    type Error = FaultError<O::Error>;

    fn line_count(&self) -> usize {
        self.inner.line_count()
    }

    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        let counted = self
            .line
            .is_none_or(|l| changes.iter().any(|c| c.line == l));
        if counted {
            if self.writes_left == 0 {
                return Err(FaultError::Injected(InjectedFailure {
                    after: self.after,
                    line: self.line,
                }));
            }
            self.writes_left -= 1;
        }
        self.inner.set_levels(changes).map_err(FaultError::Output)
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        // Switching off must keep working: that is what is under test.
        self.inner.set_all_inactive().map_err(FaultError::Output)
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        self.inner.emergency_off()
    }
}

/// Wraps an output so that its first write after a time never returns: the thread that
/// writes hangs, as on a driver stuck in the kernel. Switching off from another thread (the
/// emergency handle) still works.
pub struct HangingOutput<O: Output> {
    inner: O,
    hang_at: crate::core::Nanos,
}

impl<O: Output> HangingOutput<O> {
    /// Wraps `inner`; writes hang from `after_ms` ms from now on.
    pub fn new(inner: O, after_ms: u64) -> Self {
        let after = after_ms.saturating_mul(1_000_000);
        HangingOutput {
            inner,
            hang_at: crate::clock::monotonic_ns().saturating_add(after),
        }
    }
}

impl<O: Output> Output for HangingOutput<O> {
    type Error = O::Error;

    fn line_count(&self) -> usize {
        self.inner.line_count()
    }

    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        while crate::clock::monotonic_ns() >= self.hang_at {
            std::thread::sleep(std::time::Duration::from_secs(3600));
        }
        self.inner.set_levels(changes)
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        self.inner.set_all_inactive()
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        self.inner.emergency_off()
    }
}

/// An injected failure or the wrapped output's own error.
#[derive(Debug, thiserror::Error)]
pub enum FaultError<E: std::error::Error + 'static> {
    /// The injected failure.
    #[error(transparent)]
    Injected(InjectedFailure),
    /// The wrapped output failed by itself.
    #[error(transparent)]
    Output(E),
}

impl<E: OutputError> OutputError for FaultError<E> {
    fn kind(&self) -> ErrorKind {
        match self {
            FaultError::Injected(_) => ErrorKind::Injected,
            FaultError::Output(e) => e.kind(),
        }
    }

    fn line(&self) -> Option<usize> {
        match self {
            FaultError::Injected(i) => i.line,
            FaultError::Output(e) => e.line(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Level;
    use crate::output::SimOutput;

    #[test]
    fn parses_both_faults_and_refuses_the_rest() {
        assert_eq!(
            Fault::parse("panic-after-ms=300"),
            Ok(Fault::PanicAfterMs(300))
        );
        assert_eq!(
            Fault::parse("fail-write-after=4"),
            Ok(Fault::FailWriteAfter(4))
        );
        assert!(Fault::parse("panic")
            .unwrap_err()
            .to_string()
            .contains("panic-after-ms=N"));
        assert!(Fault::parse("fail-write-after=x").is_err());
        assert_eq!(
            Fault::parse("hang-write-after-ms=500"),
            Ok(Fault::HangWriteAfterMs(500))
        );
        assert!(Fault::parse("explode=1").is_err());
    }

    #[test]
    fn writes_fail_after_the_count_but_switching_off_works() {
        let sim = SimOutput::new(vec!["pw01".into()], None).unwrap();
        let probe = sim.probe();
        let mut out = FailingOutput::new(sim, 1);
        let on = [LineChange {
            line: 0,
            level: Level::High,
            scheduled_ns: 0,
        }];
        assert!(out.set_levels(&on).is_ok());
        assert_eq!(probe.levels(), vec![Level::High]);
        let e = out.set_levels(&on).unwrap_err();
        assert_eq!(
            e.to_string(),
            "injected output write failure after 1 writes (PWM_ACTUATOR_FAULT)"
        );
        out.set_all_inactive().unwrap();
        assert_eq!(probe.levels(), vec![Level::Low]);
    }

    #[test]
    fn a_line_restricted_failure_leaves_the_other_lines_working() {
        let sim = SimOutput::new(vec!["pw01".into(), "pw02".into()], None).unwrap();
        let mut out = FailingOutput::new(sim, 0).on_line(1);
        let change = |line| {
            [LineChange {
                line,
                level: Level::High,
                scheduled_ns: 0,
            }]
        };
        assert!(out.set_levels(&change(0)).is_ok());
        assert!(out.set_levels(&change(0)).is_ok());
        let e = out.set_levels(&change(1)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "injected output write failure on line 1 after 0 writes (PWM_ACTUATOR_FAULT)"
        );
    }
}
