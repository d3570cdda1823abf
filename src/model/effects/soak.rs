//! `soak`: slow capture, so slow terms fill only partly during a short illumination.
//!
//! Physics: traps capture with finite time constants; the charge trapped depends on how
//! long the pixel is held charged, not only on the fluence (Long et al. 2015; Tulloch
//! 2019). A trap population emitting with `tau_n` and capturing with
//! `tau_c = capture_ratio * tau_n` fills to `1 - exp(-t_ill / tau_c)` in `t_ill`.
//! Equation (response hook): `A_k,n *= 1 - exp(-t_illuminated * rate_n / capture_ratio)`
//! (1 when `capture_ratio` = 0).
//! Parameter: `capture_ratio` (default 0.1, bounds [0, 100], null 0).
//! Covariate: illumination (soak) time, and time since illumination (the slow tail).

use super::get;
use crate::model::effect::{Effect, EffectDef, ParamSpec, ResponseCtx};
use ndarray::Array3;

pub const DEF: EffectDef = EffectDef {
    name: "soak",
    summary: "slow terms fill as 1 - exp(-t_ill / (ratio tau_n))",
    params: &[ParamSpec {
        name: "capture_ratio",
        default: 0.1,
        lo: 0.0,
        hi: 100.0,
        null: Some(0.0),
        fitted: true,
        doc: "capture time constant / emission time constant",
    }],
    build: |p| {
        Box::new(Soak {
            capture_ratio: get(p, "capture_ratio"),
        })
    },
    covariate: "illumination_time",
};

#[derive(Debug, Clone)]
pub struct Soak {
    pub capture_ratio: f64,
}

impl Soak {
    /// Fill fraction of term `rate_per_s` after `t_ill_s` of illumination.
    pub fn fill(&self, rate_per_s: f64, t_ill_s: f64) -> f64 {
        if self.capture_ratio <= 0.0 {
            1.0
        } else {
            -(-t_ill_s * rate_per_s / self.capture_ratio).exp_m1()
        }
    }
}

impl Effect for Soak {
    fn name(&self) -> &'static str {
        DEF.name
    }
    fn response_is_per_pixel(&self) -> bool {
        true
    }
    fn response(&self, ctx: &ResponseCtx<'_>, ak: &mut Array3<f64>) {
        if self.capture_ratio <= 0.0 {
            return;
        }
        let f: Vec<f64> = ctx
            .rate_per_s
            .iter()
            .map(|r| self.fill(*r, ctx.t_illuminated_s))
            .collect();
        for mut lane in ak.lanes_mut(ndarray::Axis(2)) {
            for (a, fi) in lane.iter_mut().zip(&f) {
                *a *= fi;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn slow_terms_fill_partly() {
        // ratio 1, t_ill 100 s: tau 10 s -> 1 - e^-10; tau 1000 s -> 1 - e^-0.1 = 0.09516
        let f = Array2::<f64>::from_elem((1, 1), 1e5);
        let rates = [0.1, 0.001];
        let mut ak = Array3::from_elem((1, 1, 2), 100.0);
        Soak { capture_ratio: 1.0 }.response(
            &ResponseCtx {
                fluence_e: &f,
                t_illuminated_s: 100.0,
                t_exposure_s: 200.0,
                rate_per_s: &rates,
            },
            &mut ak,
        );
        assert!((ak[[0, 0, 0]] - 100.0 * (1.0 - (-10.0f64).exp())).abs() < 1e-9);
        assert!((ak[[0, 0, 1]] - 9.516_258_196).abs() < 1e-6);
    }
}
