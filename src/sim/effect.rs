//! Switchable truth effects: one trait, documented hooks, a registry.
//!
//! An effect is one type implementing [`Effect`]; every hook defaults to "no change",
//! so an effect implements only what it acts on. All effects are off by default; with
//! none switched on the simulator's output is byte-identical to the baseline (the
//! engine calls no hook when the set is empty, and no hook draws from the baseline's
//! random streams).
//!
//! Hooks, in the order the engine calls them for one exposure:
//! 1. [`Effect::trap_pixels`]: once per detector, after the per-pixel trap densities are
//!    drawn (populations);
//! 2. [`Effect::time_constants`]: per interval (exposure or slew), the bins' emission and
//!    capture time constants at the focal-plane temperature (temperature, soak);
//! 3. [`Effect::illumination`]: the photon flux map of an exposure before it is
//!    integrated, and the charge that reaches a pixel's traps without being collected
//!    by its diode (blooming);
//! 4. [`Effect::capacity`]: per pixel and segment, multiplicative factors on each bin's
//!    exposed capacity `C_j` (capacity, short_tau_boost);
//! 5. [`Effect::least_squares_persistence`]: whether the curved persistence ramp enters
//!    the slope through the on-board least-squares weights (linefit_bias);
//! 6. [`Effect::measured`]: what the readout sees, applied to the slope image and the
//!    ramp (ipc).
//!
//! Adding an effect: one file in `effects/` with a type implementing [`Effect`], and
//! one line in [`super::effects::build`].

use super::traps::{Bins, PixelTraps, TrapParams};
use ndarray::{Array2, Array3};
use std::collections::BTreeMap;

/// What the capacity hook sees for one pixel and segment.
#[derive(Debug, Clone, Copy)]
pub struct CapacityCtx<'a> {
    /// True photon fluence of this exposure, `flux * t_illuminated`, electrons.
    pub fluence_e: f64,
    /// Charge the pixel's traps hold as the exposure begins (sum over the bins),
    /// electrons: what earlier exposures left.
    pub held_e: f64,
    pub e_lin: f64,
    pub e_sat: f64,
    pub d_lin: f64,
    pub d_sat: f64,
    pub bins_per_decade: f64,
    pub tau_e: &'a [f64],
}

pub trait Effect: Send + Sync + std::fmt::Debug {
    /// The name used on the command line and in `truth.json`.
    fn name(&self) -> &'static str;
    /// The parameter values in use (for `truth.json`).
    fn params(&self) -> BTreeMap<String, f64>;
    fn trap_pixels(&self, _pixels: &mut PixelTraps, _p: &TrapParams, _seed: u64, _det: u8) {}
    fn time_constants(&self, _bins: &mut Bins, _temp_k: f64) {}
    /// Changes the photon flux map of an illuminated exposure (`flux`, e-/s) before it is
    /// integrated, and may add to `uncollected_e`: charge (e-) that raises a pixel's
    /// trap fill level without being collected by its diode,
    /// so it is in no measured ramp (the engine spreads its arrival evenly over `t_on_s`
    /// and holds it until the integration ends: the reset clears it). Both start as the
    /// exposure's flux and zeros.
    fn illumination(
        &self,
        _flux: &mut Array2<f32>,
        _uncollected_e: &mut Array2<f32>,
        _t_on_s: f64,
        _full_well: &Array2<f32>,
    ) {
    }
    /// True if [`Effect::capacity`] is implemented (the engine skips the call otherwise).
    fn has_capacity(&self) -> bool {
        false
    }
    fn capacity(&self, _ctx: &CapacityCtx<'_>, _factor: &mut [f64]) {}
    fn least_squares_persistence(&self) -> bool {
        false
    }
    fn measured(&self, _image: &mut Array2<f32>, _ramp: Option<&mut Array3<f32>>) {}
}

/// A parsed `NAME[:param=value,...]`.
#[derive(Debug, Clone, PartialEq)]
pub struct EffectSpec {
    pub name: String,
    pub params: BTreeMap<String, f64>,
}

impl std::str::FromStr for EffectSpec {
    type Err = crate::Error;
    fn from_str(s: &str) -> crate::Result<Self> {
        let (name, rest) = match s.split_once(':') {
            Some((n, r)) => (n, r),
            None => (s, ""),
        };
        let name = name.trim();
        if name.is_empty() {
            return Err(crate::Error::invalid(
                "--effect",
                format!("`{s}`: empty effect name"),
            ));
        }
        let mut params = BTreeMap::new();
        for kv in rest.split(',').filter(|p| !p.trim().is_empty()) {
            let (k, v) = kv.split_once('=').ok_or_else(|| {
                crate::Error::invalid("--effect", format!("`{kv}` in `{s}`: expected param=value"))
            })?;
            let v: f64 = v.trim().parse().map_err(|_| {
                crate::Error::invalid(
                    "--effect",
                    format!(
                        "`{s}`: parameter `{}` value `{v}` is not a number",
                        k.trim()
                    ),
                )
            })?;
            if !v.is_finite() {
                return Err(crate::Error::invalid(
                    "--effect",
                    format!("`{s}`: parameter `{}` must be finite", k.trim()),
                ));
            }
            params.insert(k.trim().to_string(), v);
        }
        Ok(EffectSpec {
            name: name.to_string(),
            params,
        })
    }
}

/// Reads named parameters with defaults and bounds, refusing unknown names.
pub struct ParamReader<'a> {
    effect: &'static str,
    given: &'a BTreeMap<String, f64>,
    used: Vec<&'static str>,
}

impl<'a> ParamReader<'a> {
    pub fn new(effect: &'static str, given: &'a BTreeMap<String, f64>) -> Self {
        ParamReader {
            effect,
            given,
            used: Vec::new(),
        }
    }

    /// The value of `name` (default `default`), which must lie in `[lo, hi]`.
    pub fn get(
        &mut self,
        name: &'static str,
        default: f64,
        lo: f64,
        hi: f64,
    ) -> crate::Result<f64> {
        self.used.push(name);
        let v = self.given.get(name).copied().unwrap_or(default);
        if !(lo..=hi).contains(&v) {
            return Err(crate::Error::invalid(
                format!("--effect {}:{name}", self.effect),
                format!("must be in [{lo}, {hi}], got {v}"),
            ));
        }
        Ok(v)
    }

    /// Fail on any parameter that was not read.
    pub fn finish(self) -> crate::Result<()> {
        for k in self.given.keys() {
            if !self.used.contains(&k.as_str()) {
                return Err(crate::Error::invalid(
                    format!("--effect {}", self.effect),
                    format!("unknown parameter `{k}` (known: {})", self.used.join(", ")),
                ));
            }
        }
        Ok(())
    }
}

/// The effects switched on for a run, in a fixed order (sorted by name), so the result
/// does not depend on the order of `--effect` options. Built by `EffectSet::from_specs`,
/// which sits with the registry in [`super::effects`] (this file imports nothing from it).
#[derive(Debug, Default)]
pub struct EffectSet {
    pub list: Vec<Box<dyn Effect>>,
}

impl EffectSet {
    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    pub fn has_capacity(&self) -> bool {
        self.list.iter().any(|e| e.has_capacity())
    }

    pub fn least_squares_persistence(&self) -> bool {
        self.list.iter().any(|e| e.least_squares_persistence())
    }

    /// `[{name, params}]` for truth.json.
    pub fn describe(&self) -> serde_json::Value {
        serde_json::Value::Array(
            self.list
                .iter()
                .map(|e| serde_json::json!({"name": e.name(), "params": e.params()}))
                .collect(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_name_and_params() {
        let s: EffectSpec = "ipc:alpha=0.02".parse().unwrap();
        assert_eq!(s.name, "ipc");
        assert_eq!(s.params["alpha"], 0.02);
        let s: EffectSpec = "soak".parse().unwrap();
        assert!(s.params.is_empty());
        assert!("ipc:alpha".parse::<EffectSpec>().is_err());
        assert!("ipc:alpha=x".parse::<EffectSpec>().is_err());
    }

    #[test]
    fn unknown_effect_and_param_are_errors_naming_them() {
        let e = EffectSet::from_specs(&["nope".parse().unwrap()]).unwrap_err();
        assert!(e.to_string().contains("nope"));
        let e = EffectSet::from_specs(&["ipc:beta=1".parse().unwrap()]).unwrap_err();
        assert!(e.to_string().contains("beta"), "{e}");
        let e = EffectSet::from_specs(&["ipc:alpha=0.9".parse().unwrap()]).unwrap_err();
        assert!(e.to_string().contains("alpha"), "{e}");
    }
}
