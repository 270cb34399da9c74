//! A valve's state file, `<state_dir>/<NAME>.state`: what the valve knows of its position,
//! kept across restarts. Written atomically (a temporary file in the same directory, synced,
//! renamed over the old one, the directory synced) at every stop and once a second while the
//! valve moves; read once at start-up.
//!
//! The file is a few lines of `key value` text ending with a checksum (64-bit FNV-1a of every
//! line before it), at most [`MAX_STATE_BYTES`]. It is used only when it is whole, checks out,
//! names this valve and the travel times and backlash in force, and is not from the future;
//! otherwise the valve starts as if there were none (referenced as `reference_at_start` says),
//! and the reason is logged.
//!
//! The bounds are restored grown by the time since the record, conservatively: unless the
//! record was taken with both lines held off (a stop, the e-stop, a fault, the lifecycle's
//! inactive states), a line may have been on from the record until the node started again
//! (killed mid-move, a line left high until the restart requested it low), so the valve may
//! have moved that long either way at the fastest travel time. The record is stamped with the
//! time its snapshot was taken in the output thread, so a drive that started after it is
//! covered whether or not its report arrived; [`REPORT_SLACK`] covers the conversion between
//! the monotonic clock and the others. Within one boot the time since the record is counted on
//! CLOCK_BOOTTIME (see [`Stamp`]), across a reboot on the wall clock. The recorded bounds are widened by [`STATE_MARGIN_PCT`]
//! too: at rest the file is rewritten only when the bounds leave the recorded ones by more.

use crate::core::valve::{Restored, ValveConfig, ValveStatus, TRAVEL_TOLERANCE};
use crate::core::Nanos;
use nix::time::{clock_gettime, ClockId};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// The first line of a state file.
pub const STATE_MAGIC: &str = "pwm_actuator valve state 1";

/// Largest state file read, bytes.
pub const MAX_STATE_BYTES: u64 = 4_096;

/// At rest the state file is not rewritten while the bounds stay within the recorded ones
/// widened by this (a noisy feedback would rewrite it at every sample): a restore widens the
/// recorded bounds by as much, percent.
pub const STATE_MARGIN_PCT: f64 = 1.0;

/// Counted as drive time either way on top of the time since the record, for the conversion of
/// the snapshot's monotonic time to the wall clock, ns.
pub const REPORT_SLACK: Nanos = 100_000_000;

/// When a record was taken: the wall clock, and the boot it was taken in with CLOCK_BOOTTIME
/// (which counts suspended time and no clock steps). Within one boot the time since a record
/// is counted on CLOCK_BOOTTIME, so a wall-clock step (NTP) while the node was down cannot
/// shorten it; across a reboot on the wall clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stamp {
    /// Wall-clock ns since the Unix epoch.
    pub wall_ns: i64,
    /// The kernel's boot id (`/proc/sys/kernel/random/boot_id`), 0 when unknown.
    pub boot_id: u128,
    /// CLOCK_BOOTTIME, ns.
    pub boot_ns: i64,
}

impl Stamp {
    /// Now.
    pub fn now() -> Stamp {
        let boot_ns = clock_gettime(ClockId::CLOCK_BOOTTIME)
            .map(|t| t.tv_sec() * 1_000_000_000 + t.tv_nsec())
            .unwrap_or(0);
        Stamp {
            wall_ns: crate::clock::wall_ns(),
            boot_id: boot_id().unwrap_or(0),
            boot_ns,
        }
    }

    /// This stamp `ns` earlier.
    pub fn earlier(self, ns: i64) -> Stamp {
        Stamp {
            wall_ns: self.wall_ns - ns,
            boot_ns: self.boot_ns - ns,
            ..self
        }
    }

    /// The time from `then` to this stamp, ns: on CLOCK_BOOTTIME within one (known) boot, on the
    /// wall clock otherwise.
    pub fn since(&self, then: &Stamp) -> Option<i64> {
        if self.boot_id != 0 && self.boot_id == then.boot_id {
            self.boot_ns.checked_sub(then.boot_ns)
        } else {
            self.wall_ns.checked_sub(then.wall_ns)
        }
    }
}

/// The kernel's boot id, a UUID, as a number; `None` when it cannot be read.
fn boot_id() -> Option<u128> {
    let text = std::fs::read_to_string("/proc/sys/kernel/random/boot_id").ok()?;
    let hex: String = text.trim().chars().filter(|c| *c != '-').collect();
    (hex.len() == 32).then(|| u128::from_str_radix(&hex, 16).ok())?
}

/// What a state file holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StateRecord {
    /// Travel times (open, close) the valve ran on, ms.
    pub travel_ms: [u64; 2],
    /// Backlash it ran on, percent.
    pub backlash_pct: f64,
    /// Motor estimate, low and high bound, percent (see
    /// [`ValveStatus::motor`](crate::core::ValveStatus::motor)).
    pub motor: [f64; 3],
    /// Both lines were held off when it was taken (nothing could raise them afterwards).
    pub lines_held: bool,
    /// When its snapshot was taken.
    pub stamp: Stamp,
}

impl StateRecord {
    /// The record of `status` (of a valve with settings `cfg`) taken at `stamp`.
    pub fn of(cfg: &ValveConfig, status: &ValveStatus, stamp: Stamp) -> StateRecord {
        let held = !status.live || status.estop || status.fault.is_some();
        StateRecord {
            travel_ms: [cfg.params.travel_open_ms, cfg.params.travel_close_ms],
            backlash_pct: cfg.params.backlash_pct,
            motor: status.motor,
            lines_held: held && status.motion == crate::core::valve::Motion::Stopped,
            stamp,
        }
    }

    /// The file's text for valve `name`.
    pub fn encode(&self, name: &str) -> String {
        let body = format!(
            "{STATE_MAGIC}\nname {name}\ntravel_open_ms {}\ntravel_close_ms {}\nbacklash_pct \
             {:?}\nmotor_pct {:?}\nmotor_low_pct {:?}\nmotor_high_pct {:?}\nlines_held {}\n\
             wall_ns {}\nboot_id {:032x}\nboot_ns {}\n",
            self.travel_ms[0],
            self.travel_ms[1],
            self.backlash_pct,
            self.motor[0],
            self.motor[1],
            self.motor[2],
            self.lines_held,
            self.stamp.wall_ns,
            self.stamp.boot_id,
            self.stamp.boot_ns
        );
        format!("{body}check {:016x}\n", fnv1a(body.as_bytes()))
    }

    /// Parses the text of valve `name`'s file; the reason when it is not usable.
    pub fn decode(name: &str, text: &str) -> Result<StateRecord, DecodeError> {
        let (body, check) = text
            .strip_suffix('\n')
            .and_then(|t| t.rsplit_once('\n'))
            .map(|(b, c)| (format!("{b}\n"), c))
            .ok_or(DecodeError::Truncated)?;
        let want = format!("check {:016x}", fnv1a(body.as_bytes()));
        if check != want {
            return Err(DecodeError::Checksum);
        }
        let mut lines = body.lines();
        if lines.next() != Some(STATE_MAGIC) {
            return Err(DecodeError::Version);
        }
        let mut get = |key: &'static str| -> Result<&str, DecodeError> {
            lines
                .next()
                .and_then(|line| line.strip_prefix(key))
                .and_then(|v| v.strip_prefix(' '))
                .ok_or(DecodeError::Missing { key })
        };
        let file_name = get("name")?;
        if file_name != name {
            return Err(DecodeError::OtherValve {
                name: file_name.to_string(),
            });
        }
        let num = |key: &'static str, v: &str| {
            v.parse::<f64>()
                .ok()
                .filter(|x| x.is_finite())
                .ok_or(DecodeError::NotANumber { key })
        };
        let int = |key: &'static str, v: &str| {
            v.parse::<u64>().map_err(|_| DecodeError::NotACount { key })
        };
        let time = |key: &'static str, v: &str| {
            v.parse::<i64>().map_err(|_| DecodeError::NotATime { key })
        };
        let open = int("travel_open_ms", get("travel_open_ms")?)?;
        let close = int("travel_close_ms", get("travel_close_ms")?)?;
        let backlash_pct = num("backlash_pct", get("backlash_pct")?)?;
        let m = num("motor_pct", get("motor_pct")?)?;
        let lo = num("motor_low_pct", get("motor_low_pct")?)?;
        let hi = num("motor_high_pct", get("motor_high_pct")?)?;
        let lines_held = match get("lines_held")? {
            "true" => true,
            "false" => false,
            _ => return Err(DecodeError::LinesHeld),
        };
        let wall_ns = time("wall_ns", get("wall_ns")?)?;
        let boot_id = u128::from_str_radix(get("boot_id")?, 16).map_err(|_| DecodeError::BootId)?;
        let boot_ns = time("boot_ns", get("boot_ns")?)?;
        let top = 100.0 + backlash_pct;
        if !(0.0 <= lo && lo <= m && m <= hi && hi <= top) {
            return Err(DecodeError::Bounds {
                motor_pct: m,
                low_pct: lo,
                high_pct: hi,
                top_pct: top,
            });
        }
        Ok(StateRecord {
            travel_ms: [open, close],
            backlash_pct,
            motor: [m, lo, hi],
            lines_held,
            stamp: Stamp {
                wall_ns,
                boot_id,
                boot_ns,
            },
        })
    }

    /// What valve `cfg` restores from this record at `now`: the bounds grown by the time since
    /// the record (see the module), or why not.
    pub fn restore(&self, cfg: &ValveConfig, now: Stamp) -> Result<Restored, RestoreError> {
        let p = &cfg.params;
        let configured = [p.travel_open_ms, p.travel_close_ms];
        if self.travel_ms != configured {
            return Err(RestoreError::TravelTimes {
                written_ms: self.travel_ms,
                configured_ms: configured,
            });
        }
        if self.backlash_pct != p.backlash_pct {
            return Err(RestoreError::Backlash {
                written_pct: self.backlash_pct,
                configured_pct: p.backlash_pct,
            });
        }
        let age = now.since(&self.stamp).ok_or(RestoreError::TimeOverflow)?;
        if age < -(REPORT_SLACK as i64) {
            return Err(RestoreError::Future { age_ns: age });
        }
        let top = 100.0 + self.backlash_pct;
        let grow = STATE_MARGIN_PCT
            + if self.lines_held {
                0.0
            } else {
                let ns = age.max(0) as f64 + REPORT_SLACK as f64;
                let fastest = p.travel_open_ms.min(p.travel_close_ms) as f64 * 1e6;
                ns / (fastest * (1.0 - TRAVEL_TOLERANCE)) * 100.0
            };
        let [m, lo, hi] = self.motor;
        let (lo, hi) = ((lo - grow).max(0.0), (hi + grow).min(top));
        if lo <= 0.0 && hi >= top {
            return Err(RestoreError::Anywhere { age_ns: age });
        }
        Ok(Restored {
            position_pct: m.clamp(lo, hi),
            low_pct: lo,
            high_pct: hi,
        })
    }
}

/// Why a state file's text is not a record of the valve (see [`StateRecord::decode`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DecodeError {
    /// The text does not end with a checksum line.
    #[error("truncated")]
    Truncated,
    /// The checksum does not match the lines before it.
    #[error("checksum mismatch (corrupted or partly written)")]
    Checksum,
    /// The first line is not [`STATE_MAGIC`].
    #[error("not a valve state file of this version")]
    Version,
    /// A line is missing, or is not the one expected there.
    #[error("{key} missing")]
    Missing {
        /// The key of the line, e.g. `travel_open_ms`.
        key: &'static str,
    },
    /// The file is another valve's.
    #[error("it is the state of valve `{name}`")]
    OtherValve {
        /// The valve the file names.
        name: String,
    },
    /// A value that must be a finite number is not one.
    #[error("{key} is not a number")]
    NotANumber {
        /// The key, e.g. `motor_pct`.
        key: &'static str,
    },
    /// A value that must be a count (an unsigned integer) is not one.
    #[error("{key} is not a count")]
    NotACount {
        /// The key, e.g. `travel_open_ms`.
        key: &'static str,
    },
    /// A time (a signed integer of ns) is not one.
    #[error("{key} is not a time")]
    NotATime {
        /// The key, `wall_ns` or `boot_ns`.
        key: &'static str,
    },
    /// `lines_held` is neither `true` nor `false`.
    #[error("lines_held is not true or false")]
    LinesHeld,
    /// `boot_id` is not 32 hexadecimal digits at most.
    #[error("boot_id is not a boot id")]
    BootId,
    /// The motor estimate is not within its bounds, or they are not within the travel.
    #[error("bounds {low_pct}..{high_pct} around {motor_pct} are not within 0..{top_pct}")]
    Bounds {
        /// The motor estimate, percent.
        motor_pct: f64,
        /// Its low bound, percent.
        low_pct: f64,
        /// Its high bound, percent.
        high_pct: f64,
        /// The top of the travel, 100 plus the backlash, percent.
        top_pct: f64,
    },
}

/// Why a valve does not restore its position from a record (see [`StateRecord::restore`]).
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum RestoreError {
    /// The record was taken with other travel times than the ones in force.
    #[error(
        "written for travel times {}/{} ms, configured {}/{} ms",
        written_ms[0], written_ms[1], configured_ms[0], configured_ms[1]
    )]
    TravelTimes {
        /// The record's travel times (open, close), ms.
        written_ms: [u64; 2],
        /// The travel times in force (open, close), ms.
        configured_ms: [u64; 2],
    },
    /// The record was taken with another backlash than the one in force.
    #[error("written for a backlash of {written_pct} %, configured {configured_pct} %")]
    Backlash {
        /// The record's backlash, percent.
        written_pct: f64,
        /// The backlash in force, percent.
        configured_pct: f64,
    },
    /// The time since the record does not fit the clock's range.
    #[error("its time overflows")]
    TimeOverflow,
    /// The record is from the future: the clock went back since.
    #[error(
        "written {:.1} s in the future (the clock went back)",
        -(*age_ns as f64) / 1e9
    )]
    Future {
        /// The time since the record, negative, ns.
        age_ns: i64,
    },
    /// So long since an unheld record that the grown bounds span the whole travel.
    #[error(
        "{:.1} s since the record with a line possibly on: the valve may be anywhere",
        *age_ns as f64 / 1e9
    )]
    Anywhere {
        /// The time since the record, ns.
        age_ns: i64,
    },
}

/// Why a valve's state file is not used (see [`read_state`]).
#[derive(Debug, thiserror::Error)]
pub enum StateFileError {
    /// The file exists but cannot be read.
    #[error("{}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The file is longer than [`MAX_STATE_BYTES`].
    #[error("{}: longer than {MAX_STATE_BYTES} bytes", path.display())]
    TooLong {
        /// The file.
        path: PathBuf,
    },
    /// The file's text is not a record of the valve.
    #[error("{}: {source}", path.display())]
    Decode {
        /// The file.
        path: PathBuf,
        /// Why.
        #[source]
        source: DecodeError,
    },
}

/// Why `state_dir` is refused at start-up (see [`check_state_dir`]).
#[derive(Debug, Clone, thiserror::Error)]
pub enum StateDirError {
    /// It cannot be looked up (it does not exist, a component is not searchable, ...).
    #[error("state_dir {}: {source}", dir.display())]
    Unreadable {
        /// The directory.
        dir: PathBuf,
        /// The OS error (shared, so that the error can be cloned).
        #[source]
        source: Arc<std::io::Error>,
    },
    /// It is not a directory.
    #[error("state_dir {} is not a directory", dir.display())]
    NotADirectory {
        /// The path.
        dir: PathBuf,
    },
    /// A file cannot be created and removed in it.
    #[error("state_dir {} is not writable: {source}", dir.display())]
    NotWritable {
        /// The directory.
        dir: PathBuf,
        /// The OS error (shared, so that the error can be cloned).
        #[source]
        source: Arc<std::io::Error>,
    },
}

/// Equal when the same check failed on the same path with the same kind of OS error.
impl PartialEq for StateDirError {
    fn eq(&self, other: &Self) -> bool {
        use StateDirError::*;
        match (self, other) {
            (Unreadable { dir: a, source: x }, Unreadable { dir: b, source: y })
            | (NotWritable { dir: a, source: x }, NotWritable { dir: b, source: y }) => {
                a == b && x.kind() == y.kind()
            }
            (NotADirectory { dir: a }, NotADirectory { dir: b }) => a == b,
            _ => false,
        }
    }
}

/// 64-bit FNV-1a: enough to tell a torn or edited file from a whole one.
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// The state file of valve `name` under `dir`.
pub fn state_path(dir: &Path, name: &str) -> PathBuf {
    dir.join(format!("{name}.state"))
}

/// Reads the record of valve `name` under `dir`: `Ok(None)` when there is no file, the reason
/// when it is not usable.
pub fn read_state(dir: &Path, name: &str) -> Result<Option<StateRecord>, StateFileError> {
    let path = state_path(dir, name);
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => return Err(StateFileError::Read { path, source }),
    };
    let mut text = String::new();
    if let Err(source) = file.take(MAX_STATE_BYTES + 1).read_to_string(&mut text) {
        return Err(StateFileError::Read { path, source });
    }
    if text.len() as u64 > MAX_STATE_BYTES {
        return Err(StateFileError::TooLong { path });
    }
    StateRecord::decode(name, &text)
        .map(Some)
        .map_err(|source| StateFileError::Decode { path, source })
}

/// Writes `text` as valve `name`'s file under `dir`, atomically: a temporary file beside it,
/// synced, renamed over it, the directory synced.
pub fn write_state(dir: &Path, name: &str, text: &str) -> std::io::Result<()> {
    let path = state_path(dir, name);
    let tmp = dir.join(format!(".{name}.state.tmp"));
    {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(text.as_bytes())?;
        f.sync_all()?;
    }
    std::fs::rename(&tmp, &path)?;
    std::fs::File::open(dir)?.sync_all()
}

/// Checks that `dir` is a directory this process can write a state file in (at start-up).
pub fn check_state_dir(dir: &Path) -> Result<(), StateDirError> {
    let meta = std::fs::metadata(dir).map_err(|e| StateDirError::Unreadable {
        dir: dir.to_path_buf(),
        source: Arc::new(e),
    })?;
    if !meta.is_dir() {
        return Err(StateDirError::NotADirectory {
            dir: dir.to_path_buf(),
        });
    }
    let probe = dir.join(".pwm_actuator.probe");
    std::fs::write(&probe, b"")
        .and_then(|()| std::fs::remove_file(&probe))
        .map_err(|e| StateDirError::NotWritable {
            dir: dir.to_path_buf(),
            source: Arc::new(e),
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::core::ValveParams;

    fn cfg() -> ValveConfig {
        ValveParams {
            travel_open_ms: 10_000,
            travel_close_ms: 20_000,
            ..ValveParams::default()
        }
        .validate()
        .unwrap()
    }

    fn record(held: bool) -> StateRecord {
        StateRecord {
            travel_ms: [10_000, 20_000],
            backlash_pct: 1.0,
            motor: [40.5, 38.0, 43.0],
            lines_held: held,
            stamp: Stamp {
                wall_ns: 1_000_000_000_000,
                boot_id: 0xfeed,
                boot_ns: 5_000_000_000,
            },
        }
    }

    /// `record(_)`'s stamp moved on by `ns` on both clocks.
    fn after(ns: i64) -> Stamp {
        Stamp {
            wall_ns: 1_000_000_000_000 + ns,
            boot_id: 0xfeed,
            boot_ns: 5_000_000_000 + ns,
        }
    }

    #[test]
    fn a_record_round_trips_and_a_changed_byte_is_refused() {
        let text = record(true).encode("mix");
        assert_eq!(StateRecord::decode("mix", &text), Ok(record(true)));
        assert_eq!(
            StateRecord::decode("hot", &text).unwrap_err().to_string(),
            "it is the state of valve `mix`"
        );
        let torn = text.replace("40.5", "41.5");
        assert_eq!(
            StateRecord::decode("mix", &torn),
            Err(DecodeError::Checksum)
        );
        assert!(StateRecord::decode("mix", &text[..text.len() / 2]).is_err());
        assert_eq!(StateRecord::decode("mix", ""), Err(DecodeError::Truncated));
    }

    #[test]
    fn the_bounds_grow_by_the_time_since_an_unheld_record() {
        let c = cfg();
        // Held: nothing raised a line since, the bounds stay (but for the margin at rest).
        let r = record(true).restore(&c, after(3_600_000_000_000)).unwrap();
        assert_eq!((r.low_pct, r.high_pct), (37.0, 44.0));
        // Not held: 2 s since, 0.1 s of slack, at 10 s × 0.9: 23.3 % either way, and the margin.
        let r = record(false).restore(&c, after(2_000_000_000)).unwrap();
        let g = 2.1 / 9.0 * 100.0 + 1.0;
        assert!((r.low_pct - (38.0 - g)).abs() < 1e-9, "{r:?}");
        assert!((r.high_pct - (43.0 + g)).abs() < 1e-9, "{r:?}");
        assert_eq!(
            record(false)
                .restore(&c, after(60_000_000_000))
                .unwrap_err()
                .to_string(),
            "60.0 s since the record with a line possibly on: the valve may be anywhere"
        );
        assert_eq!(
            record(true)
                .restore(&c, after(-5_000_000_000))
                .unwrap_err()
                .to_string(),
            "written 5.0 s in the future (the clock went back)"
        );
        // Within one boot the downtime is counted on CLOCK_BOOTTIME: a wall clock stepped back
        // by an hour while the node was down does not shorten it.
        let stepped = Stamp {
            wall_ns: after(60_000_000_000).wall_ns - 3_600_000_000_000,
            ..after(60_000_000_000)
        };
        assert!(matches!(
            record(false).restore(&c, stepped),
            Err(RestoreError::Anywhere { .. })
        ));
        // Across a reboot, on the wall clock.
        let rebooted = Stamp {
            boot_id: 0xbeef,
            boot_ns: 1,
            ..after(2_000_000_000)
        };
        assert_eq!(
            record(false).restore(&c, rebooted),
            record(false).restore(&c, after(2_000_000_000))
        );
        assert_ne!(Stamp::now().boot_id, 0, "this kernel has a boot id");
        let other = ValveParams {
            travel_open_ms: 12_000,
            ..c.params
        }
        .validate()
        .unwrap();
        assert_eq!(
            record(true)
                .restore(&other, after(0))
                .unwrap_err()
                .to_string(),
            "written for travel times 10000/20000 ms, configured 12000/20000 ms"
        );
    }

    #[test]
    fn files_are_written_atomically_and_read_bounded() {
        let dir = std::env::temp_dir().join(format!("pwm-valve-state-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        check_state_dir(&dir).unwrap();
        assert_eq!(read_state(&dir, "mix").unwrap(), None);
        write_state(&dir, "mix", &record(false).encode("mix")).unwrap();
        assert_eq!(read_state(&dir, "mix").unwrap(), Some(record(false)));
        std::fs::write(state_path(&dir, "big"), vec![b'x'; 10_000]).unwrap();
        let big = read_state(&dir, "big").unwrap_err();
        assert!(matches!(big, StateFileError::TooLong { .. }));
        assert!(
            big.to_string()
                .ends_with("big.state: longer than 4096 bytes"),
            "{big}"
        );
        write_state(&dir, "hot", &record(false).encode("mix")).unwrap();
        let other = read_state(&dir, "hot").unwrap_err().to_string();
        assert!(
            other.ends_with("hot.state: it is the state of valve `mix`"),
            "{other}"
        );
        let nope = check_state_dir(&dir.join("nope")).unwrap_err();
        assert!(matches!(nope, StateDirError::Unreadable { .. }));
        assert!(nope
            .to_string()
            .ends_with("nope: No such file or directory (os error 2)"));
        let file = state_path(&dir, "mix");
        assert_eq!(
            check_state_dir(&file),
            Err(StateDirError::NotADirectory { dir: file.clone() })
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
