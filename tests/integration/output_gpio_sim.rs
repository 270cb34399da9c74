//! The GPIO backend against a real kernel GPIO chip: a `gpio-sim` simulated chip, whose sysfs
//! attributes (`sim_gpioN/value`) show the electrical level the kernel drives on each line.
//!
//! Needs the `gpio-sim` kernel module: an existing gpio-sim chip is used, or one is created
//! through configfs (`/sys/kernel/config/gpio-sim`, root only) and removed afterwards. Without
//! one the test prints that it skipped and checks nothing.

use pwm_actuator::core::Level;
use pwm_actuator::output::gpio::{electrical_high, GpioError, GpioLine, GpioOutput, CONSUMER};
use pwm_actuator::output::{LineChange, Output};
use std::fs;
use std::path::{Path, PathBuf};

const CONFIGFS: &str = "/sys/kernel/config/gpio-sim";

/// A gpio-sim chip found or created for the test.
struct SimChip {
    /// `/dev/gpiochipN`.
    dev: PathBuf,
    /// The chip's sysfs directory holding `sim_gpioN/`.
    sysfs: PathBuf,
    /// Set when this test created the chip (removed on drop).
    _created: Option<ConfigfsChip>,
}

impl SimChip {
    /// Electrical level of a line as the simulator sees it (`true` = high).
    fn electrical(&self, offset: u32) -> bool {
        let path = self.sysfs.join(format!("sim_gpio{offset}/value"));
        let text = fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
        match text.trim() {
            "1" => true,
            "0" => false,
            other => panic!("unexpected value {other:?} in {}", path.display()),
        }
    }
}

/// A gpio-sim device created through configfs; torn down on drop.
struct ConfigfsChip {
    dir: PathBuf,
}

impl Drop for ConfigfsChip {
    fn drop(&mut self) {
        let _ = fs::write(self.dir.join("live"), "0");
        let _ = fs::remove_dir(self.dir.join("bank0"));
        let _ = fs::remove_dir(&self.dir);
    }
}

fn create_via_configfs() -> Option<SimChip> {
    if !Path::new(CONFIGFS).is_dir() {
        return None;
    }
    let dir = Path::new(CONFIGFS).join(format!("pwm-actuator-test-{}", std::process::id()));
    fs::create_dir(&dir).ok()?;
    let created = ConfigfsChip { dir: dir.clone() };
    fs::create_dir(dir.join("bank0")).ok()?;
    fs::write(dir.join("bank0/num_lines"), "4").ok()?;
    fs::write(dir.join("bank0/label"), "gpio-sim-pwm-actuator").ok()?;
    fs::write(dir.join("live"), "1").ok()?;
    let chip_name = fs::read_to_string(dir.join("bank0/chip_name")).ok()?;
    let dev_name = fs::read_to_string(dir.join("dev_name")).ok()?;
    let (chip_name, dev_name) = (chip_name.trim(), dev_name.trim());
    Some(SimChip {
        dev: Path::new("/dev").join(chip_name),
        sysfs: Path::new("/sys/devices/platform")
            .join(dev_name)
            .join(chip_name),
        _created: Some(created),
    })
}

/// An existing chip whose label starts with `gpio-sim` and that has the simulator's sysfs
/// attributes for at least three lines.
fn find_existing() -> Option<SimChip> {
    let entries = fs::read_dir("/sys/bus/gpio/devices").ok()?;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if !name.starts_with("gpiochip") {
            continue;
        }
        let sysfs = entry.path();
        if !(0..3).all(|o| sysfs.join(format!("sim_gpio{o}/value")).exists()) {
            continue;
        }
        let dev = Path::new("/dev").join(&name);
        let Ok(chip) = gpiocdev::Chip::from_path(&dev) else {
            continue;
        };
        let Ok(info) = chip.info() else { continue };
        if !info.label.starts_with("gpio-sim") {
            continue;
        }
        let free = (0..3).all(|o| chip.line_info(o).map(|i| !i.used).unwrap_or(false));
        if free {
            return Some(SimChip {
                dev,
                sysfs,
                _created: None,
            });
        }
    }
    None
}

fn line(name: &str, chip: &Path, offset: u32, active_low: bool) -> GpioLine {
    GpioLine {
        name: name.into(),
        chip: chip.to_path_buf(),
        offset,
        active_low,
    }
}

fn change(line: usize, level: Level) -> LineChange {
    LineChange {
        line,
        level,
        scheduled_ns: 0,
    }
}

/// Needs a gpio-sim chip, so it is ignored by default rather than reported as passed where
/// none exists. `scripts/test.sh` runs it (with `--ignored`) when the machine offers gpio-sim;
/// run explicitly without one, it fails and says why.
#[test]
#[ignore = "needs a gpio-sim chip (gpio-sim kernel module); scripts/test.sh runs it where one exists"]
fn gpio_output_drives_gpio_sim_lines() {
    let Some(sim) = create_via_configfs().or_else(find_existing) else {
        panic!("no gpio-sim chip on this machine (needs the gpio-sim kernel module)");
    };
    println!("using gpio-sim chip {}", sim.dev.display());

    // pw02 is active-low: the kernel inverts it, the trait stays logical.
    let polarity = [false, true, false];
    let lines: Vec<GpioLine> = ["pw01", "pw02", "pw03"]
        .iter()
        .zip(polarity)
        .enumerate()
        .map(|(i, (name, active_low))| line(name, &sim.dev, i as u32, active_low))
        .collect();
    let expect = |levels: [Level; 3], what: &str| {
        for (i, level) in levels.iter().enumerate() {
            assert_eq!(
                sim.electrical(i as u32),
                electrical_high(*level, polarity[i]),
                "line {i} after {what}"
            );
        }
    };
    use Level::{High, Low};

    let mut out = match GpioOutput::open(&lines) {
        Ok(out) => out,
        Err(e) => panic!("opening the gpio-sim lines failed: {e:?}"),
    };
    assert_eq!(out.line_count(), 3);
    assert_eq!(out.chips().len(), 1, "one request for the chip");
    expect([Low, Low, Low], "open (requested inactive)");

    let chip = gpiocdev::Chip::from_path(&sim.dev).unwrap();
    for (i, active_low) in polarity.iter().enumerate() {
        let info = chip.line_info(i as u32).unwrap();
        assert!(info.used);
        assert_eq!(info.consumer, CONSUMER);
        assert_eq!(info.direction, gpiocdev::line::Direction::Output);
        assert_eq!(info.active_low, *active_low, "line {i}");
    }

    out.set_levels(&[change(0, High), change(1, High)]).unwrap();
    expect([High, High, Low], "pw01+pw02 on in one call");
    out.set_levels(&[change(1, Low), change(2, High)]).unwrap();
    expect([High, Low, High], "pw02 off, pw03 on");
    out.set_all_inactive().unwrap();
    expect([Low, Low, Low], "set_all_inactive");
    assert!(matches!(
        out.set_levels(&[change(3, High)]),
        Err(GpioError::UnknownLine { line: 3, count: 3 })
    ));

    // The emergency handle switches off from another thread and latches.
    out.set_levels(&[change(0, High), change(2, High)]).unwrap();
    expect([High, Low, High], "before emergency off");
    let off = out.emergency_off();
    let off2 = off.clone();
    std::thread::spawn(move || off2.all_inactive())
        .join()
        .unwrap();
    expect([Low, Low, Low], "emergency off");
    assert!(matches!(
        out.set_levels(&[change(0, High)]),
        Err(GpioError::Tripped)
    ));
    expect([Low, Low, Low], "write refused after emergency off");
    drop(out);
    drop(off);

    // Drop drives inactive before release: observed while an emergency handle keeps the
    // request alive.
    let mut out = GpioOutput::open(&lines).unwrap();
    out.set_levels(&[change(0, High), change(1, High), change(2, High)])
        .unwrap();
    expect([High, High, High], "all on");
    let keep = out.emergency_off();
    drop(out);
    expect([Low, Low, Low], "drop");
    assert!(chip.line_info(0).unwrap().used, "still held by the handle");
    drop(keep);
    assert!(
        !chip.line_info(0).unwrap().used,
        "released with the last handle"
    );
}
