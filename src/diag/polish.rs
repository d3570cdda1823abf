//! A candidate's values refined against the pixel reference (or, on the neighbours,
//! against the pixels next to far brighter ones) after its fit against the
//! measurements' description.
//!
//! # Why
//! A candidate is fitted by least squares against the measurements' description
//! (`refit::fit_candidate`). Where the description misfits the data more than
//! the effect changes them, that fit follows the misfit. Measured on the second
//! generator's `temperature:arrhenius` campaign (64 x 64, seed 2, default `fit`; rates
//! x0.62 at 78 K, x1.6 at 82 K): fitted against the description, `temperature` stays
//! at `activation_ev` 0 and `smooth_temperature` takes the wrong sign at 82 K, while the
//! pixel reference's RMS at fixed values is 2.72 at 0 eV and 1.50 at the generator's
//! 0.129 eV (`examples/per_event_floor`; docs/diagnostics.md). The pixel reference
//! ([`super::base::predict_scaled`]) takes in what no effect stands for (the decay law,
//! its fluence dependence, each pixel's amplitude and decay shape), so what is left of
//! the residual there is what an effect acting between a pixel's illuminations can
//! take.
//!
//! # Rule
//! From the values fitted against the description, a pattern search over the
//! candidate's fitted parameters (not the model's own effects, not pinned ones): at
//! each of [`LEVELS`] step sizes, starting at [`FIRST_STEP`] of the parameter's range
//! (at most 1), each parameter in turn is moved one step up or down while that lowers
//! the pixel reference's normalised residual RMS on the fit's own samples; then the
//! step halves. At most [`MAX_EVALS`] evaluations. The knots are rescaled for every
//! value tried, as the fit rescales them ([`crate::calib::knots::rescale`]). Only on
//! samples of two illumination events or more: on one illumination each pixel's own
//! terms take in what an effect does to it, and the fit stays the description's. Only
//! the effects the pixel reference can see, those acting on how a pixel's
//! illuminations differ: one of (fluence, time since illumination) alone, or of the
//! pixel, it takes in whatever the values, and its RMS there would follow the noise.
//!
//! # Effects on the neighbours
//! The effects acting on `neighbour_excess_fluence` are refined against their own judge
//! ([`super::marked`]): the flexible base on the pixels next to far brighter ones, which
//! each pixel's own terms in the pixel reference would take in. Also on one
//! illumination. Their values sit at a small share of their ranges, so the first step is
//! half the value itself (at least [`MARKED_MIN_STEP`] of the range). Measured on the
//! second generator's `ipc:cross4` campaign (64 x 64, seed 1, truth 0.02 per
//! neighbour): fitted against the description on the cells split by the neighbour
//! contrast, `ipc`'s `alpha` stops at its bound 0.05, where the pixels next to the
//! pinholes lie -0.38 of their cells' spread from the cells' mean (z -18.8, -11.4
//! without the effect); at 0.02, -0.02 (z -0.8).
//!
//! # Effects on the position
//! The effects acting on `position` (`populations`) are refined against the flexible base
//! by tile of the array ([`super::marked`]), also on one illumination, from the best of
//! the fitted values, the effect's null and the surface measured at the null: the cells
//! the description is fitted on pool every pixel of a fluence and time, so a field over
//! the array shows there only as the spread of each cell, not where it lies. The
//! surface (`populations`' five coefficients) is measured directly: per pixel the
//! median of `ln(measured / flexible base)` over its samples well above the noise, a
//! quadratic in position fitted to those medians by least squares. Measured on the
//! second generator's `populations:smooth` campaign (64 x 64, seed 1; density `1 + 0.4
//! v + ...`, brighter towards larger `y`): fitted against the description
//! `populations` takes `gy` -0.20; the surface is `gx` -0.06, `gy` 0.40, `gxx` 0.13,
//! `gxy` 0.04, `gyy` -0.13, where the tiles' RMS is 1.28 (2.75 at the null; 1.66 at
//! `gy` 0.40 alone). A pattern search from the null, one parameter at a time within
//! [`MAX_EVALS`], found `gy` 0.25 alone.
//!
//! # Invariants
//! - The judge's RMS on the samples at the values returned is at most its RMS at the
//!   values given; every value stays within its parameter's bounds.
//! - Deterministic: the same model, samples and sequence give the same values.
//! - Only the model is refined: the least-squares fit's report stays the description's
//!   minimum, what a change in BIC compares (`refit::fit_candidate`).

use super::base::{predict_scaled, View};
use super::data::Sequence;
use super::eval::{self, Samples};
use super::marked::Judge;
use crate::error::Result;
use crate::model::params::ModelParams;
use crate::model::response::Response;

/// Step sizes tried, each half the one before.
pub const LEVELS: usize = 4;
/// The first step, as a share of the parameter's range (`hi - lo`), at most 1.
pub const FIRST_STEP: f64 = 0.125;
/// Evaluations of the pixel reference at most.
pub const MAX_EVALS: usize = 16;

/// The pixel reference's normalised residual RMS of `m`'s prediction at `s` (the line
/// "pixel reference" of `persist diagnose`).
pub fn pixel_rms(m: &ModelParams, seq: &Sequence, s: &Samples) -> Result<f64> {
    let pred = eval::predict(m, seq, s, false)?.current;
    let response = Response::new(&m.amplitude_knots);
    let view = View::of_model(m, seq);
    let scaled = predict_scaled(seq, &view, s, &pred, &response);
    Ok(eval::rms(&scaled.cells(s)))
}

/// One parameter the search moves: its effect's index, name and bounds.
struct Slot {
    effect: usize,
    name: &'static str,
    lo: f64,
    hi: f64,
}

/// The fitted parameters of the effects `names` (`--with` arguments) in `m` that
/// `judge` can see: the pixel reference those acting on how a pixel's illuminations
/// differ ([`super::contrast::seen_by_pixel_reference`]), the pixels next to far
/// brighter ones those acting on the neighbours ([`super::marked::acts_on_neighbours`]),
/// the tiles of the array those acting on the position ([`super::marked::acts_on`]).
fn slots(m: &ModelParams, names: &[&str], judge: Judge) -> Vec<Slot> {
    let wanted = |e: &str| names.iter().any(|n| n.split(':').next() == Some(e));
    m.effects
        .iter()
        .enumerate()
        .filter(|(_, e)| wanted(&e.name))
        .filter_map(|(i, e)| Some((i, e, crate::model::effects::lookup(&e.name)?)))
        .filter(|(_, _, def)| match judge {
            Judge::PixelReference => super::contrast::seen_by_pixel_reference(
                super::contrast::class_of(def.name, def.covariate),
            ),
            Judge::NextToBrighter => super::marked::acts_on_neighbours(&[def.name]),
            Judge::Position => super::marked::acts_on(&[def.name], super::marked::POSITION),
        })
        .flat_map(|(i, e, def)| {
            def.params.iter().filter(|p| e.fits(p)).map(move |p| Slot {
                effect: i,
                name: p.name,
                lo: p.lo,
                hi: p.hi,
            })
        })
        .collect()
}

/// The first step of slot `s` from value `x`: [`FIRST_STEP`] of its range (at most 1)
/// against the pixel reference; against the pixels next to far brighter ones half the
/// value itself (at least [`MARKED_MIN_STEP`] of the range), as the neighbours' effects
/// sit at a small share of their ranges (`blooming`'s `fraction` near 0.002 of 0 to 1).
fn first_step(judge: Judge, s: &Slot, x: f64) -> f64 {
    match judge {
        Judge::PixelReference | Judge::Position => (FIRST_STEP * (s.hi - s.lo)).min(1.0),
        Judge::NextToBrighter => (0.5 * x.abs()).max(MARKED_MIN_STEP * (s.hi - s.lo)),
    }
}

/// The smallest first step against the pixels next to far brighter ones, as a share of
/// the parameter's range.
pub const MARKED_MIN_STEP: f64 = 1e-4;

/// The pattern search's state: the values, the RMS at them and the evaluations made.
struct Search {
    x: Vec<f64>,
    best: f64,
    evals: usize,
}

impl Search {
    /// Moves value `i` by `delta` (within `s`'s bounds) while that lowers the RMS, within
    /// [`MAX_EVALS`] evaluations in all; whether it moved.
    fn walk(
        &mut self,
        i: usize,
        s: &Slot,
        delta: f64,
        rms: &impl Fn(&[f64]) -> Result<f64>,
    ) -> Result<bool> {
        let mut moved = false;
        while self.evals < MAX_EVALS {
            let v = (self.x[i] + delta).clamp(s.lo, s.hi);
            if v == self.x[i] {
                break;
            }
            let mut y = self.x.clone();
            y[i] = v;
            let r = rms(&y)?;
            self.evals += 1;
            // a NaN RMS is no improvement
            if r.partial_cmp(&self.best) != Some(std::cmp::Ordering::Less) {
                break;
            }
            (self.x, self.best, moved) = (y, r, true);
        }
        Ok(moved)
    }

    /// Move to `y` when the RMS is lower there (one evaluation; none when `y` is where
    /// the search stands).
    fn try_point(&mut self, y: Vec<f64>, rms: &impl Fn(&[f64]) -> Result<f64>) -> Result<()> {
        if y == self.x {
            return Ok(());
        }
        let r = rms(&y)?;
        self.evals += 1;
        if r.partial_cmp(&self.best) == Some(std::cmp::Ordering::Less) {
            (self.x, self.best) = (y, r);
        }
        Ok(())
    }
}

/// The null of slot `s`'s parameter (its value of no effect), if it has one.
fn null(m: &ModelParams, s: &Slot) -> Option<f64> {
    let def = crate::model::effects::lookup(&m.effects[s.effect].name)?;
    def.params.iter().find(|p| p.name == s.name)?.null
}

/// The samples whose flexible base predicts at least this many times their noise
/// count in the surface `polish` measures at the null (module docs).
pub const SURFACE_MIN_SNR: f64 = 10.0;

/// The surface of `populations` measured on `samples` against the flexible base of
/// `m` (the model at the surface's null; module docs, "Effects on the position"): per
/// pixel the median of `ln(measured / flexible base)` over its samples the base
/// predicts at least [`SURFACE_MIN_SNR`] times their noise, and the quadratic in
/// `(u, v)` with a constant (the knots' level) fitted to those medians by least
/// squares; its other coefficients, each within its bounds, in the order of `slots`.
/// `None` when a slot is not one of the surface's coefficients or fewer than 12 pixels
/// have a median.
fn surface_at(
    m: &ModelParams,
    slots: &[Slot],
    seq: &Sequence,
    samples: &Samples,
) -> Result<Option<Vec<f64>>> {
    use crate::model::effects::populations::{coordinate, COEFFICIENTS};
    let Some(index) = slots
        .iter()
        .map(|s| COEFFICIENTS.iter().position(|t| *t == s.name))
        .collect::<Option<Vec<usize>>>()
    else {
        return Ok(None);
    };
    let pred = eval::predict(m, seq, samples, false)?.current;
    let flexible = super::base::predict(seq, &View::of_model(m, seq), samples, &pred);
    let np = samples.npix().max(1);
    let mut per_pixel = vec![Vec::new(); np];
    for (i, (&b, &y)) in flexible.iter().zip(&samples.measured).enumerate() {
        if b.is_finite() && y.is_finite() && y > 0.0 && b >= SURFACE_MIN_SNR * samples.noise[i / np]
        {
            per_pixel[i % np].push((y / b).ln());
        }
    }
    let points: Vec<(f64, f64, f64)> = per_pixel
        .iter()
        .zip(&samples.pixels)
        .map(|(logs, &(y, x))| {
            (
                coordinate(x, seq.nx),
                coordinate(y, seq.ny),
                crate::stats::median(logs),
            )
        })
        .filter(|p| p.2.is_finite())
        .collect();
    let Some(c) = quadratic_fit(&points) else {
        return Ok(None);
    };
    Ok(Some(
        slots
            .iter()
            .zip(index)
            .map(|(s, k)| c[k + 1].clamp(s.lo, s.hi))
            .collect(),
    ))
}

/// The least-squares quadratic `c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2` through
/// the points `(u, v, r)`; None with fewer than 12 points or a singular system.
fn quadratic_fit(points: &[(f64, f64, f64)]) -> Option<[f64; 6]> {
    if points.len() < 12 {
        return None;
    }
    let mut ata = nalgebra::SMatrix::<f64, 6, 6>::zeros();
    let mut atb = nalgebra::SVector::<f64, 6>::zeros();
    for &(u, v, r) in points {
        let row = nalgebra::SVector::<f64, 6>::from([1.0, u, v, u * u, u * v, v * v]);
        ata += row * row.transpose();
        atb += row * r;
    }
    let c = ata.lu().solve(&atb)?;
    Some([c[0], c[1], c[2], c[3], c[4], c[5]])
}

fn value(m: &ModelParams, s: &Slot) -> Option<f64> {
    m.effects[s.effect].params.get(s.name)?.as_f64()
}

/// `fitted` with the fitted parameters of the effects `names` refined against the pixel
/// reference on `samples` (module docs); unchanged with fewer than two illumination
/// events or nothing to refine.
pub fn polish(
    fitted: ModelParams,
    names: &[&str],
    seq: &Sequence,
    samples: &Samples,
) -> Result<ModelParams> {
    let judge = Judge::of(names);
    let slots = slots(&fitted, names, judge);
    if (judge == Judge::PixelReference && samples.events().len() < 2) || slots.is_empty() {
        return Ok(fitted);
    }
    let Some(x) = slots
        .iter()
        .map(|s| value(&fitted, s))
        .collect::<Option<Vec<f64>>>()
    else {
        return Ok(fitted);
    };
    let knots_from = crate::calib::knots::scale_of(&fitted, seq)?;
    let at = |x: &[f64]| -> Result<ModelParams> {
        let mut m = fitted.clone();
        for (s, v) in slots.iter().zip(x) {
            m.effects[s.effect]
                .params
                .insert(s.name.to_string(), serde_json::json!(v));
        }
        if let Some((s_from, ramp)) = &knots_from {
            crate::calib::knots::rescale(s_from, &mut m, ramp)?;
        }
        Ok(m)
    };
    let objective = |m: &ModelParams| match judge {
        Judge::PixelReference => pixel_rms(m, seq, samples),
        judge => super::marked::rms(judge, m, seq, samples),
    };
    let start = objective(&fitted)?;
    let rms = |y: &[f64]| objective(&at(y)?);
    let mut search = Search {
        x,
        best: start,
        evals: 1,
    };
    // module docs, "Effects on the position": from the best of the fit, the null and
    // the surface measured at the null
    if judge == Judge::Position {
        if let Some(nulls) = slots
            .iter()
            .map(|s| null(&fitted, s))
            .collect::<Option<Vec<_>>>()
        {
            let surface = surface_at(&at(&nulls)?, &slots, seq, samples)?;
            search.try_point(nulls, &rms)?;
            if let Some(y) = surface {
                search.try_point(y, &rms)?;
            }
        }
    }
    for level in 0..LEVELS {
        for (i, s) in slots.iter().enumerate() {
            let step = first_step(judge, s, search.x[i]) / f64::from(1u32 << level);
            if !search.walk(i, s, step, &rms)? {
                search.walk(i, s, -step, &rms)?;
            }
        }
    }
    if search.best >= start {
        return Ok(fitted);
    }
    at(&search.x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn slot(lo: f64, hi: f64) -> Slot {
        Slot {
            effect: 0,
            name: "a",
            lo,
            hi,
        }
    }

    /// The generator's surface of `populations:smooth` on a grid (`1 + 0.4 v + 0.25 (u^2
    /// - 1/3)`, its log up to second order) comes back exactly; too few points give none.
    #[test]
    fn a_quadratic_through_a_grid_gives_back_its_coefficients() {
        let c = [0.1, -0.06, 0.4, 0.13, 0.04, -0.13];
        let f = |u: f64, v: f64| {
            c[0] + c[1] * u + c[2] * v + c[3] * u * u + c[4] * u * v + c[5] * v * v
        };
        let grid: Vec<(f64, f64, f64)> = (0..25)
            .map(|k| {
                let (u, v) = (f64::from(k % 5) / 2.0 - 1.0, f64::from(k / 5) / 2.0 - 1.0);
                (u, v, f(u, v))
            })
            .collect();
        let got = quadratic_fit(&grid).unwrap();
        for (g, w) in got.iter().zip(c) {
            assert!((g - w).abs() < 1e-9, "{got:?}");
        }
        assert!(quadratic_fit(&grid[..11]).is_none());
    }

    /// A walk stops at the first step that does not lower the RMS and never leaves the
    /// bounds: on `(x - 0.3)^2` from 0 with steps of 0.125 it stops at 0.25.
    #[test]
    fn a_walk_descends_and_stops_at_the_first_step_that_does_not_help() {
        let rms = |y: &[f64]| -> Result<f64> { Ok((y[0] - 0.3).powi(2)) };
        let mut s = Search {
            x: vec![0.0],
            best: 0.09,
            evals: 1,
        };
        assert!(s.walk(0, &slot(-1.0, 1.0), 0.125, &rms).unwrap());
        assert_eq!(s.x, vec![0.25]);
        assert_eq!(s.evals, 4);
        assert!(!s.walk(0, &slot(-1.0, 1.0), 0.125, &rms).unwrap());
        assert_eq!(s.x, vec![0.25]);
        // against a bound the walk ends without an evaluation
        let mut b = Search {
            x: vec![0.1],
            best: 0.04,
            evals: 1,
        };
        assert!(b.walk(0, &slot(0.0, 0.2), 0.125, &rms).unwrap());
        assert_eq!((b.x[0], b.evals), (0.2, 2));
    }

    /// A point is taken only where the RMS is lower: on `(x - 0.3)^2` from 1.0 the null 0
    /// is taken, from 0.35 it is not; the search's own point costs no evaluation.
    #[test]
    fn a_point_is_taken_only_where_the_rms_is_lower() {
        let rms = |y: &[f64]| -> Result<f64> { Ok((y[0] - 0.3).powi(2)) };
        let mut s = Search {
            x: vec![1.0],
            best: 0.49,
            evals: 1,
        };
        s.try_point(vec![0.0], &rms).unwrap();
        assert_eq!((s.x[0], s.best, s.evals), (0.0, 0.09, 2));
        let mut t = Search {
            x: vec![0.35],
            best: 0.0025,
            evals: 1,
        };
        t.try_point(vec![0.0], &rms).unwrap();
        assert_eq!((t.x[0], t.evals), (0.35, 2));
        t.try_point(vec![0.35], &rms).unwrap();
        assert_eq!(t.evals, 2);
    }

    /// Against the pixel reference the first step is an eighth of the range (at most 1);
    /// against the pixels next to far brighter ones half the value, at least
    /// [`MARKED_MIN_STEP`] of the range: `ipc`'s `alpha` at its bound 0.05 steps by
    /// 0.025, `blooming`'s `fraction` at 0 by 1e-4.
    #[test]
    fn the_first_step_follows_the_judge() {
        assert_eq!(
            first_step(Judge::PixelReference, &slot(0.0, 0.05), 0.05),
            0.00625
        );
        assert_eq!(
            first_step(Judge::PixelReference, &slot(-20.0, 20.0), 1.0),
            1.0
        );
        assert_eq!(
            first_step(Judge::NextToBrighter, &slot(0.0, 0.05), 0.05),
            0.025
        );
        assert_eq!(
            first_step(Judge::NextToBrighter, &slot(0.0, 1.0), 0.0),
            1e-4
        );
        assert_eq!(
            first_step(Judge::NextToBrighter, &slot(-1.0, 1.0), -0.4),
            0.2
        );
    }

    /// The evaluations are capped by [`MAX_EVALS`], and a NaN RMS is no improvement.
    #[test]
    fn a_walk_keeps_to_the_evaluation_budget_and_refuses_nan() {
        let down = |y: &[f64]| -> Result<f64> { Ok(-y[0]) };
        let mut s = Search {
            x: vec![0.0],
            best: 0.0,
            evals: 1,
        };
        assert!(s.walk(0, &slot(0.0, 1e9), 1.0, &down).unwrap());
        assert_eq!(s.evals, MAX_EVALS);
        assert_eq!(s.x[0], (MAX_EVALS - 1) as f64);
        let nan = |_: &[f64]| -> Result<f64> { Ok(f64::NAN) };
        let mut n = Search {
            x: vec![0.0],
            best: 1.0,
            evals: 1,
        };
        assert!(!n.walk(0, &slot(-1.0, 1.0), 0.5, &nan).unwrap());
        assert_eq!(n.x[0], 0.0);
    }
}
