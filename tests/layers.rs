//! The layers only go down (docs/architecture.md#layers): the storage and query layers
//! (`src/engine`, `src/index`, `src/io`, `src/geom`) name nothing of the refinement, the
//! pipeline or the command line, and the library knows neither the command line (`clap`)
//! nor the process environment (`std::env::var`): only `src/cmd` and `src/main.rs` do.
//! And no two files (or folders) of one folder name each other, directly or around a
//! circle: between siblings the names go one way.
//! Read from the source text: every path through `crate::`, `self::` or `super::` in code
//! (comments and the `#[cfg(test)]` module at a file's end aside), resolved to the
//! top-level module it names (the layers) or to the sibling it names (the circles).

use std::path::{Path, PathBuf};

/// Layers that must not name [`UPPER`].
const LOWER: &[&str] = &["engine", "index", "io", "geom"];
/// What the lower layers must not name.
const UPPER: &[&str] = &["refine", "pipeline", "cmd"];

/// Edges from a lower layer up that exist today and are being removed: `(layer, path)`,
/// a path allowed to be named from that layer, itself and anything under it. Delete an
/// entry when the edge is gone (the test then keeps it gone).
const ALLOWED_UP: &[(&str, &str)] = &[];

/// Import circles between siblings that exist today in other parts of the tree and are
/// being removed, each as its members (module paths, sorted). The list only shrinks: a
/// circle not in it, or larger than its entry, fails the test; delete an entry when its
/// circle is gone (the test then says so).
const KNOWN_CIRCLES: &[&[&str]] = &[];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
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

/// The module path of a file under `src/` (`src/engine/gpu/mod.rs` -> `engine::gpu`).
fn module_of(rel: &Path) -> Vec<String> {
    let mut parts: Vec<String> = rel
        .iter()
        .skip(1)
        .map(|s| s.to_string_lossy().trim_end_matches(".rs").to_string())
        .collect();
    if matches!(
        parts.last().map(String::as_str),
        Some("mod" | "lib" | "main")
    ) {
        parts.pop();
    }
    parts
}

/// The code of a file: the lines before its `#[cfg(test)]` module, each without its `//`
/// comment, numbered from 1.
fn code_lines(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim_start().starts_with("#[cfg(test)]") {
            break;
        }
        let code = match line.find("//") {
            Some(k) => &line[..k],
            None => line,
        };
        out.push((i + 1, code.to_string()));
    }
    out
}

fn ident(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// The paths `s` starts with: `a::b::c(...)` gives `a::b::c`, `a::{b, c::d}` gives
/// `a::b` and `a::c::d`.
fn expand(s: &str) -> Vec<Vec<String>> {
    let mut prefix = Vec::new();
    let mut s = s.trim_start();
    loop {
        if let Some(group) = s.strip_prefix('{') {
            let mut out = Vec::new();
            let (mut depth, mut start) = (0, 0);
            for (k, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        out.push(&group[start..k]);
                        break;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        out.push(&group[start..k]);
                        start = k + 1;
                    }
                    _ => {}
                }
            }
            return out
                .into_iter()
                .flat_map(expand)
                .filter(|t| !t.is_empty())
                .map(|t| prefix.iter().cloned().chain(t).collect())
                .collect();
        }
        let id = ident(s);
        if id.is_empty() {
            return vec![prefix];
        }
        prefix.push(id.to_string());
        match s[id.len()..].strip_prefix("::") {
            Some(rest) => s = rest.trim_start(),
            None => return vec![prefix],
        }
    }
}

/// Every path that `code` names from `crate`, `self` or `super`, made absolute from the
/// module `module` (`use crate::{a::b, c}` names `a::b` and `c`).
fn paths(code: &str, module: &[String]) -> Vec<String> {
    let mut out = Vec::new();
    let bytes = code.as_bytes();
    let mut i = 0;
    while i < code.len() {
        if !code.is_char_boundary(i) {
            i += 1;
            continue;
        }
        let rest = &code[i..];
        let starts_word = i == 0 || !(bytes[i - 1].is_ascii_alphanumeric() || bytes[i - 1] == b'_');
        let head = ["crate::", "self::", "super::"]
            .into_iter()
            .find(|h| starts_word && rest.starts_with(h));
        let Some(head) = head else {
            i += 1;
            continue;
        };
        // Resolve the leading `crate::` / `self::` / `super::...` segments.
        let mut base: Vec<String> = module.to_vec();
        let mut j = i;
        if head == "crate::" {
            base.clear();
            j += head.len();
        } else {
            loop {
                if code[j..].starts_with("super::") {
                    base.pop();
                    j += "super::".len();
                } else if code[j..].starts_with("self::") {
                    j += "self::".len();
                } else {
                    break;
                }
            }
        }
        for tail in expand(&code[j..]) {
            if tail.is_empty() || tail[0] == "self" {
                continue;
            }
            let mut p = base.clone();
            p.extend(tail);
            out.push(p.join("::"));
        }
        i = j.max(i + 1);
    }
    out
}

/// Every rule broken in the files under `src/`, as `file:line: ...`.
fn violations(allowed: &[(&str, &str)]) -> Vec<String> {
    let mut files = Vec::new();
    rust_files(&root().join("src"), &mut files);
    files.sort();
    let mut bad = Vec::new();
    for f in files {
        let rel = f.strip_prefix(root()).unwrap().to_path_buf();
        let module = module_of(&rel);
        let text = std::fs::read_to_string(&f).unwrap();
        let layer = module.first().cloned().unwrap_or_default();
        let front_end = layer == "cmd" || rel == Path::new("src/main.rs");
        for (n, code) in code_lines(&text) {
            let at = format!("{}:{n}", rel.display());
            if !front_end {
                let words: Vec<&str> = code
                    .split(|c: char| !(c.is_alphanumeric() || c == '_'))
                    .collect();
                if words.contains(&"clap") {
                    bad.push(format!("{at}: names clap: {}", code.trim()));
                }
                if code.contains("env::var") {
                    bad.push(format!("{at}: reads the environment: {}", code.trim()));
                }
            }
            if !LOWER.contains(&layer.as_str()) {
                continue;
            }
            for p in paths(&code, &module) {
                let top = p.split("::").next().unwrap_or("");
                if !UPPER.contains(&top) {
                    continue;
                }
                let ok = allowed
                    .iter()
                    .any(|(l, a)| *l == layer && (p == *a || p.starts_with(&format!("{a}::"))));
                if !ok {
                    bad.push(format!("{at}: {layer} names {p}"));
                }
            }
        }
    }
    bad
}

/// The module of every file under `src/` (`engine::gpu` for `src/engine/gpu/mod.rs`).
fn modules() -> Vec<(PathBuf, Vec<String>)> {
    let mut files = Vec::new();
    rust_files(&root().join("src"), &mut files);
    files.sort();
    files
        .into_iter()
        .map(|f| {
            let rel = f.strip_prefix(root()).unwrap().to_path_buf();
            let m = module_of(&rel);
            (f, m)
        })
        .collect()
}

/// The edges between siblings: `a -> b` when a file in `a` (a file, or a folder and all
/// under it) names something in `b`, `a` and `b` children of one module. A path into a
/// file's own module, or to an item of an enclosing module, is no edge: a folder's
/// `mod.rs` is the interface its files share.
fn sibling_edges() -> Vec<(String, String)> {
    let all = modules();
    let known: std::collections::HashSet<Vec<String>> =
        all.iter().map(|(_, m)| m.clone()).collect();
    let mut edges = std::collections::BTreeSet::new();
    for (f, module) in &all {
        let text = std::fs::read_to_string(f).unwrap();
        for (_, code) in code_lines(&text) {
            for p in paths(&code, module) {
                let p: Vec<String> = p.split("::").map(String::from).collect();
                let k = module.iter().zip(&p).take_while(|(a, b)| a == b).count();
                if k == module.len() || k == p.len() || !known.contains(&p[..=k]) {
                    continue;
                }
                edges.insert((module[..=k].join("::"), p[..=k].join("::")));
            }
        }
    }
    edges.into_iter().collect()
}

/// The circles of `edges`: each strongly connected set of two or more, sorted.
fn circles(edges: &[(String, String)]) -> Vec<Vec<String>> {
    let mut nodes: Vec<&String> = edges.iter().flat_map(|(a, b)| [a, b]).collect();
    nodes.sort();
    nodes.dedup();
    let reach = |from: &String| {
        let mut seen = vec![from.clone()];
        let mut k = 0;
        while k < seen.len() {
            for (a, b) in edges {
                if *a == seen[k] && !seen.contains(b) {
                    seen.push(b.clone());
                }
            }
            k += 1;
        }
        seen
    };
    let mut out: Vec<Vec<String>> = Vec::new();
    for n in &nodes {
        let mut c: Vec<String> = reach(n)
            .into_iter()
            .filter(|m| reach(m).contains(n))
            .collect();
        c.sort();
        if c.len() > 1 && !out.contains(&c) {
            out.push(c);
        }
    }
    out
}

#[test]
fn no_two_siblings_name_each_other() {
    let found = circles(&sibling_edges());
    let within_known = |c: &Vec<String>| {
        KNOWN_CIRCLES
            .iter()
            .any(|k| c.iter().all(|m| k.contains(&m.as_str())))
    };
    let new: Vec<String> = found
        .iter()
        .filter(|c| !within_known(c))
        .map(|c| c.join(" <-> "))
        .collect();
    assert!(new.is_empty(), "import circles:\n{}", new.join("\n"));
    for k in KNOWN_CIRCLES {
        assert!(
            found
                .iter()
                .any(|c| k.iter().all(|m| c.iter().any(|x| x == m))),
            "{k:?} is no longer a circle: delete it from KNOWN_CIRCLES"
        );
    }
}

#[test]
fn the_circle_finder_sees_direct_and_round_circles_only() {
    let e = |v: &[(&str, &str)]| -> Vec<(String, String)> {
        v.iter()
            .map(|(a, b)| (a.to_string(), b.to_string()))
            .collect()
    };
    assert_eq!(
        circles(&e(&[("a", "b"), ("b", "c")])),
        Vec::<Vec<String>>::new()
    );
    assert_eq!(circles(&e(&[("a", "b"), ("b", "a")])), [["a", "b"]]);
    assert_eq!(
        circles(&e(&[("a", "b"), ("b", "c"), ("c", "a"), ("c", "d")])),
        [["a", "b", "c"]]
    );
}

#[test]
fn layers_only_go_down_and_the_library_has_no_command_line() {
    let bad = violations(ALLOWED_UP);
    assert!(bad.is_empty(), "layering broken:\n{}", bad.join("\n"));
}

#[test]
fn every_allowed_edge_still_exists() {
    // An allowance nothing uses hides the next edge of the same kind: delete it.
    let without = violations(&[]);
    for (layer, path) in ALLOWED_UP {
        assert!(
            without
                .iter()
                .any(|v| v.ends_with(&format!("{layer} names {path}"))
                    || v.contains(&format!("{layer} names {path}::"))),
            "({layer}, {path}) is allowed but no longer named: delete it from ALLOWED_UP"
        );
    }
}

#[test]
fn the_reader_resolves_relative_and_grouped_paths() {
    let m: Vec<String> = ["engine", "gpu", "device"].map(String::from).to_vec();
    assert_eq!(
        paths("use super::super::refine::fit;", &m),
        ["engine::refine::fit"]
    );
    let m: Vec<String> = ["engine", "gpu"].map(String::from).to_vec();
    assert_eq!(paths("use super::super::refine::fit;", &m), ["refine::fit"]);
    assert_eq!(
        paths(
            "use crate::{geom::Segment, pipeline, refine::{Params, Fit}};",
            &m
        ),
        ["geom::Segment", "pipeline", "refine::Params", "refine::Fit"]
    );
    assert_eq!(paths("let x = crate::cmd::run(1);", &m), ["cmd::run"]);
    assert_eq!(
        paths("let x = my_crate::cmd::run(1);", &m),
        Vec::<String>::new()
    );
    assert_eq!(module_of(Path::new("src/io/mod.rs")), ["io"]);
    assert_eq!(module_of(Path::new("src/geom.rs")), ["geom"]);
}

/// The fuzz crate compiles `src/geom/` and `src/io/` itself, each root file included with
/// `#[path]` (fuzz/src/lib.rs). A file included that way looks for its own `mod x;` in
/// its own folder (`x.rs` or `x/mod.rs`) whatever its name, where the package looks in
/// `name/` for a `name.rs`: the two builds find the same files only where each included
/// root is a `mod.rs`, or has no modules of its own.
#[test]
fn the_fuzz_crate_finds_every_module_it_includes() {
    let lib = root().join("fuzz/src/lib.rs");
    let text = std::fs::read_to_string(&lib).unwrap();
    let mut roots = 0;
    for line in text.lines() {
        let Some(rest) = line.trim().strip_prefix("#[path = \"") else {
            continue;
        };
        let rel = rest.split('"').next().unwrap();
        let file = lib.parent().unwrap().join(rel);
        let src =
            std::fs::read_to_string(&file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        let dir = file.parent().unwrap();
        for l in code_lines(&src) {
            let l = l.1.trim().to_string();
            let l = l.strip_prefix("pub ").unwrap_or(&l);
            let l = l.strip_prefix("pub(crate) ").unwrap_or(l);
            if let Some(name) = l.strip_prefix("mod ").and_then(|m| m.strip_suffix(';')) {
                assert!(
                    dir.join(format!("{name}.rs")).exists()
                        || dir.join(name).join("mod.rs").exists(),
                    "{}: `mod {name};` is not in {} (the fuzz crate's #[path] include looks there)",
                    file.display(),
                    dir.display()
                );
            }
        }
        roots += 1;
    }
    assert!(roots >= 2, "fuzz/src/lib.rs includes {roots} roots");
}
