//! A trace of what any output wrote: [`Traced`] wraps an output and records each change that
//! the wrapped output accepted, with the time its write returned, into a [`SimOutput`] used as
//! the recorder (VCD/CSV files written by the recorder's background thread).
//!
//! So `--trace` works on a robot too: the files show what was written to the GPIO lines, not
//! what was scheduled. Threading is the recorder's: no file I/O and no allocation on the
//! output thread. This module must not change what is written, nor when.

use super::{EmergencyOff, LineChange, Output, SimOutput};
use std::sync::Arc;

/// An output whose successful writes are recorded by a [`SimOutput`] with a trace (or not
/// recorded at all, without a recorder: then it only passes the writes through).
///
/// Dropping it drops the wrapped output first (which drives its lines inactive), then the
/// recorder (which records the lines going inactive and finishes the trace files).
pub struct Traced<O: Output> {
    // Field order is drop order: the real lines go inactive before the trace is finished.
    inner: O,
    recorder: Option<SimOutput>,
}

impl<O: Output> Traced<O> {
    /// Wraps `inner`; `recorder` must have one line per line of `inner` (same order) and is
    /// normally created with a trace ([`SimOutput::new`]).
    pub fn new(inner: O, recorder: Option<SimOutput>) -> Traced<O> {
        Traced { inner, recorder }
    }

    /// The recorder, e.g. to flush the trace files.
    pub fn recorder(&self) -> Option<&SimOutput> {
        self.recorder.as_ref()
    }
}

impl<O: Output> Output for Traced<O> {
    type Error = O::Error;

    fn line_count(&self) -> usize {
        self.inner.line_count()
    }

    /// Writes through the wrapped output; only a write that succeeded is recorded (a failed
    /// one may have set some lines and not others, so it is not guessed at).
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), Self::Error> {
        self.inner.set_levels(changes)?;
        if let Some(recorder) = &mut self.recorder {
            let Ok(()) = recorder.set_levels(changes);
        }
        Ok(())
    }

    fn set_all_inactive(&mut self) -> Result<(), Self::Error> {
        let result = self.inner.set_all_inactive();
        if let (Ok(()), Some(recorder)) = (&result, &mut self.recorder) {
            let Ok(()) = recorder.set_all_inactive();
        }
        result
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        let inner = self.inner.emergency_off();
        match &self.recorder {
            Some(recorder) => Arc::new(TracedEmergencyOff {
                inner,
                recorder: recorder.emergency_off(),
            }),
            None => inner,
        }
    }
}

/// The emergency handle of a [`Traced`] output: the real lines first, then the trace.
struct TracedEmergencyOff {
    inner: Arc<dyn EmergencyOff>,
    recorder: Arc<dyn EmergencyOff>,
}

impl EmergencyOff for TracedEmergencyOff {
    fn all_inactive(&self) {
        self.inner.all_inactive();
        self.recorder.all_inactive();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::Level;
    use crate::output::fault::FailingOutput;
    use crate::output::SimProbe;

    fn change(line: usize, level: Level, scheduled_ns: u64) -> LineChange {
        LineChange {
            line,
            level,
            scheduled_ns,
        }
    }

    fn names() -> Vec<String> {
        vec!["pw01".into(), "pw02".into()]
    }

    /// A simulated output of [`names`] and its probe.
    fn sim() -> (SimOutput, SimProbe) {
        let out = SimOutput::new(names(), None).unwrap();
        let probe = out.probe();
        (out, probe)
    }

    #[test]
    fn records_what_the_wrapped_output_accepted() {
        let (inner, line) = sim();
        let (recorder, rec) = sim();
        // The second write of the wrapped output fails: it must not appear in the record.
        let mut out = Traced::new(FailingOutput::new(inner, 1), Some(recorder));
        assert_eq!(out.line_count(), 2);
        out.set_levels(&[change(0, Level::High, 10)]).unwrap();
        assert!(out.set_levels(&[change(1, Level::High, 20)]).is_err());
        assert_eq!(line.levels(), [Level::High, Level::Low]);
        assert_eq!(rec.levels(), [Level::High, Level::Low]);
        let edges = rec.recent_edges();
        assert_eq!(edges.len(), 1);
        assert_eq!((edges[0].channel, edges[0].level), (0, Level::High));
        assert_eq!(edges[0].scheduled_ns, 10);

        out.set_all_inactive().unwrap();
        assert_eq!(line.levels(), [Level::Low, Level::Low]);
        assert_eq!(rec.levels(), [Level::Low, Level::Low]);
    }

    #[test]
    fn the_emergency_handle_switches_off_the_lines_and_the_record() {
        let (inner, line) = sim();
        let (recorder, rec) = sim();
        let mut out = Traced::new(inner, Some(recorder));
        out.set_levels(&[change(0, Level::High, 1), change(1, Level::High, 1)])
            .unwrap();
        out.emergency_off().all_inactive();
        assert_eq!(line.levels(), [Level::Low, Level::Low]);
        assert_eq!(rec.levels(), [Level::Low, Level::Low]);
    }
}
