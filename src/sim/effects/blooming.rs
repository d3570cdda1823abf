//! `blooming`: excess charge of a saturated pixel spills into its neighbours.
//!
//! Physics: once a diode is saturated and forward biased, part of the further
//! photocurrent diffuses laterally towards the four nearest neighbours (blooming; the
//! paper, section 2.2, suggests it as a contributor to the persistence rise at
//! saturation, citing its reference "2021Blooming"). Two channels:
//! - **collected** (`fraction`): the neighbours' diodes collect it. It is in their ramps,
//!   so their measured fluence already holds it and a persistence model driven by
//!   measured fluence has nothing to miss; it is the image artefact.
//! - **uncollected** (`trapped_fraction`): charge the
//!   forward-biased source injects into its neighbours' junction region, where it raises
//!   their trap fill level as their own charge would, but which never reaches their
//!   integrating node: it is in no ramp, and the reset that ends the integration clears
//!   it. The neighbours' traps then hold more charge than their measured fluence says:
//!   the persistence signature the model's `blooming` effect describes (a neighbour's
//!   excess fluence moves a pixel along its own response). This channel is an
//!   assumption, chosen so that the paper's suspicion can be tested; nothing measured
//!   supports its form or its size (the paper only says blooming "may be a contributing
//!   factor"). A collected spill alone cannot be found by any model driven by measured
//!   fluence.
//!
//! Equation: for each pixel with flux `phi > phi_sat = Q_fw / t_on`,
//! - a fraction `fraction` of the excess flux `phi - phi_sat` is removed and shared
//!   equally by its four neighbours (`phi_nb += fraction (phi - phi_sat) / 4`), before
//!   integration;
//! - each neighbour's trap fill level sees `trapped_fraction (phi - phi_sat) t_on / 4`
//!   electrons more, arriving evenly over the illuminated time and held until the
//!   integration ends (`Effect::illumination`'s `uncollected_e`; the source's own excess
//!   is not reduced for it, and a fill level cannot exceed full well, so a neighbour
//!   that saturates on its own gains little).
//!
//! Parameters: `fraction` (default 0.05, bounds [0, 0.5]) and `trapped_fraction`
//! (default 0.2, bounds [0, 1]); both assumed, no measurement. With
//! `trapped_fraction=0` only the collected spill remains.
//! Visible as: neighbours of saturated pixels collect more charge (`fraction`), and
//! neighbours of sharp saturated sources show more persistence than their own fluence
//! gives (`trapped_fraction`); both grow with the source's excess.

use crate::sim::effect::{Effect, ParamReader};
use ndarray::Array2;
use std::collections::BTreeMap;

#[derive(Debug, Clone)]
pub struct Blooming {
    pub fraction: f64,
    pub trapped_fraction: f64,
}

impl Blooming {
    pub fn from_params(p: &BTreeMap<String, f64>) -> crate::Result<Self> {
        let mut r = ParamReader::new("blooming", p);
        let fraction = r.get("fraction", 0.05, 0.0, 0.5)?;
        let trapped_fraction = r.get("trapped_fraction", 0.2, 0.0, 1.0)?;
        r.finish()?;
        Ok(Blooming {
            fraction,
            trapped_fraction,
        })
    }
}

impl Effect for Blooming {
    fn name(&self) -> &'static str {
        "blooming"
    }
    fn params(&self) -> BTreeMap<String, f64> {
        BTreeMap::from([
            ("fraction".to_string(), self.fraction),
            ("trapped_fraction".to_string(), self.trapped_fraction),
        ])
    }
    fn illumination(
        &self,
        flux: &mut Array2<f32>,
        uncollected_e: &mut Array2<f32>,
        t_on_s: f64,
        full_well: &Array2<f32>,
    ) {
        let (ny, nx) = flux.dim();
        let src = flux.clone();
        for y in 0..ny {
            for x in 0..nx {
                let sat = f64::from(full_well[[y, x]]) / t_on_s;
                let ex = f64::from(src[[y, x]]) - sat;
                if ex <= 0.0 {
                    continue;
                }
                if self.fraction > 0.0 {
                    let moved = self.fraction * ex;
                    flux[[y, x]] -= moved as f32;
                    let share = (moved / 4.0) as f32;
                    crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| {
                        flux[[y, x]] += share;
                    });
                }
                if self.trapped_fraction > 0.0 {
                    let share = (self.trapped_fraction * ex * t_on_s / 4.0) as f32;
                    crate::model::grid::for_each_neighbour(ny, nx, y, x, |y, x| {
                        uncollected_e[[y, x]] += share;
                    });
                }
            }
        }
    }
}
