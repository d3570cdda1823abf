//! `linefit_bias`: the on-board least-squares fit of a curved persistence ramp.
//!
//! Physics: after a reset the persistence charge accumulates as `q(t) ~ A ln(t + tau)`
//! (paper Eq. logfit), a ramp that curves downward. The on-board fit is a least-squares
//! line (paper section 2.2, Zemcov et al. 2016), whose slope is
//! `sum_i w_i q(t_i) = integral i(t) 6 t (T - t) / T^3 dt` for dense samples: it weights
//! the middle of the ramp and under-weights the steep start, so it reads *lower* than
//! the mean current. This is why the paper multiplies its log-fit amplitude by 1.2.
//! Baseline (effect off): the persistence part of each slope is the mean persistence
//! current between the first and last sample used (the chord), i.e. an ideal,
//! unbiased fit of the curved part; the linear part (sky, dark) is fitted by least
//! squares either way, so the noise is the same.
//! Effect on: the persistence part goes through the same least-squares weights as the
//! rest (what SPHEREx does); the image then equals the least-squares fit of `/ramp`.
//! No parameters.
//! Visible as: the first dark integration after a bright illumination reads lower: for
//! `i = A/t` sampled from `t_1` = 1.5 s to `T` = 180 s the chord is `A ln(T/t_1)/T` and
//! the least-squares slope about `3A/T`, ~40 % lower; an hour later (flat ramps) the
//! two agree within 1 %. The default truth is calibrated to Table 1 with the effect
//! off, so switching it on lowers the lab's Table 1 slopes by ~40 %.

use crate::sim::effect::{Effect, ParamReader};
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct LinefitBias;

impl LinefitBias {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        ParamReader::new("linefit_bias", p).finish()?;
        Ok(LinefitBias)
    }
}

impl Effect for LinefitBias {
    fn name(&self) -> &'static str {
        "linefit_bias"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::new()
    }
    fn least_squares_persistence(&self) -> bool {
        true
    }
}
