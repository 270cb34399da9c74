//! The parameter reference page, `docs/parameters.md`, rendered from the one table of
//! parameters ([`table`](super::table)): every declared parameter with its type, default,
//! range, whether it can change while the node runs, its description and the rules its range
//! cannot express. `cargo run --example parameter_reference` writes the page; a test fails
//! while the page in the repository differs from what the table gives.
//!
//! Only text: nothing here declares, checks or serves a parameter.

use super::table::{self, Checked, Decl};
use super::{show_value, ParamType, Range};
use std::fmt::Write;

/// Where the page lives, relative to the repository root.
pub const REFERENCE_PATH: &str = "docs/parameters.md";

/// The command that regenerates the page.
pub const REFERENCE_COMMAND: &str = "cargo run --example parameter_reference";

/// What the page says before the tables; the rules that hold for every parameter.
const INTRO: &str = "\
The node's parameters: node-level ones by their name, channel ones as `pwNN.<name>` \
(`pw01.period_ms`). Served by the standard parameter services (`~/get_parameters`, \
`~/set_parameters`, `~/set_parameters_atomically`, `~/list_parameters`, \
`~/describe_parameters`, `~/get_parameter_types`) with the descriptions and ranges below, so \
`ros2 param describe` shows them too. What the channel parameters do together is in \
[channels.md](channels.md); the protections of the load in [protections.md](protections.md); \
how to set them at start-up in [interface.md](interface.md#command-line) and \
[deployment.md](deployment.md#2-the-parameter-file).

- **Checked whole.** A request is checked as one change, across parameters (a relay's \
`min_on_ms` against its `output_kind`, the minima against the period, and every other limit), \
before anything changes. A refused request changes nothing and says why \
(`successful=False, reason=...`); the old values stay.
- **Types.** An integer parameter accepts a double that is a whole number (`500.0` becomes \
`500`) and a double parameter accepts an integer (`1` becomes `1.0`); the log says so. \
Anything else of the wrong type is refused.
- **Start-up only** parameters are set by the command line, `-p` and `--params-file`; a live \
change to another value is refused with the reason. The others can be changed while running \
(`ros2 param set /pwm_actuator pw01.period_ms 2000`). A channel parameter takes effect at the \
next period boundary unless its details say otherwise (under `apply_at: immediate`, at once), \
never with a pulse or break below its minimum; a node parameter takes effect at once unless \
its details say otherwise (a new `status_rate_hz` applies at once, a new `phase` at each \
channel's next period start).
- **Several at once.** `~/<ch>/params` (`pwm_actuator_msgs/ChannelParams`) sets the channel \
parameters whose details say *Also on `~/<ch>/params`* in one message, applied atomically or \
refused whole.
- **Large requests.** A request may name every parameter at once (`ros2 param dump` does): \
replies larger than one datagram are sent in fragments, which rclpy (Fast DDS) clients \
receive since the DATA_FRAG fix in the vendored RustDDS \
([vendor/rustdds/README.pwm_actuator.md](../vendor/rustdds/README.pwm_actuator.md)); before \
it, such a reply and every later one to the same client were lost.
- **Minima that together exceed the period** are accepted: every duty other than 0 and 100 % \
then gives 0 or 1 for the period, with E1 ([channels.md](channels.md#minimum-on-and-off-times) \
says which).
";

/// The page, as `docs/parameters.md` must read.
pub fn reference_markdown() -> String {
    let node = table::node_decls();
    let channel = table::channel_decls();
    let valve = table::valve_decls();
    let mut page = String::new();
    page.push_str("# Parameters\n\n");
    let _ = writeln!(
        page,
        "<!-- Generated from src/ros/config/params/table.rs by `{REFERENCE_COMMAND}`. \
         Do not edit: a test fails while this page differs from the table. -->\n"
    );
    page.push_str(INTRO);
    summary(
        &mut page,
        "Node parameters",
        "Set once per node.",
        &node,
        "",
    );
    summary(
        &mut page,
        "Channel parameters",
        "Set per channel as `pwNN.<name>`: `pw01.period_ms`, `pw02.profile`, ...",
        &channel,
        "",
    );
    summary(
        &mut page,
        "Valve parameters",
        "Set per valve of the `valve` parameter as `NAME.<name>`: `mix.travel_open_ms`, ... \
         ([valve.md](valve.md) says what each does and where it comes from).",
        &valve,
        "NAME.",
    );
    page.push_str("\n## Details\n");
    for d in &node {
        details(&mut page, d, d.suffix);
    }
    for d in &channel {
        details(&mut page, d, &format!("pwNN.{}", d.suffix));
    }
    for d in &valve {
        details_titled(&mut page, d, &format!("NAME.{}", d.suffix), true);
    }
    page
}

/// A section with one summary row per parameter.
fn summary(page: &mut String, title: &str, lead: &str, decls: &[Decl], prefix: &str) {
    let _ = writeln!(page, "\n## {title}\n\n{lead}\n");
    page.push_str("| parameter | type | default | range | changes |\n");
    page.push_str("|---|---|---|---|---|\n");
    for d in decls {
        let _ = writeln!(
            page,
            "| [`{prefix}{name}`](#{anchor}) | {ty} | `{default}` | {range} | {changes} |",
            name = d.suffix,
            anchor = format!("{prefix}{}", d.suffix)
                .replace('.', "")
                .to_lowercase(),
            ty = type_name(d.ptype),
            default = show_value(&(d.default)()),
            range = cell(&range_text(d)),
            changes = if d.read_only.is_some() {
                "start-up only"
            } else {
                "while running"
            },
        );
    }
}

/// One parameter's description and rules; `name` is how it is set (`pwNN.` for a channel's).
fn details(page: &mut String, d: &Decl, name: &str) {
    details_titled(page, d, name, false);
}

/// [`details`], titled with the name as set (`titled`) rather than the bare suffix.
fn details_titled(page: &mut String, d: &Decl, name: &str, titled: bool) {
    let title = if titled { name } else { d.suffix };
    let _ = writeln!(page, "\n### {title}\n");
    let _ = writeln!(
        page,
        "`{name}`, {ty}, default `{default}`.\n\n{description}\n",
        ty = type_name(d.ptype),
        default = show_value(&(d.default)()),
        description = text(d.description),
    );
    let range = range_text(d);
    if range != "–" {
        let _ = writeln!(page, "- Range: {range}.");
    }
    if !d.constraints.is_empty() {
        let _ = writeln!(page, "- Rules: {}.", text(d.constraints));
    }
    match d.read_only {
        Some(why) => {
            let _ = writeln!(page, "- Start-up only: {}.", text(why));
        }
        None => page.push_str("- Can be changed while running.\n"),
    }
    if d.msg.is_some() {
        page.push_str("- Also on `~/<ch>/params`.\n");
    }
}

/// The type as `ros2 param describe` names it.
fn type_name(t: ParamType) -> &'static str {
    match t {
        ParamType::Bool => "bool",
        ParamType::Integer => "integer",
        ParamType::Double => "double",
        ParamType::String => "string",
    }
}

/// The advertised range (`from..to`, both inclusive), `0, or from..to` for a value whose 0
/// means off, or `–` without one.
fn range_text(d: &Decl) -> String {
    let (from, to) = match d.range {
        Range::Unbounded => return "–".into(),
        Range::Integer(from, to) => (from.to_string(), to.to_string()),
        Range::Double(from, to) => (from.to_string(), to.to_string()),
    };
    match d.checked {
        Checked::OffOr(min) => format!("0, or {min}..{to}"),
        Checked::Range | Checked::Core => format!("{from}..{to}"),
    }
}

/// Table-cell text: a `|` would end the cell.
fn cell(s: &str) -> String {
    text(s).replace('|', "\\|")
}

/// Prose for Markdown: outside code spans a `<` would open an HTML tag (`~/<ch>/duty` would
/// lose `<ch>`), so it is written as an entity; inside code spans it stays.
fn text(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut in_code = false;
    for ch in s.chars() {
        match ch {
            '`' => {
                in_code = !in_code;
                out.push(ch);
            }
            '<' if !in_code => out.push_str("&lt;"),
            _ => out.push(ch),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::ParameterValue as V;

    /// The page in the repository.
    const PAGE: &str = include_str!("../../../../docs/parameters.md");

    /// `docs/parameters.md` is exactly what the table gives; when the table changes, the page
    /// must be regenerated with the command the message names.
    #[test]
    fn the_parameter_page_is_generated_from_the_table() {
        let want = reference_markdown();
        if PAGE != want {
            let (line, (have, wanted)) = PAGE
                .lines()
                .chain(std::iter::repeat("<end of page>"))
                .zip(want.lines().chain(std::iter::repeat("<end of page>")))
                .enumerate()
                .find(|(_, (a, b))| a != b)
                .unwrap_or((0, ("<same lines>", "<a different ending>")));
            panic!(
                "{REFERENCE_PATH} is stale: regenerate it with `{REFERENCE_COMMAND}`.\n\
                 First difference, line {}:\n  page:  {have}\n  table: {wanted}",
                line + 1
            );
        }
    }

    /// The page's summary tables list exactly the declared parameters, each with its type,
    /// its default and whether it can change while running, as the table says: a check of the
    /// page as a reader sees it, independent of how it was rendered.
    #[test]
    fn the_parameter_page_lists_every_declared_parameter() {
        let mut rows = std::collections::BTreeMap::new();
        for line in PAGE.lines().filter(|l| l.starts_with("| [`")) {
            let cells: Vec<&str> = line.split(" | ").map(str::trim).collect();
            let name = cells[0]
                .trim_start_matches("| [`")
                .split('`')
                .next()
                .unwrap_or_default()
                .to_string();
            let row = (cells[1], cells[2].trim_matches('`'), cells[4]);
            assert!(rows.insert(name.clone(), row).is_none(), "{name} twice");
        }
        let declared: Vec<(Decl, &str)> = table::node_decls()
            .into_iter()
            .chain(table::channel_decls())
            .map(|d| (d, ""))
            .chain(table::valve_decls().into_iter().map(|d| (d, "NAME.")))
            .collect();
        for (d, prefix) in &declared {
            let Some((ty, default, changes)) = rows.remove(&format!("{prefix}{}", d.suffix)) else {
                panic!("{} is declared but not on the page", d.suffix);
            };
            assert_eq!(ty, type_name(d.ptype), "{}: type", d.suffix);
            let same = match (d.default)() {
                V::Boolean(b) => default == b.to_string(),
                V::Integer(i) => default.parse::<i64>() == Ok(i),
                V::Double(x) => default.parse::<f64>() == Ok(x),
                V::String(s) => default == format!("{s:?}"),
                other => panic!("{}: default {other:?}", d.suffix),
            };
            assert!(same, "{}: default on the page {default}", d.suffix);
            let start_up = changes.starts_with("start-up only");
            assert_eq!(start_up, d.read_only.is_some(), "{}: changes", d.suffix);
            assert!(
                PAGE.contains(&format!("\n### {prefix}{}\n", d.suffix)),
                "{}: no details section",
                d.suffix
            );
        }
        assert!(rows.is_empty(), "on the page but not declared: {rows:?}");
    }

    #[test]
    fn prose_keeps_angle_brackets_visible() {
        assert_eq!(
            text("~/<ch>/status and `<node>: <ch>`"),
            "~/&lt;ch>/status and `<node>: <ch>`"
        );
        assert_eq!(cell("sim|gpio"), "sim\\|gpio");
    }
}
