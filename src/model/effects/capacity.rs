//! `capacity`: a pixel's finite trap capacity: charge it still holds takes capacity
//! from the next illumination.
//!
//! Physics: a pixel has finitely many trap states; the more of them hold charge, the
//! fewer remain to capture (Langmuir filling, `dn = (1 - n/N) dx`). The knots `A_k` are
//! the measured response of empty traps (the calibration's first illumination), so the
//! saturation of a single fill is already in them; what they cannot know is the charge
//! still trapped from earlier illuminations, in any of the pixel's traps, which takes
//! capacity away from the next fill of all of them.
//! Equation (limit hook, [`crate::model::effect::AccumulateRole::Limit`]), with
//! `H = sum_m D_m C_m tau_m` the charge the pixel still holds as the exposure begins
//! (electrons: the integral of its remaining current; `D_m` the decayed amplitudes)
//! and `Q = sum_m Cap_m C_m tau_m` the charge its exposed traps could hold (the
//! knots' response before any fill fraction): every term's exposed capacity is
//! multiplied by
//! `k = (1 + C / Q_max) / (1 + (C + H) / Q_max)`, `C = Q / (1 - min(Q / Q_max, 0.9))`,
//! before the new response is combined with `D` (by `refill`, or the paper's sum).
//! This is the simulator's truth (`sim::effects::capacity`): there every bin's exposed
//! capacity is divided by `1 + (C_tot + H) / n_max`, `C_tot` the pixel's exposed
//! capacity without the effect. The knots are the calibration's first fill (`H` = 0),
//! already divided by `1 + C_tot / n_max`, so a later fill keeps `k` of it; `C` is
//! `C_tot` recovered from the knots' compressed `Q = C_tot / (1 + C_tot / n_max)`.
//! With `refill` at `beta` 1 the occupancy then relaxes toward the limited capacity,
//! `D + f max(0, k Cap - D)` (`f` the fraction filled), as the truth's bins do: a term
//! that still holds more than `k Cap` gains nothing. A first illumination (`H` = 0)
//! gives the paper's `A_k,n`; an exposure that adds nothing leaves `D`.
//! Why the limit is on the capacity, from the pixel's whole held charge: a per-term
//! limit (`D_n + (T_n - D_n)(1 - D_n * inv_a_max_per_e)`) sees only that term's held
//! charge, so the short terms, empty 30 minutes after an illumination, are never
//! limited, while the held charge is in the long ones; a cut on what the combination
//! adds (`D_n + (T_n - D_n) / (1 + H * inv_q_max_per_e)`) gives a term holding half its
//! capacity `k` of the other half where the truth gives `k Cap - D` (on the 8-repeat
//! campaign at 128 x 128 the fit's residual RMS is 1.61 that way, 1.33 with this form).
//! Model files naming `inv_a_max_per_e` (the per-term form) are refused, naming the
//! parameter.
//! Parameter: `inv_q_max_per_e` (1 / the held charge that halves a new fill, 1/e-;
//! default 5e-5, i.e. 20,000 e-, about twice the charge a saturated pixel of the paper
//! holds; bounds [0, 0.01], null 0).
//! Covariate: earlier illuminations (only pixels lit again while they hold charge
//! change; the brightest, which hold the most, change most).

use super::get;
use crate::model::effect::{AccumulateRole, Effect, EffectDef, ParamSpec};

pub const DEF: EffectDef = EffectDef {
    name: "capacity",
    summary: "held charge takes capacity: Cap *= (1 + C / Q_max) / (1 + (C + H) / Q_max)",
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
        AccumulateRole::Limit
    }
    fn limit(&self, held_e: f64, capacity_e: f64, _saturated_e: f64) -> f64 {
        let inv = self.inv_q_max_per_e;
        if !(inv > 0.0 && held_e > 0.0) {
            return 1.0;
        }
        let q = capacity_e.max(0.0);
        let c = q / (1.0 - (q * inv).min(0.9));
        (1.0 + c * inv) / (1.0 + (c + held_e) * inv)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn limits_by_hand() {
        // Q_max = 1000 e-; nothing exposed (C = 0), H = 500 e- held: 1 / (1 + 0.5)
        let c = Capacity {
            inv_q_max_per_e: 1e-3,
        };
        assert!((c.limit(500.0, 0.0, 1e9) - 2.0 / 3.0).abs() < 1e-12);
        // Q = 450 e- exposed: C = 450 / (1 - 0.45) = 818.18 e- (the knots' compressed
        // 450 = C / (1 + C / Q_max)), k = (1 + 0.81818) / (1 + 1.31818) = 0.78431
        let k = c.limit(500.0, 450.0, 1e9);
        let cc: f64 = 450.0 / 0.55;
        assert!((cc / (1.0 + cc * 1e-3) - 450.0).abs() < 1e-9);
        assert!((k - (1.0 + cc * 1e-3) / (1.0 + (cc + 500.0) * 1e-3)).abs() < 1e-12);
        assert!((k - 0.784_31).abs() < 1e-5, "{k}");
        // nothing held, or no effect: the whole capacity
        assert_eq!(c.limit(0.0, 450.0, 1e9), 1.0);
        assert_eq!(
            Capacity {
                inv_q_max_per_e: 0.0
            }
            .limit(500.0, 450.0, 1e9),
            1.0
        );
        // a pixel whose exposed capacity reaches Q_max is capped at C = 10 Q
        let k = c.limit(500.0, 5000.0, 1e9);
        assert!(k.is_finite() && k > 0.0 && k < 1.0, "{k}");
    }
}
