//! Channel-to-line bindings and the start-up check that no output line is bound to two
//! channels (000: "ensure that there are no double output assignments").
//!
//! Pure apart from resolving chip paths on the filesystem: it never opens a chip, so it runs
//! before any hardware is touched.

use std::collections::HashMap;
use std::fmt;
use std::path::{Path, PathBuf};

/// The output line a channel drives.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum LineAddr {
    /// A GPIO character device line.
    Gpio {
        /// The chip, e.g. `/dev/gpiochip0` (a bare `gpiochip0` means `/dev/gpiochip0`).
        chip: PathBuf,
        /// Line offset on the chip (0-based).
        offset: u32,
    },
    /// A line of the simulated sink.
    Sim {
        /// Line index in the sink (0-based).
        index: usize,
    },
}

impl LineAddr {
    /// The same address with the chip path normalised by [`normalize_chip_path`], so that two
    /// spellings of one chip compare equal.
    pub fn normalized(&self) -> LineAddr {
        match self {
            LineAddr::Gpio { chip, offset } => LineAddr::Gpio {
                chip: normalize_chip_path(chip),
                offset: *offset,
            },
            LineAddr::Sim { index } => LineAddr::Sim { index: *index },
        }
    }
}

impl fmt::Display for LineAddr {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            LineAddr::Gpio { chip, offset } => write!(f, "{} line {offset}", chip.display()),
            LineAddr::Sim { index } => write!(f, "sim line {index}"),
        }
    }
}

/// Normalises a chip path: a bare name (`gpiochip0`) means `/dev/gpiochip0`, and a path that
/// exists is canonicalised (symlinks such as udev's resolved). A path that does not exist is
/// kept as given, so the error that follows names it.
pub fn normalize_chip_path(chip: &Path) -> PathBuf {
    let mut components = chip.components();
    let bare = matches!(
        (components.next(), components.next()),
        (Some(std::path::Component::Normal(_)), None)
    );
    let path = if bare {
        Path::new("/dev").join(chip)
    } else {
        chip.to_path_buf()
    };
    std::fs::canonicalize(&path).unwrap_or(path)
}

/// Errors of the binding check.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BindingError {
    /// Two channels are bound to the same output line.
    #[error("{first} and {second} are both bound to {line} (000: no double output assignments)")]
    DuplicateLine {
        /// The channel bound first (in configuration order).
        first: String,
        /// The channel bound to the same line later.
        second: String,
        /// The line, normalised, as displayed by [`LineAddr`].
        line: String,
    },
}

/// Checks that no line is bound to two channels (000's warning about double output
/// assignments). `bindings` are (channel name, line) in configuration order; the first
/// duplicate found is reported with both channel names.
pub fn check_unique(bindings: &[(String, LineAddr)]) -> Result<(), BindingError> {
    let mut seen: HashMap<LineAddr, &str> = HashMap::with_capacity(bindings.len());
    for (name, addr) in bindings {
        let addr = addr.normalized();
        if let Some(first) = seen.get(&addr) {
            return Err(BindingError::DuplicateLine {
                first: (*first).to_string(),
                second: name.clone(),
                line: addr.to_string(),
            });
        }
        seen.insert(addr, name);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gpio(chip: &str, offset: u32) -> LineAddr {
        LineAddr::Gpio {
            chip: PathBuf::from(chip),
            offset,
        }
    }

    fn b(name: &str, addr: LineAddr) -> (String, LineAddr) {
        (name.to_string(), addr)
    }

    #[test]
    fn display() {
        assert_eq!(
            gpio("/dev/gpiochip0", 17).to_string(),
            "/dev/gpiochip0 line 17"
        );
        assert_eq!(LineAddr::Sim { index: 3 }.to_string(), "sim line 3");
    }

    #[test]
    fn distinct_lines_pass() {
        let bindings = [
            b("pw01", gpio("/dev/gpiochip0", 17)),
            b("pw02", gpio("/dev/gpiochip0", 18)),
            b("pw03", gpio("/dev/gpiochip1", 17)),
            b("pw04", LineAddr::Sim { index: 0 }),
            b("pw05", LineAddr::Sim { index: 1 }),
        ];
        assert_eq!(check_unique(&bindings), Ok(()));
        assert_eq!(check_unique(&[]), Ok(()));
    }

    #[test]
    fn duplicate_names_both_channels_and_the_line() {
        let bindings = [
            b("pw01", gpio("/dev/gpiochip0", 17)),
            b("pw02", gpio("/dev/gpiochip0", 17)),
        ];
        let err = check_unique(&bindings).unwrap_err();
        assert_eq!(
            err.to_string(),
            "pw01 and pw02 are both bound to /dev/gpiochip0 line 17 \
             (000: no double output assignments)"
        );
        assert_eq!(
            err,
            BindingError::DuplicateLine {
                first: "pw01".into(),
                second: "pw02".into(),
                line: "/dev/gpiochip0 line 17".into(),
            }
        );
    }

    #[test]
    fn bare_chip_name_is_the_dev_path() {
        assert_eq!(
            normalize_chip_path(Path::new("gpiochip-nonexistent9")),
            PathBuf::from("/dev/gpiochip-nonexistent9")
        );
        let bindings = [
            b("pw01", gpio("gpiochip-nonexistent9", 4)),
            b("heater", gpio("/dev/gpiochip-nonexistent9", 5)),
            b("valve", gpio("/dev/gpiochip-nonexistent9", 4)),
        ];
        let err = check_unique(&bindings).unwrap_err();
        assert_eq!(
            err,
            BindingError::DuplicateLine {
                first: "pw01".into(),
                second: "valve".into(),
                line: "/dev/gpiochip-nonexistent9 line 4".into(),
            }
        );
    }

    #[test]
    fn existing_paths_are_canonicalised() {
        // Two spellings of one existing file (through a symlink) are the same chip.
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path();
        let real = dir.join("chipfile");
        std::fs::write(&real, b"").unwrap();
        let link = dir.join("chiplink");
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let bindings = [
            b("pw01", gpio(real.to_str().unwrap(), 1)),
            b("pw02", gpio(link.to_str().unwrap(), 1)),
        ];
        let err = check_unique(&bindings).unwrap_err();
        let BindingError::DuplicateLine { line, .. } = err;
        let canon = std::fs::canonicalize(&real).unwrap();
        assert_eq!(line, format!("{} line 1", canon.display()));
    }

    #[test]
    fn sim_and_gpio_never_collide() {
        let bindings = [
            b("pw01", LineAddr::Sim { index: 0 }),
            b("pw02", gpio("/dev/gpiochip0", 0)),
            b("pw03", LineAddr::Sim { index: 0 }),
        ];
        let err = check_unique(&bindings).unwrap_err();
        assert!(err
            .to_string()
            .starts_with("pw01 and pw03 are both bound to sim line 0"));
    }
}
