//! `capacity`: a finite trap capacity saturates the accumulated amplitude.
//!
//! Physics: a pixel has finitely many traps; the more are filled, the fewer remain to
//! capture (Langmuir-like filling), so the trapped charge grows sub-linearly with what
//! the linear model would add.
//! Equation (accumulate hook), per term: `T = A_n' exp(-t_elapsed/tau_n) + A_k,n`,
//! `A_n = T / (1 + T * inv_a_max_per_e)`.
//! Parameter: `inv_a_max_per_e` (1 / saturation amplitude, 1/e-; default 5e-4, i.e.
//! 2,000 e-; bounds [0, 0.1], null 0).
//! Covariate: fluence (the largest responses are cut most) and earlier illuminations.

use super::get;
use crate::model::effect::{AccumulateRole, Effect, EffectDef, ParamSpec};

pub const DEF: EffectDef = EffectDef {
    name: "capacity",
    summary: "amplitude saturates: A = T / (1 + T / A_max)",
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
    fn accumulate(&self, a: &mut [f64], add: &[f64]) {
        for (x, y) in a.iter_mut().zip(add) {
            let t = *x + y;
            *x = t / (1.0 + t * self.inv_a_max_per_e);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saturates_by_hand() {
        // A_max = 1000 e-: 500 decayed + 500 added = 1000 -> 1000 / 2 = 500.
        let c = Capacity {
            inv_a_max_per_e: 1e-3,
        };
        let mut a = [500.0, 0.0];
        c.accumulate(&mut a, &[500.0, 100.0]);
        assert!((a[0] - 500.0).abs() < 1e-12);
        assert!((a[1] - 100.0 / 1.1).abs() < 1e-12);
    }
}
