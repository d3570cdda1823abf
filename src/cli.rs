//! The command line: parse, call the library, map the outcome to an exit code.

use clap::{Parser, Subcommand};
use persist::model::ModelParams;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser, Debug)]
#[command(
    name = "persist",
    version,
    about = "Predict and flag image persistence in H2RG arrays"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Model files: print the default, check one, show its identity.
    Model {
        #[command(subcommand)]
        action: ModelAction,
    },
    /// Check files against the ICD and their schemas: input and output products,
    /// checkpoints (`.h5`), model files (`.json`). Prints `ok <kind> <path>` per valid
    /// file and every error on stderr; exits 1 if any file failed.
    Validate {
        /// Files to check (all are checked, whatever fails).
        #[arg(required = true)]
        files: Vec<PathBuf>,
    },
}

#[derive(Subcommand, Debug)]
pub enum ModelAction {
    /// Print the default model file (the paper's constants).
    Default,
}

pub fn run(cli: Cli) -> persist::Result<ExitCode> {
    match cli.command {
        Command::Model { action } => match action {
            ModelAction::Default => {
                println!("{}", ModelParams::default().to_json_pretty());
                Ok(ExitCode::SUCCESS)
            }
        },
        Command::Validate { files } => Ok(validate(&files)),
    }
}

/// `persist validate FILE...`: every file is checked; exit 1 if any failed.
fn validate(files: &[PathBuf]) -> ExitCode {
    let mut failed = false;
    for path in files {
        match persist::product::validate_path(path) {
            Ok(kind) => println!("ok {kind} {}", path.display()),
            Err(errors) => {
                failed = true;
                for e in errors {
                    // Every error names its file; make sure of it.
                    eprintln!("{}", e.path(path));
                }
            }
        }
    }
    if failed {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    }
}
