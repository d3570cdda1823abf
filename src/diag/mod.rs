//! Comparing the model with measurements: the data ([`data`]), residuals by covariate
//! and flag quality ([`compare`]), the search for missing effects ([`diagnose`]), and
//! the HTML report ([`report`]).

pub mod compare;
pub mod data;
pub mod diagnose;
pub mod eval;
pub mod report;
pub mod spatial;
pub mod spread;
