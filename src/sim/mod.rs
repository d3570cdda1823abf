//! `persist simulate`: Level-1 products from a physical truth built independently of the
//! flagging model, so that the model can be tested against something it was not built
//! from.
//!
//! The truth is trap bins ([`traps`]), not the paper's exponential sum: per pixel, 49
//! bins of emission time constants from 1 s to 1e6 s, each with a capture time constant
//! and a capacity that depends on how far the pixel was filled or forward biased. The
//! detector ([`detector`]) adds dark current, read and shot noise, full well, cosmic
//! rays, non-functional pixels and the on-board line fit; [`engine`] integrates it all.
//! [`lab`] reproduces the paper's laboratory test, [`sky`] a SPHEREx-like survey.
//! Switchable effects ([`effect`], [`effects`]) are all off by default.
//!
//! Units: seconds, electrons, electrons per second, kelvin.
//! Determinism: all randomness comes from [`rng`] sub-streams keyed by
//! (seed, purpose, detector, exposure, row).
//!
//! Imports, downwards only (tests/import_graph.rs): the engine and the campaigns ->
//! [`effects`] (the registry: names to effects, [`effect::EffectSet::from_specs`]) ->
//! [`effect`] (the trait) -> [`traps`]. The trait file imports nothing from the registry.

pub mod analysis;
pub mod detector;
pub mod effect;
pub mod effects;
pub mod engine;
pub mod lab;
pub mod output;
pub mod rng;
pub mod sky;
pub mod traps;

use crate::product::{Exposure, ExposureMeta};
use crate::units::{DetectorId, UtcSeconds};
use ndarray::Array2;

/// One simulated exposure: the Level-1 product and its truth (kept apart: the truth is
/// written beside the products, never inside them).
#[derive(Debug, Clone)]
pub struct SimExposure {
    pub exposure: Exposure,
    /// True persistence current averaged over the integration, e-/s ([`engine`] docs).
    pub true_persistence: Array2<f32>,
    /// True photon flux while illuminated, e-/s (the sky or the lamp).
    pub true_flux: Array2<f32>,
    /// Scenario label of this exposure (e.g. `illuminated`, `dark`, `deep_field`).
    pub kind: String,
}

/// The simulator's start time: 2026-03-01T00:00:00Z.
pub fn epoch() -> UtcSeconds {
    UtcSeconds::parse("2026-03-01T00:00:00Z").expect("constant time parses")
}

/// Metadata of an exposure starting at `t_start`.
pub fn meta(
    detector: u8,
    index: u64,
    t_start: UtcSeconds,
    t_exposure_s: f64,
    temp_k: f64,
    t_illuminated_s: Option<f64>,
) -> ExposureMeta {
    // round to the microsecond so the string and the parsed value agree
    let t_start = UtcSeconds((t_start.0 * 1e6).round() / 1e6);
    ExposureMeta {
        detector: DetectorId(detector),
        exposure_index: index,
        t_start_utc: t_start.to_iso(),
        t_start,
        t_exposure_s,
        focal_plane_temp_k: Some((temp_k * 1e4).round() / 1e4),
        t_illuminated_s,
    }
}
