//! `blooming`: excess charge of a saturated pixel spills into its neighbours.
//!
//! Physics: once a diode is saturated and forward biased, part of the further
//! photocurrent diffuses laterally and is collected by the four nearest neighbours
//! (blooming; the paper, section 2.2, suggests it as a contributor to the persistence
//! rise at saturation, citing its reference "2021Blooming").
//! Equation: for each pixel with flux `phi > phi_sat = Q_fw / t_on`, a fraction
//! `fraction` of the excess `phi - phi_sat` is removed and shared equally by its four
//! neighbours (`phi_nb += fraction (phi - phi_sat) / 4`), before integration.
//! Parameter: `fraction` (default 0.05, bounds [0, 0.5]; assumed, no measurement).
//! Visible as: neighbours of saturated pixels collect more charge, so their measured
//! flux and their persistence rise; the rise is largest next to the most saturated
//! pixels.

use crate::sim::effect::{Effect, ParamReader};
use ndarray::Array2;
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Blooming {
    pub fraction: f64,
}

impl Blooming {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("blooming", p);
        let fraction = r.get("fraction", 0.05, 0.0, 0.5)?;
        r.finish()?;
        Ok(Blooming { fraction })
    }
}

impl Effect for Blooming {
    fn name(&self) -> &'static str {
        "blooming"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([("fraction".to_string(), self.fraction)])
    }
    fn illumination(&self, flux: &mut Array2<f32>, t_on_s: f64, full_well: &Array2<f32>) {
        let (ny, nx) = flux.dim();
        let src = flux.clone();
        for y in 0..ny {
            for x in 0..nx {
                let sat = f64::from(full_well[[y, x]]) / t_on_s;
                let ex = f64::from(src[[y, x]]) - sat;
                if ex <= 0.0 {
                    continue;
                }
                let moved = self.fraction * ex;
                flux[[y, x]] -= moved as f32;
                let share = (moved / 4.0) as f32;
                crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| {
                    flux[[y, x]] += share;
                });
            }
        }
    }
}
