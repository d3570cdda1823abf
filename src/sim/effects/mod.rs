//! The truth effects, one file each. They share names with the flagging model's
//! effects but not code: these act on trap bins and the detector, the model's on an
//! exponential sum.
//!
//! The registry: [`build`] maps a name to its effect, [`EffectSet::from_specs`] builds
//! a run's set.

pub mod blooming;
pub mod capacity;
pub mod ipc;
pub mod linefit_bias;
pub mod populations;
pub mod short_tau_boost;
pub mod soak;
pub mod temperature;

use super::effect::{Effect, EffectSet, EffectSpec};

/// Names accepted by `--effect`.
pub const NAMES: [&str; 8] = [
    "blooming",
    "capacity",
    "ipc",
    "linefit_bias",
    "populations",
    "short_tau_boost",
    "soak",
    "temperature",
];

/// Build one effect from its spec (parameters checked, unknown names refused).
pub fn build(s: &EffectSpec) -> crate::Result<Box<dyn Effect>> {
    let p = &s.params;
    Ok(match s.name.as_str() {
        "blooming" => Box::new(blooming::Blooming::from_params(p)?),
        "capacity" => Box::new(capacity::Capacity::from_params(p)?),
        "ipc" => Box::new(ipc::Ipc::from_params(p)?),
        "linefit_bias" => Box::new(linefit_bias::LinefitBias::from_params(p)?),
        "populations" => Box::new(populations::Populations::from_params(p)?),
        "short_tau_boost" => Box::new(short_tau_boost::ShortTauBoost::from_params(p)?),
        "soak" => Box::new(soak::Soak::from_params(p)?),
        "temperature" => Box::new(temperature::Temperature::from_params(p)?),
        other => {
            return Err(crate::Error::invalid(
                "--effect",
                format!("unknown effect `{other}` (known: {})", NAMES.join(", ")),
            ))
        }
    })
}

impl EffectSet {
    /// The effects of `specs` (each name at most once), sorted by name.
    pub fn from_specs(specs: &[EffectSpec]) -> crate::Result<EffectSet> {
        let mut list = Vec::new();
        let mut names: Vec<&str> = Vec::new();
        for s in specs {
            if names.contains(&s.name.as_str()) {
                return Err(crate::Error::invalid(
                    "--effect",
                    format!("effect `{}` given twice", s.name),
                ));
            }
            names.push(&s.name);
            list.push(build(s)?);
        }
        list.sort_by_key(|e| e.name());
        Ok(EffectSet { list })
    }
}
