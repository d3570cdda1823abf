//! `capacity`: a finite total trap capacity per pixel, which limits accumulation over
//! repeated illuminations.
//!
//! Physics: the trap states of a pixel are finite. When a large fraction is exposed at
//! once, capture competes for them and the exposed capacity saturates (Langmuir-like
//! filling); states that still hold charge from earlier illuminations are occupied and
//! count against the same total, so a pixel lit again while it holds charge exposes
//! fewer free states: trap capacity limits accumulation over repeated illuminations.
//! The per-bin relaxation of [`crate::sim::traps`] already keeps a
//! full bin from filling twice; this effect couples the bins through the pixel's total.
//! Equation: every bin's exposed capacity is multiplied by
//! `1 / (1 + (C_tot + H) / n_max)`, where `C_tot = (D_lin e_lin + D_sat e_sat) *
//! decades` is the pixel's total exposed capacity without the effect (electrons;
//! decades = log10(tau_max/tau_min) = 6) and `H` the charge its traps hold as the
//! exposure begins ([`CapacityCtx::held_e`]). A first illumination (`H` = 0) is
//! compressed by `1 / (1 + C_tot / n_max)` alone, which a calibration's knots take in
//! (so a single illumination cannot tell this effect apart); a repeated one also by what
//! the pixel still holds. Counting `H` is what makes the effect identifiable: without
//! it the effect would be a fluence response only, which the knots absorb.
//! Parameter: `n_max_e` (default 20,000 e-, bounds [100, 1e9]; assumed: about twice the
//! total trapped charge of a typical saturated pixel of the paper, ~9,000 e-).
//! Visible as: persistence of heavily saturated pixels drops by ~30 % while pixels
//! below full well change by only a few per cent; the rise beyond saturation flattens;
//! an illumination repeated while the pixel holds charge adds less persistence than the
//! first (two equal 240 s illuminations 30 minutes apart: the second's first dark is 7 %
//! lower relative to the first's than without the effect, saturated pixels,
//! `tests/sim_effects.rs`).

use crate::sim::effect::{CapacityCtx, Effect, ParamReader};
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Capacity {
    pub n_max_e: f64,
}

impl Capacity {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("capacity", p);
        let n_max_e = r.get("n_max_e", 20_000.0, 100.0, 1e9)?;
        r.finish()?;
        Ok(Capacity { n_max_e })
    }
}

impl Effect for Capacity {
    fn name(&self) -> &'static str {
        "capacity"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([("n_max_e".to_string(), self.n_max_e)])
    }
    fn has_capacity(&self) -> bool {
        true
    }
    fn capacity(&self, c: &CapacityCtx<'_>, factor: &mut [f64]) {
        let decades = c.tau_e.len().saturating_sub(1) as f64 / c.bins_per_decade;
        let total = (c.d_lin * c.e_lin + c.d_sat * c.e_sat) * decades;
        let f = 1.0 / (1.0 + (total + c.held_e) / self.n_max_e);
        factor.iter_mut().for_each(|v| *v *= f);
    }
}
