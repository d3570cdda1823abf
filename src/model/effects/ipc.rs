//! `ipc`: inter-pixel capacitance.
//!
//! Physics: capacitive coupling between neighbouring pixels' readout nodes makes each
//! pixel *read* a fraction of each neighbour's charge and lose the same fraction of its
//! own (Moore, Ninkov & Forrest 2006, Opt. Eng. 45, 076402; about 1 % per nearest
//! neighbour in H2RG arrays). The coupling is often stronger along one axis than the
//! other and reaches the diagonal neighbours at a few tenths of a percent (the 3 x 3
//! kernel with `alpha_x`, `alpha_y` and a diagonal `alpha_d` of Kannawadi et al. 2016,
//! PASP 128, 095001). The coupling acts on the readout, not on the charge the traps
//! see: what the stage measures is `K s`, with
//! `(K s)(y,x) = c s(y,x) + alpha_x (s(y,x-1) + s(y,x+1)) + alpha_y (s(y-1,x) + s(y+1,x))`
//! plus `alpha_d` times the sum of the 4 diagonal neighbours, and
//! `c = 1 - 2 alpha_x - 2 alpha_y - 4 alpha_d` (neighbours outside the array or of
//! unknown value add nothing; with `alpha_x = alpha_y` and no diagonal it is the
//! simulator's truth effect `crate::sim::effects::ipc`).
//!
//! So the flagging model, which only sees measured images, must
//! 1. recover the fluence each pixel received from the measured one (fluence hook):
//!    `F = K^-1 F'`, by the fixed-point iteration `F <- F' + (F - K F)` from `F = F'`
//!    (after `n` iterations the error is below `(2 (1 - c))^(n+1)` of the largest
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
//!
//! Parameters:
//! - `alpha` (default 0.01, bounds [0, 0.05], null 0): the mean coupling to a nearest
//!   neighbour, `(alpha_x + alpha_y) / 2`; fitted where it is not measured (below).
//! - `alpha_split` (default 0, bounds [-0.05, 0.05]): half the difference,
//!   `alpha_x = alpha + alpha_split`, `alpha_y = alpha - alpha_split` (each at least 0).
//! - `alpha_diag` (default 0, bounds [0, 0.02]): `alpha_d`.
//!
//! `alpha_split` and `alpha_diag` are not fitted: `fit --with ipc` measures them, and
//! `alpha`, on the illuminated images' isolated bright pixels
//! ([`crate::measure::coupling`]), the classic single-pixel method, and holds them;
//! where the data hold too few such pixels the shape stays as given and `alpha` is
//! fitted.
//! `alpha` 0 is bit-identical to no effect; a model file that names `alpha` alone is
//! the isotropic four-neighbour kernel. Covariate: neighbour excess fluence.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::{Array2, Array3};

pub const DEF: EffectDef = EffectDef {
    name: "ipc",
    summary: "inter-pixel capacitance: fluence deconvolved, response coupled to the 3 x 3 \
              neighbours",
    params: &[
        ParamSpec {
            name: "alpha",
            default: 0.01,
            lo: 0.0,
            hi: 0.05,
            null: Some(0.0),
            fitted: true,
            doc: "mean coupling fraction per nearest neighbour, (alpha_x + alpha_y) / 2",
        },
        ParamSpec {
            name: "alpha_split",
            default: 0.0,
            lo: -0.05,
            hi: 0.05,
            null: None,
            fitted: false,
            doc: "alpha_x - alpha (row neighbours x +- 1 take alpha + alpha_split, column \
                  neighbours alpha - alpha_split; measured by `fit --with`, not fitted)",
        },
        ParamSpec {
            name: "alpha_diag",
            default: 0.0,
            lo: 0.0,
            hi: 0.02,
            null: None,
            fitted: false,
            doc: "coupling fraction per diagonal neighbour (measured by `fit --with`, not \
                  fitted)",
        },
    ],
    build: |p| {
        Box::new(Ipc {
            alpha: get(p, "alpha"),
            alpha_split: get(p, "alpha_split"),
            alpha_diag: get(p, "alpha_diag"),
        })
    },
    covariate: "neighbour_excess_fluence",
};

/// At most this many fixed-point iterations of the deconvolution (module docs).
pub const MAX_ITERATIONS: usize = 12;

#[derive(Debug, Clone)]
pub struct Ipc {
    pub alpha: f64,
    pub alpha_split: f64,
    pub alpha_diag: f64,
}

/// The coupling to each neighbour, `(dy, dx, weight)`, and the centre's weight `c`
/// (module docs). Neighbours of weight 0 are left out.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    pub neighbours: Vec<(isize, isize, f64)>,
    pub centre: f64,
}

impl Kernel {
    /// The kernel of `alpha_x` (row neighbours), `alpha_y` (column neighbours) and
    /// `alpha_d` (diagonal neighbours).
    pub fn new(alpha_x: f64, alpha_y: f64, alpha_d: f64) -> Kernel {
        let all = [
            (-1, 0, alpha_y),
            (1, 0, alpha_y),
            (0, -1, alpha_x),
            (0, 1, alpha_x),
            (-1, -1, alpha_d),
            (-1, 1, alpha_d),
            (1, -1, alpha_d),
            (1, 1, alpha_d),
        ];
        let centre = 1.0 - all.iter().map(|k| k.2).sum::<f64>();
        Kernel {
            neighbours: all.into_iter().filter(|k| k.2 != 0.0).collect(),
            centre,
        }
    }

    /// The four nearest neighbours at `alpha` each.
    pub fn isotropic(alpha: f64) -> Kernel {
        Kernel::new(alpha, alpha, 0.0)
    }

    /// `K` applied to the row-major planes of `src` (`ny * nx` pixels of `n` values each)
    /// at pixel `(y, x)`, into `out` (`n` values): the centre's weight on its own
    /// finite values, the neighbours' finite values at their weights; a non-finite own
    /// value is left as it is.
    fn apply_at(
        &self,
        src: &[f64],
        (ny, nx, n): (usize, usize, usize),
        y: usize,
        x: usize,
        out: &mut [f64],
    ) {
        let p = y * nx + x;
        for (o, v) in out.iter_mut().zip(&src[p * n..(p + 1) * n]) {
            *o = if v.is_finite() { self.centre * v } else { *v };
        }
        for &(dy, dx, w) in &self.neighbours {
            let (Some(yy), Some(xx)) = (y.checked_add_signed(dy), x.checked_add_signed(dx)) else {
                continue;
            };
            if yy >= ny || xx >= nx {
                continue;
            }
            let q = yy * nx + xx;
            for (o, v) in out.iter_mut().zip(&src[q * n..(q + 1) * n]) {
                if o.is_finite() && v.is_finite() {
                    *o += w * v;
                }
            }
        }
    }
}

impl Ipc {
    /// The isotropic four-neighbour coupling `alpha` (a model file naming `alpha` alone).
    pub fn isotropic(alpha: f64) -> Ipc {
        Ipc {
            alpha,
            alpha_split: 0.0,
            alpha_diag: 0.0,
        }
    }

    /// The kernel of the parameters (module docs); none when `alpha` is 0.
    pub fn kernel(&self) -> Kernel {
        if self.alpha == 0.0 {
            return Kernel::new(0.0, 0.0, 0.0);
        }
        Kernel::new(
            (self.alpha + self.alpha_split).max(0.0),
            (self.alpha - self.alpha_split).max(0.0),
            self.alpha_diag,
        )
    }
}

/// `K s` (module docs) of a plane; non-finite values stay as they are and count 0 as
/// neighbours.
pub fn couple(s: &Array2<f64>, kernel: &Kernel) -> Array2<f64> {
    let (ny, nx) = s.dim();
    let src = s.as_standard_layout();
    let src = src.as_slice().expect("standard layout");
    let mut out = vec![0.0f64; ny * nx];
    for y in 0..ny {
        for x in 0..nx {
            let p = y * nx + x;
            kernel.apply_at(src, (ny, nx, 1), y, x, &mut out[p..p + 1]);
        }
    }
    Array2::from_shape_vec((ny, nx), out).expect("shape")
}

/// `K^-1 s'` by fixed-point steps (module docs), clipped at 0 (NaN stays NaN).
pub fn decouple(measured: &Array2<f64>, kernel: &Kernel) -> Array2<f64> {
    let mut f = measured.clone();
    let scale = measured
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0f64, |a, v| a.max(v.abs()));
    for _ in 0..MAX_ITERATIONS {
        let k = couple(&f, kernel);
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
        *fluence_e = decouple(fluence_e, &self.kernel());
    }
    /// `K`'s neighbours and their weights.
    fn readout_kernel(&self) -> Vec<(isize, isize, f64)> {
        self.kernel().neighbours
    }
    /// Each pixel's planes take its neighbours': one step between 4-neighbours, two to
    /// a diagonal neighbour.
    fn response_reach_px(&self) -> Option<usize> {
        let k = self.kernel();
        Some(
            k.neighbours
                .iter()
                .map(|&(dy, dx, _)| dy.unsigned_abs() + dx.unsigned_abs())
                .max()
                .unwrap_or(0),
        )
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
        let kernel = self.kernel();
        let (ny, nx, n) = ak.dim();
        let src = ak.as_standard_layout().into_owned();
        let src = src.as_slice().expect("standard layout");
        let mut out = vec![0.0f64; n];
        for y in 0..ny {
            for x in 0..nx {
                if !ctx.fluence_e[[y, x]].is_finite() {
                    continue; // the step restores its own amplitude
                }
                if !ctx.is_needed(y, x) {
                    continue; // nothing reads its planes
                }
                kernel.apply_at(src, (ny, nx, n), y, x, &mut out);
                for (t, v) in out.iter().enumerate() {
                    ak[[y, x, t]] = *v;
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
        let k = couple(&s, &Kernel::isotropic(0.01));
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
        let back = decouple(
            &couple(&s, &Kernel::isotropic(0.02)),
            &Kernel::isotropic(0.02),
        );
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
            .zip(couple(&s, &Kernel::isotropic(0.02)).iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < raw / 20.0, "{worst} {raw}");
    }

    /// An anisotropic kernel with diagonals leaks each weight to its own neighbour,
    /// conserves the charge inside the array, and is inverted by [`decouple`].
    #[test]
    fn an_anisotropic_kernel_leaks_each_weight_and_is_inverted() {
        let ipc = Ipc {
            alpha: 0.0175,
            alpha_split: 0.0075,
            alpha_diag: 0.004,
        };
        let k = ipc.kernel();
        let mut s = Array2::<f64>::zeros((5, 5));
        s[[2, 2]] = 1000.0;
        let c = couple(&s, &k);
        assert!((c[[2, 1]] - 25.0).abs() < 1e-9, "{c:?}");
        assert!((c[[1, 2]] - 10.0).abs() < 1e-9, "{c:?}");
        assert!((c[[1, 1]] - 4.0).abs() < 1e-9, "{c:?}");
        assert!((c[[2, 2]] - 1000.0 * (1.0 - 0.05 - 0.02 - 0.016)).abs() < 1e-9);
        assert!((c.sum() - 1000.0).abs() < 1e-9);
        assert_eq!(ipc.response_reach_px(), Some(2));
        assert_eq!(Ipc::isotropic(0.01).response_reach_px(), Some(1));
        let f = Array2::from_shape_fn((6, 7), |(y, x)| {
            ((y * 7 + x) as f64 * 1.3).cos().abs() * 1e5
        });
        let back = decouple(&couple(&f, &k), &k);
        let worst = f
            .iter()
            .zip(back.iter())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1.0, "{worst}");
    }

    /// A model file naming `alpha` alone is the four-neighbour kernel of earlier files;
    /// `alpha` 0 couples nothing whatever the shape.
    #[test]
    fn alpha_alone_is_the_four_neighbour_kernel_and_zero_couples_nothing() {
        let k = Ipc::isotropic(0.01).kernel();
        assert_eq!(k.neighbours.len(), 4);
        assert!((k.centre - 0.96).abs() < 1e-15);
        let off = Ipc {
            alpha: 0.0,
            alpha_split: 0.01,
            alpha_diag: 0.01,
        };
        assert!(off.kernel().neighbours.is_empty());
        assert_eq!(off.response_reach_px(), Some(0));
    }
}
