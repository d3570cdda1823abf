//! The repository describes the product, not how the work on it was organised: no
//! tracked text file names a work period (the word is built below from two halves, so
//! that this file passes its own check), an issue number (the word issue or issues,
//! then a number, with or without a hash sign; or a hash sign and a number alone in
//! prose) or a commit hash (7 to 40 hex digits, with at least one digit and one
//! letter). Every hit is reported as `file:line: what`; the examples in the tests below
//! are assembled at run time for the same reason.
//!
//! Scanned: `git ls-files`, except `Cargo.lock` and binary files (a NUL byte in the
//! first 8 KiB). Outside a git checkout (a packaged crate) the test passes with a note.
//!
//! What is *not* a hit, so that the check stays quiet on legitimate text:
//! - `#` followed by digits inside code: a format spec (`{v:#04x}`), a colour
//!   (`"#1f77b4"`, or `#999;` in CSS), an attribute (`#[...]`): a bare reference must
//!   follow the start of the line, a space or an opening parenthesis, have 1 to 5
//!   digits and end there (not before `;` or `}`);
//! - hex-looking numbers: `0x...` literals, digit groups joined by `_`, decimal
//!   exponents (`8.617333e-5`), and runs longer than 40 (SHA-256 digests in tests);
//! - a commit named inside the generated provenance header of a page that a command in
//!   the repository regenerates (between `<!-- generated header` and
//!   `<!-- end of generated header -->`), which names the date, the machine and the
//!   commit the page was produced at.

use std::path::Path;
use std::process::Command;

/// The forbidden word, in two halves (module docs).
fn work_period_words() -> [String; 2] {
    let w = format!("{}{}", "ses", "sion");
    [w.clone(), format!("{w}s")]
}

fn is_word_char(c: char) -> bool {
    c.is_ascii_alphanumeric() || c == '_'
}

/// Maximal runs of word characters with their byte offsets.
fn words(line: &str) -> Vec<(usize, &str)> {
    let mut out = Vec::new();
    let mut start = None;
    for (i, c) in line.char_indices() {
        match (is_word_char(c), start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                out.push((s, &line[s..i]));
                start = None;
            }
            _ => {}
        }
    }
    if let Some(s) = start {
        out.push((s, &line[s..]));
    }
    out
}

/// The word issue(s), then spaces, a hash sign or a colon, then digits.
fn issue_word_reference(line: &str) -> Option<String> {
    for (i, w) in words(line) {
        let lw = w.to_ascii_lowercase();
        if lw != "issue" && lw != "issues" {
            continue;
        }
        let rest = &line[i + w.len()..];
        let after = rest.trim_start_matches([' ', ':', '#']);
        let digits: String = after.chars().take_while(|c| c.is_ascii_digit()).collect();
        let next = after[digits.len()..].chars().next();
        if !digits.is_empty() && !next.is_some_and(is_word_char) && rest.starts_with([' ', '#']) {
            return Some(format!("{w} {digits}"));
        }
    }
    None
}

/// A hash sign and 1 to 5 digits alone in prose (module docs: what is not one).
fn hash_number_reference(line: &str) -> Option<String> {
    let b = line.as_bytes();
    for (i, &c) in b.iter().enumerate() {
        if c != b'#' {
            continue;
        }
        let before_ok = i == 0 || matches!(b[i - 1], b' ' | b'\t' | b'(');
        let n = b[i + 1..].iter().take_while(|d| d.is_ascii_digit()).count();
        let end = i + 1 + n;
        // not followed by a word character, nor by `;` or `}` (a CSS colour, `#999;`)
        let after_ok =
            end == b.len() || !(b[end].is_ascii_alphanumeric() || b"_;}".contains(&b[end]));
        if before_ok && (1..=5).contains(&n) && after_ok {
            return Some(line[i..end].to_string());
        }
    }
    None
}

/// A run of 7 to 40 lowercase hex digits, with at least one digit and one letter, that
/// is not part of a number (`0x...`, `1_000`, `8.617333e-5`) nor of a longer digest.
fn commit_hash(line: &str) -> Option<String> {
    for (i, w) in words(line) {
        let n = w.len();
        if !(7..=40).contains(&n) || !w.bytes().all(|c| matches!(c, b'0'..=b'9' | b'a'..=b'f')) {
            continue;
        }
        if !w.bytes().any(|c| c.is_ascii_digit()) || !w.bytes().any(|c| c.is_ascii_lowercase()) {
            continue;
        }
        // a decimal exponent: digits, one `e`, then nothing or the exponent's sign
        let is_exponent = {
            let (mant, exp) = w.split_once('e').unwrap_or((w, "x"));
            !mant.is_empty()
                && mant.bytes().all(|c| c.is_ascii_digit())
                && exp.bytes().all(|c| c.is_ascii_digit())
        };
        let before = line[..i].chars().next_back();
        if is_exponent || matches!(before, Some('.') | Some('_')) {
            continue;
        }
        return Some(w.to_string());
    }
    None
}

/// The generated provenance header of a page a command regenerates (module docs): from
/// a line opening it to the line closing it, both included.
const HEADER_OPEN: &str = "<!-- generated header";
const HEADER_CLOSE: &str = "<!-- end of generated header";

/// Every forbidden reference of each line of `text`, as `(line number, what)`.
fn text_hits(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let mut in_header = false;
    for (n, line) in text.lines().enumerate() {
        in_header |= line.contains(HEADER_OPEN);
        out.extend(hits(line, in_header).into_iter().map(|h| (n + 1, h)));
        if line.contains(HEADER_CLOSE) {
            in_header = false;
        }
    }
    out
}

/// Every forbidden reference of one line, described; `provenance`: the line is in a
/// generated header, where a commit may be named.
fn hits(line: &str, provenance: bool) -> Vec<String> {
    let mut out = Vec::new();
    let banned = work_period_words();
    for (_, w) in words(line) {
        if banned.iter().any(|b| w.eq_ignore_ascii_case(b)) {
            out.push(format!("the word `{w}`"));
        }
    }
    if let Some(r) = issue_word_reference(line) {
        out.push(format!("an issue reference `{r}`"));
    }
    if let Some(r) = hash_number_reference(line) {
        out.push(format!("an issue reference `{r}`"));
    }
    if let Some(h) = commit_hash(line).filter(|_| !provenance) {
        out.push(format!("a commit hash `{h}`"));
    }
    out
}

#[test]
fn the_patterns_catch_references_and_spare_code() {
    let w = &work_period_words()[0];
    let (issue, hash, commit) = ("issue", '#', format!("{}{}", "fdbe", "6c7"));
    let count = |line: String| hits(&line, false).len();
    assert_eq!(count(format!("As the {w} found")), 1);
    assert_eq!(count(format!("many {}S here", w.to_uppercase())), 1);
    assert_eq!(count(format!("{w}_id and pre{w}")), 0);
    let both = format!("see {issue} 38 and Issues {hash}4");
    let first = format!("an issue reference `{issue} 38`");
    assert_eq!(hits(&both, false)[0], first);
    assert_eq!(count(format!("Issues {hash}4 only")), 2);
    assert_eq!(count(format!("({hash}12) was fixed")), 1);
    assert_eq!(count(format!("{hash} 1. A heading, tissue 3")), 0);
    assert_eq!(count(format!("run on commit {commit} it fails")), 1);
    assert_eq!(count(format!("hash {commit}ab2")), 1);
    let page = format!(
        "# Page\n{HEADER_OPEN}: script -->\n| commit | `{commit}` |\n{HEADER_CLOSE} -->\n\
         at commit {commit} again\n"
    );
    assert_eq!(text_hits(&page), [(5, format!("a commit hash `{commit}`"))]);
    for code in [
        r#"format!("holds {bad:#04x}")"#,
        "#[derive(Debug)] #![allow(x)]",
        r##"color: "#1f77b4", "#000000""##,
        "let k = 8.617333e-5; let z = 0x9e37_79b9_7f4a_7c15;",
        "1772323200 and 2654435761 and 1e6 and 100000e3",
        "a decade, defaced facade",
        "sha256 5f70bf18a086007016e948b04aed3b82103a36bea41755b6cddfaf10ace3c6ef",
        "HDF5 1.14 and H5Fopen and x#3",
        "td{border:1px solid #999;padding:2px} a{color: #333}",
    ] {
        let found = hits(code, false);
        assert!(found.is_empty(), "{code}: {found:?}");
    }
}

#[test]
fn tracked_text_files_name_no_work_period_issue_or_commit() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let listed = Command::new("git")
        .args(["ls-files", "-z"])
        .current_dir(root)
        .output();
    let files = match listed {
        Ok(o) if o.status.success() && !o.stdout.is_empty() => o.stdout,
        _ => {
            eprintln!(
                "note: {} is not a git checkout (or git is missing): nothing to scan",
                root.display()
            );
            return;
        }
    };
    let mut found = Vec::new();
    for name in files.split(|&b| b == 0).filter(|n| !n.is_empty()) {
        let name = String::from_utf8_lossy(name).into_owned();
        if name == "Cargo.lock" || name.ends_with("/Cargo.lock") {
            continue;
        }
        // listed but deleted in the work tree: nothing to read
        let Ok(bytes) = std::fs::read(root.join(&name)) else {
            continue;
        };
        if bytes[..bytes.len().min(8192)].contains(&0) {
            continue;
        }
        let text = String::from_utf8_lossy(&bytes);
        for (n, h) in text_hits(&text) {
            found.push(format!("{name}:{n}: {h}"));
        }
    }
    assert!(
        found.is_empty(),
        "{} reference(s) to how the work was organised; say what the code does instead:\n{}",
        found.len(),
        found.join("\n")
    );
}
