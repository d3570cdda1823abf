use clap::Parser;
use std::process::ExitCode;

mod cli;
mod cli_reference;

fn main() -> ExitCode {
    let args = cli::Cli::parse();
    cli::init_logging(&args);
    match cli::run(args) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("persist: {e}");
            ExitCode::from(2)
        }
    }
}
