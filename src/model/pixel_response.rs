//! Each pixel's own response: a per-pixel factor on the knot table's `A_k`, from a
//! per-pixel map ([`crate::pixmap`] measures it, loads it and hands it over as an array;
//! this module knows no files).
//!
//! The paper flags every pixel with one response, the 95th percentile of its fluence
//! bin amplified by 1.2, because it could not tell the pixels' trap populations apart
//! (its Fig. 3b: three peaks in one bin). With a map the response of pixel `p` to an
//! exposure of extrapolated fluence `F` is `A_k(F) s_p(F)`, where `s_p` is the map's
//! factor in the fluence range of `F`:
//! - `F <= linear_below_e` (below full well: the depletion-region traps): `scale[0]`;
//! - `F >= saturated_above_e` (forward-biased, above full well: the traps that make the
//!   populations), and pixels whose ramp saturated with no slope (`SUR_ERROR`, not a
//!   transient): `scale[1]`;
//! - in between, linear in `F` from one to the other.
//!
//! Pixels of unknown fluence (transients, non-finite currents, ramps saturated with no
//! slope) take the pixel's own maximum: the knot table's maximum times `scale[1]` (the
//! effect step applies it, [`crate::model::effect_step`]); non-functional pixels add
//! nothing. The factor is applied in the response hook ([`Effect::response`]), so the
//! decay, the flags and early release are the model's own.
//!
//! Invariants: `scale` has shape `[2, ny, nx]`, every factor finite and `>= 0`;
//! `0 < linear_below_e <= saturated_above_e`, finite. A model with a map steps only an
//! array of the map's shape ([`crate::model::Model::step_with`] refuses another).

use super::effect::{Effect, ResponseCtx};
use ndarray::{Array3, Axis};
use std::sync::Arc;

/// A per-pixel response map as the model uses it (module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct PixelResponse {
    /// Fluence (e-) at and below which `scale[0]` applies.
    pub linear_below_e: f64,
    /// Fluence (e-) at and above which `scale[1]` applies.
    pub saturated_above_e: f64,
    /// Factor on `A_k`, `[2, ny, nx]`: range 0 (linear), range 1 (saturated).
    pub scale: Array3<f32>,
}

impl PixelResponse {
    /// Check the invariants (module docs); the error names the field.
    pub fn new(
        linear_below_e: f64,
        saturated_above_e: f64,
        scale: Array3<f32>,
    ) -> Result<PixelResponse, String> {
        if !(linear_below_e.is_finite()
            && linear_below_e > 0.0
            && saturated_above_e.is_finite()
            && saturated_above_e >= linear_below_e)
        {
            return Err(format!(
                "linear_below_e, saturated_above_e: need 0 < {linear_below_e} <= {saturated_above_e}, finite"
            ));
        }
        if scale.shape()[0] != 2 {
            return Err(format!(
                "scale: {} fluence ranges, need 2",
                scale.shape()[0]
            ));
        }
        if let Some(bad) = scale.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(format!("scale: holds {bad}, must be finite and >= 0"));
        }
        Ok(PixelResponse {
            linear_below_e,
            saturated_above_e,
            scale,
        })
    }

    /// `(ny, nx)`.
    pub fn dim(&self) -> (usize, usize) {
        (self.scale.shape()[1], self.scale.shape()[2])
    }

    /// The factor of pixel `(y, x)` at fluence `fluence_e` (module docs); `no_slope`:
    /// the ramp saturated before the fit had its reads (the saturated range).
    #[inline]
    pub fn factor(&self, y: usize, x: usize, fluence_e: f64, no_slope: bool) -> f64 {
        let lo = f64::from(self.scale[[0, y, x]]);
        let hi = f64::from(self.scale[[1, y, x]]);
        if no_slope || fluence_e >= self.saturated_above_e {
            hi
        } else if fluence_e <= self.linear_below_e || fluence_e.is_nan() {
            lo
        } else {
            let w =
                (fluence_e - self.linear_below_e) / (self.saturated_above_e - self.linear_below_e);
            lo + w * (hi - lo)
        }
    }
}

/// The map as a model effect (not in the registry: it is built from an array, not from
/// the model file's numbers; [`crate::model::Model::for_detector`] adds it).
#[derive(Debug, Clone)]
pub struct PixelScale(pub Arc<PixelResponse>);

impl Effect for PixelScale {
    fn name(&self) -> &'static str {
        "pixel_map"
    }
    /// Each pixel's own planes, by its own factor.
    fn response_reach_px(&self) -> Option<usize> {
        Some(0)
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        let (ny, nx, _) = ak.dim();
        if self.0.dim() != (ny, nx) {
            // refused before the step (Model::step_with); never scale another array
            return;
        }
        for ((y, x), mut lane) in ak
            .lanes_mut(Axis(2))
            .into_iter()
            .enumerate()
            .map(|(i, l)| ((i / nx, i % nx), l))
        {
            if !ctx.is_needed(y, x) {
                continue;
            }
            let f = ctx.fluence_e[[y, x]];
            let no_slope = ctx.no_slope[[y, x]];
            if f.is_nan() && !no_slope {
                continue; // unknown fluence: the step keeps the maximum
            }
            let s = self.0.factor(y, x, f, no_slope);
            lane.iter_mut().for_each(|a| *a *= s);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn factor_by_range_and_interpolated_between() {
        let mut s = Array3::<f32>::zeros((2, 1, 2));
        s[[0, 0, 0]] = 0.5;
        s[[1, 0, 0]] = 0.1;
        s[[0, 0, 1]] = 1.0;
        s[[1, 0, 1]] = 2.0;
        let r = PixelResponse::new(1e5, 3e5, s).unwrap();
        assert_eq!(r.factor(0, 0, 5e4, false), 0.5);
        assert_eq!(r.factor(0, 0, 4e5, false), f64::from(0.1f32));
        assert!((r.factor(0, 1, 2e5, false) - 1.5).abs() < 1e-12);
        assert_eq!(r.factor(0, 1, f64::NAN, true), 2.0);
        let bad = Array3::<f32>::from_elem((2, 1, 1), f32::NAN);
        assert!(PixelResponse::new(1e5, 3e5, bad).is_err());
        assert!(PixelResponse::new(3e5, 1e5, Array3::zeros((2, 1, 1))).is_err());
    }
}
