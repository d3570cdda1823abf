//! `blooming`: neighbours' excess fluence fills a pixel's traps as its own fluence would.
//!
//! Physics: charge spilling from a saturated, forward-biased pixel reaches its
//! neighbours' trap region and fills their traps beyond what their own measured flux
//! tells (paper section 2.2 suggests blooming behind the rise of persistence at
//! saturation). The spill fills traps the way the pixel's own charge does, so it moves
//! the pixel along its own response curve; a pixel already at saturation gains nothing
//! from it (a spill does not forward-bias it).
//! Equation (response hook): with `F` the pixel's extrapolated fluence, `E_nb` the mean
//! over the four nearest neighbours of `max(0, F_nb - f_sat_e)` (neighbours outside the
//! array or of unknown fluence count 0, except those with no slope, which count at
//! `no_slope_flux_e_per_s * t_illuminated`, the least fluence that leaves no slope) and
//! `F_c` the largest knot fluence at or below
//! `f_sat_e` (the end of the unsaturated part of the `A_k` table),
//! `A_k,n += A_k(min(F + fraction E_nb, F_c)) - A_k(min(F, F_c))` (at least 0), for every
//! term `n`; nothing where `F` is unknown.
//! Parameters: `fraction` (the share of the neighbours' mean excess fluence that the
//! pixel's traps see as their own fluence; default 0.05, bounds [0, 1], null 0),
//! `f_sat_e` (200,000 e-, the paper's saturation level; not fitted),
//! `no_slope_flux_e_per_s` (22,222 e-/s: half of 200,000 e- reached within the first
//! three 1.5 s reads, so the on-board fit has fewer than three reads below half full
//! well, ICD `SUR_ERROR`; not fitted). A source too bright for a slope is common next to
//! the sharpest, brightest sources, where blooming matters most; counting it at 0 would
//! miss exactly those.
//! Invariants: the added amplitude is finite, >= 0, and 0 at `fraction = 0`, for a
//! pixel at or above `F_c`, and for a pixel with no saturated neighbour.
//! Covariate: neighbour excess fluence.
//! Model files naming `gain_per_e` (an additive `gain_per_e * E_nb` on every pixel,
//! saturated or not, which this form replaces) are refused with the parameter named.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::Array3;

/// The saturation fluence above which a neighbour's excess counts, e- (shared with the
/// data-driven neighbour term, `super::smooth`).
pub const F_SAT: ParamSpec = ParamSpec {
    name: "f_sat_e",
    default: 2e5,
    lo: 1.0,
    hi: 1e9,
    null: None,
    fitted: false,
    doc: "saturation fluence, e-",
};

pub const DEF: EffectDef = EffectDef {
    name: "blooming",
    summary: "neighbours' excess fluence above saturation fills a pixel's traps as its own fluence",
    params: &[
        ParamSpec {
            name: "fraction",
            default: 0.05,
            lo: 0.0,
            hi: 1.0,
            null: Some(0.0),
            fitted: true,
            doc:
                "share of the neighbours' mean excess fluence the pixel's traps see as own fluence",
        },
        F_SAT,
        ParamSpec {
            name: "no_slope_flux_e_per_s",
            default: 1e5 / 4.5,
            lo: 1.0,
            hi: 1e9,
            null: None,
            fitted: false,
            doc: "least flux that leaves no slope (SUR_ERROR), e-/s",
        },
    ],
    build: |p| {
        Box::new(Blooming {
            fraction: get(p, "fraction"),
            f_sat_e: get(p, "f_sat_e"),
            no_slope_flux_e_per_s: get(p, "no_slope_flux_e_per_s"),
        })
    },
    covariate: "neighbour_excess_fluence",
};

#[derive(Debug, Clone)]
pub struct Blooming {
    pub fraction: f64,
    pub f_sat_e: f64,
    pub no_slope_flux_e_per_s: f64,
}

/// Mean over the 4 nearest neighbours of `max(0, F - f_sat)`, e-; neighbours of unknown
/// fluence count 0.
pub fn neighbour_excess(fluence_e: &ndarray::Array2<f64>, f_sat_e: f64) -> ndarray::Array2<f64> {
    mean_neighbour_excess(fluence_e, f_sat_e, |_, _| 0.0)
}

/// [`neighbour_excess`], with a neighbour of unknown fluence counted at `unknown(y, x)`
/// (its fluence, e-).
fn mean_neighbour_excess(
    fluence_e: &ndarray::Array2<f64>,
    f_sat_e: f64,
    unknown: impl Fn(usize, usize) -> f64,
) -> ndarray::Array2<f64> {
    let (ny, nx) = fluence_e.dim();
    let ex = |y: usize, x: usize| {
        let f = fluence_e[[y, x]];
        let f = if f.is_finite() { f } else { unknown(y, x) };
        (f - f_sat_e).max(0.0)
    };
    ndarray::Array2::from_shape_fn((ny, nx), |(y, x)| {
        let mut s = 0.0;
        crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| s += ex(y, x));
        s / 4.0
    })
}

impl Effect for Blooming {
    fn name(&self) -> &'static str {
        DEF.name
    }
    /// Local only when nothing spills.
    fn is_pixel_local(&self) -> bool {
        self.fraction == 0.0
    }
    /// Its response reads the neighbours' fluence and `no_slope` (built everywhere),
    /// and changes a pixel's planes from its own.
    fn response_reach_px(&self) -> Option<usize> {
        Some(0)
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.fraction == 0.0 {
            return;
        }
        let r = ctx.response;
        let f_c = r.last_knot_at_or_below(self.f_sat_e);
        let f_no_slope = self.no_slope_flux_e_per_s * ctx.t_illuminated_s;
        let e = mean_neighbour_excess(ctx.fluence_e, self.f_sat_e, |y, x| {
            if ctx.no_slope[[y, x]] {
                f_no_slope
            } else {
                0.0
            }
        });
        ndarray::Zip::from(ak.lanes_mut(ndarray::Axis(2)))
            .and(&e)
            .and(ctx.fluence_e)
            .for_each(|mut lane, &ei, &f| {
                if ei <= 0.0 || !f.is_finite() {
                    return;
                }
                let own = f.max(0.0);
                if own >= f_c {
                    return;
                }
                let to = (own + self.fraction * ei).min(f_c);
                let add = (r.amplitude_e(to) - r.amplitude_e(own)).max(0.0);
                if add > 0.0 && add.is_finite() {
                    lane.iter_mut().for_each(|a| *a += add);
                }
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::params::Knot;
    use crate::model::Response;
    use ndarray::Array2;

    /// Knots: linear 1e-3 e- per e- up to 1.8e5 e-, then a jump to 900 at 2.2e5 (the
    /// shape of the paper's Table 1 at saturation).
    fn table() -> Response {
        Response::new(&[
            Knot {
                fluence_e: 1.8e5,
                amplitude_e: 180.0,
            },
            Knot {
                fluence_e: 2.2e5,
                amplitude_e: 900.0,
            },
        ])
    }

    fn run(f: &Array2<f64>, fraction: f64) -> Array3<f64> {
        run_with(f, &Array2::from_elem(f.dim(), false), fraction)
    }

    fn run_with(f: &Array2<f64>, no_slope: &Array2<bool>, fraction: f64) -> Array3<f64> {
        let b = Blooming {
            fraction,
            f_sat_e: 2e5,
            no_slope_flux_e_per_s: 1e4,
        };
        let mut ak = Array3::<f64>::from_elem((f.dim().0, f.dim().1, 2), 10.0);
        let rates = [0.1, 0.01];
        b.response(
            &ResponseCtx {
                needed: None,
                fluence_e: f,
                no_slope,
                t_illuminated_s: 481.0,
                t_exposure_s: 613.0,
                rate_per_s: &rates,
                rate_held_per_s: &rates,
                response: &table(),
            },
            &mut ak,
        );
        ak
    }

    #[test]
    fn a_dim_neighbour_moves_along_its_response_a_saturated_one_does_not() {
        // 3x3: centre 1.2e6 e- (excess 1e6 over f_sat 2e5), corners 5e5 (excess 3e5,
        // saturated themselves, so above F_c = 1.8e5: they gain nothing), three edge
        // pixels at 1e4 e- and one at 1.7e5.
        let mut f = Array2::<f64>::from_elem((3, 3), 5e5);
        f[[1, 1]] = 1.2e6;
        f[[0, 1]] = 1e4;
        f[[1, 0]] = 1e4;
        f[[2, 1]] = 1e4;
        f[[1, 2]] = 1.7e5;
        let ak = run(&f, 0.1);
        // (0, 1): own 1e4, plus 0.1 * mean excess of its neighbours: the centre (1e6) and
        // the corners (3e5 each) -> (1e6 + 3e5 + 3e5) / 4 = 4e5 -> +4e4 e- of fluence
        // -> +40 e- of amplitude on the linear part
        assert!((ak[[0, 1, 0]] - 50.0).abs() < 1e-9, "{}", ak[[0, 1, 0]]);
        assert!((ak[[0, 1, 1]] - 50.0).abs() < 1e-9);
        // (1, 2): own 1.7e5, would go to 2.1e5: capped at F_c = 1.8e5 -> +10 e-, not into
        // the saturation jump
        assert!((ak[[1, 2, 0]] - 20.0).abs() < 1e-9, "{}", ak[[1, 2, 0]]);
        // saturated pixels gain nothing
        assert_eq!(ak[[0, 0, 0]], 10.0);
        assert_eq!(ak[[1, 1, 0]], 10.0);
        // the null changes nothing
        assert!(run(&f, 0.0).iter().all(|&a| a == 10.0));
    }

    #[test]
    fn unknown_fluence_gains_nothing() {
        let mut f = Array2::<f64>::from_elem((3, 3), 1e4);
        f[[1, 1]] = 1.2e6;
        f[[0, 1]] = f64::NAN;
        let ak = run(&f, 0.5);
        assert_eq!(ak[[0, 1, 0]], 10.0);
        assert!(ak[[1, 0, 0]] > 10.0);
    }

    #[test]
    fn a_neighbour_with_no_slope_counts_at_the_least_fluence_that_leaves_none() {
        // centre of unknown fluence: a transient counts 0, no slope counts
        // 1e4 e-/s * 481 s = 4.81e6 e- (excess 4.61e6; mean over four 1.1525e6);
        // fraction 0.01 -> +11,525 e- of fluence at 1e-3 e- per e- -> +11.525 e-
        let mut f = Array2::<f64>::from_elem((3, 3), 1e4);
        f[[1, 1]] = f64::NAN;
        let none = Array2::from_elem((3, 3), false);
        let mut no_slope = none.clone();
        no_slope[[1, 1]] = true;
        assert!(run_with(&f, &none, 0.01).iter().all(|&a| a == 10.0));
        let ak = run_with(&f, &no_slope, 0.01);
        assert!((ak[[0, 1, 0]] - 21.525).abs() < 1e-9, "{}", ak[[0, 1, 0]]);
        assert_eq!(ak[[0, 0, 0]], 10.0); // diagonal
        assert_eq!(ak[[1, 1, 0]], 10.0); // the unknown pixel itself
    }
}
