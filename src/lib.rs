//! `persist`: predict and flag image persistence in HAWAII-2RG arrays (SPHEREx).
//!
//! ARCHITECTURE.md (at the repository's root) is the one-page map: the data path, each
//! folder's job, and what may import what. The data take one straight path, each step
//! one module:
//!
//! ```text
//! product::format -> model::fluence -> model::Model::step -> product::format -> checkpoint
//!                                      (predict, flag, early release, decay, respond)
//! ```
//!
//! - [`model`] is the pure core (no files, no clock, no HDF5); everything else reuses it.
//! - [`product`] is the only code that knows the HDF5 layout of the ICD
//!   (`docs/contract.md`) and checks files against the JSON Schemas in `schemas/`.
//! - [`checkpoint`] keeps each detector's state, keyed by (detector, exposure index).
//! - [`model_file`] reads model files (JSON, `schemas/model.schema.json`).
//! - [`h5io`] holds what products and checkpoints share: deterministic HDF5 creation
//!   (no object times) and atomic publication (`.NAME.part`, validate, sync, rename).
//! - [`stage`] runs detectors' histories through the model.
//! - [`validate`] recognises any file (product, checkpoint, model file) and checks it;
//!   it sits above [`product`] and [`checkpoint`]: [`checkpoint`] reuses
//!   [`product::schema`], and [`product`] imports neither.
//! - [`stats`] holds the robust statistics (medians, clipped medians, quantiles) that
//!   the simulator's checks, the fitter, the diagnostics and the benchmarks share.
//!
//! Invariants: NaN or Inf never enters the model state; an output is published (renamed
//! into place) only after it validates, and before the checkpoint that includes it; the
//! same inputs and model give byte-identical `/persistence` datasets.
//!
//! Units: seconds, electrons, electrons per second; names carry them (`t_exposure_s`).

#[macro_use]
pub mod choice;
pub mod bench;
pub mod calib;
pub mod checkpoint;
pub mod demo;
pub mod diag;
pub mod error;
pub mod fits;
pub mod flag_causes;
pub mod flag_quality;
pub mod flags;
pub mod fuzz;
pub mod guard;
pub mod h5io;
pub mod measure;
pub mod model;
pub mod model_file;
pub mod pixmap;
pub mod plot;
pub mod product;
pub mod sim;
pub mod slurm;
pub mod stage;
pub mod stats;
pub mod textfile;
pub mod tile;
pub mod timesplit;
pub mod trapgen;
pub mod units;
pub mod validate;
pub mod verify;

pub use error::{Error, ErrorKind, Result};

/// The software version recorded in outputs.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
