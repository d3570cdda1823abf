//! The extrapolated fluence of a pixel in one exposure: the one place that says what
//! charge an exposure puts into a pixel's traps.
//!
//! The paper (section 2.2) bins pixels by their *extrapolated fluence*: the measured
//! current times the illumination time, "assumed equivalent to the accumulated charge
//! for pixels far from saturation and extrapolated for saturated pixels". So:
//!
//! - `fluence_e = max(current_e_per_s, 0) * t_illuminated_s` ([`extrapolated_fluence_e`];
//!   the ICD's "Timing": `t_illuminated` is `t_illuminated_s` when the product has it,
//!   `t_exposure_s` otherwise). A negative current is noise about zero: zero fluence;
//! - a `NONFUNC` pixel has no fluence (a dead pixel collects no charge);
//! - a `TRANSIENT` or `SUR_ERROR` pixel, or one whose current is NaN or infinite, has an
//!   *unknown* fluence: the model responds with the maximum amplitude of its knot table
//!   (a `TRANSIENT` pixel without `SUR_ERROR`: the model's transient rule, the maximum
//!   unless measured in flight) and flags the pixel in the next exposure (paper
//!   section 3, conservative, as for transients).
//!
//! Invariant: a [`PixelFluence::Known`] fluence is finite and non-negative whenever
//! `t_illuminated_s` is (the model checks that it is, in `(0, t_exposure_s]`), so NaN
//! and Inf never reach the state through it.

use crate::flags::{bits, pbits};
use ndarray::{Array2, ArrayView2, Zip};

/// The on-board flag values the model acts on, and the persistence flag bits it writes
/// (the ICD's by default; [`crate::model::Model::with_flag_bits`] sets others).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FlagBits {
    pub transient: u32,
    pub sur_error: u32,
    pub nonfunc: u32,
    pub persist: u32,
    /// The bits of the persistence flag plane the step writes (`/persistence/flags`):
    /// current above the high and the low threshold, maximum amplitude used, released
    /// early, history incomplete.
    pub high: u8,
    pub low: u8,
    pub max_amplitude: u8,
    pub released: u8,
    pub history_incomplete: u8,
}

impl Default for FlagBits {
    fn default() -> Self {
        FlagBits {
            transient: bits::TRANSIENT,
            sur_error: bits::SUR_ERROR,
            nonfunc: bits::NONFUNC,
            persist: bits::PERSIST,
            high: pbits::HIGH,
            low: pbits::LOW,
            max_amplitude: pbits::MAX_AMPLITUDE,
            released: pbits::RELEASED,
            history_incomplete: pbits::HISTORY_INCOMPLETE,
        }
    }
}

/// What one exposure says about one pixel's fluence.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PixelFluence {
    /// `max(current, 0) * t_illuminated_s`, e-.
    Known(f64),
    /// Transient, fit error, or a current that is not finite.
    Unknown,
    /// A non-functional pixel: no fluence, no response.
    NonFunctional,
}

impl PixelFluence {
    /// The fluence when known, e-.
    #[inline(always)]
    pub fn known_e(self) -> Option<f64> {
        match self {
            PixelFluence::Known(f) => Some(f),
            _ => None,
        }
    }
}

/// `max(current_e_per_s, 0) * t_illuminated_s`, e- (the paper's extrapolated fluence).
/// A NaN current gives 0 here: [`pixel_fluence`] sorts those out first.
#[inline(always)]
pub fn extrapolated_fluence_e(current_e_per_s: f32, t_illuminated_s: f64) -> f64 {
    f64::from(current_e_per_s.max(0.0)) * t_illuminated_s
}

/// One pixel's fluence from its measured current and its on-board flags (module docs:
/// non-functional first, then unknown, then the extrapolated fluence).
#[inline(always)]
pub fn pixel_fluence(
    current_e_per_s: f32,
    flags: u32,
    bits: &FlagBits,
    t_illuminated_s: f64,
) -> PixelFluence {
    if flags & bits.nonfunc != 0 {
        PixelFluence::NonFunctional
    } else if flags & (bits.transient | bits.sur_error) != 0 || !current_e_per_s.is_finite() {
        PixelFluence::Unknown
    } else {
        PixelFluence::Known(extrapolated_fluence_e(current_e_per_s, t_illuminated_s))
    }
}

/// [`pixel_fluence`] over an image, e-: NaN where the fluence is not known (unknown or
/// non-functional pixels).
pub fn fluence_map_e(
    image_e_per_s: ArrayView2<'_, f32>,
    flags: ArrayView2<'_, u32>,
    bits: &FlagBits,
    t_illuminated_s: f64,
) -> Array2<f64> {
    let mut f = Array2::<f64>::from_elem(image_e_per_s.dim(), f64::NAN);
    Zip::from(&mut f)
        .and(image_e_per_s)
        .and(flags)
        .for_each(|o, &v, &fl| {
            if let PixelFluence::Known(e) = pixel_fluence(v, fl, bits, t_illuminated_s) {
                *o = e;
            }
        });
    f
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    #[test]
    fn flags_decide_before_the_current_and_negative_currents_count_as_zero() {
        let b = FlagBits::default();
        let t = 100.0;
        assert_eq!(pixel_fluence(2.5, 0, &b, t), PixelFluence::Known(250.0));
        assert_eq!(pixel_fluence(-3.0, 0, &b, t), PixelFluence::Known(0.0));
        assert_eq!(pixel_fluence(f32::NAN, 0, &b, t), PixelFluence::Unknown);
        assert_eq!(
            pixel_fluence(f32::INFINITY, 0, &b, t),
            PixelFluence::Unknown
        );
        assert_eq!(
            pixel_fluence(2.5, bits::TRANSIENT, &b, t),
            PixelFluence::Unknown
        );
        assert_eq!(
            pixel_fluence(2.5, bits::SUR_ERROR, &b, t),
            PixelFluence::Unknown
        );
        // non-functional wins over an unknown fluence
        let dead_transient = bits::NONFUNC | bits::TRANSIENT;
        assert_eq!(
            pixel_fluence(f32::NAN, dead_transient, &b, t),
            PixelFluence::NonFunctional
        );
        // bits the rule does not read change nothing
        assert_eq!(
            pixel_fluence(1.0, bits::OVERFLOW, &b, t),
            PixelFluence::Known(100.0)
        );
    }

    #[test]
    fn map_is_nan_where_the_fluence_is_not_known() {
        let img = array![[1.0f32, -1.0], [f32::NAN, 4.0]];
        let fl = array![[0u32, 0], [0, bits::NONFUNC]];
        let m = fluence_map_e(img.view(), fl.view(), &FlagBits::default(), 10.0);
        assert_eq!(m[(0, 0)], 10.0);
        assert_eq!(m[(0, 1)], 0.0);
        assert!(m[(1, 0)].is_nan() && m[(1, 1)].is_nan());
    }
}
