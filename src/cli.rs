//! The command line: parse, call the library, map the outcome to an exit code.

use clap::{Parser, Subcommand};
use persist::model::ModelParams;
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
    }
}
