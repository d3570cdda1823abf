//! `populations`: spatially correlated trap populations.
//!
//! Physics: the paper (end of section 4) notes that "groupings can be made of pixels
//! across the array that exhibit similar persistence current response, likely a result
//! of similar trap distributions" — trap density follows the material (growth defects,
//! implant variations), which varies smoothly across the array.
//! Equation: two Gaussian random fields `g1, g2` of unit variance and correlation length
//! `length_px` (white noise smoothed by three box passes). A pixel's population is
//! chosen by the quantile of `g1` (`Phi(g1)` against the cumulative mixture weights, so
//! the weights are kept), and both densities are multiplied by
//! `exp(density_scatter * g2)`.
//! Parameters: `length_px` (default 8, bounds [1, 512]), `density_scatter` (default 0.2,
//! bounds [0, 2]).
//! Visible as: neighbouring pixels share populations: the correlation of the saturated
//! persistence between adjacent pixels rises from ~0 to > 0.5; the population fractions
//! and medians stay about the same.

use crate::sim::effect::{Effect, ParamReader};
use crate::sim::rng::{purpose, stream};
use crate::sim::traps::{pick, PixelTraps, TrapParams};
use ndarray::Array2;
use rand_distr::{Distribution, StandardNormal};
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Populations {
    pub length_px: f64,
    pub density_scatter: f64,
}

impl Populations {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("populations", p);
        let length_px = r.get("length_px", 8.0, 1.0, 512.0)?;
        let density_scatter = r.get("density_scatter", 0.2, 0.0, 2.0)?;
        r.finish()?;
        Ok(Populations {
            length_px,
            density_scatter,
        })
    }
}

/// A unit-variance smooth Gaussian field.
pub fn field(ny: usize, nx: usize, length: f64, seed: u64, tags: &[u64]) -> Array2<f64> {
    let mut f = Array2::<f64>::zeros((ny, nx));
    for y in 0..ny {
        let mut t = tags.to_vec();
        t.push(y as u64);
        let mut r = stream(seed, &t);
        for x in 0..nx {
            f[[y, x]] = StandardNormal.sample(&mut r);
        }
    }
    let h = (length / 2.0).round().max(1.0) as usize;
    for _ in 0..3 {
        f = crate::sim::analysis::box_blur(&f, h);
    }
    let n = (ny * nx) as f64;
    let mean = f.sum() / n;
    let sd = (f.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    f.mapv(|v| (v - mean) / sd.max(1e-300))
}

/// Standard normal CDF (Abramowitz-Stegun 7.1.26 erf, |error| < 1.5e-7).
pub fn norm_cdf(z: f64) -> f64 {
    let x = z.abs() / std::f64::consts::SQRT_2;
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let y = 1.0
        - (((((1.061_405_429 * t - 1.453_152_027) * t) + 1.421_413_741) * t - 0.284_496_736) * t
            + 0.254_829_592)
            * t
            * (-x * x).exp();
    if z >= 0.0 {
        0.5 * (1.0 + y)
    } else {
        0.5 * (1.0 - y)
    }
}

impl Effect for Populations {
    fn name(&self) -> &'static str {
        "populations"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([
            ("length_px".to_string(), self.length_px),
            ("density_scatter".to_string(), self.density_scatter),
        ])
    }
    fn trap_pixels(&self, px: &mut PixelTraps, p: &TrapParams, seed: u64, det: u8) {
        let (ny, nx) = px.d_lin.dim();
        let d = u64::from(det);
        let g1 = field(ny, nx, self.length_px, seed, &[purpose::POPULATIONS, d, 1]);
        let g2 = field(ny, nx, self.length_px, seed, &[purpose::POPULATIONS, d, 2]);
        let wsum: f64 = p.populations.iter().map(|q| q.weight).sum();
        for y in 0..ny {
            for x in 0..nx {
                let old = usize::from(px.population[[y, x]]);
                let k = pick(&p.populations, norm_cdf(g1[[y, x]]) * wsum);
                // keep the pixel's own lognormal scatter, change its population mean
                let rel = if p.populations[old].d_sat_e_per_decade > 0.0 {
                    f64::from(px.d_sat[[y, x]]) / p.populations[old].d_sat_e_per_decade
                } else {
                    1.0
                };
                let m = (self.density_scatter * g2[[y, x]]).exp();
                px.population[[y, x]] = k as u8;
                px.d_sat[[y, x]] = (p.populations[k].d_sat_e_per_decade * rel * m) as f32;
                px.d_lin[[y, x]] = (f64::from(px.d_lin[[y, x]]) * m) as f32;
            }
        }
    }
}
