//! `populations`: a spatially smooth scale of the trap density across the array.
//!
//! Physics: the paper (end of section 4) notes that "groupings can be made of pixels
//! across the array that exhibit similar persistence current response, likely a result
//! of similar trap distributions": trap density follows the material (growth defects,
//! implant variations), which varies smoothly across the array. Persistence amplitudes
//! are proportional to the trap density (the simulator's truth effect
//! `crate::sim::effects::populations` scales both trap densities by a smooth field and
//! draws the population from another), so the model scales its response by a smooth
//! function of position.
//!
//! What the flagging model can honestly carry is a handful of numbers, not a per-pixel
//! map: here a quadratic surface in the log of the amplitude,
//! `A_k,n(y,x) <- A_k,n(y,x) * exp(gx u + gy v + gxx u^2 + gxy u v + gyy v^2)`,
//! with `u = (x - (nx-1)/2) / (nx/2)` and `v = (y - (ny-1)/2) / (ny/2)` (about -1 at one
//! edge, +1 at the other, the same normalisation as `compare`'s position covariate).
//! There is no constant term: the global scale is the knot table's.
//! Parameters: `gx`, `gy`, `gxx`, `gxy`, `gyy` (default 0, bounds [-2, 2], null 0; all
//! zero is bit-identical to no effect; `fit --with` fits all five). `diagnose` tests
//! the effect's first parameter with a null, `spread_corr` (below), by the spread
//! score (`crate::diag::spread::score`).
//!
//! The pixels' spread: `spread_corr` and `spread_length_px` state how the pixels'
//! places in their population's spread are correlated between neighbours
//! ([`crate::model::effect::SpreadCorrelation`]: patches of a few pixels that share
//! their traps, the simulator's default field). They change no prediction and no flag;
//! `compare`, `fit` and `diagnose` widen each cell's `sigma_q` by its design effect
//! (`crate::diag::spread`). `fit --with populations` measures them from the fitted
//! model's residuals (a moment estimator, `crate::diag::spread::fit_kernel`), not by
//! least squares on the cells, which any widening lowers; they are not fitted
//! otherwise. Defaults 0 and 4 px (bounds [0, 1] and [1, 16]): independent pixels.
//!
//! Limit: it follows array-scale trends only. Patches a few pixels across (the
//! simulator's default correlation length, `length_px` 8) are not representable by
//! five numbers; with the simulator's `populations:length_px=512` the field is
//! array-scale and the surface can follow it.
//! Covariate: position on the array.

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx, SpreadCorrelation};
use ndarray::{Array2, Array3};
use std::sync::OnceLock;

const fn coef(name: &'static str, doc: &'static str) -> ParamSpec {
    ParamSpec {
        name,
        default: 0.0,
        lo: -2.0,
        hi: 2.0,
        null: Some(0.0),
        fitted: true,
        doc,
    }
}

/// The surface's coefficients, in the order of `Populations::new`.
pub const COEFFICIENTS: [&str; 5] = ["gx", "gy", "gxx", "gxy", "gyy"];

/// A pixel's coordinate `v` of `n` along one axis, normalised as in the module docs:
/// about -1 at one edge, +1 at the other.
pub fn coordinate(v: usize, n: usize) -> f64 {
    (v as f64 - (n as f64 - 1.0) / 2.0) / (n as f64 / 2.0)
}

pub const DEF: EffectDef = EffectDef {
    name: "populations",
    summary: "trap density across the array: log A *= quadratic in position; the pixels' \
              spread correlated between neighbours (noise only)",
    params: &[
        ParamSpec {
            name: "spread_corr",
            default: 0.0,
            lo: 0.0,
            hi: 1.0,
            null: Some(0.0),
            fitted: false,
            doc: "correlation of two neighbouring pixels' places in their population's \
                  spread at distance 0 (module docs; measured by `fit --with`, not fitted)",
        },
        ParamSpec {
            name: "spread_length_px",
            default: 4.0,
            lo: 1.0,
            hi: 16.0,
            null: None,
            fitted: false,
            doc: "pixels: the correlation's Gaussian length (module docs)",
        },
        coef(
            COEFFICIENTS[0],
            "log amplitude per half array width in x (u)",
        ),
        coef(
            COEFFICIENTS[1],
            "log amplitude per half array height in y (v)",
        ),
        coef(COEFFICIENTS[2], "coefficient of u^2 in log amplitude"),
        coef(COEFFICIENTS[3], "coefficient of u v in log amplitude"),
        coef(COEFFICIENTS[4], "coefficient of v^2 in log amplitude"),
    ],
    build: |p| {
        let mut e = Populations::new([
            get(p, "gx"),
            get(p, "gy"),
            get(p, "gxx"),
            get(p, "gxy"),
            get(p, "gyy"),
        ]);
        e.spread = SpreadCorrelation {
            corr: get(p, "spread_corr"),
            length_px: get(p, "spread_length_px"),
        };
        Box::new(e)
    },
    covariate: "position",
};

#[derive(Clone)]
pub struct Populations {
    /// `gx, gy, gxx, gxy, gyy`.
    pub g: [f64; 5],
    /// The pixels' spread correlation (module docs); `corr` 0: independent pixels.
    pub spread: SpreadCorrelation,
    /// The scale map of the first array size asked for, kept: it depends on the
    /// parameters and the position only, and a model steps the same array at every
    /// exposure (one `exp` per pixel per exposure saved).
    map: OnceLock<Array2<f64>>,
}

impl std::fmt::Debug for Populations {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Populations")
            .field("g", &self.g)
            .field("spread", &self.spread)
            .finish()
    }
}

impl Populations {
    pub fn new(g: [f64; 5]) -> Populations {
        Populations {
            g,
            spread: SpreadCorrelation {
                corr: 0.0,
                length_px: 4.0,
            },
            map: OnceLock::new(),
        }
    }

    /// The amplitude scale map `[ny, nx]` (module docs).
    pub fn scale(&self, ny: usize, nx: usize) -> Array2<f64> {
        let [gx, gy, gxx, gxy, gyy] = self.g;
        Array2::from_shape_fn((ny, nx), |(y, x)| {
            let (u, v) = (coordinate(x, nx), coordinate(y, ny));
            (gx * u + gy * v + gxx * u * u + gxy * u * v + gyy * v * v).exp()
        })
    }
}

impl Effect for Populations {
    fn name(&self) -> &'static str {
        DEF.name
    }
    /// Local only when the surface is flat (it scales by position).
    fn is_pixel_local(&self) -> bool {
        self.g.iter().all(|g| *g == 0.0)
    }
    /// It scales each pixel's planes by its position alone.
    fn response_reach_px(&self) -> Option<usize> {
        Some(0)
    }
    fn spread_correlation(&self) -> Option<SpreadCorrelation> {
        (self.spread.corr > 0.0).then_some(self.spread)
    }
    fn response(&self, _ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.g.iter().all(|g| *g == 0.0) {
            return;
        }
        let (ny, nx, _) = ak.dim();
        let kept = self.map.get_or_init(|| self.scale(ny, nx));
        let other;
        let s = if kept.dim() == (ny, nx) {
            kept
        } else {
            other = self.scale(ny, nx);
            &other
        };
        ndarray::Zip::from(ak.lanes_mut(ndarray::Axis(2)))
            .and(s)
            .for_each(|mut lane, si| lane.iter_mut().for_each(|a| *a *= si));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gradient_scales_as_documented() {
        // 1 x 4: u = (x - 1.5) / 2 = -0.75, -0.25, 0.25, 0.75; gx = ln 2 -> scale 2^u
        let p = Populations::new([std::f64::consts::LN_2, 0.0, 0.0, 0.0, 0.0]);
        let s = p.scale(1, 4);
        for (x, u) in [-0.75f64, -0.25, 0.25, 0.75].iter().enumerate() {
            assert!((s[[0, x]] - 2f64.powf(*u)).abs() < 1e-12);
        }
        let q = Populations::new([0.0, 0.0, 1.0, 0.0, 1.0]);
        let s = q.scale(3, 3); // u, v in {-2/3, 0, 2/3}
        assert_eq!(s[[1, 1]], 1.0);
        assert!((s[[0, 0]] - (8.0f64 / 9.0).exp()).abs() < 1e-12);
    }
}
