//! Command-line options shared by `persist run`, `persist status` and `persist slurm`:
//! the checkpoint cadence and retention ([`crate::checkpoint::Retention`]).

use crate::checkpoint::{Retention, DEFAULT_CADENCE};
use clap::Args;

/// Checkpoint cadence and retention.
#[derive(Args, Debug, Clone)]
pub struct CheckpointArgs {
    /// Write a checkpoint after every exposure whose index + 1 is a multiple of N (and a
    /// tail checkpoint at the end of a batch, when stopping, and when a watch is idle);
    /// a crash replays at most N - 1 exposures, rewriting nothing.
    #[arg(long, default_value_t = DEFAULT_CADENCE, value_parser = clap::value_parser!(u64).range(1..))]
    pub checkpoint_every: u64,
    /// Keep the newest checkpoint and the N - 1 grid checkpoints before it; older ones
    /// thin with their age (hourly, daily, weekly).
    #[arg(long, default_value_t = 20)]
    pub keep_latest: usize,
    /// Beyond the newest: keep the first checkpoint of each hour of data for this many
    /// hours (by reset time, counted back from the newest checkpoint).
    #[arg(long, default_value_t = 24.0, value_parser = nonnegative)]
    pub keep_hourly_h: f64,
    /// Then the first of each day for this many days (counted back from the newest).
    #[arg(long, default_value_t = 30.0, value_parser = nonnegative)]
    pub keep_daily_d: f64,
    /// Do not keep the first checkpoint of each week beyond the daily ones.
    #[arg(long)]
    pub no_weekly_checkpoints: bool,
    /// Keep only the newest checkpoints (no hourly, daily or weekly ones).
    #[arg(long)]
    pub no_hourly_checkpoints: bool,
}

fn nonnegative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
        _ => Err(format!("`{s}`: expected a number >= 0")),
    }
}

impl CheckpointArgs {
    /// The retention rule these options describe.
    pub fn retention(&self) -> Retention {
        Retention {
            keep_latest: self.keep_latest,
            keep_one_per_hour: !self.no_hourly_checkpoints,
            hourly_for_s: self.keep_hourly_h * 3600.0,
            daily_for_s: self.keep_daily_d * 86_400.0,
            weekly: !self.no_weekly_checkpoints,
            cadence: self.checkpoint_every,
        }
    }

    /// These options as `persist run` arguments (for worker processes and batch scripts).
    pub fn to_args(&self) -> Vec<String> {
        let mut v = vec![
            "--checkpoint-every".to_owned(),
            self.checkpoint_every.to_string(),
            "--keep-latest".to_owned(),
            self.keep_latest.to_string(),
            "--keep-hourly-h".to_owned(),
            self.keep_hourly_h.to_string(),
            "--keep-daily-d".to_owned(),
            self.keep_daily_d.to_string(),
        ];
        if self.no_weekly_checkpoints {
            v.push("--no-weekly-checkpoints".to_owned());
        }
        if self.no_hourly_checkpoints {
            v.push("--no-hourly-checkpoints".to_owned());
        }
        v
    }
}
