//! The pipeline stage around the model: discover products, order each detector's
//! history, run them through the model, publish outputs and checkpoints; watch a
//! directory, quarantine bad inputs, lock the directories, report status.

pub mod exposure;
pub mod fallback;
pub mod lock;
pub mod metrics;
pub mod options;
pub mod quarantine;
pub mod queue;
pub mod run;
pub mod startup;
pub mod status;
pub mod table;
pub mod watch;
pub mod workers;

pub use run::{
    processing_time, Bookkeeping, ExposureReport, OnlyDetector, Ops, RunConfig, RunReport,
    WatchOpts, DUPLICATE_WINDOW,
};

/// Process every product in `cfg.input` once (batch, no quarantine).
pub fn run(cfg: &RunConfig, on_exposure: &(dyn Fn(&ExposureReport) + Sync)) -> RunReport {
    run_with(cfg, &Ops::default(), on_exposure)
}

/// Run the stage as `ops` says: one batch ([`mod@run`] module docs), or watching until
/// [`Ops::stop`] ([`watch`]).
pub fn run_with(
    cfg: &RunConfig,
    ops: &Ops,
    on_exposure: &(dyn Fn(&ExposureReport) + Sync),
) -> RunReport {
    let mut stage = match run::Stage::open(cfg, ops, on_exposure) {
        Ok(stage) => stage,
        Err(report) => return report,
    };
    match &ops.watch {
        None => stage.batch(),
        Some(w) => watch::watch(&mut stage, w),
    }
    stage.finish()
}
