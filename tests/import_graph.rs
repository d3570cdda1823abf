//! Modules import downwards only: the graph of `crate::` and `super::` paths between the
//! files of `src/` has no cycle, neither between files nor between top-level folders
//! (ARCHITECTURE.md, "What may import what").
//!
//! Read as text, the way a reader meets the imports: every `crate::...` and `super::...`
//! path outside comments and before a file's `#[cfg(test)]` module (in `use` lines,
//! grouped `{...}` included, and inline in code) is an edge from the file to the file
//! that defines the longest prefix of the path. A name a folder's `mod.rs` (or `lib.rs`)
//! re-exports (`pub use child::Name`) leads on to the file it comes from, so that a
//! re-export hides no cycle. A `mod.rs` only declares and re-exports its children: its
//! edges into its own folder are not counted. `main.rs`, `cli_reference.rs` and the
//! files of `cli/` are the binary (they import `persist::`).
//!
//! No cycle is allowed, not even between a folder of plug-ins and its parent: the
//! registry that maps names to effects lives in the folder of the effects, and the
//! trait's file imports nothing from it (`model/effects/`, `sim/effects/`).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The binary's files (by name, or a folder ending in `/`).
const BINARY: [&str; 3] = ["main.rs", "cli/", "cli_reference.rs"];

fn is_binary(file: &str) -> bool {
    BINARY
        .iter()
        .any(|b| file == *b || (b.ends_with('/') && file.starts_with(b)))
}

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

/// What a folder's `mod.rs` (or `lib.rs`) re-exports: per name the path it stands for;
/// a glob (`pub use path::*`) under the name `*`.
type Reexports = BTreeMap<String, Vec<(String, Vec<String>)>>;

fn is_folder_file(file: &str) -> bool {
    file == "lib.rs" || file.ends_with("/mod.rs")
}

/// The `pub use` paths of every folder file.
fn reexports(files: &BTreeMap<String, String>) -> Reexports {
    let mut out = Reexports::new();
    for (file, text) in files.iter().filter(|(f, _)| is_folder_file(f)) {
        let me = module_of(file);
        let code = code_of(text);
        let mut names = Vec::new();
        let mut i = 0;
        while i < code.len() {
            let starts = |w: &str| code[i..].iter().take(w.len()).copied().eq(w.chars());
            if !(starts("pub use ") && (i == 0 || code[i - 1] == '\n')) {
                i += 1;
                continue;
            }
            let mut j = i + 8;
            let mut base = me.clone();
            if code[j..].iter().take(7).copied().eq("crate::".chars()) {
                base.clear();
                j += 7;
            }
            while code[j..].iter().take(7).copied().eq("super::".chars()) {
                base.pop();
                j += 7;
            }
            let end = code[j..]
                .iter()
                .position(|&c| c == ';')
                .map_or(code.len(), |e| j + e);
            let glob = code[j..end].contains(&'*');
            let mut found = Vec::new();
            paths(&code, j, &base, &mut found);
            for segs in found {
                let name = if glob {
                    "*".to_string()
                } else {
                    segs.last().cloned().unwrap_or_default()
                };
                names.push((name, segs));
            }
            i = end;
        }
        out.insert(file.clone(), names);
    }
    out
}

/// The file that defines the longest prefix of `segs`, following the re-exports of a
/// folder file to the file a name comes from.
fn file_of(files: &BTreeMap<String, String>, re: &Reexports, segs: &[String]) -> Option<String> {
    resolve(files, re, segs, 0)
}

fn resolve(
    files: &BTreeMap<String, String>,
    re: &Reexports,
    segs: &[String],
    depth: usize,
) -> Option<String> {
    for n in (0..=segs.len()).rev() {
        let base = segs[..n].join("/");
        let candidates = if n == 0 {
            vec!["lib.rs".to_string()]
        } else {
            vec![format!("{base}.rs"), format!("{base}/mod.rs")]
        };
        let Some(c) = candidates.into_iter().find(|c| files.contains_key(c)) else {
            continue;
        };
        if n < segs.len() && depth < 8 {
            let on = |target: &[String]| {
                let mut next = target.to_vec();
                next.extend_from_slice(&segs[n + 1..]);
                resolve(files, re, &next, depth + 1)
            };
            let names = re.get(&c).map(Vec::as_slice).unwrap_or_default();
            if let Some((_, target)) = names.iter().find(|(name, _)| *name == segs[n]) {
                if let Some(t) = on(target) {
                    return Some(t);
                }
            }
            for (_, glob) in names.iter().filter(|(name, _)| name == "*") {
                let mut next = glob.clone();
                next.extend_from_slice(&segs[n..]);
                let own = resolve(files, re, glob, depth + 1);
                match resolve(files, re, &next, depth + 1) {
                    Some(t) if Some(&t) != own.as_ref() => return Some(t),
                    _ => {}
                }
            }
        }
        return Some(c);
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

/// Every path of `code` that starts with one of `prefixes` (a word before `::`, with the
/// module path it stands for), as full module paths.
fn scan(code: &[char], prefixes: &[(String, Vec<String>)]) -> Vec<Vec<String>> {
    let mut found = Vec::new();
    let mut i = 0;
    while i < code.len() {
        let boundary = i == 0 || !(is_ident(code[i - 1]) || code[i - 1] == ':');
        let rest = |w: &str| code[i..].iter().take(w.len()).copied().eq(w.chars());
        let Some((word, base)) = prefixes
            .iter()
            .find(|(w, _)| boundary && rest(&format!("{w}::")))
        else {
            i += 1;
            continue;
        };
        let mut base = base.clone();
        let mut j = i + word.len() + 2;
        while code[j..].iter().take(7).copied().eq("super::".chars()) {
            base.pop();
            j += 7;
        }
        i = paths(code, j, &base, &mut found).max(i + 1);
    }
    found
}

fn edges(files: &BTreeMap<String, String>) -> BTreeMap<String, BTreeSet<String>> {
    let re = reexports(files);
    let mut graph = BTreeMap::new();
    for (file, text) in files {
        if is_binary(file) {
            continue;
        }
        let code = code_of(text);
        let me = module_of(file);
        let roots = [
            ("crate".to_string(), Vec::new()),
            (
                "super".to_string(),
                me[..me.len().saturating_sub(1)].to_vec(),
            ),
        ];
        let mut targets = BTreeSet::new();
        // a module brought in by name (`use crate::measure::{eval, spread}`, `{self}`)
        // and then used as `eval::cell_z`: its paths are edges too
        let mut aliases: Vec<(String, Vec<String>)> = Vec::new();
        for segs in scan(&code, &roots) {
            let Some(t) = file_of(files, &re, &segs) else {
                continue;
            };
            let module = module_of(&t);
            if !module.is_empty() && module.last() == segs.last() {
                aliases.push((module.last().cloned().unwrap_or_default(), module));
            }
            targets.insert(t);
        }
        for segs in scan(&code, &aliases) {
            targets.extend(file_of(files, &re, &segs));
        }
        targets.remove(file);
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
    let found = cycles(&src_graph());
    assert!(
        found.is_empty(),
        "import cycles between files of src/: {found:?}"
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

/// The cycles of a planted `src/`: `lib.rs` declares `a`, `a/mod.rs` declares `x` and `y`
/// and re-exports what `reexport` says, `a/x.rs` and `a/y.rs` hold `x` and `y`.
fn planted(reexport: &str, x: &str, y: &str) -> Vec<Vec<String>> {
    let files: BTreeMap<String, String> = [
        ("lib.rs", "pub mod a;\n".to_string()),
        ("a/mod.rs", format!("pub mod x;\npub mod y;\n{reexport}")),
        ("a/x.rs", x.to_string()),
        ("a/y.rs", y.to_string()),
    ]
    .into_iter()
    .map(|(f, t)| (f.to_string(), t))
    .collect();
    cycles(&edges(&files))
}

fn x_and_y() -> Vec<Vec<String>> {
    vec![vec!["a/x.rs".to_string(), "a/y.rs".to_string()]]
}

#[test]
fn the_reader_sees_a_cycle_it_is_shown() {
    // A check that could be false: a planted two-file cycle is found.
    let found = planted(
        "",
        "use super::y::Y;\npub struct X;\n",
        "use crate::a::{x::X, self};\n// use super::nothing;\npub struct Y;\n",
    );
    assert_eq!(found, x_and_y());
}

#[test]
fn a_cycle_behind_a_re_export_is_shown() {
    // `y` names `X` by the path its folder re-exports it under: the edge leads on to
    // `x.rs`, which imports `y` back (read without the re-export, `y` would import the
    // folder's `mod.rs` only, and no cycle would show).
    let found = planted(
        "\npub use x::{X, Z};\n",
        "use super::y::Y;\npub struct X;\npub struct Z;\n",
        "pub struct Y(crate::a::X);\n",
    );
    assert_eq!(found, x_and_y());
}

#[test]
fn a_module_used_by_its_name_is_an_edge() {
    // `use super::y;` then `y::f()`: the edge goes to `y.rs`, which imports `x` back.
    let found = planted(
        "",
        "use super::y;\npub fn g() -> u8 {\n    y::f()\n}\n",
        "pub fn f() -> u8 {\n    crate::a::x::g();\n    1\n}\n",
    );
    assert_eq!(found, x_and_y());
}
