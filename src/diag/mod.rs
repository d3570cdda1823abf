//! Comparing the model with measurements: the data ([`data`]), residuals by covariate
//! and flag quality ([`compare`]), the search for missing effects ([`diagnose`]), and
//! the HTML report ([`report`]).

pub mod base;
pub mod compare;
pub mod contrast;
pub mod data;
pub mod diagnose;
pub mod eval;
pub mod report;
pub mod spatial;
pub mod spread;
