//! `A_k`: the amplitude added by one exposure, a piecewise-linear function of the
//! extrapolated fluence (paper Eq. A_n and Fig. modelAparams).
//!
//! Linear from (0, 0) to the first knot, linear between knots, and the last knot's
//! value beyond the last knot. Fluence <= 0 gives 0. The caller never passes NaN:
//! what non-finite and negative currents do is decided in [`crate::model::step`].

use serde::{Deserialize, Serialize};

/// One knot of the piecewise-linear response `A_k(fluence)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Knot {
    /// Extrapolated fluence, electrons.
    pub fluence_e: f64,
    /// Amplitude `A_k`, electrons.
    pub amplitude_e: f64,
}

/// The knot table, prepared for fast evaluation.
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    /// Fluence of each knot, with a leading 0.
    x: Vec<f64>,
    /// Amplitude at each knot, with a leading 0.
    y: Vec<f64>,
    /// Slope of each segment `[x_i, x_{i+1}]`.
    slope: Vec<f64>,
    max_e: f64,
}

impl Response {
    /// `knots` must be validated (fluences strictly increasing from 0, amplitudes finite).
    pub fn new(knots: &[Knot]) -> Self {
        let mut x = vec![0.0];
        let mut y = vec![0.0];
        for k in knots {
            x.push(k.fluence_e);
            y.push(k.amplitude_e);
        }
        let slope = x
            .windows(2)
            .zip(y.windows(2))
            .map(|(xs, ys)| (ys[1] - ys[0]) / (xs[1] - xs[0]))
            .collect();
        let max_e = y.iter().copied().fold(0.0, f64::max);
        Response { x, y, slope, max_e }
    }

    /// `A_k` in electrons for an extrapolated fluence in electrons.
    #[inline(always)]
    pub fn amplitude_e(&self, fluence_e: f64) -> f64 {
        if fluence_e <= 0.0 {
            return 0.0;
        }
        let last = self.x.len() - 1;
        if fluence_e >= self.x[last] {
            return self.y[last];
        }
        // Few knots: a linear scan beats a binary search and is branch-predictable.
        let mut i = 0;
        while fluence_e >= self.x[i + 1] {
            i += 1;
        }
        self.y[i] + self.slope[i] * (fluence_e - self.x[i])
    }

    /// The first segment `(x_1, y_0, slope_0, x_0)`: for `0 < fluence < x_1`,
    /// [`Response::amplitude_e`] is `y_0 + slope_0 * (fluence - x_0)`.
    pub fn first_segment(&self) -> (f64, f64, f64, f64) {
        (self.x[1], self.y[0], self.slope[0], self.x[0])
    }

    /// The segments of the table below `fluence_e`, each `(from_e, to_e, slope)`, the
    /// last one cut at `fluence_e`: `amplitude_e(F)` is the sum of `slope * (to - from)`
    /// over `segments_below(F)`. Nothing for `fluence_e <= 0` or NaN; beyond the last knot
    /// the table is flat and adds nothing.
    pub fn segments_below(
        &self,
        fluence_e: f64,
    ) -> impl DoubleEndedIterator<Item = (f64, f64, f64)> + '_ {
        // segments starting below the fluence (none for NaN)
        let m = self.x[..self.x.len() - 1].partition_point(|&x0| x0 < fluence_e);
        (0..m).map(move |i| (self.x[i], self.x[i + 1].min(fluence_e), self.slope[i]))
    }

    /// The largest knot fluence at or below `fluence_e` (0 if there is none).
    pub fn last_knot_at_or_below(&self, fluence_e: f64) -> f64 {
        let m = self.x.partition_point(|&x| x <= fluence_e);
        if m == 0 {
            0.0
        } else {
            self.x[m - 1]
        }
    }

    /// The largest amplitude of the table: used when the fluence is unknown.
    pub fn max_e(&self) -> f64 {
        self.max_e
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::params::ModelParams;

    fn table1() -> Response {
        Response::new(&ModelParams::default().amplitude_knots)
    }

    #[test]
    fn segments_below_sum_to_the_amplitude() {
        let r = table1();
        for f in [1.0, 5e3, 101_000.0, 3e5, 4e6, 1e8] {
            let sum: f64 = r.segments_below(f).map(|(a, b, s)| s * (b - a)).sum();
            assert!((sum - r.amplitude_e(f)).abs() < 1e-9 * r.max_e(), "{f}");
        }
        assert_eq!(r.segments_below(0.0).count(), 0);
        assert_eq!(r.segments_below(f64::NAN).count(), 0);
    }

    #[test]
    fn knots_are_hit_exactly() {
        // Table 1, column A_bin.
        let r = table1();
        assert_eq!(r.amplitude_e(101_000.0), 54.1);
        assert_eq!(r.amplitude_e(401_000.0), 711.1);
        assert_eq!(r.amplitude_e(3_833_000.0), 878.0);
    }

    #[test]
    fn linear_from_origin_between_and_flat_beyond() {
        let r = table1();
        assert_eq!(r.amplitude_e(0.0), 0.0);
        assert_eq!(r.amplitude_e(-5.0), 0.0);
        // Half way to the first knot: 54.1 / 2.
        assert!((r.amplitude_e(50_500.0) - 27.05).abs() < 1e-12);
        // Half way between 201k (144.2) and 401k (711.1): 427.65.
        assert!((r.amplitude_e(301_000.0) - 427.65).abs() < 1e-9);
        // Decreasing segment 401k (711.1) -> 1.54M (676.9) is allowed.
        assert!(r.amplitude_e(1_000_000.0) < 711.1);
        assert_eq!(r.amplitude_e(1e9), 878.0);
        assert_eq!(r.max_e(), 878.0);
    }
}
