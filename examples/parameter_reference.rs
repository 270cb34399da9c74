//! Writes the parameter reference page, `docs/parameters.md`, from the node's parameter table
//! (`src/ros/config/params/table.rs`). Run it after changing a parameter:
//!
//! ```sh
//! cargo run --example parameter_reference
//! ```
//!
//! A unit test fails while the page in the repository differs from what this writes.

use pwm_actuator::ros::config::params::{reference_markdown, REFERENCE_PATH};
use std::path::Path;

fn main() -> std::io::Result<()> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(REFERENCE_PATH);
    std::fs::write(&path, reference_markdown())?;
    println!("wrote {}", path.display());
    Ok(())
}
