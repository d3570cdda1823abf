//! The persistence model core: pure array code (ndarray + rayon), no files, no clock,
//! no HDF5. The stage, the simulator's checks, the fitter and the diagnostics all reach
//! the model through [`Model::step`].
//!
//! Units: amplitudes `A_n` in electrons, `C_n` in 1/s, currents in e-/s, times in s.
//!
//! Imports, downwards only (tests/import_graph.rs): [`params`] (the model file) ->
//! [`effects`] (the registry of effects by name) -> [`effect`] (the trait every effect
//! implements) -> [`response`]. The trait and the response import nothing from the
//! registry or the model file; an effect's file imports the trait, never the model file.

pub mod decay;
pub mod effect;
pub mod effect_step;
pub mod effects;
pub mod fluence;
pub mod grid;
pub mod params;
pub mod pixel_response;
pub mod reference;
pub mod response;
pub mod state;
pub mod step;

pub use decay::ExpSum;
pub use effect_step::StepContext;
pub use params::{
    BackgroundEstimate, EarlyRelease, Knot, ModelParams, ReleaseKeep, ReleaseRule, Term, Thresholds,
};
pub use pixel_response::PixelResponse;
pub use response::Response;
pub use state::State;
pub use step::{FlagBits, Input, Model, Output, StepSummary};
