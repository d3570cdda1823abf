//! Every command of the README that is marked runnable runs: the blocks that follow a
//! `<!-- runnable -->` line (fenced ```sh) are executed in order, each with
//! `bash -euo pipefail`, in one temporary directory (later blocks use what earlier ones
//! wrote), with the built `persist` first on `PATH`. A block fails the test when any of
//! its commands fails; a command the README expects to fail is written
//! `cmd || echo "exit code $?"`.

use std::path::Path;
use std::process::Command;
use std::time::Instant;

/// The runnable blocks of a markdown text, with the line each starts on.
fn runnable_blocks(markdown: &str) -> Vec<(usize, String)> {
    let mut blocks = Vec::new();
    let mut lines = markdown.lines().enumerate();
    while let Some((_, line)) = lines.next() {
        if line.trim() != "<!-- runnable -->" {
            continue;
        }
        let (n, fence) = lines.next().expect("a code block after <!-- runnable -->");
        assert_eq!(
            fence.trim(),
            "```sh",
            "README line {}: <!-- runnable --> must be followed by a ```sh block",
            n + 1
        );
        let mut body = String::new();
        for (_, l) in lines.by_ref() {
            if l.trim() == "```" {
                break;
            }
            body.push_str(l);
            body.push('\n');
        }
        blocks.push((n + 1, body));
    }
    blocks
}

#[test]
fn extracts_marked_blocks_only() {
    let md = "text\n```sh\nnot this\n```\n<!-- runnable -->\n```sh\necho a\necho b\n```\n";
    let blocks = runnable_blocks(md);
    assert_eq!(blocks, vec![(6, "echo a\necho b\n".to_string())]);
}

#[test]
fn readme_runnable_blocks_run() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).expect("README.md");
    let blocks = runnable_blocks(&readme);
    assert!(
        blocks.len() >= 4,
        "expected the README's runnable walks, found {} blocks",
        blocks.len()
    );
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_persist"))
        .parent()
        .expect("binary directory")
        .to_path_buf();
    let path = format!(
        "{}:{}",
        bin_dir.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let dir = tempfile::tempdir().expect("temporary directory");
    let start = Instant::now();
    for (line, body) in &blocks {
        let t = Instant::now();
        let out = Command::new("bash")
            .args(["-euo", "pipefail", "-c", body])
            .current_dir(dir.path())
            .env("PATH", &path)
            .output()
            .expect("run bash");
        assert!(
            out.status.success(),
            "README block at line {line} failed ({}):\n{body}\n--- stdout\n{}\n--- stderr\n{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        eprintln!(
            "README block at line {line}: {:.1} s",
            t.elapsed().as_secs_f64()
        );
    }
    eprintln!(
        "{} README blocks in {:.1} s",
        blocks.len(),
        start.elapsed().as_secs_f64()
    );
}
