//! Detector: dark current, noise, full well, sampling and the on-board line fit.
//!
//! Numbers and sources:
//! - dark current 0.01 e-/s (paper section 1: the secondary threshold "on the order of
//!   magnitude of the dark current");
//! - full well 200,000 e- (paper section 2.1, "saturation level of approximately
//!   200,000 e-"), 1.5 % pixel-to-pixel scatter (assumed);
//! - read noise 10 e- per sample (typical H2RG single read, Rauscher et al. 2007;
//!   assumed), shot noise Poisson in the accumulated charge;
//! - samples every 1.5 s after the reset (SPHEREx frame time, Crill et al. 2020);
//! - on-board fit: least squares over the samples below half of full well; fewer than
//!   three such samples give no slope (paper section 2.1), flagged `SUR_ERROR`, and
//!   `OVERFLOW` when the pixel saturated;
//! - cosmic rays: 5 /cm^2/s in orbit (typical of low Earth orbit outside the SAA),
//!   0.02 /cm^2/s in the laboratory (sea-level muons), 18 um pixels; a hit adds a jump
//!   of 300 to 20,000 e- (log-uniform) at a random sample; the on-board jump detection
//!   sets `TRANSIENT` and fits around the jump, so the slope is unbiased;
//! - non-functional pixels: 0.2 % (assumed), `NONFUNC`, no value.
//!
//! Slope noise in closed form: with LS weights `w_i` over `m` samples at `t_i`,
//! `var = sigma_r^2 sum w_i^2 + f sum_ik w_i w_k min(t_i, t_k)` for read noise
//! `sigma_r` and total current `f` (the Poisson charge is cumulative, so samples are
//! correlated).

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DetectorParams {
    pub dark_e_per_s: f64,
    pub full_well_e: f64,
    pub full_well_scatter: f64,
    pub read_noise_e: f64,
    pub frame_time_s: f64,
    pub cosmic_rate_per_cm2_s: f64,
    pub pixel_pitch_um: f64,
    pub nonfunc_fraction: f64,
    /// Draw noise and cosmic rays (tests switch it off to compare paths exactly).
    pub noise: bool,
}

impl Default for DetectorParams {
    fn default() -> Self {
        DetectorParams {
            dark_e_per_s: 0.01,
            full_well_e: 200_000.0,
            full_well_scatter: 0.015,
            read_noise_e: 10.0,
            frame_time_s: 1.5,
            cosmic_rate_per_cm2_s: 5.0,
            pixel_pitch_um: 18.0,
            nonfunc_fraction: 0.002,
            noise: true,
        }
    }
}

impl DetectorParams {
    /// Probability that a pixel is hit in `t` seconds.
    pub fn cosmic_probability(&self, t: f64) -> f64 {
        let area_cm2 = (self.pixel_pitch_um * 1e-4).powi(2);
        1.0 - (-self.cosmic_rate_per_cm2_s * area_cm2 * t).exp()
    }
}

/// Least-squares weights of the slope over samples `t[..m]`.
pub fn ls_weights(t: &[f64]) -> Vec<f64> {
    let m = t.len() as f64;
    let mean = t.iter().sum::<f64>() / m;
    let sxx: f64 = t.iter().map(|v| (v - mean).powi(2)).sum();
    t.iter().map(|v| (v - mean) / sxx).collect()
}

/// LS slope of samples `y` at times `t`.
pub fn ls_slope(t: &[f64], y: &[f64]) -> f64 {
    ls_weights(t).iter().zip(y).map(|(w, v)| w * v).sum()
}

/// Per-exposure tables of the on-board fit for `m` = 0..=n samples.
#[derive(Debug, Clone)]
pub struct FitTables {
    pub times: Vec<f64>,
    /// `sum w_i^2` (read-noise variance per e-^2).
    pub v_read: Vec<f64>,
    /// `sum w_i w_k min(t_i,t_k)` (shot-noise variance per e-/s).
    pub v_shot: Vec<f64>,
}

impl FitTables {
    pub fn new(t_exposure_s: f64, frame_time_s: f64) -> FitTables {
        let n = ((t_exposure_s / frame_time_s) + 1e-9).floor() as usize;
        let times: Vec<f64> = (0..n).map(|i| (i + 1) as f64 * frame_time_s).collect();
        let mut v_read = vec![f64::NAN; n + 1];
        let mut v_shot = vec![f64::NAN; n + 1];
        for m in 3..=n {
            let t = &times[..m];
            let w = ls_weights(t);
            v_read[m] = w.iter().map(|v| v * v).sum();
            // sum_i w_i [ sum_{k<=i} w_k t_k + t_i sum_{k>i} w_k ]
            let mut pre = 0.0;
            let total: f64 = w.iter().sum();
            let mut cum_w = 0.0;
            let mut acc = 0.0;
            for i in 0..m {
                pre += w[i] * t[i];
                cum_w += w[i];
                acc += w[i] * (pre + t[i] * (total - cum_w));
            }
            v_shot[m] = acc;
        }
        FitTables {
            times,
            v_read,
            v_shot,
        }
    }

    pub fn n_samples(&self) -> usize {
        self.times.len()
    }

    /// Number of samples the fit uses: taken while illuminated (`t_i <= t_on`) and with
    /// linear charge `rate * t_i` below half of full well.
    pub fn samples_used(&self, rate: f64, t_on: f64, fw: f64) -> usize {
        let n_on = self.times.iter().take_while(|&&t| t <= t_on + 1e-9).count();
        if rate <= 0.0 {
            return n_on;
        }
        let dt = self.times[0];
        // samples i with (i+1) dt rate < fw/2
        let lim = (0.5 * fw / (rate * dt)).ceil() as i64 - 1;
        (lim.max(0) as usize).min(n_on)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ls_slope_of_line_is_exact() {
        let t = [1.5, 3.0, 4.5, 6.0];
        let y: Vec<f64> = t.iter().map(|v| 7.0 + 2.5 * v).collect();
        assert!((ls_slope(&t, &y) - 2.5).abs() < 1e-12);
    }

    #[test]
    fn read_noise_variance_closed_form() {
        // 12 / (dt^2 m (m^2 - 1)) for equally spaced samples
        let f = FitTables::new(180.0, 1.5);
        let m = 120usize;
        let want = 12.0 / (1.5f64.powi(2) * m as f64 * ((m * m - 1) as f64));
        assert!((f.v_read[m] / want - 1.0).abs() < 1e-9);
        // shot: 6 (m^2+1) / (5 m (m^2-1) dt) for cumulative Poisson (Rauscher 2007)
        let want_s = 6.0 * ((m * m + 1) as f64) / (5.0 * m as f64 * ((m * m - 1) as f64) * 1.5);
        assert!(
            (f.v_shot[m] / want_s - 1.0).abs() < 1e-6,
            "{} {}",
            f.v_shot[m],
            want_s
        );
    }

    #[test]
    fn samples_below_half_well() {
        let f = FitTables::new(613.0, 1.5);
        assert_eq!(f.samples_used(0.0, 481.0, 2e5), 320);
        // 100k/ (1e4 * 1.5) = 6.67 -> samples 1..6
        assert_eq!(f.samples_used(1e4, 481.0, 2e5), 6);
        assert_eq!(f.samples_used(1e6, 481.0, 2e5), 0);
    }
}
