//! `soak`: slow capture, so persistence depends on how long a pixel is held charged.
//!
//! Physics: traps capture with finite time constants; when capture is slow, the charge
//! trapped depends on the time the pixel is held at a given level ("soak"), not only on
//! the fluence (Long et al. 2015, WFC3/IR persistence grows with exposure time at fixed
//! fluence; Tulloch 2019).
//! Equation: capture time constants `tau_c,j *= capture_scale` for every interval.
//! Parameter: `capture_scale` (default 10, bounds [0.01, 1e4]); baseline
//! `tau_c = 0.002 tau_e` (`TrapParams::capture_ratio`), so 0.02 tau_e at the default.
//! Visible as: after the laboratory illumination (~10 min) the slow bins are less
//! filled: the late persistence (hours) drops much more than the first dark
//! integration's, which is dominated by fast traps that still fill.

use crate::sim::effect::{Effect, ParamReader};
use crate::sim::traps::Bins;
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Soak {
    pub capture_scale: f64,
}

impl Soak {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("soak", p);
        let capture_scale = r.get("capture_scale", 10.0, 0.01, 1e4)?;
        r.finish()?;
        Ok(Soak { capture_scale })
    }
}

impl Effect for Soak {
    fn name(&self) -> &'static str {
        "soak"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([("capture_scale".to_string(), self.capture_scale)])
    }
    fn time_constants(&self, bins: &mut Bins, _temp_k: f64) {
        bins.tau_c.iter_mut().for_each(|t| *t *= self.capture_scale);
    }
}
