//! The on-board readout this generator imitates: sample-up-the-ramp and a line fit.
//!
//! The array is read non-destructively every [`FRAME_S`] seconds after the reset; the
//! sample `i` (1-based) is taken at `t_i = i * FRAME_S`. The reported current is the
//! least-squares slope (with intercept) of the samples below half of the pixel's full
//! well; a pixel whose charge reached full well is flagged `OVERFLOW`. With fewer than
//! two samples below half well the slope is the first sample over its time (through the
//! reset), and with none, the first sample (at full well) over its time: a lower bound.
//!
//! For an illuminated integration the fit uses only the samples taken while the shutter
//! was open (the laboratory's "extrapolated fluence" is that slope times the lit time).
//!
//! Dark integrations without a stored ramp use the fit's linearity: the slope of the
//! noise-free ramp `d t + sum_j q_j (1 - exp(-k_j t))` is `d + sum_j q_j G_j` with
//! `G_j = sum_i w_i (1 - exp(-k_j t_i))` (the [`LineFit`] gains, `w_i` the slope
//! weights), and its noise is drawn with the fit's exact variance
//! `sigma_read^2 sum_i w_i^2 + I sum_i sum_l w_i w_l min(t_i, t_l)` (Poisson arrivals
//! at the mean current `I`, white read noise). Darks that keep their ramp are sampled
//! and fitted explicitly.

/// Time between non-destructive reads, s.
pub const FRAME_S: f64 = 1.5;

/// Sample times of an integration of `t_exposure_s`, s after the reset.
pub fn sample_times(t_exposure_s: f64) -> Vec<f64> {
    let n = (t_exposure_s / FRAME_S + 1e-9).floor().max(2.0) as usize;
    (1..=n).map(|i| i as f64 * FRAME_S).collect()
}

/// Least-squares slope of `values` against `times` (with intercept); `None` for fewer
/// than two points.
pub fn fit_slope(times: &[f64], values: &[f64]) -> Option<f64> {
    let n = times.len().min(values.len());
    if n < 2 {
        return None;
    }
    let tm = times[..n].iter().sum::<f64>() / n as f64;
    let vm = values[..n].iter().sum::<f64>() / n as f64;
    let (mut sxy, mut sxx) = (0.0, 0.0);
    for i in 0..n {
        let dt = times[i] - tm;
        sxy += dt * (values[i] - vm);
        sxx += dt * dt;
    }
    (sxx > 0.0).then(|| sxy / sxx)
}

/// The line fit of a whole dark integration as linear functionals (module docs).
#[derive(Debug, Clone)]
pub struct LineFit {
    pub times_s: Vec<f64>,
    /// Slope weights `w_i`.
    pub weights: Vec<f64>,
    /// `sum_i w_i^2` (read-noise variance per unit read variance).
    pub read_var: f64,
    /// `sum_i sum_l w_i w_l min(t_i, t_l)` (shot-noise variance per unit current).
    pub shot_var: f64,
}

impl LineFit {
    pub fn new(t_exposure_s: f64) -> LineFit {
        let times_s = sample_times(t_exposure_s);
        let n = times_s.len() as f64;
        let tm = times_s.iter().sum::<f64>() / n;
        let sxx: f64 = times_s.iter().map(|t| (t - tm) * (t - tm)).sum();
        let weights: Vec<f64> = times_s.iter().map(|t| (t - tm) / sxx).collect();
        let read_var = weights.iter().map(|w| w * w).sum();
        // sum_i sum_l w_i w_l min(t_i, t_l) = sum_m (t_m - t_{m-1}) (sum_{i >= m} w_i)^2
        let mut shot_var = 0.0;
        let mut tail: f64 = weights.iter().sum();
        let mut prev_t = 0.0;
        for (t, w) in times_s.iter().zip(&weights) {
            shot_var += (t - prev_t) * tail * tail;
            tail -= w;
            prev_t = *t;
        }
        LineFit {
            times_s,
            weights,
            read_var,
            shot_var,
        }
    }

    /// `G_j` for each rate: the fitted slope per electron trapped on that rate at the
    /// reset.
    pub fn gains(&self, rates_per_s: &[f64]) -> Vec<f64> {
        rates_per_s
            .iter()
            .map(|k| {
                self.times_s
                    .iter()
                    .zip(&self.weights)
                    .map(|(t, w)| w * (1.0 - (-k * t).exp()))
                    .sum()
            })
            .collect()
    }

    /// Standard deviation of the fitted slope for read noise `read_e` per sample and a
    /// mean current `current_e_per_s`.
    pub fn slope_sd(&self, read_e: f64, current_e_per_s: f64) -> f64 {
        (read_e * read_e * self.read_var + current_e_per_s.max(0.0) * self.shot_var).sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_fit_of_a_line_is_its_slope_and_gains_match_an_explicit_fit() {
        let f = LineFit::new(180.0);
        let v: Vec<f64> = f.times_s.iter().map(|t| 3.0 + 0.25 * t).collect();
        assert!((fit_slope(&f.times_s, &v).unwrap() - 0.25).abs() < 1e-12);
        let k = 1.0 / 50.0;
        let ramp: Vec<f64> = f
            .times_s
            .iter()
            .map(|t| 1000.0 * (1.0 - (-k * t).exp()))
            .collect();
        let explicit = fit_slope(&f.times_s, &ramp).unwrap();
        assert!((f.gains(&[k])[0] * 1000.0 - explicit).abs() < 1e-9);
        // the shot-noise variance of a fit over n evenly spaced samples ~ 6/5 / T
        let t_total = f.times_s.last().unwrap();
        assert!((f.shot_var * t_total / 1.2 - 1.0).abs() < 0.05);
    }
}
