//! `temperature`: Arrhenius emission.
//!
//! Physics: trap emission is thermally activated, `tau_e ~ exp(E_a / k T)`; warmer
//! arrays release trapped charge faster (Tulloch 2018, persistence temperature
//! dependence). Capture is taken as temperature independent.
//! Equation: `tau_e,j(T) = tau_e,j * exp(E_a/k (1/T - 1/T_ref))`, `k` = 8.617e-5 eV/K,
//! `T` the focal-plane temperature of the interval (metadata `focal_plane_temp_k`).
//! Parameters: `activation_ev` (default 0.25 eV: `E = k T ln(nu tau)` for an attempt
//! frequency ~1e12 /s and tau ~1e3 to 1e4 s at 80 K; bounds [0, 2]), `t_ref_k` (default
//! 80 K, the temperature at which the bins' time constants are tabulated; bounds
//! [10, 300]).
//! Visible as: with the array warmer than `t_ref_k` the time constants shorten
//! (x0.64 per kelvin at the defaults). Where the decay is 1/t, a common rescaling of all
//! time constants changes nothing (`sum_j n_j/(s tau_j) exp(-t/(s tau_j))` is scale free
//! for equal charge per decade), so the first dark integrations barely change; what
//! changes is the tail: the slowest filled traps (capture limits filling to
//! `tau_e` <~ 1e5 s) now release within hours, so the current hours after an
//! illumination drops (4 K warmer: -20 % or more at 2.5 h); colder arrays keep it.

use crate::sim::effect::{Effect, ParamReader};
use crate::sim::traps::Bins;
use std::collections::BTreeMap;

pub const BOLTZMANN_EV_PER_K: f64 = 8.617_333e-5;

#[derive(Debug, Clone)]
pub struct Temperature {
    pub activation_ev: f64,
    pub t_ref_k: f64,
}

impl Temperature {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("temperature", p);
        let activation_ev = r.get("activation_ev", 0.25, 0.0, 2.0)?;
        let t_ref_k = r.get("t_ref_k", 80.0, 10.0, 300.0)?;
        r.finish()?;
        Ok(Temperature {
            activation_ev,
            t_ref_k,
        })
    }

    pub fn factor(&self, temp_k: f64) -> f64 {
        (self.activation_ev / BOLTZMANN_EV_PER_K * (1.0 / temp_k - 1.0 / self.t_ref_k)).exp()
    }
}

impl Effect for Temperature {
    fn name(&self) -> &'static str {
        "temperature"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([
            ("activation_ev".to_string(), self.activation_ev),
            ("t_ref_k".to_string(), self.t_ref_k),
        ])
    }
    fn time_constants(&self, bins: &mut Bins, temp_k: f64) {
        let f = self.factor(temp_k);
        bins.tau_e.iter_mut().for_each(|t| *t *= f);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warmer_is_faster() {
        let t = Temperature::from_params(&BTreeMap::new()).unwrap();
        assert!((t.factor(80.0) - 1.0).abs() < 1e-12);
        assert!(t.factor(81.0) < 0.7 && t.factor(81.0) > 0.6);
        assert!(t.factor(79.0) > 1.0);
    }
}
