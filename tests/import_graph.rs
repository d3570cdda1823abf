//! Modules import downwards only: the graph of `crate::` and `super::` paths between the
//! files of `src/` has no cycle, neither between files nor between top-level folders
//! (ARCHITECTURE.md, "What may import what").
//!
//! Read as text, the way a reader meets the imports: every `crate::...` and `super::...`
//! path outside comments and before a file's `#[cfg(test)]` module (in `use` lines,
//! grouped `{...}` included, and inline in code) is an edge from the file to the file
//! that defines the longest prefix of the path. A folder's `mod.rs` (and `lib.rs`) only
//! declares and re-exports its children: its edges into its own folder are not counted.
//! `main.rs`, `cli.rs` and `cli_reference.rs` are the binary (they import `persist::`).
//!
//! Allowed, each with its reason (the test fails when one disappears, so the list only
//! shrinks):
//! - `model/effects/` and `sim/effects/`: a folder of plug-ins implements its parent's
//!   `Effect` trait, and the parent looks them up by name (the registry).
//! - `measure/eval.rs` <-> `measure/spread.rs`: `eval::rss_cells` widens the cells with
//!   `spread::model_cell_z`; moving it to `spread.rs` changes its public path
//!   (`diag::eval::rss_cells`), which callers outside `measure/` use.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

const BINARY: [&str; 3] = ["main.rs", "cli.rs", "cli_reference.rs"];

const ALLOWED: [&[&str]; 3] = [
    &[
        "model/effect.rs",
        "model/effects/mod.rs",
        "model/params.rs",
        "model/response.rs",
    ],
    &["sim/effect.rs", "sim/effects/mod.rs"],
    &["measure/eval.rs", "measure/spread.rs"],
];

fn rs_files(dir: &Path, root: &Path, out: &mut BTreeMap<String, String>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            rs_files(&p, root, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            let rel = p
                .strip_prefix(root)
                .unwrap()
                .to_string_lossy()
                .replace('\\', "/");
            out.insert(rel, std::fs::read_to_string(&p).unwrap());
        }
    }
}

/// The module path of a file: `a/b.rs` and `a/b/mod.rs` are `[a, b]`, `lib.rs` is `[]`.
fn module_of(file: &str) -> Vec<String> {
    let mut parts: Vec<String> = file
        .trim_end_matches(".rs")
        .split('/')
        .map(String::from)
        .collect();
    if matches!(parts.last().map(String::as_str), Some("mod" | "lib")) {
        parts.pop();
    }
    parts
}

/// The file that defines the longest prefix of `segs`.
fn file_of(files: &BTreeMap<String, String>, segs: &[String]) -> Option<String> {
    for n in (0..=segs.len()).rev() {
        let base = segs[..n].join("/");
        let candidates = if n == 0 {
            vec!["lib.rs".to_string()]
        } else {
            vec![format!("{base}.rs"), format!("{base}/mod.rs")]
        };
        if let Some(c) = candidates.into_iter().find(|c| files.contains_key(c)) {
            return Some(c);
        }
    }
    None
}

fn is_ident(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// The paths of the tree that starts at `s[i..]` after `prefix::` (one path, or a
/// `{...}` group); returns where it ends.
fn paths(s: &[char], mut i: usize, prefix: &[String], out: &mut Vec<Vec<String>>) -> usize {
    let mut segs = prefix.to_vec();
    loop {
        let start = i;
        while i < s.len() && is_ident(s[i]) {
            i += 1;
        }
        if i == start {
            if i < s.len() && s[i] == '{' {
                i += 1;
                loop {
                    while i < s.len() && (s[i].is_whitespace() || s[i] == ',') {
                        i += 1;
                    }
                    if i >= s.len() || s[i] == '}' {
                        return i + 1;
                    }
                    let before = i;
                    i = paths(s, i, &segs, out);
                    if i == before {
                        i += 1;
                    }
                }
            }
            out.push(segs);
            return i;
        }
        let word: String = s[start..i].iter().collect();
        if word != "self" {
            segs.push(word);
        }
        if s.get(i) == Some(&':') && s.get(i + 1) == Some(&':') {
            i += 2;
            continue;
        }
        out.push(segs);
        return i;
    }
}

/// The code of a file as the graph reads it: comment lines and the test module left out.
fn code_of(text: &str) -> Vec<char> {
    let mut code = String::new();
    for line in text.lines() {
        if line.starts_with("#[cfg(test)]") {
            break;
        }
        if line.trim_start().starts_with("//") {
            continue;
        }
        code.push_str(line);
        code.push('\n');
    }
    code.chars().collect()
}

fn edges(files: &BTreeMap<String, String>) -> BTreeMap<String, BTreeSet<String>> {
    let mut graph = BTreeMap::new();
    for (file, text) in files {
        if BINARY.contains(&file.as_str()) {
            continue;
        }
        let code = code_of(text);
        let me = module_of(file);
        let mut targets = BTreeSet::new();
        let mut i = 0;
        while i < code.len() {
            let boundary = i == 0 || !(is_ident(code[i - 1]) || code[i - 1] == ':');
            let rest = |w: &str| code[i..].iter().take(w.len()).copied().eq(w.chars());
            let (base, mut j) = if boundary && rest("crate::") {
                (Vec::new(), i + 7)
            } else if boundary && rest("super::") {
                (me[..me.len().saturating_sub(1)].to_vec(), i + 7)
            } else {
                i += 1;
                continue;
            };
            let mut base = base;
            while code[j..].iter().take(7).copied().eq("super::".chars()) {
                base.pop();
                j += 7;
            }
            let mut found = Vec::new();
            i = paths(&code, j, &base, &mut found).max(i + 1);
            for segs in found {
                if let Some(t) = file_of(files, &segs).filter(|t| t != file) {
                    targets.insert(t);
                }
            }
        }
        if file.ends_with("mod.rs") || file == "lib.rs" {
            let dir = file.rsplit_once('/').map_or("", |(d, _)| d);
            targets.retain(|t| !(dir.is_empty() || t.starts_with(&format!("{dir}/"))));
        }
        graph.insert(file.clone(), targets);
    }
    graph
}

/// The strongly connected components with more than one node (Tarjan).
fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    struct T<'g> {
        g: &'g BTreeMap<String, BTreeSet<String>>,
        index: BTreeMap<&'g str, usize>,
        low: BTreeMap<&'g str, usize>,
        stack: Vec<&'g str>,
        on: BTreeSet<&'g str>,
        out: Vec<Vec<String>>,
    }
    fn visit<'g>(t: &mut T<'g>, v: &'g str) {
        let n = t.index.len();
        t.index.insert(v, n);
        t.low.insert(v, n);
        t.stack.push(v);
        t.on.insert(v);
        let g = t.g;
        for w in g.get(v).into_iter().flatten() {
            if !t.index.contains_key(w.as_str()) {
                visit(t, w);
                let lw = t.low[w.as_str()];
                let lv = t.low[v];
                t.low.insert(v, lv.min(lw));
            } else if t.on.contains(w.as_str()) {
                let iw = t.index[w.as_str()];
                let lv = t.low[v];
                t.low.insert(v, lv.min(iw));
            }
        }
        if t.low[v] == t.index[v] {
            let mut comp = Vec::new();
            while let Some(w) = t.stack.pop() {
                t.on.remove(w);
                comp.push(w.to_string());
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                t.out.push(comp);
            }
        }
    }
    let mut t = T {
        g: graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !t.index.contains_key(v.as_str()) {
            visit(&mut t, v);
        }
    }
    t.out.sort();
    t.out
}

fn folder(file: &str) -> String {
    file.split_once('/')
        .map_or(file.trim_end_matches(".rs"), |(d, _)| d)
        .to_string()
}

fn src_graph() -> BTreeMap<String, BTreeSet<String>> {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut files = BTreeMap::new();
    rs_files(&root, &root, &mut files);
    edges(&files)
}

#[test]
fn no_file_imports_a_file_that_imports_it_back() {
    let graph = src_graph();
    let mut allowed: Vec<Vec<String>> = ALLOWED
        .iter()
        .map(|c| c.iter().map(|s| s.to_string()).collect())
        .collect();
    allowed.sort();
    let found = cycles(&graph);
    let unexpected: Vec<_> = found.iter().filter(|c| !allowed.contains(c)).collect();
    assert!(
        unexpected.is_empty(),
        "import cycles between files of src/: {unexpected:?}"
    );
    let gone: Vec<_> = allowed.iter().filter(|c| !found.contains(c)).collect();
    assert!(
        gone.is_empty(),
        "these allowed cycles are gone: remove them from ALLOWED: {gone:?}"
    );
}

#[test]
fn no_folder_imports_a_folder_that_imports_it_back() {
    let mut folders: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (a, targets) in src_graph() {
        for b in targets {
            if folder(&a) != folder(&b) {
                folders.entry(folder(&a)).or_default().insert(folder(&b));
            }
        }
    }
    assert_eq!(cycles(&folders), Vec::<Vec<String>>::new());
    // the model is at the bottom: it imports no other part of the crate but the shared
    // error type, units, statistics and flag bit names
    let model: BTreeSet<&str> = folders
        .get("model")
        .into_iter()
        .flatten()
        .map(String::as_str)
        .collect();
    assert!(
        model
            .iter()
            .all(|f| ["error", "units", "lib", "stats", "flags"].contains(f)),
        "model/ imports {model:?}"
    );
}

#[test]
fn the_reader_sees_a_cycle_it_is_shown() {
    // A check that could be false: a planted two-file cycle is found.
    let mut files = BTreeMap::new();
    files.insert("lib.rs".to_string(), "pub mod a;\n".to_string());
    files.insert(
        "a/mod.rs".to_string(),
        "pub mod x;\npub mod y;\n".to_string(),
    );
    files.insert(
        "a/x.rs".to_string(),
        "use super::y::Y;\npub struct X;\n".to_string(),
    );
    files.insert(
        "a/y.rs".to_string(),
        "use crate::a::{x::X, self};\n// use super::nothing;\npub struct Y;\n".to_string(),
    );
    let found = cycles(&edges(&files));
    assert_eq!(
        found,
        vec![vec!["a/x.rs".to_string(), "a/y.rs".to_string()]]
    );
}
