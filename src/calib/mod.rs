//! `persist fit`: the paper's calibration from a laboratory sequence, the effects
//! fitted on it, and the flags calibrated to a coverage.
//!
//! - [`algorithm`]: the calibration itself (steps 1-5 of the paper's section 2.3), pure:
//!   a sequence in, a model and its report out.
//! - [`command`]: the `persist fit` driver (reads the sequence, writes the model file
//!   and the report).
//! - [`coverage`], [`effects`], [`knots`], [`exponent`], [`dark`], [`logfit`],
//!   [`readout`]: the parts the calibration and the fit use.

pub mod algorithm;
pub mod command;
pub mod coverage;
pub mod dark;
pub mod effects;
pub mod exponent;
pub mod knots;
pub mod logfit;
pub mod readout;

pub use algorithm::*;
pub use command::*;
