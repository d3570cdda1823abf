//! `blooming`: persistence added by the neighbours' excess fluence.
//!
//! Physics: charge spilling from a saturated, forward-biased pixel into its neighbours
//! fills their traps beyond what their own measured flux tells (paper section 2.2
//! suggests blooming behind the rise of persistence at saturation).
//! Equation (response hook): `A_k,n += gain_per_e * E_nb`, where `E_nb` is the mean over
//! the four nearest neighbours of `max(0, F_nb - f_sat_e)`, `F` the extrapolated
//! fluence (neighbours outside the array or of unknown fluence count 0).
//! Parameters: `gain_per_e` (amplitude electrons per electron of neighbour excess
//! fluence; default 2e-5, bounds [0, 1e-2], null 0), `f_sat_e` (200,000 e-, the paper's
//! saturation level; not fitted).
//! Covariate: neighbour excess fluence.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::Array3;

pub const DEF: EffectDef = EffectDef {
    name: "blooming",
    summary: "neighbours' excess fluence above saturation adds amplitude",
    params: &[
        ParamSpec {
            name: "gain_per_e",
            default: 2e-5,
            lo: 0.0,
            hi: 1e-2,
            null: Some(0.0),
            fitted: true,
            doc: "amplitude (e-) per e- of mean neighbour excess fluence",
        },
        ParamSpec {
            name: "f_sat_e",
            default: 2e5,
            lo: 1.0,
            hi: 1e9,
            null: None,
            fitted: false,
            doc: "saturation fluence, e-",
        },
    ],
    build: |p| {
        Box::new(Blooming {
            gain_per_e: get(p, "gain_per_e"),
            f_sat_e: get(p, "f_sat_e"),
        })
    },
    covariate: "neighbour_excess_fluence",
};

#[derive(Debug, Clone)]
pub struct Blooming {
    pub gain_per_e: f64,
    pub f_sat_e: f64,
}

/// Mean over the 4 nearest neighbours of `max(0, F - f_sat)`, e-.
pub fn neighbour_excess(fluence_e: &ndarray::Array2<f64>, f_sat_e: f64) -> ndarray::Array2<f64> {
    let (ny, nx) = fluence_e.dim();
    let ex = |y: usize, x: usize| {
        let f = fluence_e[[y, x]];
        if f.is_finite() {
            (f - f_sat_e).max(0.0)
        } else {
            0.0
        }
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
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.gain_per_e == 0.0 {
            return;
        }
        let e = neighbour_excess(ctx.fluence_e, self.f_sat_e);
        ndarray::Zip::from(ak.lanes_mut(ndarray::Axis(2)))
            .and(&e)
            .for_each(|mut lane, ei| {
                let add = self.gain_per_e * ei;
                lane.iter_mut().for_each(|a| *a += add);
            });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn neighbour_of_a_saturated_pixel_gains() {
        // 3x3, centre at 1.2e6 e-, f_sat 2e5: excess 1e6 shared as mean over 4 neighbours
        // -> each edge-adjacent pixel sees (1e6)/4 = 2.5e5; gain 1e-4 -> +25 e-.
        let mut f = Array2::<f64>::zeros((3, 3));
        f[[1, 1]] = 1.2e6;
        let b = Blooming {
            gain_per_e: 1e-4,
            f_sat_e: 2e5,
        };
        let mut ak = Array3::<f64>::from_elem((3, 3, 2), 10.0);
        let rates = [0.1, 0.01];
        b.response(
            &ResponseCtx {
                fluence_e: &f,
                t_illuminated_s: 481.0,
                t_exposure_s: 613.0,
                rate_per_s: &rates,
                response: &crate::model::Response::new(
                    &crate::model::ModelParams::default().amplitude_knots,
                ),
            },
            &mut ak,
        );
        assert!((ak[[0, 1, 0]] - 35.0).abs() < 1e-9);
        assert!((ak[[1, 2, 1]] - 35.0).abs() < 1e-9);
        assert_eq!(ak[[0, 0, 0]], 10.0); // diagonal: no neighbour excess
        assert_eq!(ak[[1, 1, 0]], 10.0); // the saturated pixel itself
    }
}
