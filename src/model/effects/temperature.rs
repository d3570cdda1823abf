//! `temperature`: Arrhenius emission.
//!
//! Physics: trap emission is thermally activated, `tau ~ exp(E_a / k T)`: warmer arrays
//! release trapped charge faster (Tulloch 2018).
//! Equation (rates hook), for the interval ending with an exposure at temperature `T`:
//! `f = exp(E_a/k (1/T - 1/T_ref))`, `1/tau_n -> 1/(f tau_n)` and `C_n -> C_n / f`
//! (the charge `A_n C_n tau_n` of each term is kept). Unknown temperature: no change.
//! Parameters: `activation_ev` (default 0.25 eV, bounds [0, 2], null 0), `t_ref_k`
//! (80 K; not fitted). `k` = 8.617333e-5 eV/K.
//! Covariate: temperature.

use super::get;
use crate::model::effect::{Effect, EffectDef, IntervalCtx, ParamSpec};

pub const BOLTZMANN_EV_PER_K: f64 = 8.617_333e-5;

pub const DEF: EffectDef = EffectDef {
    name: "temperature",
    summary: "time constants scale as exp(E_a/k (1/T - 1/T_ref))",
    params: &[
        ParamSpec {
            name: "activation_ev",
            default: 0.25,
            lo: 0.0,
            hi: 2.0,
            null: Some(0.0),
            fitted: true,
            doc: "activation energy, eV",
        },
        ParamSpec {
            name: "t_ref_k",
            default: 80.0,
            lo: 10.0,
            hi: 300.0,
            null: None,
            fitted: false,
            doc: "temperature at which the terms apply, K",
        },
    ],
    build: |p| {
        Box::new(Temperature {
            activation_ev: get(p, "activation_ev"),
            t_ref_k: get(p, "t_ref_k"),
        })
    },
    covariate: "temperature",
};

#[derive(Debug, Clone)]
pub struct Temperature {
    pub activation_ev: f64,
    pub t_ref_k: f64,
}

impl Temperature {
    /// `tau(T) / tau(T_ref)`.
    pub fn factor(&self, temp_k: f64) -> f64 {
        (self.activation_ev / BOLTZMANN_EV_PER_K * (1.0 / temp_k - 1.0 / self.t_ref_k)).exp()
    }
}

impl Effect for Temperature {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn rates(&self, ctx: &IntervalCtx, c: &mut [f64], r: &mut [f64]) {
        let Some(t) = ctx.focal_plane_temp_k.filter(|t| t.is_finite() && *t > 0.0) else {
            return;
        };
        let f = self.factor(t);
        if !(f.is_finite() && f > 0.0) {
            return;
        }
        c.iter_mut().for_each(|v| *v /= f);
        r.iter_mut().for_each(|v| *v /= f);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn warmer_decays_faster_and_keeps_charge() {
        let t = Temperature {
            activation_ev: 0.25,
            t_ref_k: 80.0,
        };
        let ctx = |k| IntervalCtx {
            t_slew_s: 0.0,
            t_exposure_s: 180.0,
            t_meas_s: 90.0,
            t_elapsed_s: 180.0,
            focal_plane_temp_k: k,
        };
        // 81 K: f = exp(0.25/8.617333e-5 * (1/81 - 1/80)) = exp(-0.447696) = 0.63909
        let (mut c, mut r) = ([1.0], [0.01]);
        t.rates(&ctx(Some(81.0)), &mut c, &mut r);
        let f = (-0.25 / 8.617_333e-5 / 6480.0f64).exp();
        assert!((f - 0.639_09).abs() < 1e-4);
        assert!((r[0] - 0.01 / f).abs() < 1e-12);
        assert!((c[0] / r[0] - 100.0).abs() < 1e-9); // charge per amplitude kept
        let (mut c, mut r) = ([1.0], [0.01]);
        t.rates(&ctx(None), &mut c, &mut r);
        assert_eq!((c[0], r[0]), (1.0, 0.01));
    }
}
