//! `capacity`: a finite trap capacity limits how much charge a pixel that still holds
//! charge can take.
//!
//! Physics: a pixel has finitely many traps; the more are filled, the fewer remain to
//! capture. In Langmuir filling, `dn = (1 - n/N) dx` for an exposure `x`, an exposure
//! that would fill `f` into empty traps fills, to first order, `f (1 - n/N)` from
//! occupancy `n`. The
//! knots `A_k` are the measured response of empty traps (the calibration's first
//! illumination), so their own saturation is already in them; what the knots cannot
//! know is the charge still trapped from earlier illuminations, which takes capacity
//! away from the next one.
//! Equation (saturate hook, [`crate::model::effect::AccumulateRole::Saturate`]), per
//! term, with the decayed amplitude `D = A_n' exp(-t_elapsed/tau_n)` and `T` the
//! amplitude after combining it with the new response (`D + A_k,n` in the paper; what
//! `refill` gives when it is in the model):
//! `A_n = D + (T - D) max(0, 1 - D * inv_a_max_per_e)`.
//! A first illumination (`D` = 0) gives the paper's `A_k,n`; an exposure that adds
//! nothing leaves `D`.
//! (Until 2026-11-22 the equation was `A_n = T / (1 + T * inv_a_max_per_e)`, applied to
//! the whole amplitude at every exposure: a first illumination came out below the
//! calibrated knots and every dark exposure shrank a bright pixel's amplitude again by
//! `1 / (1 + A_n * inv_a_max_per_e)`, so the predicted decay of saturated pixels
//! steepened with the number of exposures instead of following the `C_n`. Found with
//! `examples/truth_shape`.)
//! Parameter: `inv_a_max_per_e` (1 / saturation amplitude `N`, 1/e-; default 5e-4,
//! i.e. 2,000 e-; bounds [0, 0.1], null 0).
//! Covariate: earlier illuminations (only pixels lit again while they hold charge
//! change), and fluence (the brightest hold the most).

use super::get;
use crate::model::effect::{AccumulateRole, Effect, EffectDef, ParamSpec};

pub const DEF: EffectDef = EffectDef {
    name: "capacity",
    summary: "held charge takes capacity: A = D + (T - D)(1 - D / A_max)",
    params: &[ParamSpec {
        name: "inv_a_max_per_e",
        default: 5e-4,
        lo: 0.0,
        hi: 0.1,
        null: Some(0.0),
        fitted: true,
        doc: "1 / saturation amplitude, 1/e-",
    }],
    build: |p| {
        Box::new(Capacity {
            inv_a_max_per_e: get(p, "inv_a_max_per_e"),
        })
    },
    covariate: "fluence",
};

#[derive(Debug, Clone)]
pub struct Capacity {
    pub inv_a_max_per_e: f64,
}

impl Effect for Capacity {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn has_accumulate(&self) -> bool {
        true
    }
    fn accumulate_role(&self) -> AccumulateRole {
        AccumulateRole::Saturate
    }
    fn saturate(&self, a: &mut [f64], decayed: &[f64]) {
        if self.inv_a_max_per_e <= 0.0 {
            return;
        }
        for (t, d) in a.iter_mut().zip(decayed) {
            let free = (1.0 - d * self.inv_a_max_per_e).max(0.0);
            *t = d + (*t - d) * free;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saturates_by_hand() {
        // A_max = 1000 e-: 500 held + 500 added -> 500 + 500 * (1 - 0.5) = 750;
        // empty traps take all of the response; a full pixel takes nothing more
        let c = Capacity {
            inv_a_max_per_e: 1e-3,
        };
        let mut a = [1000.0, 100.0, 1500.0];
        c.saturate(&mut a, &[500.0, 0.0, 1000.0]);
        assert_eq!(a, [750.0, 100.0, 1000.0]);
    }

    /// Regression: the old map `T / (1 + T / A_max)` was applied to the whole amplitude
    /// at every exposure, so each dark exposure shrank a bright pixel's amplitude again.
    /// An exposure that adds nothing must leave the decayed amplitude as it is.
    #[test]
    fn an_exposure_adding_nothing_leaves_the_amplitude_unchanged() {
        let c = Capacity {
            inv_a_max_per_e: 1e-3,
        };
        let d = [500.0, 999.0, 0.0, 20.0, 3000.0];
        let mut a = d;
        for _ in 0..100 {
            c.saturate(&mut a, &d);
        }
        assert_eq!(a, d);
    }
}
