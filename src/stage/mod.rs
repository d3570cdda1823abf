//! The pipeline stage around the model: discover products, order each detector's
//! history, run them through the model, publish outputs and checkpoints.

pub mod lock;
pub mod quarantine;
pub mod queue;
pub mod run;

pub use run::{processing_time, run, ExposureReport, RunConfig, RunReport};
