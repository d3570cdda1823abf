//! `persist help-markdown`: the command-line reference (docs/cli.md) generated from
//! the clap definitions, so that the page cannot drift from the program.
//!
//! The page is the root command's help, then every visible subcommand's long help
//! (depth first, in declaration order), each under its own heading in a `text` block.
//! Hidden commands and arguments (this one, the benchmark's child-process options) are
//! left out, as `--help` leaves them out. The output depends only on the definitions:
//! no terminal width (clap is built without `wrap_help`), no colour, no clock.

use clap::Command;

/// The whole reference page for the root command `root`.
pub fn markdown(mut root: Command) -> String {
    // Building sets every subcommand's `bin_name` ("persist simulate lab"), so that
    // each usage line names the full command.
    root.build();
    let mut page = String::new();
    page.push_str("# Command-line reference\n\n");
    page.push_str(
        "Generated from the program's own definitions by `persist help-markdown > \
         docs/cli.md`;\na test (`tests/cli_reference.rs`) fails when this page and that \
         output differ.\nEvery section is what `--help` prints for that command.\n\n",
    );
    page.push_str("Commands:\n\n");
    let mut index = Vec::new();
    collect(&root, &mut index);
    for cmd in &index {
        let name = full_name(cmd);
        page.push_str(&format!("- [`{name}`](#{})\n", anchor(&name)));
    }
    page.push('\n');
    for cmd in &index {
        let name = full_name(cmd);
        page.push_str(&format!("## {name}\n\n```text\n"));
        let help = cmd.clone().render_long_help().to_string();
        for line in help.trim_end().lines() {
            page.push_str(line.trim_end());
            page.push('\n');
        }
        page.push_str("```\n\n");
    }
    page.truncate(page.trim_end().len());
    page.push('\n');
    page
}

/// `cmd` and its visible subcommands, depth first (clap's generated `help` left out).
fn collect(cmd: &Command, out: &mut Vec<Command>) {
    out.push(cmd.clone());
    for sub in cmd.get_subcommands() {
        if sub.is_hide_set() || sub.get_name() == "help" {
            continue;
        }
        collect(sub, out);
    }
}

fn full_name(cmd: &Command) -> String {
    cmd.get_bin_name()
        .unwrap_or_else(|| cmd.get_name())
        .to_string()
}

/// The heading anchor GitHub-flavoured markdown gives `## name`.
fn anchor(name: &str) -> String {
    name.chars()
        .filter_map(|c| match c {
            ' ' => Some('-'),
            c if c.is_alphanumeric() || c == '-' || c == '_' => Some(c.to_ascii_lowercase()),
            _ => None,
        })
        .collect()
}
