//! `soak`: slow capture, so slow terms fill only partly during a short illumination.
//!
//! Physics: traps capture with finite time constants; the charge trapped depends on how
//! long the pixel is held charged, not only on the fluence (Long et al. 2015; Tulloch
//! 2019). A trap population emitting with `tau_n` and capturing with
//! `tau_c = capture_ratio * tau_n`, held charged for `t`, fills to `1 - exp(-t / tau_c)`.
//!
//! # Levels
//! Traps are exposed level by level as charge accumulates (the depletion region shrinks
//! with it). Under a constant flux a pixel of extrapolated fluence `F` lit for `t_ill`
//! reaches level `L` at `t_ill L / F` (beyond full well the excess charge keeps
//! counting, so the same holds with `F` the extrapolated fluence), so the traps at `L`
//! are held for `t_ill (1 - L / F)`. The trap charge per level is read from the model's
//! own `A_k` table: `A'(L)`. Hence, per term, with `k = t_ill rate_n / capture_ratio`,
//! `fill_n(F) = (1/A(F)) integral_0^F A'(L) (1 - exp(-k (1 - L/F))) dL`, in closed form per
//! linear segment of the table ([`Soak::fill_at`]). A pixel whose charge is mostly
//! reached early (far above saturation) fills almost as if held the whole time; a
//! pixel just above the saturation jump holds its forward-bias traps only briefly.
//! Where `F` is unknown because the ramp had no slope (`SUR_ERROR`,
//! [`ResponseCtx::no_slope`]) the pixel is brighter than any measured one: its charge
//! is reached early and its traps are held nearly the whole integration, so the fill is
//! the level-blind `1 - exp(-k)`, `k = t_exp rate_n / capture_ratio` ([`Soak::fill`]).
//! Kept at the full amplitude instead, the brightest pixels of the laboratory campaign's
//! x4 illumination would carry unsoaked slow terms into the next illumination. A
//! transient's fluence is unknown for another reason; it keeps the transient rule's
//! amplitude (the maximum unless measured in flight) whatever the hooks do.
//! Below the first knot the table is linear through 0 and the fill does not depend on
//! `F`: one value per term and exposure (every dark pixel).
//!
//! # Emission while held
//! A trap held charged also emits, so it fills to the equilibrium
//! `r_c / (r_c + r_e)` of capture (`r_c = rate_n / capture_ratio`) against emission
//! (`r_e`), as the truth simulator's traps do (`sim::traps`, "Occupancy"). The knots are
//! measured at the reference temperature, where that equilibrium is already in them; at
//! another temperature the rate hooks (`temperature`) change `r_e` to `rate_held_n`
//! ([`ResponseCtx::rate_held_per_s`]) and the fill is scaled by the equilibrium's
//! change, `eq_n = (r_c + rate_n) / (r_c + rate_held_n)` (1 without a rate hook, so a
//! model without `temperature` is unchanged). A warmer exposure fills every term less
//! (x0.973 at 82 K for `capture_ratio` 0.02 and 0.25 eV), a colder one more. The
//! filling speed keeps capture alone (`k` above): `capture_ratio` << 1.
//! Without this factor, with hidden `soak` and `temperature` the truth's first darks
//! after the 82 K illumination are 2.5 % below the product of the two effects apart,
//! and the model's are not.
//!
//! # Relative to the calibration illumination
//! The paper's flagging calibration takes its knots from the calibration illumination's
//! first dark (95th percentile, 1.2 margin) and its `C_n` from measured decays: both
//! already hold the fill of an illumination of that duration. With a reference
//! (`reference_lit_s` > 0, lit that long in an integration of `reference_exposure_s`)
//! the fill is taken relative to it, `fill_n(F) / fill_n,ref(F)` (the same pixel's
//! fluence, the reference's timing): an illumination like the calibration's keeps its
//! calibrated response and margin, a shorter one fills its slow terms less, a longer
//! one more. `capture_ratio` means the same in both forms (the ratio of two absolute
//! fills is the relative fill), so a value measured against the measurements'
//! description carries over. `persist fit` sets the reference to the calibration
//! illumination when it adds `soak` to a calibration that already holds that
//! illumination's response: the flagging calibration, or one whose decay law was
//! measured on it (`--fit-decay-exponent`, as `diagnose`'s description of the
//! measurements; [`crate::calib::effects`]).
//! Without a reference (0, the default of a model file that names none, and of a fit
//! whose decay law is given, `persist fit --preset readout`) the fill is absolute, as in
//! the simulator's truth (`sim::effects::soak`), where the `C_n` are those of full
//! traps; there it also lowers the calibration illumination's slow terms, i.e. it
//! reshapes the decay law as well as the contrast between durations.
//! Why the flagging model is relative: measured on the second truth generator (family
//! soak:capture, seed 1, 64 x 64, examples/family_matrix), the flagging model with the
//! absolute form missed 13 % of the samples truly above 0.1 e-/s after the calibration
//! illumination itself (0.9 % without `soak`), and 18 % after the 120 s one.
//!
//! Equation (response hook): `A_k,n *= fill_n(F) eq_n / fill_n,ref(F)` (1 when
//! `capture_ratio` = 0; `fill_n,ref` = 1 without a reference).
//! Parameters: `capture_ratio` (default 0.1, bounds [0, 100], null 0);
//! `reference_lit_s`, `reference_exposure_s` (not fitted; default 0: no reference).
//! Covariate: illumination (soak) time, and time since illumination (the slow tail).
//!
//! A `capture_ratio` fitted with the level-blind form `A_k,n *= 1 - exp(-k)` for every
//! pixel does not carry over to this one.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use crate::model::Response;
use ndarray::parallel::prelude::*;
use ndarray::{Array3, Axis};

/// The parameters naming the reference illumination (module docs, "Relative to the
/// calibration illumination"): its lit time and its integration, s.
pub const REFERENCE_LIT_S: &str = "reference_lit_s";
pub const REFERENCE_EXPOSURE_S: &str = "reference_exposure_s";

pub const DEF: EffectDef = EffectDef {
    name: "soak",
    summary: "slow terms fill as 1 - exp(-t_ill / (ratio tau_n))",
    params: &[
        ParamSpec {
            name: "capture_ratio",
            default: 0.1,
            lo: 0.0,
            hi: 100.0,
            null: Some(0.0),
            fitted: true,
            doc: "capture time constant / emission time constant",
        },
        ParamSpec {
            name: REFERENCE_LIT_S,
            default: 0.0,
            lo: 0.0,
            hi: 1e6,
            null: None,
            fitted: false,
            doc: "the calibration illumination's lit time, s (0: absolute fill)",
        },
        ParamSpec {
            name: REFERENCE_EXPOSURE_S,
            default: 0.0,
            lo: 0.0,
            hi: 1e6,
            null: None,
            fitted: false,
            doc: "the calibration illumination's integration, s",
        },
    ],
    build: |p| {
        Box::new(Soak {
            capture_ratio: get(p, "capture_ratio"),
            reference: Some((get(p, REFERENCE_LIT_S), get(p, REFERENCE_EXPOSURE_S)))
                .filter(|(lit, _)| *lit > 0.0),
        })
    },
    covariate: "illumination_time",
};

#[derive(Debug, Clone)]
pub struct Soak {
    pub capture_ratio: f64,
    /// The calibration illumination's (lit, integration) times, s: the fill is relative
    /// to it (module docs); None: absolute.
    pub reference: Option<(f64, f64)>,
}

impl Soak {
    /// Fill fraction of term `rate_per_s` for charge held `t_held_s` (the level-blind
    /// form: every trap held for the whole time).
    pub fn fill(&self, rate_per_s: f64, t_held_s: f64) -> f64 {
        if self.capture_ratio <= 0.0 {
            1.0
        } else {
            -(-t_held_s * rate_per_s / self.capture_ratio).exp_m1()
        }
    }

    /// The change of term `rate_per_s`'s equilibrium fill when it emits at
    /// `rate_held_per_s` instead (module docs, "Emission while held").
    pub fn held_factor(&self, rate_per_s: f64, rate_held_per_s: f64) -> f64 {
        if self.capture_ratio <= 0.0 || !(rate_held_per_s.is_finite() && rate_held_per_s > 0.0) {
            return 1.0;
        }
        let r_c = rate_per_s / self.capture_ratio;
        let f = (r_c + rate_per_s) / (r_c + rate_held_per_s);
        if f.is_finite() {
            f
        } else {
            1.0
        }
    }

    /// Fill fraction of term `rate_per_s` in a pixel of extrapolated fluence
    /// `fluence_e` lit for `t_ill_s` of an integration of `t_exp_s`, with `A_k` =
    /// `response` (module docs, "Levels"). Traps at level `L` are held
    /// `t_exp (1 - L/G)`, `G = F t_exp / t_ill`, so with `k = t_exp rate / ratio`:
    /// `(1/A(F)) integral_0^F A'(L) (1 - exp(-k (1 - L/G))) dL`. The level-blind
    /// [`Soak::fill`] over `t_exp` where `F` is unknown (NaN) or `A(F)` is 0.
    pub fn fill_at(
        &self,
        response: &Response,
        fluence_e: f64,
        rate_per_s: f64,
        t_ill_s: f64,
        t_exp_s: f64,
    ) -> f64 {
        if self.capture_ratio <= 0.0 {
            return 1.0;
        }
        let t_exp_s = t_exp_s.max(t_ill_s);
        let a = response.amplitude_e(fluence_e);
        if fluence_e.is_nan() || fluence_e <= 0.0 || a.is_nan() || a <= 0.0 || t_ill_s <= 0.0 {
            return self.fill(rate_per_s, t_exp_s);
        }
        let g = fluence_e * (t_exp_s / t_ill_s);
        let k = t_exp_s * rate_per_s / self.capture_ratio;
        if k < 1e-6 {
            // first order in k: k * integral A'(L) (1 - L/G) dL / A(F)
            let m: f64 = response
                .segments_below(fluence_e)
                .map(|(l0, l1, s)| s * ((l1 - l0) - (l1 * l1 - l0 * l0) / (2.0 * g)))
                .sum();
            return (k * m / a).clamp(0.0, 1.0);
        }
        // per segment [l0, l1], slope s: s [(l1 - l0) - (G/k) (e1 - e0)], so
        // held = A(F) - (G/k) sum s (e1 - e0), e_i = exp(-k (1 - l_i/G)) <= 1. From the top
        // segment down: below the level where e1 < e^-60 the terms are below rounding
        // (a fast term of a laboratory exposure, lit 481 s of 613, adds none at all).
        // e1 - e0 = e0 expm1(k (l1 - l0)/G) where that argument is small (no
        // cancellation), the plain difference elsewhere (no overflow).
        let mut sum = 0.0;
        for (l0, l1, s) in response.segments_below(fluence_e).rev() {
            let arg1 = k * (1.0 - l1 / g);
            if arg1 > 60.0 {
                break;
            }
            let e0 = (-k * (1.0 - l0 / g)).exp();
            let x = k * (l1 - l0) / g;
            let de = if x < 1.0 {
                e0 * x.exp_m1()
            } else {
                (-arg1).exp() - e0
            };
            sum += s * de;
        }
        let held = a - g / k * sum;
        let f = held / a;
        if f.is_finite() {
            f.clamp(0.0, 1.0)
        } else {
            self.fill(rate_per_s, t_exp_s)
        }
    }

    /// [`Soak::fill_at`] over the same pixel's fill in the reference illumination
    /// (module docs, "Relative to the calibration illumination"); the absolute fill
    /// without a reference. A NaN fluence takes the level-blind form in both.
    pub fn fill_relative(
        &self,
        response: &Response,
        fluence_e: f64,
        rate_per_s: f64,
        t_ill_s: f64,
        t_exp_s: f64,
    ) -> f64 {
        let f = self.fill_at(response, fluence_e, rate_per_s, t_ill_s, t_exp_s);
        let Some((lit_ref, exp_ref)) = self.reference else {
            return f;
        };
        let f_ref = self.fill_at(response, fluence_e, rate_per_s, lit_ref, exp_ref);
        if f_ref > 0.0 && (f / f_ref).is_finite() {
            f / f_ref
        } else {
            f
        }
    }
}

impl Effect for Soak {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn response_is_per_pixel(&self) -> bool {
        true
    }
    fn response_is_fill(&self) -> bool {
        true
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.capture_ratio <= 0.0 {
            return;
        }
        let (t, t_exp) = (ctx.t_illuminated_s, ctx.t_exposure_s);
        // Below the first knot the table is linear through 0, so the fill does not depend
        // on the fluence (the ramp is self-similar): one value per term and exposure for
        // most pixels (every dark pixel), the integral only above it.
        let x1 = ctx.response.first_segment().0;
        let eq: Vec<f64> = ctx
            .rate_per_s
            .iter()
            .zip(ctx.rate_held_per_s)
            .map(|(r, h)| self.held_factor(*r, *h))
            .collect();
        let first: Vec<f64> = ctx
            .rate_per_s
            .iter()
            .zip(&eq)
            .map(|(r, e)| self.fill_relative(ctx.response, x1, *r, t, t_exp) * e)
            .collect();
        let blind: Vec<f64> = ctx
            .rate_per_s
            .iter()
            .zip(&eq)
            .map(|(r, e)| self.fill_relative(ctx.response, f64::NAN, *r, t, t_exp) * e)
            .collect();
        ak.axis_iter_mut(Axis(0))
            .into_par_iter()
            .zip(ctx.fluence_e.axis_iter(Axis(0)).into_par_iter())
            .zip(ctx.no_slope.axis_iter(Axis(0)).into_par_iter())
            .enumerate()
            .for_each(|(y, ((mut a_row, f_row), ns_row))| {
                for (x, ((mut lane, f), ns)) in
                    a_row.outer_iter_mut().zip(f_row).zip(ns_row).enumerate()
                {
                    if !ctx.is_needed(y, x) {
                        continue;
                    }
                    if *ns {
                        // no slope: held nearly the whole integration (module docs)
                        for (a, fi) in lane.iter_mut().zip(&blind) {
                            *a *= fi;
                        }
                        continue;
                    }
                    if f.is_nan() || *f <= 0.0 {
                        // no charge (A_k = 0), or a transient: the step keeps its own rule
                        continue;
                    }
                    if *f <= x1 {
                        for (a, fi) in lane.iter_mut().zip(&first) {
                            *a *= fi;
                        }
                    } else {
                        for ((a, r), e) in lane.iter_mut().zip(ctx.rate_per_s).zip(&eq) {
                            *a *= self.fill_relative(ctx.response, *f, *r, t, t_exp) * e;
                        }
                    }
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::params::Knot;
    use ndarray::Array2;

    fn linear() -> Response {
        // A(L) = L / 1000 up to 1e6 e-
        Response::new(&[Knot {
            fluence_e: 1e6,
            amplitude_e: 1e3,
        }])
    }

    #[test]
    fn a_uniform_trap_density_fills_as_a_ramp() {
        // A linear in L: traps at level L are held t (1 - L/F), so the fill is
        // integral_0^1 (1 - e^{-k(1-x)}) dx = 1 - (1 - e^{-k})/k.
        let s = Soak {
            capture_ratio: 1.0,
            reference: None,
        };
        for k in [1e-9f64, 1e-3, 0.1, 1.0, 10.0, 1e3, 1e6] {
            let want = if k < 1e-6 {
                k / 2.0
            } else {
                1.0 + (-k).exp_m1() / k
            };
            let got = s.fill_at(&linear(), 5e5, k / 100.0, 100.0, 100.0);
            assert!(
                (got - want).abs() < 1e-9 * want.max(1e-9),
                "k {k}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn charge_reached_early_is_held_longer() {
        // a step at 1e3 e- (all of A reached in the first 1 % of the illumination) fills
        // as if held the whole time; an unknown fluence takes the level-blind form.
        let step = Response::new(&[
            Knot {
                fluence_e: 1e3,
                amplitude_e: 10.0,
            },
            Knot {
                fluence_e: 1e5,
                amplitude_e: 10.0,
            },
        ]);
        let s = Soak {
            capture_ratio: 1.0,
            reference: None,
        };
        let (r, t) = (0.01, 100.0);
        let blind = s.fill(r, t);
        let got = s.fill_at(&step, 1e5, r, t, t);
        // held between 0.99 t and t
        assert!(got > s.fill(r, 0.99 * t) && got < blind, "{got}");
        assert_eq!(s.fill_at(&step, f64::NAN, r, t, t), blind);
    }

    #[test]
    fn below_the_first_knot_the_fill_does_not_depend_on_the_fluence() {
        let r = Response::new(&[
            Knot {
                fluence_e: 3e3,
                amplitude_e: 3.0,
            },
            Knot {
                fluence_e: 2e5,
                amplitude_e: 400.0,
            },
        ]);
        let s = Soak {
            capture_ratio: 0.05,
            reference: None,
        };
        for rate in [1.0, 1e-2, 1e-4] {
            let at_knot = s.fill_at(&r, 3e3, rate, 481.0, 613.0);
            for f in [1.0, 10.0, 2999.0] {
                let v = s.fill_at(&r, f, rate, 481.0, 613.0);
                assert!((v - at_knot).abs() < 1e-9, "{rate} {f}: {v} vs {at_knot}");
            }
        }
    }

    #[test]
    fn charge_is_held_until_the_reset() {
        // lit 100 s of a 200 s integration: the charge stays until the reset, so traps
        // at level L are held 200 - 100 L/F s; for a linear table that is
        // integral_0^1 (1 - e^{-k (1 - x/2)}) dx, k = 200 rate / ratio
        let s = Soak {
            capture_ratio: 1.0,
            reference: None,
        };
        let r = 0.004;
        let k = 200.0 * r;
        let want = 1.0 - 2.0 / k * ((-k / 2.0f64).exp() - (-k).exp());
        let got = s.fill_at(&linear(), 5e5, r, 100.0, 200.0);
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        assert!(got > s.fill_at(&linear(), 5e5, r, 100.0, 100.0));
    }

    #[test]
    fn slow_terms_fill_partly() {
        // ratio 1, t_ill 100 s, a pixel far above the table's last knot (A flat beyond
        // 1e3 e-, so all of it is reached in the first 1e-4 of the time): tau 10 s ->
        // 1 - e^-10; tau 1000 s -> close to 1 - e^-0.1 = 0.09516
        let f = Array2::<f64>::from_elem((1, 1), 1e7);
        let rates = [0.1, 0.001];
        let mut ak = Array3::from_elem((1, 1, 2), 100.0);
        let response = Response::new(&[Knot {
            fluence_e: 1e3,
            amplitude_e: 100.0,
        }]);
        Soak {
            capture_ratio: 1.0,
            reference: None,
        }
        .response(
            &ResponseCtx {
                needed: None,
                fluence_e: &f,
                no_slope: &ndarray::Array2::from_elem(f.dim(), false),
                t_illuminated_s: 100.0,
                t_exposure_s: 100.0,
                rate_per_s: &rates,
                rate_held_per_s: &rates,
                response: &response,
            },
            &mut ak,
        );
        assert!((ak[[0, 0, 0]] - 100.0 * (1.0 - (-10.0f64).exp())).abs() < 1e-3);
        assert!((ak[[0, 0, 1]] - 9.516_258_196).abs() < 1e-3);
    }

    #[test]
    fn the_reference_illumination_keeps_its_calibrated_response() {
        // relative to a 481 s illumination of a 613 s integration: that illumination's
        // fill ratio is 1 for every term and fluence, a 120 s one fills the slow terms
        // less, a longer one more; the fast terms (filled either way) stay at 1
        let s = Soak {
            capture_ratio: 0.5,
            reference: Some((481.0, 613.0)),
        };
        for f in [f64::NAN, 10.0, 5e5, 5e7] {
            for rate in [1.0, 1e-2, 1e-4] {
                let same = s.fill_relative(&linear(), f, rate, 481.0, 613.0);
                assert!((same - 1.0).abs() < 1e-12, "{f} {rate}: {same}");
            }
            let short = s.fill_relative(&linear(), f, 1e-4, 120.0, 252.0);
            let long = s.fill_relative(&linear(), f, 1e-4, 2000.0, 2132.0);
            assert!(short < 0.6 && long > 2.0, "{f}: {short} {long}");
            let fast = s.fill_relative(&linear(), f, 1.0, 120.0, 252.0);
            assert!((fast - 1.0).abs() < 1e-3, "{f}: {fast}");
        }
        // without a reference the fill is absolute
        let abs = Soak {
            reference: None,
            ..s
        };
        let v = abs.fill_relative(&linear(), 5e5, 1e-4, 481.0, 613.0);
        assert_eq!(v, abs.fill_at(&linear(), 5e5, 1e-4, 481.0, 613.0));
        assert!(v < 0.1, "{v}");
    }
}
