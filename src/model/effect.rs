//! Model effects: physical corrections to the paper's exponential sum, plugged into the
//! same [`crate::model::Model::step`] the stage uses (ARCHITECTURE.md, "Where effects
//! plug in").
//!
//! An effect is one type implementing [`Effect`], with named parameters (value and
//! bounds, [`ParamSpec`]) so that `persist fit` and `persist diagnose` can vary them.
//! Every hook defaults to "no change"; an effect implements only what it acts on.
//! For one exposure `k+1` after exposure `k` the step calls, in this order:
//!
//! 0. [`Effect::fluence`]: the extrapolated fluence the response is evaluated at, from
//!    the measured one (ipc: what the pixel received before inter-pixel coupling mixed
//!    it with its neighbours'); pixels whose fluence it changes get the paper's `A_k`
//!    of the new value;
//! 1. [`Effect::rates`]: the `(C_n, 1/tau_n)` in force over the interval from the reset
//!    ending `k` to the reset ending `k+1` (temperature). Both the prediction weights
//!    `C_n exp(-t_meas/tau_n)` and the decay factors `exp(-t_elapsed/tau_n)` use them;
//! 2. [`Effect::observe`]: the per-term weights that turn amplitudes `A_n` into the
//!    current the on-board line fit *measures* (linefit_bias). By default the weight is
//!    the instantaneous current at `t_meas`;
//! 3. [`Effect::response`]: this exposure's response planes `A_k,n` (one per term, all
//!    equal to the paper's `A_k(fluence)` on entry): blooming reads the neighbours'
//!    excess fluence, soak the illumination time, short_tau_boost a fluence window;
//! 4. [`Effect::accumulate`]: replaces `A_n = A_n' exp(-t_elapsed/tau_n) + A_k,n`.
//!    Accumulating effects run by [`AccumulateRole`], not by their order in the model
//!    file: first the `Combine` ones (how old and new trapped charge combine: refill;
//!    only the first of them is handed the new response; the plain sum when there is
//!    none), and before them the `Limit` ones ([`Effect::limit`]: the factor on what
//!    the exposed traps of every term can hold, from the charge the pixel still
//!    holds; the new response is multiplied by it before the combination, the fraction
//!    each exposure fills unchanged: capacity). So `[capacity, refill]` and
//!    `[refill, capacity]` are the same model.
//!    An exposure that adds nothing leaves the decayed amplitudes as they are, whatever
//!    the effects (a saturating map of the whole amplitude would compound once per
//!    exposure).
//!
//! With no effect in the model the step is the paper's, bit for bit (the effect path is
//! not entered; see [`crate::model::step`]).
//!
//! # Adding an effect
//! 1. one file in `src/model/effects/` with a type implementing [`Effect`] and a
//!    `pub const DEF: EffectDef` naming it, listing its parameters and building it;
//! 2. one line in [`crate::model::effects::REGISTRY`].
//!
//! Everything else (model file validation, `fit --with NAME`, `compare`, `diagnose`,
//! `run`) finds it through the registry.

use super::response::Response;
use ndarray::{Array2, Array3};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Debug;

/// Where an accumulating effect runs in the step's accumulate stage (see the module
/// docs, item 4): the `Limit` effects scale the new response, then the `Combine`
/// effects (in model-file order) combine it with the decayed amplitudes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum AccumulateRole {
    /// Combines the decayed amplitude with the new response (the first such effect
    /// receives the response; later ones are called with zeros).
    Combine,
    /// Limits what the exposed traps can hold before the combination
    /// ([`Effect::limit`]).
    Limit,
}

/// One named parameter of an effect.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ParamSpec {
    pub name: &'static str,
    /// The value used when the model file does not give one.
    pub default: f64,
    /// Inclusive bounds, checked by `ModelParams::validate` and respected by the fitter.
    pub lo: f64,
    pub hi: f64,
    /// The value at which the effect does nothing (the null hypothesis of `diagnose`),
    /// when this is the parameter that switches the effect on.
    pub null: Option<f64>,
    /// Whether `fit --with` fits this parameter (others keep their value).
    pub fitted: bool,
    /// Unit and meaning.
    pub doc: &'static str,
}

/// A registered effect: its name, parameters and constructor.
#[derive(Clone, Copy)]
pub struct EffectDef {
    pub name: &'static str,
    pub summary: &'static str,
    pub params: &'static [ParamSpec],
    /// Build from a complete, checked parameter map (every `params` name present).
    pub build: fn(&BTreeMap<String, f64>) -> Box<dyn Effect>,
    /// The covariate of `persist compare` that carries this effect's evidence.
    pub covariate: &'static str,
}

impl Debug for EffectDef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EffectDef")
            .field("name", &self.name)
            .finish()
    }
}

impl EffectDef {
    /// Its parameters' names, comma-separated (for errors that name a wrong one).
    pub fn param_names(&self) -> String {
        self.params
            .iter()
            .map(|p| p.name)
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// Fill defaults and check names, finiteness and bounds. Errors name the field as
    /// `effects[i].params.NAME` (the caller adds the index prefix).
    pub fn resolve(
        &self,
        given: &serde_json::Map<String, serde_json::Value>,
    ) -> Result<BTreeMap<String, f64>, String> {
        for k in given.keys() {
            if !self.params.iter().any(|p| p.name == k) {
                let known: Vec<&str> = self.params.iter().map(|p| p.name).collect();
                return Err(format!(
                    "params.{k}: unknown parameter of `{}` (known: {})",
                    self.name,
                    if known.is_empty() {
                        "none".to_string()
                    } else {
                        known.join(", ")
                    }
                ));
            }
        }
        let mut out = BTreeMap::new();
        for p in self.params {
            let v = match given.get(p.name) {
                None => p.default,
                Some(v) => v
                    .as_f64()
                    .ok_or_else(|| format!("params.{}: must be a number", p.name))?,
            };
            if !(v.is_finite() && v >= p.lo && v <= p.hi) {
                return Err(format!(
                    "params.{}: must be finite and in [{}, {}], got {v}",
                    p.name, p.lo, p.hi
                ));
            }
            out.insert(p.name.to_string(), v);
        }
        Ok(out)
    }

    /// The parameter that switches the effect on, with its null value.
    pub fn switch(&self) -> Option<(&'static ParamSpec, f64)> {
        self.params.iter().find_map(|p| p.null.map(|n| (p, n)))
    }
}

/// A named physical effect with its parameters: one entry of a model file's `effects`
/// ([`crate::model::params::ModelParams`]; ARCHITECTURE.md, "Where effects plug in").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EffectSpec {
    pub name: String,
    #[serde(default)]
    pub params: serde_json::Map<String, serde_json::Value>,
    /// Parameters held at their value by `persist fit` and by `diagnose`'s refits,
    /// whatever their [`ParamSpec::fitted`] (a value known from elsewhere: `persist fit
    /// --with NAME:param=value`). Not written when empty, so a
    /// model without pinned parameters has the same identity as one without the field.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fixed: Vec<String>,
}

impl EffectSpec {
    /// The effect `name` at its defaults, nothing pinned.
    pub fn named(name: impl Into<String>) -> EffectSpec {
        EffectSpec {
            name: name.into(),
            params: serde_json::Map::new(),
            fixed: Vec::new(),
        }
    }

    /// Whether `param` is fitted: the effect fits it ([`ParamSpec::fitted`])
    /// and this model does not pin it.
    pub fn fits(&self, param: &ParamSpec) -> bool {
        param.fitted && !self.fixed.iter().any(|f| f == param.name)
    }
}

/// The interval from the reset ending exposure `k` to the reset ending `k+1`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IntervalCtx {
    /// Time from the reset to the start of the integration, s.
    pub t_slew_s: f64,
    pub t_exposure_s: f64,
    /// `t_slew + t_exposure / 2`, s.
    pub t_meas_s: f64,
    /// `t_slew + t_exposure`, s.
    pub t_elapsed_s: f64,
    /// Focal-plane temperature of exposure `k+1`, when known.
    pub focal_plane_temp_k: Option<f64>,
}

/// What the response hook sees of exposure `k+1`.
#[derive(Debug, Clone, Copy)]
pub struct ResponseCtx<'a> {
    /// Extrapolated fluence `max(current, 0) * t_illuminated`, e-; NaN where unknown
    /// (transient, SUR error, non-finite) and 0 for non-functional pixels.
    pub fluence_e: &'a Array2<f64>,
    /// True where the fluence is unknown because the ramp saturated before the on-board
    /// fit had enough reads (`SUR_ERROR`, not a transient): brighter than any pixel with
    /// a slope.
    pub no_slope: &'a Array2<bool>,
    pub t_illuminated_s: f64,
    pub t_exposure_s: f64,
    /// Decay rates `1/tau_n` of the model (before any rate hook), 1/s.
    pub rate_per_s: &'a [f64],
    /// The same terms' emission rates during this exposure: after the rate hooks
    /// ([`Effect::rates`], e.g. at the exposure's focal-plane temperature), 1/s. Equal to
    /// `rate_per_s` in a model without a rate hook.
    pub rate_held_per_s: &'a [f64],
    /// The model's `A_k` table (its knots), which `A_k,n` starts from.
    pub response: &'a Response,
    /// Pixels whose `A_k,n` is read after the hooks (row-major, `ny * nx`); `None` for
    /// all. A hook may leave the planes of the others as they are: nothing reads them.
    /// The step builds it from [`crate::model::effect_step::StepContext::active_pixels`]
    /// widened by the sum of the hooks' [`Effect::response_reach_px`], so that a hook
    /// reading its neighbours' planes finds them as the hooks before it left them
    /// (`None` when a hook's reach is unknown).
    pub needed: Option<&'a [bool]>,
}

impl ResponseCtx<'_> {
    /// Whether pixel `(y, x)`'s planes are read ([`ResponseCtx::needed`]).
    pub fn is_needed(&self, y: usize, x: usize) -> bool {
        self.needed
            .is_none_or(|m| m[y * self.fluence_e.ncols() + x])
    }
}

/// A model effect (module docs). Parameters come from the model file through
/// [`EffectDef::build`]; hooks must not panic and must keep amplitudes finite and >= 0.
pub trait Effect: Send + Sync + Debug {
    fn name(&self) -> &'static str;
    /// Adjust `C_n` (1/s) and `1/tau_n` (1/s) for one interval.
    fn rates(&self, _ctx: &IntervalCtx, _c_per_s: &mut [f64], _rate_per_s: &mut [f64]) {}
    /// Adjust the per-term weights (1/s) that turn amplitudes into the measured current.
    /// `c_per_s`, `rate_per_s` are those of the interval (after [`Effect::rates`]).
    fn observe(
        &self,
        _ctx: &IntervalCtx,
        _c_per_s: &[f64],
        _rate_per_s: &[f64],
        _weights: &mut [f64],
    ) {
    }
    /// True if [`Effect::fluence`] is implemented.
    fn has_fluence(&self) -> bool {
        false
    }
    /// Adjust the extrapolated fluence `[ny, nx]` (e-) of this exposure before `A_k` is
    /// evaluated. NaN marks an unknown fluence and must stay NaN; values must stay
    /// finite and >= 0 elsewhere (others are set to 0).
    fn fluence(&self, _fluence_e: &mut Array2<f64>) {}
    /// The readout's linear coupling of everything the stage measures, if this effect
    /// models one: each pixel reads the pixel at offset `(dy, dx)` with weight `w` and
    /// keeps `1 - sum w` of its own (pixels outside the array add nothing). Empty for
    /// none. A tool that evaluates a response of its own at the model's fluence (the
    /// diagnostics' base) couples it the same way.
    fn readout_kernel(&self) -> Vec<(isize, isize, f64)> {
        Vec::new()
    }
    /// Adjust this exposure's response `A_k,n`, electrons, shape `[ny, nx, n_terms]`.
    fn response(&self, _ctx: &ResponseCtx<'_>, _ak: &mut Array3<f64>) {}
    /// True if [`Effect::response`] changes a pixel's planes from that pixel's own
    /// fluence and the exposure alone (not its position or its neighbours): the
    /// calibration then rescales the knots with it ([`crate::calib::knots`]).
    fn response_is_per_pixel(&self) -> bool {
        false
    }
    /// True if this effect's hooks treat each pixel on its own: what they do to a pixel
    /// depends on that pixel's values and the exposure alone, not on its position, its
    /// neighbours or the array's size. A model whose effects all are
    /// ([`crate::model::Model::is_pixel_local`]) predicts any selection of its pixels
    /// laid out anew as it would on the whole array. False unless the effect says so.
    fn is_pixel_local(&self) -> bool {
        false
    }
    /// How far [`Effect::response`] reaches into the response planes, in steps
    /// between 4-neighbours: a pixel's `A_k,n` after the hook depends on the planes of
    /// the pixels this many steps away or nearer (0: its own alone; what it reads of
    /// the fluence and `no_slope` planes, which are built everywhere, does not count).
    /// The step widens [`ResponseCtx::needed`] by it. `None`: it may read any pixel's
    /// planes, and the step builds them everywhere. Defaults to 0 for a pixel-local
    /// effect ([`Effect::is_pixel_local`]) and to `None` for any other, so that an
    /// effect that declares neither is never given planes it did not expect.
    fn response_reach_px(&self) -> Option<usize> {
        self.is_pixel_local().then_some(0)
    }
    /// True if [`Effect::response`] multiplies `A_k,n` by the fraction (in [0, 1]) of the
    /// exposed traps that fill during the exposure (`soak`). Such hooks run after the
    /// other response hooks, and the combining effects see the fraction
    /// ([`Effect::accumulate`]'s `fill`).
    fn response_is_fill(&self) -> bool {
        false
    }
    /// True if [`Effect::accumulate`] is implemented.
    fn has_accumulate(&self) -> bool {
        false
    }
    /// Where this effect's [`Effect::accumulate`] runs among the accumulating effects.
    fn accumulate_role(&self) -> AccumulateRole {
        AccumulateRole::Combine
    }
    /// Replace `a_n = a_n * decay_n + add_n` for one pixel (`a` holds the decayed
    /// amplitudes on entry). `fill_n` is the fraction of the exposed traps of term `n`
    /// that this exposure fills ([`Effect::response_is_fill`]; 1 without such an
    /// effect): `add_n = fill_n` times the charge the exposed traps could hold.
    fn accumulate(&self, a: &mut [f64], add: &[f64], _fill: &[f64]) {
        for (x, y) in a.iter_mut().zip(add) {
            *x += y;
        }
    }
    /// `Limit` effects (instead of [`Effect::accumulate`]): the factor, finite and in
    /// [0, 1], on what the exposed traps of every term can hold in this exposure, given
    /// `held_e`, the charge the pixel holds as it begins (`sum_n D_n C_n tau_n` over the
    /// decayed amplitudes `D_n`, electrons), and `capacity_e`, the charge its exposed
    /// traps could hold (`sum_n Cap_n C_n tau_n`, the response before the fill fraction
    /// of [`Effect::response_is_fill`]), and `saturated_e`, the charge its traps hold
    /// after a saturating fill (the pixel's largest amplitude on every term, `A_max sum_n
    /// C_n tau_n`). The step multiplies the new response by it before the combination,
    /// leaving the fraction each term fills as it was.
    fn limit(&self, _held_e: f64, _capacity_e: f64, _saturated_e: f64) -> f64 {
        1.0
    }
    /// `Limit` effects: how [`Effect::limit`]'s factor `k` is shared among the terms,
    /// given each term's emission rate in this exposure: term `n` keeps `k^w_n`, `w_n`
    /// finite and >= 0 (so its factor stays in [0, 1]). None: every term keeps `k`.
    fn limit_exponents(&self, _rate_per_s: &[f64]) -> Option<Vec<f64>> {
        None
    }
    /// How the pixels' spread about the prediction is correlated between neighbours
    /// ([`SpreadCorrelation`]; `populations`). Never read by the step: it changes no
    /// prediction and no flag, only how `compare`, `fit` and `diagnose` weigh a cell's
    /// 95th percentile. None: independent pixels.
    fn spread_correlation(&self) -> Option<SpreadCorrelation> {
        None
    }
}

/// The correlation of two distinct pixels' places in their population's spread (above
/// or below a cell's 95th percentile) at a distance `d`: `corr exp(-d^2 / (2
/// length_px^2))` (neighbouring pixels sharing their traps; measured and used by
/// `crate::diag::spread`). A statement about the noise of statistics over many
/// pixels, not about any pixel's persistence.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SpreadCorrelation {
    /// At distance 0, in [0, 1].
    pub corr: f64,
    /// Pixels, > 0.
    pub length_px: f64,
}

impl SpreadCorrelation {
    /// The correlation at `d_px` pixels.
    pub fn at(&self, d_px: f64) -> f64 {
        self.corr * (-d_px * d_px / (2.0 * self.length_px * self.length_px)).exp()
    }
}

/// The observe hook of a measurement model: each term's weight becomes
/// `(1 - s) w_n + s c_n factor(r_n)`, a mix of the weight in force and the term's
/// measured response per unit `C_n` (`chord`: mean current; `linefit_bias`:
/// least-squares slope). `s` = 0 leaves the weights untouched.
pub fn mix_observation(
    w: &mut [f64],
    c_per_s: &[f64],
    rate_per_s: &[f64],
    s: f64,
    factor: impl Fn(f64) -> f64,
) {
    if s == 0.0 {
        return;
    }
    for ((wn, cn), rn) in w.iter_mut().zip(c_per_s).zip(rate_per_s) {
        *wn = (1.0 - s) * *wn + s * (cn * factor(*rn));
    }
}

/// The readout effects' `first_read_s`: the first read of a ramp, s after its reset.
/// The slope measures the charge between the first and the last read, so the current
/// released before the first read is not seen. Not fitted (a property of the readout).
pub const FIRST_READ: ParamSpec = ParamSpec {
    name: "first_read_s",
    default: 0.0,
    lo: 0.0,
    hi: 1000.0,
    null: None,
    fitted: false,
    doc: "first read of the ramp after its reset, s (the frame time)",
};

/// The span the readout sees: from the first read, `t_slew + first_read_s` after the
/// previous reset, to the end of the integration; `(start, length)`, s. A first read
/// at or beyond the integration's end leaves the whole integration.
pub fn read_span(ctx: &IntervalCtx, first_read_s: f64) -> (f64, f64) {
    let t0 = first_read_s.max(0.0);
    if t0 < ctx.t_exposure_s {
        (ctx.t_slew_s + t0, ctx.t_exposure_s - t0)
    } else {
        (ctx.t_slew_s, ctx.t_exposure_s)
    }
}

/// The observe hook of a readout effect (`chord`, `linefit_bias`): [`mix_observation`]
/// with strength `s` of `factor(rate, start, length)` over the [`read_span`] of
/// `first_read_s` (computed once per interval, not per term).
pub fn mix_readout(
    ctx: &IntervalCtx,
    c_per_s: &[f64],
    rate_per_s: &[f64],
    w: &mut [f64],
    s: f64,
    first_read_s: f64,
    factor: fn(f64, f64, f64) -> f64,
) {
    let (t0, t) = read_span(ctx, first_read_s);
    mix_observation(w, c_per_s, rate_per_s, s, |rn| factor(rn, t0, t));
}

/// Least-squares slope weight of one exponential term for an integration of
/// `t_exposure_s` starting `t_slew_s` after the reset, per unit `C_n`:
/// `(6 / T^3) integral_0^T exp(-r (t_slew + u)) u (T - u) du` (dense, uniform samples;
/// the slope of `q(u) = integral i` fitted by least squares, derived by parts from
/// `slope = 12/T^3 integral q(u) (u - T/2) du`). For `r -> 0` it is 1.
pub fn ls_slope_factor(rate_per_s: f64, t_slew_s: f64, t_exposure_s: f64) -> f64 {
    let t = t_exposure_s;
    let x = rate_per_s * t;
    // closed form of (6/T^3) int_0^T e^{-r u} u (T-u) du with x = rT:
    // 6/x^3 [ x(1 + e^{-x}) - 2 (1 - e^{-x}) ]; series for small x.
    let g = if x < 1e-3 {
        1.0 - x / 2.0 + x * x / 10.0
    } else {
        let e = (-x).exp();
        6.0 / (x * x * x) * (x * (1.0 + e) - 2.0 * (1.0 - e))
    };
    (-rate_per_s * t_slew_s).exp() * g
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ls_factor_matches_quadrature() {
        for &(r, ts, t) in &[(0.1, 10.0, 180.0), (1e-3, 0.0, 180.0), (1e-6, 5.0, 112.0)] {
            let n = 20000;
            let h = t / n as f64;
            let mut s = 0.0;
            for i in 0..n {
                let u = (i as f64 + 0.5) * h;
                s += (-r * (ts + u)).exp() * u * (t - u) * h;
            }
            let q = 6.0 / (t * t * t) * s;
            let g = ls_slope_factor(r, ts, t);
            assert!((g / q - 1.0).abs() < 1e-5, "{r} {g} {q}");
        }
    }

    #[test]
    fn resolve_fills_defaults_and_checks_bounds() {
        let def = crate::model::effects::lookup("capacity").unwrap();
        let m = def.resolve(&serde_json::Map::new()).unwrap();
        assert_eq!(m.len(), def.params.len());
        let mut g = serde_json::Map::new();
        g.insert("nope".into(), serde_json::json!(1.0));
        assert!(def.resolve(&g).unwrap_err().contains("params.nope"));
        let mut g = serde_json::Map::new();
        g.insert(def.params[0].name.into(), serde_json::json!(-1e30));
        assert!(def.resolve(&g).unwrap_err().contains(def.params[0].name));
    }

    /// An effect that declares neither locality nor reach is run the safe way: not
    /// local (the diagnostics step the whole array) and any reach (every pixel's planes
    /// built); a local one reaches nothing.
    #[test]
    fn an_effect_that_declares_nothing_is_given_every_pixel() {
        #[derive(Debug)]
        struct Plain;
        impl Effect for Plain {
            fn name(&self) -> &'static str {
                "plain"
            }
        }
        #[derive(Debug)]
        struct Local;
        impl Effect for Local {
            fn name(&self) -> &'static str {
                "local"
            }
            fn is_pixel_local(&self) -> bool {
                true
            }
        }
        assert!(!Plain.is_pixel_local());
        assert_eq!(Plain.response_reach_px(), None);
        assert_eq!(Local.response_reach_px(), Some(0));
    }
}
