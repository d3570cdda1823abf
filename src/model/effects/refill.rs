//! `refill`: a trap that is still full cannot be filled again.
//!
//! Physics: the paper's model adds each illumination's response to the decayed
//! amplitudes, `A_n = A_n' exp(-t/tau_n) + A_k,n`, as if every illumination found empty
//! traps. A trap is either full or empty: an illumination fills the traps its charge
//! exposes up to their equilibrium occupancy, and traps still holding charge from an
//! earlier illumination cannot capture more (they relax toward equilibrium, draining
//! with their emission time constant when above it). For traps that fill during the
//! illumination the occupancy after it is therefore `max(decayed, new)`, not the sum;
//! traps that fill only partly behave in between. Repeated illuminations (a campaign)
//! are over-predicted by the linear rule.
//! Equation (accumulate hook), per term, with the decayed amplitude
//! `D = A_n' exp(-t_elapsed/tau_n)` and the new response `A = A_k,n`:
//! `A_n = D + A - beta min(f D, A)`: `D + A` (the paper) at `beta` = 0, `max(D, A)` (a trap
//! cannot fill twice) at `beta` = 1 when the exposure fills every exposed trap (`f` = 1).
//! `f` is the fraction of the exposed traps the exposure fills (`soak`,
//! [`Effect::response_is_fill`]; 1 without it), `A = f Cap` with `Cap` what the exposed
//! traps could hold: at `beta` = 1 the occupancy relaxes toward `Cap` by the fraction
//! `f`, `D + f max(0, Cap - D)` (the truth simulator's relaxation, `sim::traps`). With
//! `f` = 1 in every term this is `D + A - beta min(D, A)` (bit for bit).
//! Parameter: `beta` (dimensionless; default 0.5, the start of the fit; bounds [0, 1],
//! null 0).
//! Covariate: earlier illuminations: only pixels lit again while their traps
//! still hold charge change; a single illumination is not affected.
//!
//! Role [`AccumulateRole::Combine`]: in a model with `capacity` as well, `capacity`
//! first limits the capacity the new response exposes and `refill` then combines old
//! and new charge, whatever their order in the model file.

use super::get;
use crate::model::effect::{AccumulateRole, Effect, EffectDef, ParamSpec};

pub const DEF: EffectDef = EffectDef {
    name: "refill",
    summary: "traps cannot fill twice: A = D + A_k - beta min(D, A_k)",
    params: &[ParamSpec {
        name: "beta",
        default: 0.5,
        lo: 0.0,
        hi: 1.0,
        null: Some(0.0),
        fitted: true,
        doc: "overlap of old and new filling: 0 adds (paper), 1 takes the larger",
    }],
    build: |p| {
        Box::new(Refill {
            beta: get(p, "beta"),
        })
    },
    covariate: "earlier_illuminations",
};

#[derive(Debug, Clone)]
pub struct Refill {
    pub beta: f64,
}

impl Effect for Refill {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn has_accumulate(&self) -> bool {
        true
    }
    fn accumulate_role(&self) -> AccumulateRole {
        AccumulateRole::Combine
    }
    fn accumulate(&self, a: &mut [f64], add: &[f64], fill: &[f64]) {
        for ((d, n), f) in a.iter_mut().zip(add).zip(fill) {
            *d = *d + n - self.beta * (f * *d).min(*n);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refills_by_hand() {
        // beta 0.5: D = 300, A = 200 -> 300 + 200 - 0.5 * 200 = 400;
        // D = 0 (never lit): the paper's A = 50; A = 0 (dark): D = 80 decays on.
        let r = Refill { beta: 0.5 };
        let mut a = [300.0, 0.0, 80.0];
        r.accumulate(&mut a, &[200.0, 50.0, 0.0], &[1.0; 3]);
        assert_eq!(a, [400.0, 50.0, 80.0]);
        // beta 1: the larger; beta 0: the sum (the paper)
        let mut a = [300.0, 100.0];
        Refill { beta: 1.0 }.accumulate(&mut a, &[200.0, 250.0], &[1.0; 2]);
        assert_eq!(a, [300.0, 250.0]);
        let mut a = [300.0];
        Refill { beta: 0.0 }.accumulate(&mut a, &[200.0], &[1.0]);
        assert_eq!(a, [500.0]);
    }

    #[test]
    fn partly_filling_traps_relax_toward_their_capacity() {
        // beta 1, D + f max(0, Cap - D): D = 100, Cap = 400, f = 0.25 (A = 100) -> 175;
        // D = 300 above Cap = 200, f = 0.5 (A = 100): nothing added -> 300
        let mut a = [100.0, 300.0];
        Refill { beta: 1.0 }.accumulate(&mut a, &[100.0, 100.0], &[0.25, 0.5]);
        assert_eq!(a, [175.0, 300.0]);
    }
}
