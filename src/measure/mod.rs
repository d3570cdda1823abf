//! Measurements as the model sees them, shared by the calibration ([`crate::calib`])
//! and the diagnostics ([`crate::diag`]): the sequence of exposures with each one's
//! background and noise ([`data`]), the readout's coupling of neighbours
//! ([`coupling`]), residual cells by covariate ([`eval`]) and the pixels' spread
//! ([`spread`]). Invariant: this module imports neither `calib` nor
//! `diag`, so that `diag` may use `calib` and `calib` never uses `diag`.

pub mod coupling;
pub mod data;
pub mod eval;
pub mod spread;
