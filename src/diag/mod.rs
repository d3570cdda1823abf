//! Comparing the model with measurements: residuals by covariate and flag quality
//! ([`compare`]), the search for missing effects ([`diagnose`], against the model or a
//! description of the measurements fitted from the input, [`reference`](mod@reference)),
//! the spatial check ([`spatial`]) and the HTML report ([`report`]). The measurements
//! themselves ([`data`], [`eval`], [`spread`]) live in [`crate::measure`], which the
//! calibration shares; they are re-exported here under their former paths.
//!
//! `diagnose` is built from parts that import downwards only:
//! - [`config`]: what it is asked (statistic, refit, cells) and the defaults;
//! - [`command`]: the `persist fit` commands it prints;
//! - [`refit`]: a candidate refitted with the model's own effects, the change in BIC,
//!   the held-out check;
//! - [`score`]: the score test and its bootstrap threshold;
//! - [`contrast`] and [`base`]: what the data can test, and what a flexible base's
//!   residual depends on; [`separate`]: whether two such kinds can be told apart;
//! - [`shape`]: whether the decay's shape depends on the fluence, measured directly;
//! - [`data_term`]: the data-driven term offered along that covariate; [`offer`]: which
//!   refitted candidate is offered, judged held out against the pixel reference;
//! - [`finding`]: what a diagnosis decided, as data; [`verdict`] puts it into words
//!   once the reference is resolved ([`diagnose`] decides, [`reference`](mod@reference)
//!   chooses what it decides against).

pub use crate::measure::{data, eval, spread};

pub mod base;
pub mod command;
pub mod compare;
pub mod compare_command;
pub mod config;
pub mod contrast;
pub mod data_term;
pub mod diagnose;
pub mod finding;
pub mod marked;
pub mod offer;
pub mod polish;
pub mod reference;
pub mod refit;
pub mod report;
pub mod score;
pub mod separate;
pub mod shape;
pub mod spatial;
pub mod verdict;
