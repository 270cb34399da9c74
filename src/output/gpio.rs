//! GPIO character-device backend (Linux uAPI v2 through gpiocdev): one request per chip, holding
//! all of the node's lines on that chip for the process lifetime, consumer `pwm_actuator`,
//! outputs requested inactive.
//!
//! The logical level of the trait is handed to the kernel as gpiocdev's logical [`Value`]; the
//! polarity (`active_low`) is part of the line configuration, so the kernel does the inversion
//! and an inactive line is electrically high on an active-low line.
//!
//! Threading: [`GpioOutput::set_levels`] runs on the real-time output thread. It does not
//! allocate (per-chip value sets are preallocated) and takes one mutex that only the emergency
//! handle and the same thread ever take. `gpiocdev::Request` is `Send + Sync` and its
//! `set_values` takes `&self` (one ioctl on the request fd), so the emergency handle shares the
//! requests through an `Arc` and writes them from any thread. This module must not decide
//! timing, and must never release a line before driving it inactive.

use super::bindings::{check_unique, normalize_chip_path, BindingError, LineAddr};
use super::panic_off::{lock_bounded, lock_ignore_poison, warn, EMERGENCY_LOCK_BUDGET};
use super::{EmergencyOff, ErrorKind, LineChange, Output, OutputError};
use crate::core::Level;
use gpiocdev::line::{Value, Values};
use gpiocdev::request::Config;
use gpiocdev::Request;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// Consumer label of every request (shown by `gpioinfo`).
pub const CONSUMER: &str = "pwm_actuator";

// The emergency handle writes the requests from another thread while the output thread keeps
// them: this relies on `Request` being shareable.
const _: fn() = || {
    fn shareable<T: Send + Sync>() {}
    shareable::<Request>();
};

/// One output line of a channel.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GpioLine {
    /// Channel name, for error messages (e.g. `pw01`).
    pub name: String,
    /// Chip path, e.g. `/dev/gpiochip0`; a bare `gpiochip0` means `/dev/gpiochip0`.
    pub chip: PathBuf,
    /// Line offset on the chip (0-based).
    pub offset: u32,
    /// `true` when the actuator is on with the line electrically low.
    pub active_low: bool,
}

impl GpioLine {
    /// The line's address, for the duplicate check.
    pub fn addr(&self) -> LineAddr {
        LineAddr::Gpio {
            chip: self.chip.clone(),
            offset: self.offset,
        }
    }
}

/// Parses a line address `[CHIP:]OFFSET` (`17`, `gpiochip1:4`, `/dev/gpiochip1:4`): the chip
/// (`None`: the default chip) and the offset. `None` when it is not one.
pub fn parse_line_addr(s: &str) -> Option<(Option<&str>, u32)> {
    let (chip, offset) = match s.rsplit_once(':') {
        Some((chip, off)) if !chip.is_empty() => (Some(chip), off),
        _ => (None, s),
    };
    Some((chip, offset.parse().ok()?))
}

/// Errors of the GPIO backend.
#[derive(Debug, thiserror::Error)]
pub enum GpioError {
    /// No line to drive.
    #[error("no GPIO lines given")]
    NoLines,
    /// The chip path does not exist.
    #[error("GPIO chip {chip} does not exist (channel {name}, line {offset})")]
    ChipNotFound {
        /// The (normalised) chip path.
        chip: PathBuf,
        /// First channel bound to that chip.
        name: String,
        /// Its line offset.
        offset: u32,
    },
    /// Two channels are bound to one line.
    #[error(transparent)]
    Binding(#[from] BindingError),
    /// The kernel refused the request (not a GPIO chip, offset out of range, line busy,
    /// permission denied, ...).
    #[error("cannot request lines {offsets:?} of {} as outputs", chip.display())]
    Request {
        /// The chip.
        chip: PathBuf,
        /// The offsets requested.
        offsets: Vec<u32>,
        /// What gpiocdev reported.
        #[source]
        source: gpiocdev::Error,
    },
    /// A line is already requested by another process (or another request): a configuration
    /// error, found at start-up before anything is driven.
    #[error(
        "{} line {offset} (channel {name}) is busy: held by consumer `{holder}`",
        chip.display()
    )]
    LineBusy {
        /// The chip.
        chip: PathBuf,
        /// The busy line's offset.
        offset: u32,
        /// The channel bound to it.
        name: String,
        /// The holder's consumer label as the kernel reports it (`gpioinfo`); empty when the
        /// holder gave none.
        holder: String,
    },
    /// Setting line values failed.
    #[error("cannot set lines {offsets:?} of {}", chip.display())]
    Write {
        /// The chip.
        chip: PathBuf,
        /// The offsets being written.
        offsets: Vec<u32>,
        /// The backend's index of the first line being written.
        line: usize,
        /// What gpiocdev reported.
        #[source]
        source: gpiocdev::Error,
    },
    /// A change names a line index the backend does not have.
    #[error("line index {line} is out of range: {count} lines are bound")]
    UnknownLine {
        /// The index given.
        line: usize,
        /// Number of bound lines.
        count: usize,
    },
    /// The emergency handle has driven every line inactive; further writes are refused.
    #[error("outputs were switched off by the emergency handle; writes are refused")]
    Tripped,
}

impl OutputError for GpioError {
    fn kind(&self) -> ErrorKind {
        match self {
            GpioError::Tripped => ErrorKind::Tripped,
            GpioError::UnknownLine { .. } => ErrorKind::UnknownLine,
            _ => ErrorKind::Write,
        }
    }

    fn line(&self) -> Option<usize> {
        match self {
            GpioError::Write { line, .. } => Some(*line),
            _ => None,
        }
    }
}

/// One line as planned for a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedLine {
    /// Line index in the backend (= position in the `lines` given to [`plan_requests`]).
    pub index: usize,
    /// Channel name.
    pub name: String,
    /// Line offset on the chip.
    pub offset: u32,
    /// Electrical polarity.
    pub active_low: bool,
}

/// The lines of one chip, requested together.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ChipPlan {
    /// Normalised chip path ([`normalize_chip_path`]).
    pub chip: PathBuf,
    /// The lines, in the order given.
    pub lines: Vec<PlannedLine>,
}

impl ChipPlan {
    /// The line offsets, in the order given.
    pub fn offsets(&self) -> Vec<u32> {
        self.lines.iter().map(|l| l.offset).collect()
    }

    /// The gpiocdev request configuration: every line an output, initially inactive (logical),
    /// with its polarity.
    pub fn request_config(&self) -> Config {
        let mut cfg = Config::default();
        cfg.on_chip(&self.chip);
        for line in &self.lines {
            cfg.with_line(line.offset).as_output(Value::Inactive);
            if line.active_low {
                cfg.as_active_low();
            } else {
                cfg.as_active_high();
            }
        }
        cfg
    }
}

/// Groups lines per chip (chip paths normalised, chips in order of first appearance) and
/// rejects an empty list and a line bound to two channels ([`check_unique`], the one
/// duplicate check). Opens nothing.
pub fn plan_requests(lines: &[GpioLine]) -> Result<Vec<ChipPlan>, GpioError> {
    if lines.is_empty() {
        return Err(GpioError::NoLines);
    }
    let bindings: Vec<(String, LineAddr)> =
        lines.iter().map(|l| (l.name.clone(), l.addr())).collect();
    check_unique(&bindings)?;
    let mut plans: Vec<ChipPlan> = Vec::new();
    for (index, line) in lines.iter().enumerate() {
        let chip = normalize_chip_path(&line.chip);
        let pos = match plans.iter().position(|p| p.chip == chip) {
            Some(pos) => pos,
            None => {
                plans.push(ChipPlan {
                    chip,
                    lines: Vec::new(),
                });
                plans.len() - 1
            }
        };
        plans[pos].lines.push(PlannedLine {
            index,
            name: line.name.clone(),
            offset: line.offset,
            active_low: line.active_low,
        });
    }
    Ok(plans)
}

/// The gpiocdev value for a logical level (`High` = active). Polarity is not applied here: it
/// is in the line configuration and applied by the kernel.
pub const fn to_value(level: Level) -> Value {
    match level {
        Level::High => Value::Active,
        Level::Low => Value::Inactive,
    }
}

/// The electrical level (`true` = high) of a line with polarity `active_low` at logical
/// `level`, as the kernel drives it.
pub const fn electrical_high(level: Level, active_low: bool) -> bool {
    level.is_high() != active_low
}

struct ChipRequest {
    chip: PathBuf,
    offsets: Vec<u32>,
    /// The backend's index of the chip's first line (named by a failed write).
    first_line: usize,
    request: Request,
    /// Every line of the request inactive, prebuilt for the emergency path.
    all_inactive: Values,
}

impl ChipRequest {
    fn write_all_inactive(&self) -> Result<(), GpioError> {
        self.request
            .set_values(&self.all_inactive)
            .map_err(|source| GpioError::Write {
                chip: self.chip.clone(),
                offsets: self.offsets.clone(),
                line: self.first_line,
                source,
            })
    }
}

struct GpioShared {
    chips: Vec<ChipRequest>,
    /// Serialises writes with the emergency handle, so that once the handle has written
    /// "inactive" no write decided before the trip can land after it.
    write: Mutex<()>,
    /// Set by the emergency handle: [`GpioOutput::set_levels`] refuses to write from then on.
    tripped: AtomicBool,
}

impl GpioShared {
    /// Drives every line of every chip inactive; returns the first error after trying all.
    fn all_inactive(&self) -> Result<(), GpioError> {
        let mut first = Ok(());
        for chip in &self.chips {
            let r = chip.write_all_inactive();
            if first.is_ok() {
                first = r;
            }
        }
        first
    }
}

/// Output lines on GPIO character devices.
///
/// Dropping it drives every line inactive; the requests are released once the last emergency
/// handle is gone too (until then they stay held, inactive).
pub struct GpioOutput {
    shared: Arc<GpioShared>,
    /// Line index -> (chip index, offset).
    lines: Vec<(usize, u32)>,
    /// Per chip: the values of the current write; empty between calls, with capacity for every
    /// line of the chip so that filling it never allocates.
    scratch: Vec<Values>,
}

impl GpioOutput {
    /// Requests every line (one request per chip, consumer [`CONSUMER`], outputs, inactive,
    /// polarity from `active_low`). Line index = position in `lines`.
    pub fn open(lines: &[GpioLine]) -> Result<GpioOutput, GpioError> {
        GpioOutput::open_planned(&plan_requests(lines)?, lines.len())
    }

    /// Requests the lines of `plans` (from [`plan_requests`] over `count` lines), as
    /// [`GpioOutput::open`] does.
    pub fn open_planned(plans: &[ChipPlan], count: usize) -> Result<GpioOutput, GpioError> {
        let mut chips = Vec::with_capacity(plans.len());
        let mut map = vec![(0usize, 0u32); count];
        let mut scratch = Vec::with_capacity(plans.len());
        for (ci, plan) in plans.iter().enumerate() {
            let offsets = plan.offsets();
            let request = request_plan(plan)?;
            for line in &plan.lines {
                map[line.index] = (ci, line.offset);
            }
            scratch.push(empty_with_capacity(&offsets));
            chips.push(ChipRequest {
                chip: plan.chip.clone(),
                first_line: plan.lines[0].index,
                all_inactive: Values::from_offsets(&offsets),
                offsets,
                request,
            });
        }
        Ok(GpioOutput {
            shared: Arc::new(GpioShared {
                chips,
                write: Mutex::new(()),
                tripped: AtomicBool::new(false),
            }),
            lines: map,
            scratch,
        })
    }

    /// The chip paths, one per request, in request order.
    pub fn chips(&self) -> Vec<PathBuf> {
        self.shared.chips.iter().map(|c| c.chip.clone()).collect()
    }

    fn clear_scratch(&mut self, changes: &[LineChange]) {
        for c in changes {
            if let Some(&(ci, offset)) = self.lines.get(c.line) {
                if let Some(values) = self.scratch.get_mut(ci) {
                    values.unset(offset);
                }
            }
        }
    }
}

/// Requests the lines of one chip as [`GpioOutput::open`] does: a missing chip is
/// [`GpioError::ChipNotFound`], and a refusal because a line is held elsewhere is reported as
/// [`GpioError::LineBusy`] naming the holder.
pub fn request_plan(plan: &ChipPlan) -> Result<Request, GpioError> {
    if !plan.chip.exists() {
        let first = &plan.lines[0];
        return Err(GpioError::ChipNotFound {
            chip: plan.chip.clone(),
            name: first.name.clone(),
            offset: first.offset,
        });
    }
    Request::from_config(plan.request_config())
        .with_consumer(CONSUMER)
        .request()
        .map_err(|source| {
            for line in &plan.lines {
                if let Some(holder) = line_holder(&plan.chip, line.offset) {
                    return GpioError::LineBusy {
                        chip: plan.chip.clone(),
                        offset: line.offset,
                        name: line.name.clone(),
                        holder,
                    };
                }
            }
            GpioError::Request {
                chip: plan.chip.clone(),
                offsets: plan.offsets(),
                source,
            }
        })
}

/// The consumer label of whoever holds line `offset` of `chip`, or `None` when the line is
/// free (or its state cannot be read).
pub fn line_holder(chip: &std::path::Path, offset: u32) -> Option<String> {
    let info = gpiocdev::Chip::from_path(chip)
        .ok()?
        .line_info(offset)
        .ok()?;
    info.used.then_some(info.consumer)
}

/// An empty value set that can hold `offsets` without allocating.
fn empty_with_capacity(offsets: &[u32]) -> Values {
    let mut v = Values::from_offsets(offsets);
    for offset in offsets {
        v.unset(*offset);
    }
    v
}

impl Output for GpioOutput {
    type Error = GpioError;

    fn line_count(&self) -> usize {
        self.lines.len()
    }

    /// Writes the changes, one `set_values` call per chip touched. On an error the other chips
    /// are still written and the first error is returned.
    fn set_levels(&mut self, changes: &[LineChange]) -> Result<(), GpioError> {
        let count = self.lines.len();
        if let Some(bad) = changes.iter().find(|c| c.line >= count) {
            return Err(GpioError::UnknownLine {
                line: bad.line,
                count,
            });
        }
        for c in changes {
            let (ci, offset) = self.lines[c.line];
            self.scratch[ci].set(offset, to_value(c.level));
        }
        let mut result = Ok(());
        {
            let _guard = lock_ignore_poison(&self.shared.write);
            if self.shared.tripped.load(Ordering::SeqCst) {
                result = Err(GpioError::Tripped);
            } else {
                for (ci, (chip, values)) in self.shared.chips.iter().zip(&self.scratch).enumerate()
                {
                    // An empty set would mean "every line" to the uAPI v2 encoding.
                    if values.is_empty() {
                        continue;
                    }
                    if let Err(source) = chip.request.set_values(values) {
                        if result.is_ok() {
                            let line = changes
                                .iter()
                                .find(|c| self.lines[c.line].0 == ci)
                                .map_or(chip.first_line, |c| c.line);
                            result = Err(GpioError::Write {
                                chip: chip.chip.clone(),
                                offsets: values.iter().map(|lv| lv.offset).collect(),
                                line,
                                source,
                            });
                        }
                    }
                }
            }
        }
        self.clear_scratch(changes);
        result
    }

    /// Writes every line inactive, whatever was written before (also after a failed write or
    /// an emergency off).
    fn set_all_inactive(&mut self) -> Result<(), GpioError> {
        let _guard = lock_ignore_poison(&self.shared.write);
        self.shared.all_inactive()
    }

    fn emergency_off(&self) -> Arc<dyn EmergencyOff> {
        Arc::new(GpioEmergencyOff {
            shared: Arc::clone(&self.shared),
        })
    }
}

impl Drop for GpioOutput {
    fn drop(&mut self) {
        if let Err(e) = self.set_all_inactive() {
            warn(format_args!(
                "gpio output: cannot drive lines inactive on release: {e}: {}",
                source_text(&e)
            ));
        }
    }
}

fn source_text(e: &GpioError) -> String {
    std::error::Error::source(e).map_or_else(String::new, |s| s.to_string())
}

/// The emergency handle of a [`GpioOutput`].
///
/// Safe in a panic hook: it latches the backend (later writes are refused), tries the write
/// lock for at most [`EMERGENCY_LOCK_BUDGET`] (enough for a write in progress on the output
/// thread to finish; it goes on without the lock if the holder is stuck or is the panicking
/// thread itself), then writes "all inactive" to every request through `&Request`, which needs
/// no lock. Errors are printed, never raised.
struct GpioEmergencyOff {
    shared: Arc<GpioShared>,
}

impl EmergencyOff for GpioEmergencyOff {
    fn all_inactive(&self) {
        self.shared.tripped.store(true, Ordering::SeqCst);
        let guard = lock_bounded(&self.shared.write, EMERGENCY_LOCK_BUDGET);
        if guard.is_none() {
            warn(format_args!(
                "gpio output: emergency off: write lock busy, writing without it"
            ));
        }
        for chip in &self.shared.chips {
            if let Err(e) = chip.write_all_inactive() {
                warn(format_args!(
                    "gpio output: emergency off: {e}: {}",
                    source_text(&e)
                ));
            }
        }
        drop(guard);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use gpiocdev::line::Direction;
    use std::path::Path;

    fn line(name: &str, chip: &str, offset: u32, active_low: bool) -> GpioLine {
        GpioLine {
            name: name.into(),
            chip: chip.into(),
            offset,
            active_low,
        }
    }

    #[test]
    fn lines_are_grouped_per_chip_in_order() {
        let lines = [
            line("pw01", "/dev/gpiochip-x0", 17, false),
            line("pw02", "/dev/gpiochip-x1", 3, true),
            line("pw03", "gpiochip-x0", 4, false),
        ];
        let plans = plan_requests(&lines).unwrap();
        assert_eq!(plans.len(), 2);
        assert_eq!(plans[0].chip, Path::new("/dev/gpiochip-x0"));
        assert_eq!(plans[0].offsets(), [17, 4]);
        let idx: Vec<usize> = plans[0].lines.iter().map(|l| l.index).collect();
        assert_eq!(idx, [0, 2]);
        assert_eq!(plans[1].chip, Path::new("/dev/gpiochip-x1"));
        assert_eq!(plans[1].lines[0].index, 1);
        assert!(plans[1].lines[0].active_low);
    }

    #[test]
    fn request_config_outputs_inactive_with_polarity() {
        let lines = [
            line("pw01", "/dev/gpiochip-x0", 17, false),
            line("pw02", "/dev/gpiochip-x0", 18, true),
        ];
        let plan = &plan_requests(&lines).unwrap()[0];
        let cfg = plan.request_config();
        assert_eq!(cfg.chip(), Path::new("/dev/gpiochip-x0"));
        assert_eq!(cfg.num_lines(), 2);
        let mut offsets: Vec<u32> = cfg.lines().to_vec();
        offsets.sort_unstable();
        assert_eq!(offsets, [17, 18]);
        for (offset, active_low) in [(17, false), (18, true)] {
            let lc = cfg.line_config(offset).unwrap();
            assert_eq!(lc.direction, Some(Direction::Output), "line {offset}");
            assert_eq!(lc.value, Some(Value::Inactive), "line {offset}");
            assert_eq!(lc.active_low, active_low, "line {offset}");
        }
    }

    #[test]
    fn logical_levels_map_to_values_and_polarity_is_electrical() {
        assert_eq!(to_value(Level::High), Value::Active);
        assert_eq!(to_value(Level::Low), Value::Inactive);
        assert!(electrical_high(Level::High, false));
        assert!(!electrical_high(Level::Low, false));
        assert!(!electrical_high(Level::High, true));
        assert!(
            electrical_high(Level::Low, true),
            "inactive active-low line is high"
        );
    }

    #[test]
    fn a_line_given_twice_is_rejected() {
        let lines = [
            line("pw01", "/dev/gpiochip-x0", 17, false),
            line("pw02", "gpiochip-x0", 17, true),
        ];
        let err = plan_requests(&lines).unwrap_err();
        assert_eq!(
            err.to_string(),
            "pw01 and pw02 are both bound to /dev/gpiochip-x0 line 17 \
             (000: no double output assignments)"
        );
    }

    #[test]
    fn no_lines_is_an_error() {
        assert!(matches!(plan_requests(&[]), Err(GpioError::NoLines)));
        assert!(matches!(GpioOutput::open(&[]), Err(GpioError::NoLines)));
    }

    /// Why opening pw01 on `chip` line `offset` fails (it must).
    fn open_error(chip: &str, offset: u32) -> GpioError {
        match GpioOutput::open(&[line("pw01", chip, offset, false)]) {
            Err(err) => err,
            Ok(_) => panic!("{chip} was opened as a GPIO chip"),
        }
    }

    #[test]
    fn missing_chip_names_the_path() {
        let err = open_error("/dev/gpiochip-does-not-exist", 17);
        assert!(matches!(err, GpioError::ChipNotFound { .. }), "{err:?}");
        assert_eq!(
            err.to_string(),
            "GPIO chip /dev/gpiochip-does-not-exist does not exist (channel pw01, line 17)"
        );
    }

    #[test]
    fn a_path_that_is_not_a_chip_is_a_request_error_with_its_source() {
        let err = open_error("/dev/null", 2);
        assert!(matches!(err, GpioError::Request { .. }), "{err:?}");
        assert!(err.to_string().contains("/dev/null"), "{err}");
        assert!(std::error::Error::source(&err).is_some());
    }

    #[test]
    fn scratch_values_are_empty_but_hold_every_line() {
        let v = empty_with_capacity(&[5, 1, 9]);
        assert!(v.is_empty());
        let mut v = v;
        v.set(9, Value::Active).set(1, Value::Inactive);
        assert_eq!(v.get(9), Some(Value::Active));
        assert_eq!(v.get(1), Some(Value::Inactive));
        v.unset(9);
        v.unset(1);
        assert!(v.is_empty());
    }
}
