//! The documentation holds together: the README stays short and links every page, and every
//! relative link in the README, CONTRIBUTING.md, `docs/` and `launch-notes/` leads to a file that
//! exists and, where it names a heading (`page.md#heading`), to a heading of that page.
//!
//! (The parameter page is compared with the parameter table in `ros::config::params::reference`.)

use std::collections::BTreeSet;
use std::fs;
use std::path::{Path, PathBuf};

/// The README's size limit, bytes: what it is, one picture, the two commands, a quick start, the
/// tables, the links. The rest belongs in `docs/`.
const README_MAX_BYTES: usize = 12 * 1024;
/// A note in the README's table of topics and services is read at a glance.
const NOTE_MAX_CHARS: usize = 80;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn read(path: &Path) -> String {
    fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The markdown files of a folder of the repository, sorted.
fn pages(dir: &str) -> Vec<PathBuf> {
    let mut out: Vec<PathBuf> = fs::read_dir(repo().join(dir))
        .unwrap_or_else(|e| panic!("{dir}: {e}"))
        .map(|e| e.expect("a directory entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    out.sort();
    out
}

/// The text outside fenced code blocks (links in code are examples, not links).
fn prose(text: &str) -> String {
    let mut fenced = false;
    let mut out = String::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if !fenced {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// The targets of the inline links and images in `text`: `[label](target)`, `![alt](target)`.
fn link_targets(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut rest = prose(text);
    while let Some(k) = rest.find("](") {
        let after = &rest[k + 2..];
        let end = after.find(')').unwrap_or(after.len());
        // A title after the target (`(target "title")`) is not part of it.
        let target = after[..end].split_whitespace().next().unwrap_or("");
        out.push(target.to_string());
        rest = after[end..].to_string();
    }
    out
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            '-' | '_' => Some(c),
            c if c.is_alphanumeric() => Some(c),
            _ => None,
        })
        .collect()
}

/// The anchors of a page's headings, with GitHub's `-1`, `-2` for repeated ones.
fn anchors(text: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    for line in prose(text).lines() {
        let Some(heading) = line.strip_prefix('#') else {
            continue;
        };
        let base = slug(heading.trim_start_matches('#'));
        let mut anchor = base.clone();
        let mut n = 0;
        while !out.insert(anchor.clone()) {
            n += 1;
            anchor = format!("{base}-{n}");
        }
    }
    out
}

/// The problems with the relative links of the page at `page`.
fn broken_links(page: &Path) -> Vec<String> {
    let text = read(page);
    let dir = page.parent().expect("a page has a folder");
    let mut out = Vec::new();
    for target in link_targets(&text) {
        if target.contains("://") || target.starts_with("mailto:") || target.is_empty() {
            continue;
        }
        let (file, anchor) = match target.split_once('#') {
            Some((f, a)) => (f, Some(a)),
            None => (target.as_str(), None),
        };
        let file_path = if file.is_empty() {
            page.to_path_buf()
        } else {
            dir.join(file)
        };
        if !file_path.exists() {
            out.push(format!("{}: {target}: no such file", page.display()));
            continue;
        }
        if let Some(anchor) = anchor {
            if file_path.extension().is_some_and(|x| x == "md")
                && !anchors(&read(&file_path)).contains(anchor)
            {
                out.push(format!("{}: {target}: no such heading", page.display()));
            }
        }
    }
    out
}

#[test]
fn the_readme_is_at_most_12_kib() {
    let size = read(&repo().join("README.md")).len();
    assert!(
        size <= README_MAX_BYTES,
        "README.md is {size} bytes, more than {README_MAX_BYTES}: move detail to docs/"
    );
}

#[test]
fn the_readme_links_every_page() {
    let readme = read(&repo().join("README.md"));
    let linked: BTreeSet<String> = link_targets(&readme)
        .into_iter()
        .map(|t| t.split('#').next().unwrap_or("").to_string())
        .collect();
    let mut wanted: Vec<String> = pages("docs")
        .iter()
        .map(|p| format!("docs/{}", p.file_name().unwrap().to_string_lossy()))
        .collect();
    wanted.extend(["CONTRIBUTING.md", "CHANGELOG.md", "launch-notes/README.md"].map(String::from));
    let missing: Vec<&String> = wanted.iter().filter(|w| !linked.contains(*w)).collect();
    assert!(missing.is_empty(), "not linked from README.md: {missing:?}");
}

#[test]
fn every_relative_link_leads_to_a_file_and_heading() {
    let mut all = vec![repo().join("README.md"), repo().join("CONTRIBUTING.md")];
    all.extend(pages("docs"));
    all.extend(pages("launch-notes"));
    let broken: Vec<String> = all.iter().flat_map(|p| broken_links(p)).collect();
    assert!(broken.is_empty(), "broken links:\n{}", broken.join("\n"));
}

#[test]
fn the_notes_of_the_topic_table_are_short() {
    let readme = read(&repo().join("README.md"));
    let table = readme
        .split("## Topics and services")
        .nth(1)
        .expect("README.md has a section 'Topics and services'");
    let rows: Vec<&str> = table
        .lines()
        .take_while(|l| !l.starts_with("## "))
        .filter(|l| l.starts_with("| `"))
        .collect();
    assert!(rows.len() >= 10, "the topic table has {} rows", rows.len());
    for row in rows {
        let note = row
            .trim_end_matches('|')
            .rsplit('|')
            .next()
            .unwrap_or("")
            .trim();
        assert!(
            note.chars().count() < NOTE_MAX_CHARS,
            "a note of {} characters: {row}",
            note.chars().count()
        );
    }
}

#[test]
fn the_link_checker_finds_what_it_should() {
    // The checker itself: a heading's anchor, a repeated heading, a link inside code ignored.
    let page =
        "# A title\n## Run it: `ros2` (CLI)\n## Run it: `ros2` (CLI)\n```\n[x](nowhere.md)\n```\n";
    let a = anchors(page);
    assert!(a.contains("a-title"), "{a:?}");
    assert!(
        a.contains("run-it-ros2-cli") && a.contains("run-it-ros2-cli-1"),
        "{a:?}"
    );
    assert!(link_targets(page).is_empty());
    assert_eq!(
        link_targets("see [a](b.md#c \"t\") and ![p](d.png)"),
        vec!["b.md#c".to_string(), "d.png".to_string()]
    );
}
