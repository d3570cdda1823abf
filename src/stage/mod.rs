//! The pipeline stage around the model: discover products, order each detector's
//! history, run them through the model, publish outputs and checkpoints; watch a
//! directory, quarantine bad inputs, lock the directories, report status.

pub mod fallback;
pub mod lock;
pub mod options;
pub mod quarantine;
pub mod queue;
pub mod run;
pub mod status;
pub mod table;
pub mod watch;
pub mod workers;

pub use run::{
    processing_time, run, run_with, Bookkeeping, ExposureReport, OnlyDetector, Ops, RunConfig,
    RunReport, WatchOpts, DUPLICATE_WINDOW,
};
