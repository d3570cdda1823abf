//! Data-driven terms: a smooth function of one covariate, fitted from the data, where no
//! library form carries the physics that `persist diagnose` finds along it.
//!
//! Physics: none assumed. A detector's response to illumination time, temperature,
//! earlier illuminations or its neighbours' charge need not follow any of the library's
//! forms (`soak`'s capture, `temperature`'s Arrhenius law, `capacity`'s Langmuir
//! filling, `blooming`'s spill). Each term here acts on the same quantity as the
//! library effect of its covariate, through a piecewise-linear function `g(u)` of the
//! covariate `u` with three knots, at `u_lo`, `(u_lo + u_hi) / 2` and `u_hi`, whose
//! values `at_lo`, `at_mid`, `at_hi` are fitted (`persist fit --with
//! smooth_duration:log10_t_lo_s=2.08,log10_t_hi_s=2.68`; the knot positions of each term
//! are named with their units, [`Axis::range_names`]). Outside `[u_lo, u_hi]` `g` is constant at its end value, so the term never
//! extrapolates a slope beyond the data it was fitted on. All values 0 is no change.
//!
//! | effect | covariate `u` | what `g` acts on |
//! |---|---|---|
//! | `smooth_duration` | `log10(t_illuminated / 1 s)` | every term's new response, `A_k,n *= exp(g)` (response hook) |
//! | `smooth_temperature` | focal-plane temperature, K | every term's emission rate, `1/tau_n *= exp(g)`, `C_n *= exp(g)` (the charge `A_n C_n tau_n` kept; rates hook) |
//! | `smooth_history` | `log10(H / Q_sat)`, `H` the charge the pixel still holds, `Q_sat` the charge its traps hold after a saturating fill (its largest amplitude on every term) | the capacity of the exposed traps: term `n` keeps `exp(g)^w_n` in (0, 1], `w_n = (tau_n / 1000 s)^-tau_tilt` (limit hook; `tau_tilt` fitted, 0: one factor for every term) |
//! | `smooth_neighbour` | `log10(E_nb / max(F, 1 e-))` | the pixel's fluence, `F += g E_nb` (at least 0; fluence hook) |
//! | `smooth_shape` | `log10(F / 1 e-)` | the decay's shape: every term's new response, `A_k,n *= (tau_n / 1000 s)^g` (response hook; `g > 0`: slower) |
//!
//! `E_nb` is `blooming`'s mean excess of the four nearest neighbours over `f_sat_e`, `F`
//! the pixel's own extrapolated fluence: `g` is the share of the neighbours' excess
//! that the pixel's traps see (positive: charge spills in; negative: the measured
//! fluence holds the neighbours' signal, which the traps did not see).
//!
//! Anchors, held at 0 and not fitted, so that a term cannot act as a change of the whole
//! model (a common factor on every response or every rate is a misfit of the base, not
//! a dependence on the covariate): `smooth_duration`'s `at_hi` (the longest
//! illumination, as a calibration's own usually is: the knots are rescaled for the
//! calibration illumination anyway, [`Effect::response_is_per_pixel`]),
//! `smooth_temperature`'s `at_mid` (the middle of the temperatures measured; measured
//! without it on a family campaign at 78, 80 and 82 K: the three values fitted to
//! -3.66, -3.71, -3.77, a common slowing of every rate) and `smooth_history`'s `at_lo`
//! (a pixel holding little charge keeps its capacity) and `smooth_shape`'s `at_lo` (the
//! faintest pixels keep the model's decay shape: a tilt shared by every fluence is a
//! misfit of the decay law, which `persist fit` measures, not a dependence on the
//! fluence).
//!
//! `smooth_history`'s `tau_tilt` shares the blocking among the terms: a pixel's history
//! need not block its fast and slow traps' fill alike. Measured on the second
//! generator's `capacity:langmuir` campaigns (64 x 64, default `fit`, the term as
//! `diagnose` offers it, flags at 0.1 e-/s by `persist compare`): with `tau_tilt` held
//! at 0 the term under-predicts late, history-holding units, and the flags' margin
//! rises to cover them (seed 1: x 0.660 -> x 0.945, over-flagged 0.67 % -> 0.91 %,
//! 0.71 % at the first model's coverage); offered with `tau_tilt` 0.041, x 0.899,
//! 0.86 %, 0.66 %. Seed 2: 0.91 % -> 1.17 % (0.95 %) held at 0; 0.84 % (0.88 %) with
//! `tau_tilt` 0.075.
//!
//! `smooth_history`'s covariate is the share of the pixel's traps still occupied: a
//! ratio of two charges of the same model, not the held charge in electrons. A model
//! whose amplitudes are all scaled (the flagging model's knots stand at 1.2 times the
//! 95th percentile, the description's at the measured level) holds the same share and
//! gets the same factor, so the term measured against the description keeps its
//! meaning in the flagging model. In electrons the flagging model's larger held charge
//! had moved every pixel up the curve (measured with examples/family_matrix,
//! capacity:ceiling at 64 x 64: the missed fraction at 0.1 e-/s rose from 0.05-0.07 to
//! 0.34-0.37 once the term was added). The share is of the saturated charge, not of
//! what this exposure's traps could hold: at equal history a bright pixel holds a
//! larger share of its traps than a faint one, and blocks more of its next fill
//! (Langmuir blocking, `1 - H / N`), which a ratio to the exposure's own capacity
//! cannot tell apart (a pixel lit alike twice holds the same ratio at every fluence).
//! Invariants: factors finite and > 0 (capacity factor <= 1), fluence finite and >= 0
//! where it was, unknown (NaN) fluence stays unknown, unknown temperature changes
//! nothing; all values at 0 leaves the step unchanged.

use super::blooming::neighbour_excess;
use super::get;
use crate::model::effect::{
    AccumulateRole, Effect, EffectDef, IntervalCtx, ParamSpec, ResponseCtx,
};
use ndarray::{Array2, Array3};
use std::collections::BTreeMap;

/// What a data-driven term acts on (module docs).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Axis {
    Duration,
    Temperature,
    History,
    Neighbour,
    Shape,
}

/// The decay time `smooth_shape` tilts the terms about: a term of this `tau_n` keeps
/// its response, s.
pub const SHAPE_PIVOT_S: f64 = 1000.0;

/// The knot positions and values of one term.
#[derive(Debug, Clone, PartialEq)]
pub struct Smooth {
    pub axis: Axis,
    pub u_lo: f64,
    pub u_hi: f64,
    /// Values at `u_lo`, the midpoint and `u_hi`.
    pub at: [f64; 3],
    /// `smooth_neighbour`'s saturation fluence, e-.
    pub f_sat_e: f64,
    /// `smooth_history`'s tilt of the capacity factor along the decay time: term `n`
    /// keeps `exp(g)^w_n`, `w_n = (tau_n / SHAPE_PIVOT_S)^-tau_tilt` (0: every term
    /// `exp(g)`; > 0: the faster terms blocked more).
    pub tau_tilt: f64,
}

impl Smooth {
    /// `g(u)`: piecewise linear through the three knots, constant outside them; the
    /// first knot's value when `u_hi <= u_lo`, 0 for a non-finite `u`.
    pub fn g(&self, u: f64) -> f64 {
        if !u.is_finite() {
            return 0.0;
        }
        let [a, m, b] = self.at;
        let span = self.u_hi - self.u_lo;
        if span.is_nan() || span <= 0.0 || u <= self.u_lo {
            return a;
        }
        if u >= self.u_hi {
            return b;
        }
        let x = 2.0 * (u - self.u_lo) / span; // 0..2
        if x <= 1.0 {
            a + (m - a) * x
        } else {
            m + (b - m) * (x - 1.0)
        }
    }

    fn is_null(&self) -> bool {
        self.at.iter().all(|v| *v == 0.0)
    }

    /// `smooth_shape`'s response: each term of a pixel of fluence `F` times
    /// `(tau_n / SHAPE_PIVOT_S)^g(log10 F)`; unknown or zero fluence unchanged.
    fn tilt(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.is_null() {
            return;
        }
        // ln(tau_n / pivot)
        let log_tau: Vec<f64> = ctx
            .rate_per_s
            .iter()
            .map(|r| (1.0 / (r * SHAPE_PIVOT_S)).ln())
            .collect();
        for ((y, x), f) in ctx.fluence_e.indexed_iter() {
            if !(f.is_finite() && *f > 0.0) {
                continue;
            }
            let g = self.g(f.log10());
            for (n, lt) in log_tau.iter().enumerate() {
                let k = (g * lt).exp();
                if k.is_finite() {
                    ak[[y, x, n]] *= k;
                }
            }
        }
    }
}

/// An axis' parameters: the two knot positions (`u_lo`, `u_hi`: names with their
/// units, defaults and bounds; not fitted) and the three knot values (`at_lo`, `at_mid`,
/// `at_hi`: default 0, bounds `at_bounds`, fitted unless an anchor; `what` they are, per
/// knot).
const fn axis_params(
    positions: [(&'static str, f64, &'static str); 2],
    position_bounds: (f64, f64),
    at_bounds: (f64, f64),
    fitted: [bool; 3],
    what: [&'static str; 3],
) -> [ParamSpec; 5] {
    const fn spec(
        name: &'static str,
        default: f64,
        (lo, hi): (f64, f64),
        fitted: bool,
        doc: &'static str,
    ) -> ParamSpec {
        ParamSpec {
            name,
            default,
            lo,
            hi,
            null: None,
            fitted,
            doc,
        }
    }
    let [(lo_name, lo_default, lo_doc), (hi_name, hi_default, hi_doc)] = positions;
    [
        spec(lo_name, lo_default, position_bounds, false, lo_doc),
        spec(hi_name, hi_default, position_bounds, false, hi_doc),
        spec("at_lo", 0.0, at_bounds, fitted[0], what[0]),
        spec("at_mid", 0.0, at_bounds, fitted[1], what[1]),
        spec("at_hi", 0.0, at_bounds, fitted[2], what[2]),
    ]
}

impl Axis {
    pub const ALL: [Axis; 5] = [
        Axis::Duration,
        Axis::Temperature,
        Axis::History,
        Axis::Neighbour,
        Axis::Shape,
    ];

    /// The registered effect of this axis.
    pub fn def(self) -> &'static EffectDef {
        match self {
            Axis::Duration => &DURATION,
            Axis::Temperature => &TEMPERATURE,
            Axis::History => &HISTORY,
            Axis::Neighbour => &NEIGHBOUR,
            Axis::Shape => &SHAPE,
        }
    }

    /// The names of its two knot-position parameters (units in the names).
    pub fn range_names(self) -> (&'static str, &'static str) {
        let p = self.def().params;
        (p[0].name, p[1].name)
    }
}

fn build(axis: Axis, p: &BTreeMap<String, f64>) -> Box<dyn Effect> {
    let (lo, hi) = axis.range_names();
    Box::new(Smooth {
        axis,
        u_lo: get(p, lo),
        u_hi: get(p, hi),
        at: [get(p, "at_lo"), get(p, "at_mid"), get(p, "at_hi")],
        f_sat_e: p.get("f_sat_e").copied().unwrap_or(2e5),
        tau_tilt: p.get("tau_tilt").copied().unwrap_or(0.0),
    })
}

const DURATION_PARAMS: [ParamSpec; 5] = axis_params(
    [
        ("log10_t_lo_s", 1.5, "log10 of the shortest illumination, s"),
        ("log10_t_hi_s", 2.7, "log10 of the longest illumination, s"),
    ],
    (-3.0, 6.0),
    (-5.0, 2.0),
    [true, true, false],
    [
        "log of the response factor at u_lo",
        "log of the response factor at the midpoint",
        "log of the response factor at u_hi (the anchor)",
    ],
);

pub const DURATION: EffectDef = EffectDef {
    name: "smooth_duration",
    summary: "data-driven: A_k,n *= exp(g(log10 t_ill)), g piecewise linear, fitted",
    params: &DURATION_PARAMS,
    build: |p| build(Axis::Duration, p),
    covariate: "illumination_time",
};

const TEMPERATURE_PARAMS: [ParamSpec; 5] = axis_params(
    [
        ("t_lo_k", 78.0, "lowest temperature, K"),
        ("t_hi_k", 82.0, "highest temperature, K"),
    ],
    (10.0, 300.0),
    (-5.0, 5.0),
    [true, false, true],
    [
        "log of the emission-rate factor at u_lo",
        "log of the emission-rate factor at the midpoint (the anchor)",
        "log of the emission-rate factor at u_hi",
    ],
);

pub const TEMPERATURE: EffectDef = EffectDef {
    name: "smooth_temperature",
    summary: "data-driven: 1/tau_n and C_n *= exp(g(T)), g piecewise linear, fitted",
    params: &TEMPERATURE_PARAMS,
    build: |p| build(Axis::Temperature, p),
    covariate: "temperature",
};

const HISTORY_PARAMS: [ParamSpec; 6] = {
    let a = axis_params(
    [
        (
            "log10_held_fraction_lo",
            -2.0,
            "log10 of the held charge over the pixel's saturated charge, below which nothing changes",
        ),
        (
            "log10_held_fraction_hi",
            0.0,
            "log10 of the held charge over the pixel's saturated charge, high knot",
        ),
    ],
    (-9.0, 9.0),
    (-5.0, 0.0),
    [false, true, true],
    [
        "log of the capacity factor at u_lo (the anchor)",
        "log of the capacity factor at the midpoint",
        "log of the capacity factor at u_hi",
    ],
    );
    [a[0], a[1], a[2], a[3], a[4], TAU_TILT]
};

/// `smooth_history`'s `tau_tilt` ([`Smooth::tau_tilt`]).
const TAU_TILT: ParamSpec = ParamSpec {
    name: "tau_tilt",
    default: 0.0,
    lo: -1.0,
    hi: 1.0,
    // no null: a data-driven term is not scored (`EffectDef::switch`)
    null: None,
    fitted: true,
    doc: "tilt of the capacity factor along the decay time: term n keeps exp(g)^((tau_n / 1000 s)^-tau_tilt)",
};

pub const HISTORY: EffectDef = EffectDef {
    name: "smooth_history",
    summary:
        "data-driven: exposed capacity *= exp(g(log10 held / saturated charge)), g piecewise linear",
    params: &HISTORY_PARAMS,
    build: |p| build(Axis::History, p),
    covariate: "earlier_illuminations",
};

const NEIGHBOUR_PARAMS: [ParamSpec; 6] = {
    let a = axis_params(
        [
            (
                "log10_ratio_lo",
                0.0,
                "log10 of the neighbours' excess over the own fluence, low knot",
            ),
            (
                "log10_ratio_hi",
                3.0,
                "log10 of the neighbours' excess over the own fluence, high knot",
            ),
        ],
        (-6.0, 9.0),
        (-1.0, 1.0),
        [true, true, true],
        [
            "share of the neighbours' excess fluence at u_lo",
            "share of the neighbours' excess fluence at the midpoint",
            "share of the neighbours' excess fluence at u_hi",
        ],
    );
    [a[0], a[1], a[2], a[3], a[4], super::blooming::F_SAT]
};

pub const NEIGHBOUR: EffectDef = EffectDef {
    name: "smooth_neighbour",
    summary: "data-driven: F += g(log10 E_nb/F) E_nb, g piecewise linear, fitted",
    params: &NEIGHBOUR_PARAMS,
    build: |p| build(Axis::Neighbour, p),
    covariate: "neighbour_excess_fluence",
};

const SHAPE_PARAMS: [ParamSpec; 5] = axis_params(
    [
        (
            "log10_f_lo_e",
            4.5,
            "log10 of the fluence below which the shape is the model's, e-",
        ),
        (
            "log10_f_hi_e",
            7.0,
            "log10 of the fluence of the high knot, e-",
        ),
    ],
    (0.0, 12.0),
    (-1.0, 1.0),
    [false, true, true],
    [
        "tilt of the decay at u_lo (the anchor)",
        "tilt of the decay at the midpoint, per decade of tau_n",
        "tilt of the decay at u_hi, per decade of tau_n",
    ],
);

pub const SHAPE: EffectDef = EffectDef {
    name: "smooth_shape",
    summary: "data-driven: A_k,n *= (tau_n / 1000 s)^g(log10 F), g piecewise linear, fitted",
    params: &SHAPE_PARAMS,
    build: |p| build(Axis::Shape, p),
    covariate: "fluence_x_time",
};

/// The axis of a data-driven term, by effect name.
pub fn axis_of(name: &str) -> Option<Axis> {
    Axis::ALL.into_iter().find(|a| a.def().name == name)
}

/// The data-driven term acting on a contrast class's covariate
/// (`crate::diag::contrast::class_of`), if there is one.
pub fn for_covariate(covariate: &str) -> Option<&'static EffectDef> {
    Axis::ALL
        .into_iter()
        .map(Axis::def)
        .find(|d| d.covariate == covariate)
}

impl Effect for Smooth {
    fn name(&self) -> &'static str {
        self.axis.def().name
    }
    fn is_pixel_local(&self) -> bool {
        self.axis != Axis::Neighbour || self.is_null()
    }
    fn response_reach_px(&self) -> Option<usize> {
        Some(0)
    }
    fn response_is_per_pixel(&self) -> bool {
        matches!(self.axis, Axis::Duration | Axis::Shape)
    }
    fn rates(&self, ctx: &IntervalCtx, c_per_s: &mut [f64], rate_per_s: &mut [f64]) {
        if self.axis != Axis::Temperature {
            return;
        }
        let Some(t) = ctx.focal_plane_temp_k.filter(|t| t.is_finite()) else {
            return;
        };
        let f = self.g(t).exp();
        for (c, r) in c_per_s.iter_mut().zip(rate_per_s.iter_mut()) {
            *c *= f;
            *r *= f;
        }
    }
    fn has_fluence(&self) -> bool {
        self.axis == Axis::Neighbour && !self.is_null()
    }
    fn fluence(&self, fluence_e: &mut Array2<f64>) {
        if !self.has_fluence() {
            return;
        }
        let e_nb = neighbour_excess(fluence_e, self.f_sat_e);
        ndarray::Zip::from(fluence_e).and(&e_nb).for_each(|f, &e| {
            if !f.is_finite() || e.is_nan() || e <= 0.0 {
                return;
            }
            let u = (e / f.max(1.0)).log10();
            let v = *f + self.g(u) * e;
            *f = if v.is_finite() { v.max(0.0) } else { *f };
        });
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.axis == Axis::Shape {
            return self.tilt(ctx, ak);
        }
        if self.axis != Axis::Duration || ctx.t_illuminated_s <= 0.0 {
            return;
        }
        let f = self.g(ctx.t_illuminated_s.log10()).exp();
        if f != 1.0 && f.is_finite() {
            ak.mapv_inplace(|a| a * f);
        }
    }
    fn has_accumulate(&self) -> bool {
        self.axis == Axis::History
    }
    fn accumulate_role(&self) -> AccumulateRole {
        AccumulateRole::Limit
    }
    fn limit_exponents(&self, rate_per_s: &[f64]) -> Option<Vec<f64>> {
        (self.axis == Axis::History && self.tau_tilt != 0.0 && self.tau_tilt.is_finite()).then(
            || {
                rate_per_s
                    .iter()
                    .map(|r| (r * SHAPE_PIVOT_S).powf(self.tau_tilt))
                    .collect()
            },
        )
    }
    fn limit(&self, held_e: f64, _capacity_e: f64, saturated_e: f64) -> f64 {
        if self.axis != Axis::History || !(held_e > 0.0 && saturated_e > 0.0) {
            return 1.0;
        }
        let k = self.g((held_e / saturated_e).log10()).exp();
        if k.is_finite() {
            k.clamp(0.0, 1.0)
        } else {
            1.0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn term(axis: Axis, at: [f64; 3]) -> Smooth {
        Smooth {
            axis,
            u_lo: 2.0,
            u_hi: 3.0,
            at,
            f_sat_e: 100.0,
            tau_tilt: 0.0,
        }
    }

    #[test]
    fn g_is_piecewise_linear_and_flat_outside_the_knots() {
        let s = term(Axis::Duration, [-1.0, 0.5, 0.0]);
        assert_eq!(s.g(1.0), -1.0);
        assert_eq!(s.g(2.0), -1.0);
        assert!((s.g(2.25) - (-0.25)).abs() < 1e-12);
        assert!((s.g(2.5) - 0.5).abs() < 1e-12);
        assert!((s.g(2.75) - 0.25).abs() < 1e-12);
        assert_eq!(s.g(4.0), 0.0);
        assert_eq!(s.g(f64::NAN), 0.0);
    }

    #[test]
    fn the_history_factor_is_a_limit_in_zero_one() {
        // u = log10(held / saturated)
        let s = term(Axis::History, [0.0, -0.5, -2.0]);
        assert_eq!(s.limit(0.0, 1.0, 10.0), 1.0);
        assert_eq!(s.limit(50.0, 1.0, 0.0), 1.0); // no saturated charge: no ratio
        assert_eq!(s.limit(50.0, 1.0, 1.0), 1.0); // below u_lo: the anchor
        assert!((s.limit(1e3, 1.0, 1.0) - (-2.0f64).exp()).abs() < 1e-12);
        assert!((s.limit(10f64.powf(2.5), 1.0, 1.0) - (-0.5f64).exp()).abs() < 1e-12);
        // a model with every amplitude scaled gets the same factor
        let k = s.limit(10f64.powf(2.3), 1.0, 1.0);
        assert!((s.limit(1.44 * 10f64.powf(2.3), 1.0, 1.44) - k).abs() < 1e-12);
        // what this exposure could hold does not enter: the share held is the pixel's
        assert_eq!(s.limit(10f64.powf(2.3), 1e-3, 1.0), k);
    }

    #[test]
    fn the_neighbour_term_moves_fluence_by_a_share_of_the_excess() {
        // one pixel of 10 e- next to a saturated one of 500 e- (f_sat 100): E_nb = 100
        // e-, u = log10(100 / 10) = 1 (below u_lo = 2): share at_lo = 0.5 -> 10 + 50
        let s = term(Axis::Neighbour, [0.5, 0.0, 0.0]);
        let mut f = ndarray::array![[10.0, 500.0], [f64::NAN, 0.0]];
        s.fluence(&mut f);
        assert!((f[[0, 0]] - 60.0).abs() < 1e-9, "{}", f[[0, 0]]);
        assert_eq!(f[[0, 1]], 500.0); // no neighbour above saturation
        assert!(f[[1, 0]].is_nan());
        // a negative share cannot make the fluence negative
        let s = term(Axis::Neighbour, [-1.0, -1.0, -1.0]);
        let mut f = ndarray::array![[10.0, 500.0]];
        s.fluence(&mut f);
        assert_eq!(f[[0, 0]], 0.0);
    }

    #[test]
    fn the_temperature_term_keeps_each_term_s_charge() {
        let s = term(Axis::Temperature, [0.0, 0.0, 0.0]);
        let mut s = s;
        s.u_lo = 78.0;
        s.u_hi = 82.0;
        s.at = [0.2, 0.0, -0.2];
        let ctx = IntervalCtx {
            t_slew_s: 0.0,
            t_exposure_s: 100.0,
            t_meas_s: 50.0,
            t_elapsed_s: 100.0,
            focal_plane_temp_k: Some(78.0),
        };
        let (mut c, mut r) = (vec![2.0, 3.0], vec![0.1, 0.01]);
        s.rates(&ctx, &mut c, &mut r);
        assert!((r[0] - 0.1 * 0.2f64.exp()).abs() < 1e-12);
        assert!((c[1] / r[1] - 300.0).abs() < 1e-9);
        let unknown = IntervalCtx {
            focal_plane_temp_k: None,
            ..ctx
        };
        let (mut c, mut r) = (vec![2.0], vec![0.1]);
        s.rates(&unknown, &mut c, &mut r);
        assert_eq!((c[0], r[0]), (2.0, 0.1));
    }

    /// `smooth_history`'s `tau_tilt`: term `n`'s exponent `(tau_n / 1000 s)^-tau_tilt`,
    /// 1 at the pivot; > 0 the faster terms' larger (blocked more), < 0 the slower ones'.
    #[test]
    fn the_history_tilt_shares_the_factor_along_the_decay_time() {
        let tilted = |t: f64| Smooth {
            tau_tilt: t,
            ..term(Axis::History, [0.0, -0.5, -2.0])
        };
        let rates = [1e-1, 1e-3, 1e-5]; // tau 10 s, 1000 s, 10^5 s
        let w = tilted(0.5).limit_exponents(&rates).expect("tilted");
        for (got, want) in w.iter().zip([10.0, 1.0, 0.1]) {
            assert!((got - want).abs() < 1e-12, "{w:?}");
        }
        let w = tilted(-0.5).limit_exponents(&rates).expect("tilted");
        assert!(w[0] < w[1] && w[1] == 1.0 && w[1] < w[2], "{w:?}");
        assert!(tilted(0.0).limit_exponents(&rates).is_none());
        assert!(tilted(f64::NAN).limit_exponents(&rates).is_none());
        // only the history's term shares a factor
        let shape = Smooth {
            tau_tilt: 0.5,
            ..term(Axis::Shape, [0.0, 0.1, 0.2])
        };
        assert!(shape.limit_exponents(&rates).is_none());
    }

    #[test]
    fn every_term_resolves_with_its_defaults_to_no_change() {
        for def in Axis::ALL.map(Axis::def) {
            let p = def
                .resolve(&serde_json::Map::new())
                .expect("defaults resolve");
            let e = (def.build)(&p);
            assert_eq!(e.name(), def.name);
            assert!(e.is_pixel_local(), "{}", def.name);
            assert_eq!(e.limit(1e4, 1e3, 1e3), 1.0);
            assert!(e.limit_exponents(&[0.1, 1e-3]).is_none(), "{}", def.name);
            assert!(def.switch().is_none(), "{} is not scored", def.name);
        }
    }

    #[test]
    fn shape_tilts_each_term_about_the_pivot_by_the_pixels_own_fluence() {
        // g(log10 F): 0 at 10^4 e- (the anchor), 0.2 from 10^6 e- on
        let s = Smooth {
            axis: Axis::Shape,
            u_lo: 4.0,
            u_hi: 6.0,
            at: [0.0, 0.1, 0.2],
            f_sat_e: 0.0,
            tau_tilt: 0.0,
        };
        let f = Array2::from_shape_vec((1, 3), vec![1e4, 1e7, f64::NAN]).unwrap();
        let rates = [1e-1, 1e-3, 1e-5]; // tau 10 s, 1000 s, 10^5 s
        let mut ak = Array3::from_elem((1, 3, 3), 2.0);
        s.response(
            &ResponseCtx {
                needed: None,
                fluence_e: &f,
                no_slope: &Array2::from_elem(f.dim(), false),
                t_illuminated_s: 481.0,
                t_exposure_s: 613.0,
                rate_per_s: &rates,
                rate_held_per_s: &rates,
                response: &crate::model::Response::new(
                    &crate::model::ModelParams::default().amplitude_knots,
                ),
            },
            &mut ak,
        );
        let a = ak.as_slice().unwrap();
        // faint pixel and unknown fluence: unchanged
        assert_eq!(&a[0..3], &[2.0; 3]);
        assert_eq!(&a[6..9], &[2.0; 3]);
        // bright pixel: (tau / 1000 s)^0.2 = 10^-0.4, 1, 10^0.4
        let want = [2.0 * 10f64.powf(-0.4), 2.0, 2.0 * 10f64.powf(0.4)];
        for (got, w) in a[3..6].iter().zip(want) {
            assert!((got - w).abs() < 1e-12, "{got} {w}");
        }
        assert!(s.response_is_per_pixel());
    }
}
