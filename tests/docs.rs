//! The documentation holds together: every `docs/<page>.md#<anchor>` that a code comment
//! cites and every link between the README and the pages lands on a heading that exists,
//! and the README stays a front door.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a Markdown file's headings (outside code blocks).
fn anchors(md: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let mut code = false;
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            code = !code;
        } else if !code && line.starts_with('#') {
            out.insert(slug(line.trim_start_matches('#')));
        }
    }
    out
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// Every `docs/<page>.md` or `docs/<page>.md#<anchor>` in `text`.
fn citations(text: &str) -> Vec<(String, Option<String>)> {
    let mut out = Vec::new();
    for (at, _) in text.match_indices("docs/") {
        let rest = &text[at + 5..];
        let end = rest
            .find(|c: char| !(c.is_alphanumeric() || "-_.#".contains(c)))
            .unwrap_or(rest.len());
        let cite = rest[..end].trim_end_matches('.');
        if let Some((page, anchor)) = cite.split_once('#') {
            out.push((page.to_string(), Some(anchor.to_string())));
        } else if cite.ends_with(".md") {
            out.push((cite.to_string(), None));
        }
    }
    out
}

/// Whether `page` (a file in docs/) has `anchor`; errors say what is missing.
fn check(page: &str, anchor: Option<&str>, from: &str, bad: &mut Vec<String>) {
    let path = root().join("docs").join(page);
    let Ok(md) = std::fs::read_to_string(&path) else {
        bad.push(format!("{from}: docs/{page} does not exist"));
        return;
    };
    if let Some(a) = anchor {
        if !anchors(&md).contains(a) {
            bad.push(format!("{from}: docs/{page} has no heading #{a}"));
        }
    }
}

#[test]
fn headings_become_githubs_anchors() {
    assert_eq!(slug(" Step 8. Merge and join"), "step-8-merge-and-join");
    assert_eq!(slug("The engine contract"), "the-engine-contract");
    assert_eq!(
        slug("Files, frames and the report"),
        "files-frames-and-the-report"
    );
    let md = "# A\n```\n# not a heading\n```\n## Step 2. Radius\n";
    assert_eq!(
        anchors(md),
        ["a", "step-2-radius"]
            .map(String::from)
            .into_iter()
            .collect()
    );
}

#[test]
fn every_page_a_code_comment_cites_has_the_anchor() {
    let mut files = Vec::new();
    rust_files(&root().join("src"), &mut files);
    let mut bad = Vec::new();
    let mut n = 0;
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        for (page, anchor) in citations(&text) {
            n += 1;
            let from = f.strip_prefix(root()).unwrap().display().to_string();
            check(&page, anchor.as_deref(), &from, &mut bad);
        }
    }
    assert!(n >= 50, "only {n} citations found");
    assert!(bad.is_empty(), "{bad:#?}");
}

#[test]
fn a_citation_of_a_missing_heading_is_caught() {
    let mut bad = Vec::new();
    for (page, anchor) in
        citations("see docs/method.md#step-4-translate and docs/method.md#step-11.")
    {
        check(&page, anchor.as_deref(), "here", &mut bad);
    }
    assert_eq!(bad, ["here: docs/method.md has no heading #step-11"]);
}

/// Links `](page.md#anchor)` between the pages (relative to docs/) and from the README
/// (`docs/page.md#anchor`) land on a heading, where the page exists.
#[test]
fn links_between_the_pages_land_on_headings() {
    let mut bad = Vec::new();
    let mut pages: Vec<PathBuf> = std::fs::read_dir(root().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    pages.push(root().join("README.md"));
    for p in &pages {
        let md = std::fs::read_to_string(p).unwrap();
        let in_docs = p.parent().is_some_and(|d| d.ends_with("docs"));
        let from = p.file_name().unwrap().to_string_lossy().into_owned();
        for (at, _) in md.match_indices("](") {
            let rest = &md[at + 2..];
            let link = &rest[..rest.find(')').unwrap_or(rest.len())];
            if link.starts_with("http") || !link.contains(".md") {
                if let Some(a) = link.strip_prefix('#') {
                    if !anchors(&md).contains(a) {
                        bad.push(format!("{from}: no heading #{a}"));
                    }
                }
                continue;
            }
            let (file, anchor) = match link.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (link, None),
            };
            let page = if in_docs {
                file
            } else {
                file.trim_start_matches("docs/")
            };
            // Pages written alongside (evaluation, cluster, python, robustness) are checked
            // once they exist.
            if root().join("docs").join(page).exists() {
                check(page, anchor, &from, &mut bad);
            }
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

/// The README is a front door: short, and no history in it or in the pages (git log
/// holds the history).
#[test]
fn the_readme_is_short_and_nothing_tells_history() {
    let readme = std::fs::read_to_string(root().join("README.md")).unwrap();
    assert!(
        readme.lines().count() <= 250,
        "README.md: {} lines",
        readme.lines().count()
    );
    let mut files = vec![root().join("README.md")];
    for e in std::fs::read_dir(root().join("docs")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "md") {
            files.push(p);
        }
    }
    rust_files(&root().join("src"), &mut files);
    let mut bad = Vec::new();
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap().to_lowercase();
        for word in ["session", "issue #"] {
            if text.contains(word) {
                bad.push(format!("{}: {word}", f.display()));
            }
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}

/// The docs are reference, not a log: each page holds at most one date (when its numbers
/// were measured).
#[test]
fn each_page_holds_at_most_one_date() {
    let mut bad = Vec::new();
    for e in std::fs::read_dir(root().join("docs")).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_none_or(|x| x != "md") {
            continue;
        }
        let text = std::fs::read_to_string(&p).unwrap();
        let b = text.as_bytes();
        // YYYY-MM-DD
        let dates: BTreeSet<&str> = (0..b.len().saturating_sub(9))
            .filter(|&i| {
                let d = |k: usize| b[i + k].is_ascii_digit();
                (i == 0 || !b[i - 1].is_ascii_alphanumeric())
                    && d(0)
                    && d(1)
                    && d(2)
                    && d(3)
                    && b[i + 4] == b'-'
                    && d(5)
                    && d(6)
                    && b[i + 7] == b'-'
                    && d(8)
                    && d(9)
            })
            .map(|i| &text[i..i + 10])
            .collect();
        let count = (0..b.len().saturating_sub(9))
            .filter(|&i| dates.contains(&text.get(i..i + 10).unwrap_or("")))
            .count();
        if count > 1 {
            bad.push(format!("{}: {count} dates {dates:?}", p.display()));
        }
    }
    assert!(bad.is_empty(), "{bad:#?}");
}
