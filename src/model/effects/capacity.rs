//! `capacity`: a pixel's finite trap capacity: charge it still holds takes capacity
//! from the next illumination.
//!
//! Physics: a pixel has finitely many trap states; the more of them hold charge, the
//! fewer remain to capture (Langmuir filling, `dn = (1 - n/N) dx`). The knots `A_k` are
//! the measured response of empty traps (the calibration's first illumination), so the
//! saturation of a single fill is already in them; what they cannot know is the charge
//! still trapped from earlier illuminations, in any of the pixel's traps, which takes
//! capacity away from the next fill of all of them.
//! Equation (saturate hook, [`crate::model::effect::AccumulateRole::Saturate`]), with
//! the decayed amplitudes `D_n = A_n' exp(-t_elapsed/tau_n)`, `T_n` the amplitude after
//! combining `D_n` with the new response (`D_n + A_k,n` in the paper; what `refill`
//! gives when it is in the model), and `H = sum_m D_m C_m tau_m` the charge the pixel
//! still holds (electrons: the integral of its remaining current):
//! `A_n = D_n + (T_n - D_n) / (1 + H * inv_q_max_per_e)`.
//! A first illumination (`H` = 0) gives the paper's `A_k,n`; an exposure that adds
//! nothing leaves `D`; the fill of every term is cut by the same factor, the short
//! terms included, whose own held charge has long decayed.
//! This is the simulator's truth `capacity` (`sim::effects::capacity`): there every
//! bin's exposed capacity is divided by `1 + (C_tot + H) / n_max`, whose first-fill part
//! the knots take in, leaving `1 / (1 + H / (n_max + C_tot))` for a repeated fill.
//! (History: until 2026-11-22 the map `T / (1 + T * inv)` was applied to the whole
//! amplitude at every exposure and compounded, found with `examples/truth_shape`; until
//! 2026-11-24 the limit was per term, `D_n + (T_n - D_n)(1 - D_n * inv_a_max_per_e)`,
//! so a term's fill saw only that term's held charge: the short terms, empty 30 minutes
//! after an illumination, were never limited, where the held charge is in the long ones.
//! Model files naming `inv_a_max_per_e` are refused, naming the parameter.)
//! Parameter: `inv_q_max_per_e` (1 / the held charge that halves a new fill, 1/e-;
//! default 5e-5, i.e. 20,000 e-, about twice the charge a saturated pixel of the paper
//! holds; bounds [0, 0.01], null 0).
//! Covariate: earlier illuminations (only pixels lit again while they hold charge
//! change; the brightest, which hold the most, change most).

use super::get;
use crate::model::effect::{AccumulateRole, Effect, EffectDef, ParamSpec};

pub const DEF: EffectDef = EffectDef {
    name: "capacity",
    summary: "held charge takes capacity: A = D + (T - D) / (1 + H / Q_max)",
    params: &[ParamSpec {
        name: "inv_q_max_per_e",
        default: 5e-5,
        lo: 0.0,
        hi: 0.01,
        null: Some(0.0),
        fitted: true,
        doc: "1 / the held charge that halves a new fill, 1/e-",
    }],
    build: |p| {
        Box::new(Capacity {
            inv_q_max_per_e: get(p, "inv_q_max_per_e"),
        })
    },
    covariate: "earlier_illuminations",
};

#[derive(Debug, Clone)]
pub struct Capacity {
    pub inv_q_max_per_e: f64,
}

impl Effect for Capacity {
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
        AccumulateRole::Saturate
    }
    fn saturate(&self, a: &mut [f64], decayed: &[f64], charge_per_amplitude: &[f64]) {
        if self.inv_q_max_per_e <= 0.0 {
            return;
        }
        let held: f64 = decayed
            .iter()
            .zip(charge_per_amplitude)
            .map(|(d, q)| d * q)
            .sum();
        let keep = 1.0 / (1.0 + held.max(0.0) * self.inv_q_max_per_e);
        for (t, d) in a.iter_mut().zip(decayed) {
            *t = d + (*t - d) * keep;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn saturates_by_hand() {
        // Q_max = 1000 e-; held charge H = 2 * 250 + 1 * 0 = 500 e- -> a new fill is
        // kept at 1 / (1 + 0.5) = 2/3, in every term (the empty second one too)
        let c = Capacity {
            inv_q_max_per_e: 1e-3,
        };
        let mut a = [550.0, 90.0];
        c.saturate(&mut a, &[250.0, 0.0], &[2.0, 1.0]);
        assert!(
            (a[0] - 450.0).abs() < 1e-12 && (a[1] - 60.0).abs() < 1e-12,
            "{a:?}"
        );
        // nothing held: the whole fill
        let mut a = [400.0, 90.0];
        c.saturate(&mut a, &[0.0, 0.0], &[2.0, 1.0]);
        assert_eq!(a, [400.0, 90.0]);
    }

    /// Regression: the old map `T / (1 + T / A_max)` was applied to the whole amplitude
    /// at every exposure, so each dark exposure shrank a bright pixel's amplitude again.
    /// An exposure that adds nothing must leave the decayed amplitude as it is.
    #[test]
    fn an_exposure_adding_nothing_leaves_the_amplitude_unchanged() {
        let c = Capacity {
            inv_q_max_per_e: 1e-3,
        };
        let d = [500.0, 999.0, 0.0, 20.0, 3000.0];
        let q = [1.8, 1.8, 1.8, 1.8, 1.8];
        let mut a = d;
        for _ in 0..100 {
            c.saturate(&mut a, &d, &q);
        }
        assert_eq!(a, d);
    }
}
