//! `ipc`: inter-pixel capacitance.
//!
//! Physics: capacitive coupling between neighbouring pixels' readout nodes makes each
//! pixel read a fraction of its neighbours' charge (Moore, Ninkov & Forrest 2006;
//! about 1 % per nearest neighbour in H2RG arrays).
//! Equation: measured `s'(y,x) = (1 - 4 alpha) s(y,x) + alpha * sum of the 4 nearest
//! neighbours`, applied to every ramp sample and to the slope image (the least-squares
//! slope is linear in the samples, so the two commute where pixels share samples).
//! Neighbours without a value (NaN) or outside the array contribute nothing.
//! Parameter: `alpha` (default 0.01, bounds [0, 0.05]).
//! Visible as: isolated bright features leak ~1 % into each neighbour; flat regions are
//! unchanged; the charge is conserved away from edges.

use crate::sim::effect::{Effect, ParamReader};
use ndarray::{Array2, Array3, ArrayViewMut2, Axis};
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Ipc {
    pub alpha: f64,
}

impl Ipc {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("ipc", p);
        let alpha = r.get("alpha", 0.01, 0.0, 0.05)?;
        r.finish()?;
        Ok(Ipc { alpha })
    }
}

/// Apply the IPC kernel in place.
pub fn convolve(mut img: ArrayViewMut2<'_, f32>, alpha: f64) {
    let src = img.to_owned();
    let (ny, nx) = src.dim();
    let a = alpha as f32;
    let c = 1.0 - 4.0 * a;
    let val = |y: usize, x: usize| {
        let v = src[[y, x]];
        if v.is_finite() {
            v
        } else {
            0.0
        }
    };
    for y in 0..ny {
        for x in 0..nx {
            let v = src[[y, x]];
            if !v.is_finite() {
                continue;
            }
            let mut s = 0.0f32;
            crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| s += val(y, x));
            img[[y, x]] = c * v + a * s;
        }
    }
}

impl Effect for Ipc {
    fn name(&self) -> &'static str {
        "ipc"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([("alpha".to_string(), self.alpha)])
    }
    fn measured(&self, image: &mut Array2<f32>, ramp: Option<&mut Array3<f32>>) {
        convolve(image.view_mut(), self.alpha);
        if let Some(r) = ramp {
            for s in r.axis_iter_mut(Axis(0)) {
                convolve(s, self.alpha);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_leaks_alpha_to_each_neighbour_and_conserves_charge() {
        let mut a = Array2::<f32>::zeros((5, 5));
        a[[2, 2]] = 100.0;
        convolve(a.view_mut(), 0.01);
        assert!((a[[1, 2]] - 1.0).abs() < 1e-5);
        assert!((a[[2, 2]] - 96.0).abs() < 1e-4);
        assert!((a.sum() - 100.0).abs() < 1e-3);
    }
}
