//! Comparing the model with measurements: residuals by covariate and flag quality
//! ([`compare`]), the search for missing effects ([`diagnose`], against the model or a description
//! of the measurements fitted from the input, [`reference`](mod@reference): what the data can test
//! and what a flexible base's residual depends on, [`contrast`] and [`base`]; the
//! data-driven term offered along it, [`data_term`]), the
//! spatial check ([`spatial`]) and the HTML report ([`report`]). The measurements
//! themselves ([`data`], [`eval`], [`spread`]) live in [`crate::measure`], which the
//! calibration shares; they are re-exported here under their former paths.

pub use crate::measure::{data, eval, spread};

pub mod base;
pub mod compare;
pub mod contrast;
pub mod data_term;
pub mod diagnose;
pub mod reference;
pub mod report;
pub mod spatial;
