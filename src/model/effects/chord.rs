//! `chord`: the measured current is the mean persistence current over the integration.
//!
//! Physics: the slope of a ramp measures the charge collected between its first and
//! last read divided by the time between them. For a constant current that is the
//! current; for a decaying persistence current it is the mean current over the
//! integration (the chord of the curved charge ramp), which for a convex decay lies
//! above the instantaneous current at mid-exposure that the paper's model predicts
//! (for `i ~ 1/t` from 10 s to 190 s by 64 %). An ideal fit of the curved persistence
//! ramp (charge difference, or a fit of the curve itself) measures the chord; the
//! on-board least-squares line measures less ([`super::linefit_bias`]).
//! Equation (observe hook), per term: the weight `C_n exp(-t_meas/tau_n)` becomes
//! `(1 - s) C_n exp(-t_meas/tau_n) + s C_n M_n`, with
//! `M_n = exp(-t_slew/tau_n) (1 - exp(-T/tau_n)) / (T/tau_n)` (the mean of
//! `exp(-t/tau_n)` from `t_slew` to `t_slew + T`; 1 for `T/tau_n -> 0`).
//! Parameters: `strength` `s` (default 1, bounds [0, 1], null 0); `first_read_s` (default
//! 0, not fitted): the ramp's first read after its reset. The slope measures the charge
//! between the first and the last read, so the mean runs from `t_slew + first_read_s`
//! to `t_slew + T` ([`crate::model::effect::read_span`]); the simulator's and SPHEREx's
//! first read is one frame, 1.5 s, after the reset. With 0 (the default) the mean runs
//! from the reset, and the current of the fastest terms before the first read, which no
//! read sees, counts: with terms from 1 s that over-predicts the first dark after a
//! bright illumination (a fitted `strength` of ~0.86 then makes up for it).
//! `persist fit --with chord:strength=1,first_read_s=1.5` pins both: the readout is
//! known, not fitted.
//! Covariate: time since illumination (the first integrations after a bright one).
//!
//! With `linefit_bias` as well, list `chord` first: `linefit_bias` then mixes the chord
//! with the least-squares slope (its null keeps the chord).

use super::get;
use crate::model::effect::{mix_readout, Effect, EffectDef, IntervalCtx, ParamSpec, FIRST_READ};

pub const DEF: EffectDef = EffectDef {
    name: "chord",
    summary: "the measured current is the mean current over the integration",
    params: &[
        ParamSpec {
            name: "strength",
            default: 1.0,
            lo: 0.0,
            hi: 1.0,
            null: Some(0.0),
            fitted: true,
            doc: "mix between the mid-exposure current (0) and the mean current (1)",
        },
        FIRST_READ,
    ],
    build: |p| {
        Box::new(Chord {
            strength: get(p, "strength"),
            first_read_s: get(p, "first_read_s"),
        })
    },
    covariate: "time_since_illumination",
};

/// Mean of `exp(-r t)` over `t` in `[t_slew, t_slew + T]`.
pub fn mean_factor(rate_per_s: f64, t_slew_s: f64, t_exposure_s: f64) -> f64 {
    let x = rate_per_s * t_exposure_s;
    let g = if x < 1e-6 {
        1.0 - x / 2.0
    } else {
        -(-x).exp_m1() / x
    };
    (-rate_per_s * t_slew_s).exp() * g
}

#[derive(Debug, Clone)]
pub struct Chord {
    pub strength: f64,
    pub first_read_s: f64,
}

impl Effect for Chord {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn observe(&self, ctx: &IntervalCtx, c: &[f64], r: &[f64], w: &mut [f64]) {
        mix_readout(ctx, c, r, w, self.strength, self.first_read_s, mean_factor);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Slew 10 s, integration 20 s (measured mid-exposure at 20 s).
    fn slew_10_exposure_20() -> IntervalCtx {
        IntervalCtx {
            t_slew_s: 10.0,
            t_exposure_s: 20.0,
            t_meas_s: 20.0,
            t_elapsed_s: 30.0,
            focal_plane_temp_k: None,
        }
    }

    #[test]
    fn mean_current_by_hand() {
        // r = 0.1/s, slew 10 s, T = 20 s: mean of e^{-0.1 t} over [10, 30]
        // = (e^{-1} - e^{-3}) / (0.1 * 20) = (0.367879 - 0.049787) / 2 = 0.159046
        let ctx = slew_10_exposure_20();
        let mut w = [(-2.0f64).exp(), 1.0];
        Chord {
            strength: 1.0,
            first_read_s: 0.0,
        }
        .observe(&ctx, &[1.0, 2.0], &[0.1, 1e-12], &mut w);
        assert!((w[0] - 0.159046).abs() < 1e-6, "{}", w[0]);
        assert!((w[1] - 2.0).abs() < 1e-9);
        // above the mid-exposure value e^{-2} = 0.135335 (convex decay)
        assert!(w[0] > (-2.0f64).exp());
        let mut w0 = [0.5];
        Chord {
            strength: 0.0,
            first_read_s: 0.0,
        }
        .observe(&ctx, &[1.0], &[0.1], &mut w0);
        assert_eq!(w0, [0.5]);
    }

    /// `first_read_s`: the mean from the first read, not from the reset. r = 0.1/s,
    /// slew 10 s, T = 20 s, first read 5 s: the mean of e^{-0.1 t} over [15, 30]
    /// = (e^{-1.5} - e^{-3}) / (0.1 * 15) = (0.223130 - 0.049787) / 1.5 = 0.115562,
    /// below the 0.159046 from the reset; a first read at or past the end keeps the
    /// whole integration.
    #[test]
    fn mean_current_from_the_first_read() {
        let ctx = slew_10_exposure_20();
        let chord = |first_read_s| {
            let mut w = [(-2.0f64).exp()];
            Chord {
                strength: 1.0,
                first_read_s,
            }
            .observe(&ctx, &[1.0], &[0.1], &mut w);
            w[0]
        };
        assert!((chord(5.0) - 0.115562).abs() < 1e-6, "{}", chord(5.0));
        assert!((chord(0.0) - 0.159046).abs() < 1e-6);
        assert_eq!(chord(20.0), chord(0.0));
    }
}
