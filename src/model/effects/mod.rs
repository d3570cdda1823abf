//! The model effects, one file each, and the registry by name.
//!
//! They share names with the simulator's truth effects ([`crate::sim::effects`]) but not
//! code: these act on the exponential sum, the simulator's on trap bins. The model's
//! `populations` is a smooth (quadratic) surface, not the simulator's per-pixel map
//! (see its module docs).

pub mod blooming;
pub mod capacity;
pub mod chord;
pub mod ipc;
pub mod linefit_bias;
pub mod populations;
pub mod refill;
pub mod short_tau_boost;
pub mod smooth;
pub mod soak;
pub mod temperature;

use super::effect::{Effect, EffectDef, EffectSpec};
use std::collections::BTreeMap;

/// Every effect this build knows, sorted by name.
pub const REGISTRY: [EffectDef; 15] = [
    blooming::DEF,
    capacity::DEF,
    chord::DEF,
    ipc::DEF,
    linefit_bias::DEF,
    populations::DEF,
    refill::DEF,
    short_tau_boost::DEF,
    smooth::DURATION,
    smooth::HISTORY,
    smooth::NEIGHBOUR,
    smooth::SHAPE,
    smooth::TEMPERATURE,
    soak::DEF,
    temperature::DEF,
];

/// The names of [`REGISTRY`].
pub fn names() -> Vec<&'static str> {
    REGISTRY.iter().map(|d| d.name).collect()
}

pub fn lookup(name: &str) -> Option<&'static EffectDef> {
    REGISTRY.iter().find(|d| d.name == name)
}

/// Check a model file's effect entry; returns its full parameter map.
pub fn resolve(spec: &EffectSpec) -> Result<(&'static EffectDef, BTreeMap<String, f64>), String> {
    let def = lookup(&spec.name).ok_or_else(|| {
        format!(
            "name: unknown effect `{}` (known: {})",
            spec.name,
            names().join(", ")
        )
    })?;
    if let Some(f) = spec
        .fixed
        .iter()
        .find(|f| !def.params.iter().any(|p| p.name == f.as_str()))
    {
        return Err(format!(
            "fixed: `{f}` is not a parameter of `{}` (its parameters: {})",
            spec.name,
            def.param_names()
        ));
    }
    Ok((def, def.resolve(&spec.params)?))
}

/// Build the effect of a validated entry.
pub fn build(spec: &EffectSpec) -> Result<Box<dyn Effect>, String> {
    let (def, p) = resolve(spec)?;
    Ok((def.build)(&p))
}

/// The pixels' spread correlation a model's effects state (the first that states one;
/// [`Effect::spread_correlation`]), None when none does or an entry does not resolve.
pub fn spread_correlation(effects: &[EffectSpec]) -> Option<super::effect::SpreadCorrelation> {
    effects
        .iter()
        .filter_map(|e| build(e).ok())
        .find_map(|e| e.spread_correlation())
}

/// Parameter value from a resolved map (present by construction).
pub(crate) fn get(p: &BTreeMap<String, f64>, name: &str) -> f64 {
    p.get(name).copied().unwrap_or(f64::NAN)
}
