//! `short_tau_boost`: the fastest terms respond more in a fluence window.
//!
//! Physics: the paper (end of section 4) found "the shortest time constants had a
//! strong boost, particularly for pixels with fluence between 200000 and 500000 e-".
//! Equation (response hook): `A_k,n *= factor` for terms with `tau_n <= tau_max_s`
//! where `fluence_min_e <= F <= fluence_max_e`.
//! Parameters: `factor` (default 3, bounds [0.1, 100], null 1), `tau_max_s` (30 s: the
//! paper's 10 s term), `fluence_min_e` (200,000), `fluence_max_e` (500,000); only
//! `factor` is fitted.
//! Covariate: fluence x time since illumination (first integrations, mid fluences).

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::Array3;

pub const DEF: EffectDef = EffectDef {
    name: "short_tau_boost",
    summary: "fast terms multiplied by a factor in a fluence window",
    params: &[
        ParamSpec {
            name: "factor",
            default: 3.0,
            lo: 0.1,
            hi: 100.0,
            null: Some(1.0),
            fitted: true,
            doc: "gain of the fast terms inside the window",
        },
        ParamSpec {
            name: "tau_max_s",
            default: 30.0,
            lo: 0.0,
            hi: 1e7,
            null: None,
            fitted: false,
            doc: "terms with tau_n up to this are boosted, s",
        },
        ParamSpec {
            name: "fluence_min_e",
            default: 2e5,
            lo: 0.0,
            hi: 1e12,
            null: None,
            fitted: false,
            doc: "window start, e-",
        },
        ParamSpec {
            name: "fluence_max_e",
            default: 5e5,
            lo: 0.0,
            hi: 1e12,
            null: None,
            fitted: false,
            doc: "window end, e-",
        },
    ],
    build: |p| {
        Box::new(ShortTauBoost {
            factor: get(p, "factor"),
            tau_max_s: get(p, "tau_max_s"),
            fluence_min_e: get(p, "fluence_min_e"),
            fluence_max_e: get(p, "fluence_max_e"),
        })
    },
    covariate: "fluence_x_time",
};

#[derive(Debug, Clone)]
pub struct ShortTauBoost {
    pub factor: f64,
    pub tau_max_s: f64,
    pub fluence_min_e: f64,
    pub fluence_max_e: f64,
}

impl Effect for ShortTauBoost {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn is_pixel_local(&self) -> bool {
        true
    }
    fn response_is_per_pixel(&self) -> bool {
        true
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        let terms: Vec<usize> = (0..ctx.rate_per_s.len())
            .filter(|&n| 1.0 / ctx.rate_per_s[n] <= self.tau_max_s)
            .collect();
        if terms.is_empty() || self.factor == 1.0 {
            return;
        }
        for ((y, x), f) in ctx.fluence_e.indexed_iter() {
            if *f >= self.fluence_min_e && *f <= self.fluence_max_e {
                for &n in &terms {
                    ak[[y, x, n]] *= self.factor;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn boosts_fast_terms_in_window_only() {
        let f = Array2::from_shape_vec((1, 3), vec![1e5, 3e5, f64::NAN]).unwrap();
        let rates = [0.1, 0.01]; // tau 10 s and 100 s
        let mut ak = Array3::from_elem((1, 3, 2), 2.0);
        let b = ShortTauBoost {
            factor: 3.0,
            tau_max_s: 30.0,
            fluence_min_e: 2e5,
            fluence_max_e: 5e5,
        };
        b.response(
            &ResponseCtx {
                needed: None,
                fluence_e: &f,
                no_slope: &ndarray::Array2::from_elem(f.dim(), false),
                t_illuminated_s: 1.0,
                t_exposure_s: 1.0,
                rate_per_s: &rates,
                rate_held_per_s: &rates,
                response: &crate::model::Response::new(
                    &crate::model::ModelParams::default().amplitude_knots,
                ),
            },
            &mut ak,
        );
        assert_eq!(ak.as_slice().unwrap(), &[2.0, 2.0, 6.0, 2.0, 2.0, 2.0]);
    }
}
