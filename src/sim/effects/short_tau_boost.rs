//! `short_tau_boost`: extra short-lived traps for fluences of 200,000 to 500,000 e-.
//!
//! Physics: the paper (end of section 4) found that "the shortest time constants had a
//! strong boost, particularly for pixels with fluence between 200000 and 500000 e-",
//! cause unknown (blooming suspected). Modelled as extra capacity in the fast bins for
//! pixels whose true photon fluence of the exposure lies in the window.
//! Equation: `C_j *= factor` for `tau_e,j <= tau_max_s` when
//! `fluence_min_e <= flux * t_illuminated <= fluence_max_e`.
//! Parameters: `factor` (default 3, bounds [1, 100]), `tau_max_s` (default 30 s, the
//! paper's fastest model term has tau = 10 s), `fluence_min_e` (200,000),
//! `fluence_max_e` (500,000).
//! Visible as: in the first dark integration after illumination, pixels in the window
//! read higher (fast traps dominate the first minutes); pixels outside are unchanged;
//! an hour later the difference is gone.

use crate::sim::effect::{CapacityCtx, Effect, ParamReader};
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct ShortTauBoost {
    pub factor: f64,
    pub tau_max_s: f64,
    pub fluence_min_e: f64,
    pub fluence_max_e: f64,
}

impl ShortTauBoost {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("short_tau_boost", p);
        let factor = r.get("factor", 3.0, 1.0, 100.0)?;
        let tau_max_s = r.get("tau_max_s", 30.0, 0.0, 1e7)?;
        let fluence_min_e = r.get("fluence_min_e", 2e5, 0.0, 1e12)?;
        let fluence_max_e = r.get("fluence_max_e", 5e5, 0.0, 1e12)?;
        r.finish()?;
        if fluence_max_e < fluence_min_e {
            return Err(crate::Error::invalid(
                "--effect short_tau_boost:fluence_max_e",
                "must be >= fluence_min_e",
            ));
        }
        Ok(ShortTauBoost {
            factor,
            tau_max_s,
            fluence_min_e,
            fluence_max_e,
        })
    }
}

impl Effect for ShortTauBoost {
    fn name(&self) -> &'static str {
        "short_tau_boost"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([
            ("factor".to_string(), self.factor),
            ("tau_max_s".to_string(), self.tau_max_s),
            ("fluence_min_e".to_string(), self.fluence_min_e),
            ("fluence_max_e".to_string(), self.fluence_max_e),
        ])
    }
    fn has_capacity(&self) -> bool {
        true
    }
    fn capacity(&self, c: &CapacityCtx<'_>, factor: &mut [f64]) {
        if c.fluence_e < self.fluence_min_e || c.fluence_e > self.fluence_max_e {
            return;
        }
        for (f, &t) in factor.iter_mut().zip(c.tau_e) {
            if t <= self.tau_max_s {
                *f *= self.factor;
            }
        }
    }
}
