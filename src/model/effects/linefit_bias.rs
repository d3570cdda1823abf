//! `linefit_bias`: the on-board least-squares fit of a curved persistence ramp.
//!
//! Physics: persistence charge accumulates as `q(t) ~ A ln(t + tau)` (paper Eq. logfit);
//! a least-squares line through it weights the middle of the ramp (`6 u (T - u) / T^3`),
//! so for a convex decay it reads lower than the mean current over the integration and
//! higher than the instantaneous current at mid-exposure, which the model predicts by
//! default (the paper's factor 1.2 compensates the first of these).
//! Equation (observe hook), per term: the weight `C_n exp(-t_meas/tau_n)` becomes
//! `(1 - s) C_n exp(-t_meas/tau_n) + s C_n G_n`, with
//! `G_n = (6/T^3) integral_0^T exp(-(t_slew + u)/tau_n) u (T - u) du`
//! ([`crate::model::effect::ls_slope_factor`]), the least-squares slope of one term.
//! Parameters: `strength` `s` (default 1, bounds [0, 1], null 0); `first_read_s` (default
//! 0, not fitted): the ramp's first read after its reset; the line is fitted to the reads
//! from there to the end ([`crate::model::effect::read_span`]), as for `chord`.
//! Covariate: time since illumination (the first integrations after a bright one).

use super::get;
use crate::model::effect::{
    ls_slope_factor, mix_readout, Effect, EffectDef, IntervalCtx, ParamSpec, FIRST_READ,
};

pub const DEF: EffectDef = EffectDef {
    name: "linefit_bias",
    summary: "the measured current is the least-squares slope of the ramp",
    params: &[
        ParamSpec {
            name: "strength",
            default: 1.0,
            lo: 0.0,
            hi: 1.0,
            null: Some(0.0),
            fitted: true,
            doc: "mix between the mid-exposure current (0) and the least-squares slope (1)",
        },
        FIRST_READ,
    ],
    build: |p| {
        Box::new(LinefitBias {
            strength: get(p, "strength"),
            first_read_s: get(p, "first_read_s"),
        })
    },
    covariate: "time_since_illumination",
};

#[derive(Debug, Clone)]
pub struct LinefitBias {
    pub strength: f64,
    pub first_read_s: f64,
}

impl Effect for LinefitBias {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn observe(&self, ctx: &IntervalCtx, c: &[f64], r: &[f64], w: &mut [f64]) {
        mix_readout(
            ctx,
            c,
            r,
            w,
            self.strength,
            self.first_read_s,
            ls_slope_factor,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slow_terms_unchanged_fast_terms_lower() {
        let ctx = IntervalCtx {
            t_slew_s: 0.0,
            t_exposure_s: 180.0,
            t_meas_s: 90.0,
            t_elapsed_s: 180.0,
            focal_plane_temp_k: None,
        };
        let c = [1.0, 1.0];
        let r = [1e-9, 0.1];
        let mut w = [(-90.0f64 * 1e-9).exp(), (-9.0f64).exp()];
        LinefitBias {
            strength: 1.0,
            first_read_s: 0.0,
        }
        .observe(&ctx, &c, &r, &mut w);
        // slow term: G -> 1; fast term (x = rT = 18): 6/x^3 (x(1+e^-x) - 2(1-e^-x))
        assert!((w[0] - 1.0).abs() < 1e-6);
        let x: f64 = 18.0;
        let g = 6.0 / x.powi(3) * (x * (1.0 + (-x).exp()) - 2.0 * (1.0 - (-x).exp()));
        assert!((w[1] - g).abs() < 1e-12, "{}", w[1]);
        // s = 0: unchanged
        let mut w0 = [0.5, 0.25];
        LinefitBias {
            strength: 0.0,
            first_read_s: 0.0,
        }
        .observe(&ctx, &c, &r, &mut w0);
        assert_eq!(w0, [0.5, 0.25]);
    }
}
