//! The logs on stderr (`tracing`) and the progress bar of a batch run drawn below them.

use super::{Cli, Command};
use std::io::{IsTerminal, Write};
use std::sync::OnceLock;

/// The progress bar of a batch run, when one is drawn: logs are printed above it.
pub(super) static BAR: OnceLock<indicatif::ProgressBar> = OnceLock::new();

struct LogWriter;

impl Write for LogWriter {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match BAR.get() {
            Some(pb) if !pb.is_hidden() => pb.suspend(|| std::io::stderr().write_all(buf))?,
            _ => std::io::stderr().write_all(buf)?,
        }
        Ok(buf.len())
    }
    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// Install the log subscriber (once, before anything logs).
pub fn init_logging(cli: &Cli) {
    use tracing_subscriber::EnvFilter;
    let quiet = matches!(&cli.command, Command::Run(a) if a.quiet);
    let level = if quiet {
        "warn"
    } else {
        cli.log_level.as_str()
    };
    let filter = EnvFilter::try_from_env("PERSIST_LOG")
        .or_else(|_| EnvFilter::try_new(level))
        .unwrap_or_else(|_| EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(|| LogWriter)
        .with_target(false);
    let _ = if cli.log_json {
        builder
            .json()
            .flatten_event(true)
            .with_current_span(false)
            .try_init()
    } else {
        builder
            .with_ansi(std::io::stderr().is_terminal())
            .try_init()
    };
}
