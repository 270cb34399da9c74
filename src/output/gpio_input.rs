//! GPIO input lines with edge events (Linux uAPI v2 through gpiocdev), for end switches: one
//! request per chip, consumer `pwm_actuator`, both edges detected, the kernel's debounce
//! (hardware, or the character device's own software debounce where the chip has none) and the
//! polarity in the line configuration, so that a level read or an edge reported is logical:
//! `true` = the switch is active.
//!
//! This module only reads lines; what a switch means is decided by its caller.

use super::bindings::normalize_chip_path;
use super::gpio::{line_holder, CONSUMER};
use gpiocdev::line::{EdgeDetection, EdgeKind, Value};
use gpiocdev::Request;
use std::path::PathBuf;
use std::time::Duration;

/// Longest debounce period the kernel is asked for, ms.
pub const MAX_DEBOUNCE_MS: u64 = 100;

/// One input line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct InputLine {
    /// What it is, for error messages (e.g. `valve mix close limit`).
    pub name: String,
    /// Chip path, e.g. `/dev/gpiochip0`; a bare `gpiochip0` means `/dev/gpiochip0`.
    pub chip: PathBuf,
    /// Line offset on the chip (0-based).
    pub offset: u32,
    /// `true` when the switch is active with the line electrically low.
    pub active_low: bool,
}

/// Why input lines cannot be requested (a start-up configuration error).
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    /// The chip path does not exist.
    #[error("GPIO chip {} does not exist ({name}, line {offset})", chip.display())]
    ChipNotFound {
        /// The (normalised) chip path.
        chip: PathBuf,
        /// The line's name.
        name: String,
        /// Its offset.
        offset: u32,
    },
    /// A line is already requested by another process or request.
    #[error("{} line {offset} ({name}) is busy: held by consumer `{holder}`", chip.display())]
    LineBusy {
        /// The chip.
        chip: PathBuf,
        /// The busy line's offset.
        offset: u32,
        /// The line's name.
        name: String,
        /// The holder's consumer label (empty when it gave none).
        holder: String,
    },
    /// The kernel refused the request (offset out of range, no edge detection, permission).
    #[error(
        "cannot request line {offset} of {} ({name}) as an input with edge detection",
        chip.display()
    )]
    Request {
        /// The chip.
        chip: PathBuf,
        /// The offset.
        offset: u32,
        /// The line's name.
        name: String,
        /// What gpiocdev reported.
        #[source]
        source: gpiocdev::Error,
    },
    /// The initial level cannot be read.
    #[error("cannot read line {offset} of {} ({name})", chip.display())]
    Read {
        /// The chip.
        chip: PathBuf,
        /// The offset.
        offset: u32,
        /// The line's name.
        name: String,
        /// What gpiocdev reported.
        #[source]
        source: gpiocdev::Error,
    },
}

/// One requested input line: its level and its edges.
pub struct InputRequest {
    req: Request,
    offset: u32,
}

impl std::fmt::Debug for InputRequest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("InputRequest")
            .field("offset", &self.offset)
            .finish_non_exhaustive()
    }
}

impl InputRequest {
    /// Requests `line` as an input with both edges detected and `debounce` (at most
    /// [`MAX_DEBOUNCE_MS`]; zero: none), and reads its level. Returns the request and the
    /// logical level at the time of the request: every change after it is an edge event.
    pub fn open(line: &InputLine, debounce: Duration) -> Result<(InputRequest, bool), InputError> {
        let chip = normalize_chip_path(&line.chip);
        if !chip.exists() {
            return Err(InputError::ChipNotFound {
                chip,
                name: line.name.clone(),
                offset: line.offset,
            });
        }
        let debounce = debounce.min(Duration::from_millis(MAX_DEBOUNCE_MS));
        let mut b = Request::builder();
        b.on_chip(&chip)
            .with_consumer(CONSUMER)
            .with_line(line.offset)
            .as_input()
            .with_edge_detection(EdgeDetection::BothEdges);
        if line.active_low {
            b.as_active_low();
        }
        if !debounce.is_zero() {
            b.with_debounce_period(debounce);
        }
        let req = b
            .request()
            .map_err(|source| match line_holder(&chip, line.offset) {
                Some(holder) => InputError::LineBusy {
                    chip: chip.clone(),
                    offset: line.offset,
                    name: line.name.clone(),
                    holder,
                },
                None => InputError::Request {
                    chip: chip.clone(),
                    offset: line.offset,
                    name: line.name.clone(),
                    source,
                },
            })?;
        let level = req.value(line.offset).map_err(|source| InputError::Read {
            chip,
            offset: line.offset,
            name: line.name.clone(),
            source,
        })?;
        Ok((
            InputRequest {
                req,
                offset: line.offset,
            },
            level == Value::Active,
        ))
    }

    /// Waits up to `timeout` for the next edge: `Some(active)` for an edge (the logical level
    /// after it), `None` when none came in time. An error of the character device is
    /// returned as is.
    pub fn next_edge(&self, timeout: Duration) -> Result<Option<bool>, gpiocdev::Error> {
        if !self.req.wait_edge_event(timeout)? {
            return Ok(None);
        }
        let e = self.req.read_edge_event()?;
        Ok(Some(e.kind == EdgeKind::Rising))
    }

    /// The line's logical level now.
    pub fn level(&self) -> Result<bool, gpiocdev::Error> {
        Ok(self.req.value(self.offset)? == Value::Active)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_chip_is_named_with_the_line() {
        let line = InputLine {
            name: "valve mix close limit".into(),
            chip: PathBuf::from("/dev/no-such-gpiochip-77"),
            offset: 3,
            active_low: false,
        };
        let e = InputRequest::open(&line, Duration::from_millis(5)).unwrap_err();
        let s = e.to_string();
        assert!(
            matches!(e, InputError::ChipNotFound { offset: 3, .. }),
            "{s}"
        );
        assert!(s.contains("/dev/no-such-gpiochip-77") && s.contains("valve mix close limit"));
    }
}
