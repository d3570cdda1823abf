//! `ipc`: inter-pixel capacitance.
//!
//! Physics: capacitive coupling between neighbouring pixels' readout nodes makes each
//! pixel *read* a fraction `alpha` of each nearest neighbour's charge and lose the same
//! fraction of its own (Moore, Ninkov & Forrest 2006, Opt. Eng. 45, 076402; about 1 %
//! per nearest neighbour in H2RG arrays). The coupling acts on the readout, not on the
//! charge the traps see: what the stage measures is `K s`, with
//! `(K s)(y,x) = (1 - 4 alpha) s(y,x) + alpha * (sum of the 4 nearest neighbours)`
//! (neighbours outside the array or of unknown value add nothing; the simulator's truth
//! effect `crate::sim::effects::ipc` uses the same kernel).
//!
//! So the flagging model, which only sees measured images, must
//! 1. recover the fluence each pixel received from the measured one (fluence hook):
//!    `F = K^-1 F'`, by the fixed-point iteration `F <- F' + (F - K F)` from `F = F'`
//!    (after `n` iterations the error is below `(8 alpha)^(n+1)` of the largest
//!    fluence; it stops when an update changes no pixel by more than 1e-8 of the
//!    largest fluence, at most [`MAX_ITERATIONS`]), negative values set to 0;
//! 2. evaluate the paper's `A_k(F)` on it (done by the step for the pixels it changes);
//! 3. predict what the readout will show of the trapped charge: the response planes are
//!    coupled the same way, `A_k,n <- K A_k,n` (response hook); a pixel of unknown
//!    fluence in the illumination (no slope: saturated, a cosmic ray) has the largest
//!    amplitude and a value in the later exposures, so it couples too. The decay is
//!    the same for every pixel, so coupling each exposure's addition couples the whole
//!    prediction: the predicted current is `K` of the uncoupled one.
//!
//! Effect on predictions: next to a bright isolated pixel (a star, a saturated spot) a
//! faint neighbour's measured fluence `F' ~ alpha F_bright` no longer counts as its own
//! fluence (without the effect a neighbour of a 1e8 e- star is given the saturated
//! amplitude); instead it is predicted `alpha` of the bright pixel's persistence. On
//! smooth illumination (flat fields, the laboratory pinhole away from its centre) the
//! effect is of order `alpha` times the curvature of the image and vanishes.
//! Parameter: `alpha` (default 0.01, bounds [0, 0.05], null 0: bit-identical to no
//! effect). Covariate: neighbour excess fluence.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::{Array2, Array3};

pub const DEF: EffectDef = EffectDef {
    name: "ipc",
    summary: "inter-pixel capacitance: fluence deconvolved, response coupled to 4 neighbours",
    params: &[ParamSpec {
        name: "alpha",
        default: 0.01,
        lo: 0.0,
        hi: 0.05,
        null: Some(0.0),
        fitted: true,
        doc: "coupling fraction per nearest neighbour",
    }],
    build: |p| {
        Box::new(Ipc {
            alpha: get(p, "alpha"),
        })
    },
    covariate: "neighbour_excess_fluence",
};

/// At most this many fixed-point iterations of the deconvolution (module docs).
pub const MAX_ITERATIONS: usize = 12;

#[derive(Debug, Clone)]
pub struct Ipc {
    pub alpha: f64,
}

/// `K s` (module docs) of a plane; non-finite values stay as they are and count 0 as
/// neighbours.
pub fn couple(s: &Array2<f64>, alpha: f64) -> Array2<f64> {
    let (ny, nx) = s.dim();
    let src = s.as_standard_layout();
    let src = src.as_slice().expect("standard layout");
    let val = |v: f64| if v.is_finite() { v } else { 0.0 };
    let c = 1.0 - 4.0 * alpha;
    let mut out = vec![0.0f64; ny * nx];
    for y in 0..ny {
        for (x, o) in out[y * nx..(y + 1) * nx].iter_mut().enumerate() {
            let v = src[y * nx + x];
            if !v.is_finite() {
                *o = v;
                continue;
            }
            let mut n = 0.0;
            crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| n += val(src[y * nx + x]));
            *o = c * v + alpha * n;
        }
    }
    Array2::from_shape_vec((ny, nx), out).expect("shape")
}

/// `K^-1 s'` by fixed-point steps (module docs), clipped at 0 (NaN stays NaN).
pub fn decouple(measured: &Array2<f64>, alpha: f64) -> Array2<f64> {
    let mut f = measured.clone();
    let scale = measured
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0f64, |a, v| a.max(v.abs()));
    for _ in 0..MAX_ITERATIONS {
        let k = couple(&f, alpha);
        let mut change = 0.0f64;
        ndarray::Zip::from(&mut f)
            .and(measured)
            .and(&k)
            .for_each(|f, m, k| {
                let new = *m + (*f - *k);
                if new.is_finite() {
                    change = change.max((new - *f).abs());
                }
                *f = new;
            });
        if change <= 1e-8 * scale {
            break;
        }
    }
    f.mapv_inplace(|v| if v.is_nan() { v } else { v.max(0.0) });
    f
}

impl Effect for Ipc {
    fn name(&self) -> &'static str {
        DEF.name
    }
    /// Local only when it couples nothing.
    fn is_pixel_local(&self) -> bool {
        self.alpha == 0.0
    }
    fn has_fluence(&self) -> bool {
        self.alpha != 0.0
    }
    fn fluence(&self, fluence_e: &mut Array2<f64>) {
        if self.alpha == 0.0 {
            return;
        }
        *fluence_e = decouple(fluence_e, self.alpha);
    }
    /// `K`: `alpha` from each of the four nearest neighbours.
    fn readout_kernel(&self) -> Vec<(isize, isize, f64)> {
        if self.alpha == 0.0 {
            return Vec::new();
        }
        [(-1, 0), (1, 0), (0, -1), (0, 1)]
            .map(|(dy, dx)| (dy, dx, self.alpha))
            .to_vec()
    }
    /// Each pixel's planes take its four neighbours'.
    fn response_reach_px(&self) -> Option<usize> {
        Some(usize::from(self.alpha != 0.0))
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.alpha == 0.0 {
            return;
        }
        // `K` on every term plane in one pass (the same arithmetic as [`couple`]). A
        // pixel of unknown fluence (no slope in the illuminated exposure: saturated, a
        // cosmic ray) is given the largest amplitude by the step, which also restores its
        // own amplitude after this hook; it reads a value in the later exposures, so its
        // persistence is coupled into its neighbours like any other's (regression test
        // `a_star_without_a_slope_still_leaks_its_persistence_into_its_neighbours`).
        // Non-finite amplitudes add nothing.
        let (ny, nx, n) = ak.dim();
        let src = ak.as_standard_layout().into_owned();
        let src = src.as_slice().expect("standard layout");
        let c = 1.0 - 4.0 * self.alpha;
        let mut sum = vec![0.0f64; n];
        for y in 0..ny {
            for x in 0..nx {
                if !ctx.fluence_e[[y, x]].is_finite() {
                    continue; // the step restores its own amplitude
                }
                if !ctx.is_needed(y, x) {
                    continue; // nothing reads its planes
                }
                let p = y * nx + x;
                sum.fill(0.0);
                let mut add = |q: usize| {
                    for (s, v) in sum.iter_mut().zip(&src[q * n..(q + 1) * n]) {
                        if v.is_finite() {
                            *s += v;
                        }
                    }
                };
                crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| add(y * nx + x));
                for (t, s) in sum.iter().enumerate() {
                    let v = src[p * n + t];
                    if v.is_finite() {
                        ak[[y, x, t]] = c * v + self.alpha * s;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn couple_leaks_alpha_and_conserves_inside() {
        let mut s = Array2::<f64>::zeros((5, 5));
        s[[2, 2]] = 100.0;
        let k = couple(&s, 0.01);
        assert!((k[[1, 2]] - 1.0).abs() < 1e-12);
        assert!((k[[2, 2]] - 96.0).abs() < 1e-12);
        assert!((k.sum() - 100.0).abs() < 1e-9);
        assert_eq!(k[[1, 1]], 0.0);
    }

    #[test]
    fn decouple_inverts_couple() {
        let s = Array2::from_shape_fn((6, 7), |(y, x)| {
            ((y * 7 + x) as f64 * 1.7).sin().abs() * 1e5
        });
        let back = decouple(&couple(&s, 0.02), 0.02);
        // converged to 1e-8 of the largest value (module docs)
        let bound = 1e-5 * 1e5;
        let worst = s
            .iter()
            .zip(back.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < bound, "{worst} {bound}");
        // and it is a real improvement over not deconvolving
        let raw = s
            .iter()
            .zip(couple(&s, 0.02).iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < raw / 20.0, "{worst} {raw}");
    }
}
