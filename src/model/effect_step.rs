//! [`Model::step`] for a model with effects: the same algorithm as the fused kernel of
//! [`crate::model::step`] (predict, flag, early release, decay, respond), with the
//! hooks of [`crate::model::effect`] in between. Entered only when the model file lists
//! effects, so the paper's model keeps its fused kernel unchanged.
//!
//! Per exposure: the fluence hook ([`Effect::fluence`], only when an effect has one);
//! interval rates and observation weights (vectors, [`Effect::rates`],
//! [`Effect::observe`]); the response planes `A_k,n` `[ny, nx, n_terms]`
//! ([`Effect::response`]; built only here); then one pass over the pixels with
//! [`Effect::accumulate`] when an effect has it. Pixels of unknown fluence keep the
//! maximum amplitude (a transient: the model's transient rule) and non-functional
//! pixels add nothing, whatever the hooks say;
//! except pixels with no slope (`SUR_ERROR`, not a transient): brighter than any
//! measured pixel, they take the hooks' amplitudes capped at the maximum, so that a
//! hook that fills less than the whole capacity (`soak`'s level-blind fill) applies to
//! them too (otherwise the brightest pixels of an illumination would carry unsoaked
//! slow terms into the next one).
//! The per-pixel prediction, flags, early release and outputs are the fused kernel's
//! own code (`Kernel::predict_flag_release`, `Kernel::write_pixel`); only the decay and
//! the per-term response differ. With [`StepContext::active_pixels`] the pixel pass
//! skips the pixels the caller does not read, except in the rows the early-release
//! background samples ([`Model::quiet_rows`]): their states are read, so they are
//! always advanced. The response hooks may skip the pixels whose planes nothing reads
//! ([`ResponseCtx::needed`]: those, widened by the hooks' reach to their neighbours).

use super::effect::{AccumulateRole, Effect, IntervalCtx, ResponseCtx};
use super::fluence::{pixel_fluence, PixelFluence};
use super::state::State;
use super::step::{Input, Model, Output, StepSummary};
use crate::error::Error;
use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// What the step knows beyond the product's image: the exposure's environment, and
/// which pixels the caller needs.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepContext<'a> {
    /// `focal_plane_temp_k` of the exposure, when the product has it.
    pub focal_plane_temp_k: Option<f64>,
    /// Pixels the caller will read (row-major, `ny * nx`), `None` for all. A model with
    /// effects advances only these pixels; the state, current and flags of the others
    /// are left as they were and must not be used afterwards. Exact for the pixels it
    /// keeps: a pixel's state depends on its own history, on the response planes
    /// (built wherever they are read, [`ResponseCtx::needed`]: spatial hooks see every
    /// neighbour they reach), and on the early-release background, whose sample rows
    /// ([`Model::quiet_rows`]) are always advanced.
    /// The paper's fused kernel ignores it (it advances every pixel). Used by the
    /// diagnostics, which read predictions at a random subsample of pixels.
    pub active_pixels: Option<&'a [bool]>,
}

/// Pixel kinds of the response planes.
const KNOWN: u8 = 0;
/// Unknown fluence (transient, fit error, non-finite): the maximum amplitude (a
/// transient: the transient rule's, [`crate::model::ModelParams::transient_amplitude_e`]).
const UNKNOWN: u8 = 1;
/// Non-functional: adds nothing.
const NONFUNC: u8 = 2;
/// Unknown fluence because the ramp saturated before the on-board fit had its reads:
/// the hooks' amplitudes, capped at the maximum.
const NO_SLOPE: u8 = 3;

/// The pixels whose response planes are read: `active`, every pixel of the rows the
/// early-release background samples (`quiet_rows`), and the pixels `reach` steps
/// between 4-neighbours from them ([`ResponseCtx::needed`]).
fn needed_pixels(
    active: &[bool],
    ny: usize,
    nx: usize,
    quiet_rows: Option<usize>,
    reach: usize,
) -> Vec<bool> {
    let mut m = active.to_vec();
    if let Some(r) = quiet_rows {
        for y in (0..ny).step_by(r.max(1)) {
            m[y * nx..(y + 1) * nx].fill(true);
        }
    }
    for _ in 0..reach {
        let was = m.clone();
        for y in 0..ny {
            for x in 0..nx {
                if was[y * nx + x] {
                    crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| {
                        m[y * nx + x] = true
                    });
                }
            }
        }
    }
    m
}

impl Model {
    /// [`Model::step`] with the exposure's environment (temperature), which effects
    /// may use. A model without effects ignores it.
    pub fn step_with(
        &self,
        state: &mut State,
        input: &Input<'_>,
        ctx: &StepContext,
        out: &mut Output<'_>,
    ) -> Result<StepSummary, Error> {
        if self.effects().is_empty() {
            return self.step_fused(state, input, out);
        }
        self.check_pixel_response(state)?;
        step(self, self.effects(), state, input, ctx, out)
    }

    /// Run one exposure: see the documentation of [`super::step`]. Nothing is changed
    /// on error. A model with effects goes through this module's step (without an
    /// environment; the stage uses [`Model::step_with`]).
    pub fn step(
        &self,
        state: &mut State,
        input: &Input<'_>,
        out: &mut Output<'_>,
    ) -> Result<StepSummary, Error> {
        self.step_with(state, input, &StepContext::default(), out)
    }
}

pub(crate) fn step(
    model: &Model,
    effects: &[Box<dyn Effect>],
    state: &mut State,
    input: &Input<'_>,
    ctx: &StepContext<'_>,
    out: &mut Output<'_>,
) -> Result<StepSummary, Error> {
    let (ny, nx) = state.shape();
    if let Some(a) = ctx.active_pixels {
        if a.len() != ny * nx {
            return Err(Error::invalid(
                "active_pixels",
                format!("{} entries for a {ny} x {nx} state", a.len()),
            ));
        }
    }
    let k = model.prepare(state, input, out)?;
    let quiet_rows = model.quiet_rows(input);
    let n = k.n;
    let sum = model.exp_sum();
    let (w, decay) = match state.t_reset_unix_s {
        None => (k.w.clone(), k.decay.clone()),
        Some(t_reset) => {
            let t_slew = input.t_start_unix_s - t_reset;
            let ictx = IntervalCtx {
                t_slew_s: t_slew,
                t_exposure_s: input.t_exposure_s,
                t_meas_s: t_slew + 0.5 * input.t_exposure_s,
                t_elapsed_s: t_slew + input.t_exposure_s,
                focal_plane_temp_k: ctx.focal_plane_temp_k,
            };
            let (w, d) = interval_weights(effects, &sum.c_per_s, &sum.rate_per_s, &ictx);
            (w, d)
        }
    };
    // the pixels whose planes are read (all without `active_pixels`)
    let reach: Option<usize> = effects.iter().map(|e| e.response_reach_px()).sum();
    let needed = ctx
        .active_pixels
        .zip(reach)
        .map(|(a, reach)| needed_pixels(a, ny, nx, quiet_rows, reach));
    let is_needed = |i: usize| needed.as_ref().is_none_or(|m| m[i]);
    // Response planes: per pixel its kind and its fluence (every pixel: the fluence
    // hooks and the spatial hooks read them at any neighbour), and the paper's
    // amplitude where it is read (rows in parallel; the same `response_of` as the
    // fused kernel).
    let image = input.image_e_per_s.as_standard_layout();
    let image = image.as_slice().expect("standard layout");
    let flags_in = contiguous(out.flags);
    let mut base = Array2::<f64>::zeros((ny, nx));
    let mut kind = Array2::<u8>::zeros((ny, nx)); // KNOWN, UNKNOWN (max) or NONFUNC
    let mut fluence = Array2::<f64>::zeros((ny, nx));
    (
        base.as_slice_mut().expect("owned").par_chunks_mut(nx),
        kind.as_slice_mut().expect("owned").par_chunks_mut(nx),
        fluence.as_slice_mut().expect("owned").par_chunks_mut(nx),
        image.par_chunks(nx),
        flags_in.par_chunks(nx),
    )
        .into_par_iter()
        .enumerate()
        .for_each(|(y, (b, kd, fl, img, f))| {
            for x in 0..img.len() {
                b[x] = if is_needed(y * nx + x) {
                    k.response_of(img[x], f[x]).0
                } else {
                    0.0
                };
                match pixel_fluence(img[x], f[x], &k.bits, k.t_illuminated_s) {
                    PixelFluence::NonFunctional => kd[x] = NONFUNC,
                    PixelFluence::Unknown => {
                        kd[x] = UNKNOWN;
                        fl[x] = f64::NAN;
                    }
                    PixelFluence::Known(e) => fl[x] = e,
                }
            }
        });
    if effects.iter().any(|e| e.has_fluence()) {
        let mut adjusted = fluence.clone();
        for e in effects.iter().filter(|e| e.has_fluence()) {
            e.fluence(&mut adjusted);
        }
        // only pixels whose fluence changed get a new `A_k` (a null hook changes nothing)
        for (i, (((b, f), g), kd)) in base
            .iter_mut()
            .zip(fluence.iter_mut())
            .zip(adjusted.iter())
            .zip(kind.iter())
            .enumerate()
        {
            if *kd == KNOWN && g.to_bits() != f.to_bits() {
                let g = if g.is_finite() { g.max(0.0) } else { 0.0 };
                *f = g;
                if is_needed(i) {
                    *b = k.response.amplitude_e(g);
                }
            }
        }
    }
    let mut ak = Array3::<f64>::zeros((ny, nx, n));
    ak.as_slice_mut()
        .expect("owned")
        .par_chunks_mut(nx * n)
        .zip(base.as_slice().expect("owned").par_chunks(nx))
        .enumerate()
        .for_each(|(y, (a_row, b_row))| {
            for (x, (a, b)) in a_row.chunks_exact_mut(n).zip(b_row).enumerate() {
                if is_needed(y * nx + x) {
                    a.fill(*b);
                }
            }
        });
    // unknown because the ramp saturated before the on-board fit had its reads (not a
    // transient): brighter than any measured pixel
    let no_slope = Array2::from_shape_vec(
        (ny, nx),
        kind.iter()
            .zip(flags_in.iter())
            .map(|(kd, f)| *kd == UNKNOWN && f & k.bits.sur_error != 0 && f & k.bits.transient == 0)
            .collect(),
    )
    .expect("ny * nx");
    for (kd, ns) in kind.iter_mut().zip(no_slope.iter()) {
        if *ns {
            *kd = NO_SLOPE;
        }
    }
    // with a per-pixel map, a pixel's maximum is its own: the table's maximum times its
    // factor above full well (crate::model::pixel_response)
    let pixel_response = model.pixel_response();
    let max_factor =
        |y: usize, x: usize| pixel_response.map_or(1.0, |r| r.factor(y, x, f64::NAN, true));
    if pixel_response.is_some() {
        for ((y, x), b) in base.indexed_iter_mut() {
            if kind[[y, x]] == UNKNOWN || kind[[y, x]] == NO_SLOPE {
                *b *= max_factor(y, x);
            }
        }
    }
    // the terms' emission rates while this exposure holds its charge (its temperature)
    let held_rates = {
        let ictx = IntervalCtx {
            t_slew_s: 0.0,
            t_exposure_s: input.t_exposure_s,
            t_meas_s: 0.5 * input.t_exposure_s,
            t_elapsed_s: input.t_exposure_s,
            focal_plane_temp_k: ctx.focal_plane_temp_k,
        };
        let mut c = sum.c_per_s.clone();
        let mut r = sum.rate_per_s.clone();
        for e in effects {
            e.rates(&ictx, &mut c, &mut r);
        }
        r
    };
    let rctx = ResponseCtx {
        needed: needed.as_deref(),
        fluence_e: &fluence,
        no_slope: &no_slope,
        t_illuminated_s: k.t_illuminated_s,
        t_exposure_s: input.t_exposure_s,
        rate_per_s: &sum.rate_per_s,
        rate_held_per_s: &held_rates,
        response: k.response,
    };
    // limiting effects before combining ones, whatever the model file's order
    let (combiners, limiters): (Vec<&dyn Effect>, Vec<&dyn Effect>) = effects
        .iter()
        .filter(|e| e.has_accumulate())
        .map(|e| e.as_ref())
        .partition(|e| e.accumulate_role() == AccumulateRole::Combine);
    // filling hooks last; what the exposed traps could hold is kept for the combiners
    for e in effects.iter().filter(|e| !e.response_is_fill()) {
        e.response(&rctx, &mut ak);
    }
    let capacity =
        (!combiners.is_empty() && effects.iter().any(|e| e.response_is_fill())).then(|| ak.clone());
    for e in effects.iter().filter(|e| e.response_is_fill()) {
        e.response(&rctx, &mut ak);
    }

    let zero = vec![0.0; n];
    let zero = zero.as_slice();
    // each term's charge per unit amplitude, C_n tau_n (the model's terms, for
    // `limit`)
    let charge_per_amplitude: Vec<f64> = sum
        .c_per_s
        .iter()
        .zip(&sum.rate_per_s)
        .map(|(c, r)| c / r)
        .collect();
    // the charge a saturating fill leaves on every term (`limit`): the table's largest
    // amplitude, times a pixel's own factor above full well where the model has a map
    let saturated_charge_e = k.response.max_e() * charge_per_amplitude.iter().sum::<f64>();
    // how each limiter's factor is shared among the terms (`limit_exponents`): None when
    // every limiter gives every term the same factor
    let exponents = limit_exponents(&limiters, &sum.rate_per_s);
    let amps = state.amplitudes_e.as_slice_mut().expect("owned state");
    let count = state.release_count.as_slice_mut().expect("owned state");
    let pending = state.pending.as_slice_mut().expect("owned state");
    let kind = kind.as_slice().expect("standard layout");
    let base = base.as_slice().expect("standard layout");
    let ak = ak.as_slice().expect("standard layout");
    let capacity = capacity
        .as_ref()
        .map(|c| c.as_slice().expect("standard layout"));
    let flags = flags_in;
    let current = contiguous(out.current_e_per_s);
    let pflags = contiguous(out.pflags);
    let mut summary = (
        amps.par_chunks_mut(nx * n),
        count.par_chunks_mut(nx),
        pending.par_chunks_mut(nx),
        image.par_chunks(nx),
        flags.par_chunks_mut(nx),
        current.par_chunks_mut(nx),
        pflags.par_chunks_mut(nx),
        ak.par_chunks(nx * n),
        kind.par_chunks(nx),
        base.par_chunks(nx),
    )
        .into_par_iter()
        .enumerate()
        .map(|(y, (a_row, c, p, img, f, cur, pf, ak_row, kd, b_row))| {
            let mut s = StepSummary::default();
            // the early-release background's rows are read next exposure: advanced always
            let active = ctx
                .active_pixels
                .filter(|_| quiet_rows.is_none_or(|r| y % r != 0))
                .map(|a| &a[y * nx..(y + 1) * nx]);
            let mut fixed = vec![0.0; n];
            let mut limited = vec![0.0; n];
            let ones = vec![1.0; n];
            let mut fill = vec![1.0; n];
            for (x, a) in a_row.chunks_exact_mut(n).enumerate() {
                if active.is_some_and(|act| !act[x]) {
                    continue;
                }
                s.pixels += 1;
                let v = k.predict_flag_release(a, &w, &mut c[x], p[x], img[x]);
                // Whatever the hooks did: unknown pixels keep the maximum amplitude
                // (a transient the transient rule's; those with no slope at most it), non-functional ones add nothing,
                // and no NaN, Inf or negative amplitude enters the state.
                let hooked = kd[x] == KNOWN || kd[x] == NO_SLOPE;
                let mut add = &ak_row[x * n..(x + 1) * n];
                if kd[x] != KNOWN || !add.iter().all(|v| v.is_finite() && *v >= 0.0) {
                    for (v, raw) in fixed.iter_mut().zip(add) {
                        *v = if !hooked {
                            b_row[x]
                        } else if raw.is_finite() && *raw >= 0.0 {
                            if kd[x] == NO_SLOPE {
                                raw.min(b_row[x])
                            } else {
                                *raw
                            }
                        } else {
                            0.0
                        };
                    }
                    add = &fixed;
                }
                for (aj, dj) in a.iter_mut().zip(&decay) {
                    *aj *= dj;
                }
                // the capacity the pixel can still expose (`limit`): the response scaled,
                // the fraction of the exposed traps it fills (`fill`, below) as it was
                let unlimited = add;
                if !limiters.is_empty() {
                    let charge = |v: &[f64]| -> f64 {
                        v.iter()
                            .zip(&charge_per_amplitude)
                            .map(|(a, q)| a * q)
                            .sum()
                    };
                    let held = charge(a);
                    let exposed = match capacity {
                        Some(c) if hooked => charge(&c[(y * nx + x) * n..(y * nx + x + 1) * n]),
                        _ => charge(add),
                    };
                    let saturated = saturated_charge_e * max_factor(y, x);
                    if let Some(w) = &exponents {
                        limited_per_term(
                            &limiters,
                            w,
                            (held, exposed, saturated),
                            add,
                            &mut limited,
                        );
                    } else {
                        let keep: f64 = limiters
                            .iter()
                            .map(|e| e.limit(held, exposed, saturated))
                            .product();
                        let keep = unit_factor(keep);
                        for (l, v) in limited.iter_mut().zip(add) {
                            *l = v * keep;
                        }
                    }
                    add = &limited;
                }
                if combiners.is_empty() {
                    for (aj, bj) in a.iter_mut().zip(add) {
                        *aj += bj;
                    }
                } else {
                    let fill = match capacity {
                        Some(c) if hooked => {
                            let c = &c[(y * nx + x) * n..(y * nx + x + 1) * n];
                            for ((f, cj), aj) in fill.iter_mut().zip(c).zip(unlimited) {
                                *f = if *cj > 0.0 && cj.is_finite() {
                                    (aj / cj).clamp(0.0, 1.0)
                                } else {
                                    1.0
                                };
                            }
                            &fill
                        }
                        _ => &ones,
                    };
                    // the first combiner adds; later ones see nothing more to add
                    for (i, e) in combiners.iter().enumerate() {
                        e.accumulate(a, if i == 0 { add } else { zero }, fill);
                    }
                }
                for aj in a.iter_mut() {
                    if !(aj.is_finite() && *aj >= 0.0) {
                        *aj = 0.0;
                    }
                }
                // the next exposure is flagged whatever the prediction (`Kernel::response_of`)
                let forced =
                    kd[x] == NO_SLOPE || (kd[x] == UNKNOWN && !k.transient_ruled(img[x], f[x]));
                k.write_pixel(&v, forced, &mut p[x], &mut cur[x], &mut pf[x], &mut f[x]);
                s.above_high += v.high as u64;
                s.above_low += v.low as u64;
                s.released += v.released as u64;
                s.max_amplitude += v.max_prev as u64;
            }
            s
        })
        .reduce(StepSummary::default, StepSummary::add);
    summary.t_meas_s = k.t_meas_s;
    summary.previous_index = state.last_index;
    state.t_reset_unix_s = Some(input.t_start_unix_s + input.t_exposure_s);
    state.last_index = Some(input.exposure_index);
    Ok(summary)
}

/// A limiter's factor as the step applies it: finite and in [0, 1], else 1 (no limit).
fn unit_factor(k: f64) -> f64 {
    if k.is_finite() {
        k.clamp(0.0, 1.0)
    } else {
        1.0
    }
}

/// Each limiter's exponent per term ([`Effect::limit_exponents`]; 1 for every term of
/// a limiter that shares its factor alike, and for an exponent not finite or below 0);
/// None when every limiter shares its factor alike.
fn limit_exponents(limiters: &[&dyn Effect], rate_per_s: &[f64]) -> Option<Vec<Vec<f64>>> {
    let per: Vec<Option<Vec<f64>>> = limiters
        .iter()
        .map(|e| e.limit_exponents(rate_per_s))
        .collect();
    if per.iter().all(Option::is_none) {
        return None;
    }
    let ones = || vec![1.0; rate_per_s.len()];
    Some(
        per.into_iter()
            .map(|w| match w {
                Some(w) if w.len() == rate_per_s.len() => w
                    .into_iter()
                    .map(|x| if x.is_finite() && x >= 0.0 { x } else { 1.0 })
                    .collect(),
                _ => ones(),
            })
            .collect(),
    )
}

/// `limited_n = add_n prod_e k_e^w_en` over the limiters `e`, `k_e` each one's factor
/// ([`unit_factor`]) and `w` their exponents ([`limit_exponents`]): in [0, add_n].
fn limited_per_term(
    limiters: &[&dyn Effect],
    w: &[Vec<f64>],
    (held_e, exposed_e, saturated_e): (f64, f64, f64),
    add: &[f64],
    limited: &mut [f64],
) {
    limited.copy_from_slice(add);
    for (e, w) in limiters.iter().zip(w) {
        let k = unit_factor(e.limit(held_e, exposed_e, saturated_e));
        for (l, wn) in limited.iter_mut().zip(w) {
            *l *= k.powf(*wn);
        }
    }
}

/// The prediction weights and decay factors of one interval with the effects' rate and
/// observation hooks applied: `(w_n, exp(-t_elapsed r_n'))`.
pub fn interval_weights(
    effects: &[Box<dyn Effect>],
    c_per_s: &[f64],
    rate_per_s: &[f64],
    ictx: &IntervalCtx,
) -> (Vec<f64>, Vec<f64>) {
    let mut c = c_per_s.to_vec();
    let mut r = rate_per_s.to_vec();
    for e in effects {
        e.rates(ictx, &mut c, &mut r);
    }
    let mut w: Vec<f64> = c
        .iter()
        .zip(&r)
        .map(|(ci, ri)| ci * (-ictx.t_meas_s * ri).exp())
        .collect();
    for e in effects {
        e.observe(ictx, &c, &r, &mut w);
    }
    let d = r.iter().map(|ri| (-ictx.t_elapsed_s * ri).exp()).collect();
    (w, d)
}

fn contiguous<T: Clone>(a: &mut Array2<T>) -> &mut [T] {
    if !a.is_standard_layout() {
        *a = a.as_standard_layout().into_owned();
    }
    a.as_slice_mut().expect("standard layout")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::effects::smooth::{Axis, Smooth};

    /// A limiter with a fixed factor and fixed exponents (none: shared alike).
    #[derive(Debug)]
    struct Fixed(f64, Option<Vec<f64>>);

    impl Effect for Fixed {
        fn name(&self) -> &'static str {
            "fixed"
        }
        fn limit(&self, _: f64, _: f64, _: f64) -> f64 {
            self.0
        }
        fn limit_exponents(&self, _: &[f64]) -> Option<Vec<f64>> {
            self.1.clone()
        }
    }

    #[test]
    fn a_limiters_factor_outside_zero_one_is_clamped_and_a_non_finite_one_is_none() {
        assert_eq!(unit_factor(0.25), 0.25);
        assert_eq!(unit_factor(1.5), 1.0);
        assert_eq!(unit_factor(-0.5), 0.0);
        assert_eq!(unit_factor(f64::NAN), 1.0);
        assert_eq!(unit_factor(f64::INFINITY), 1.0);
    }

    /// Exponents: none when every limiter shares alike; 1 in place of a limiter's
    /// missing, mis-sized, negative or non-finite ones.
    #[test]
    fn exponents_are_one_where_a_limiter_gives_none_or_a_bad_one() {
        let rates = [0.1, 1e-3, 1e-5];
        let alike = Fixed(0.5, None);
        assert!(limit_exponents(&[&alike], &rates).is_none());
        let bad = Fixed(0.5, Some(vec![2.0, f64::NAN, -1.0]));
        let short = Fixed(0.5, Some(vec![2.0]));
        let w = limit_exponents(&[&alike, &bad, &short], &rates).expect("one limiter tilts");
        assert_eq!(w, vec![vec![1.0; 3], vec![2.0, 1.0, 1.0], vec![1.0; 3]]);
    }

    /// Each term keeps the product of the limiters' factors to its exponents: with
    /// `smooth_history` at `exp(-2)` and `tau_tilt` 0.5, the 10 s term keeps
    /// `exp(-20)`, the 1000 s term `exp(-2)`, the 10^5 s term `exp(-0.2)`, times a
    /// second limiter's 0.5 alike; in [0, add] whatever the factors.
    #[test]
    fn each_term_keeps_the_limiters_factors_to_its_exponents() {
        let history = Smooth {
            axis: Axis::History,
            u_lo: -2.0,
            u_hi: 0.0,
            at: [0.0, -1.0, -2.0],
            f_sat_e: 0.0,
            tau_tilt: 0.5,
        };
        let half = Fixed(0.5, None);
        let rates = [0.1, 1e-3, 1e-5];
        let limiters: [&dyn Effect; 2] = [&history, &half];
        let w = limit_exponents(&limiters, &rates).expect("tilted");
        let add = [1.0, 2.0, 4.0];
        let mut limited = [0.0; 3];
        // held = saturated: u = 0, the high knot, exp(-2)
        limited_per_term(&limiters, &w, (5.0, 1.0, 5.0), &add, &mut limited);
        for ((l, a), e) in limited.iter().zip(add).zip([-20.0, -2.0, -0.2f64]) {
            let want = a * e.exp() * 0.5;
            assert!((l - want).abs() < 1e-12 * a, "{limited:?}");
        }
        let wild = Fixed(f64::NAN, Some(vec![0.0, 3.0, 1e9]));
        let limiters: [&dyn Effect; 2] = [&history, &wild];
        let w = limit_exponents(&limiters, &rates).expect("tilted");
        limited_per_term(&limiters, &w, (5.0, 1.0, 5.0), &add, &mut limited);
        assert!(limited.iter().zip(add).all(|(l, a)| (0.0..=a).contains(l)));
    }
}
