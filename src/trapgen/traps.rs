//! Trap charge of one pixel on a private quadrature grid of emission rates.
//!
//! A population's density of emission rates is a continuous function of `ln k`; this
//! module samples it at [`RATES_PER_DECADE`] nodes per decade of emission time from
//! [`TAU_MIN_S`] to [`TAU_MAX_S`] (midpoint rule in `ln k`), so a population is a vector
//! of node weights that sum to one. The grid is an integration device of this generator
//! only: it is finer than, and unrelated to, any model's set of time constants.
//!
//! Per node `j` with emission rate `k_j`, a pixel holds trapped charge `q_j` (electrons).
//! Over an interval `dt` with a target occupancy `T_j` (the sites the collected charge
//! exposes) and a capture rate `c_j` (1/s):
//! - if `T_j > q_j`, capture and emission act together, exactly:
//!   `q_j <- q_eq + (q_j - q_eq) exp(-(c_j + k_j) dt)`, `q_eq = c_j T_j / (c_j + k_j)`;
//! - otherwise the node only emits: `q_j <- q_j exp(-k_j dt)`.
//!
//! Charge emitted by node `j` between `t0` and `t1` after it stopped filling is
//! `q_j (exp(-k_j t0) - exp(-k_j t1))`; its current at `t` is `q_j k_j exp(-k_j t)`.
//! Invariants: `q_j >= 0`, finite, and never above `max(T_j, q_j before)`.

/// Shortest emission time of the grid, s.
pub const TAU_MIN_S: f64 = 1.0;
/// Longest emission time of the grid, s.
pub const TAU_MAX_S: f64 = 1.0e6;
/// Grid nodes per decade of emission time.
pub const RATES_PER_DECADE: usize = 12;

/// The quadrature grid: emission rates `k_j` (1/s), from slowest to fastest.
#[derive(Debug, Clone)]
pub struct Grid {
    pub rates_per_s: Vec<f64>,
}

impl Default for Grid {
    fn default() -> Self {
        Grid::new(TAU_MIN_S, TAU_MAX_S, RATES_PER_DECADE)
    }
}

impl Grid {
    /// Midpoints of `per_decade` equal steps per decade in `ln tau` between `tau_min_s`
    /// and `tau_max_s`.
    pub fn new(tau_min_s: f64, tau_max_s: f64, per_decade: usize) -> Grid {
        let decades = (tau_max_s / tau_min_s).log10();
        let n = (decades * per_decade as f64).round().max(1.0) as usize;
        let step = decades / n as f64;
        let rates_per_s = (0..n)
            .map(|j| {
                let log_tau = tau_max_s.log10() - (j as f64 + 0.5) * step;
                10f64.powf(-log_tau)
            })
            .collect();
        Grid { rates_per_s }
    }

    pub fn len(&self) -> usize {
        self.rates_per_s.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rates_per_s.is_empty()
    }

    /// Node weights of a density per `ln k` proportional to `k^(beta - 1)` (a current
    /// falling as `t^-beta` between the grid's ends), normalised to sum to one.
    pub fn power_law(&self, beta: f64) -> Vec<f64> {
        normalise(
            self.rates_per_s
                .iter()
                .map(|k| k.powf(beta - 1.0))
                .collect(),
        )
    }

    /// Node weights of a log-normal density of emission times: centre `10^log10_tau`
    /// s, width `sigma_dex` decades, normalised to sum to one.
    pub fn log_normal(&self, log10_tau: f64, sigma_dex: f64) -> Vec<f64> {
        normalise(
            self.rates_per_s
                .iter()
                .map(|k| {
                    let z = (-k.log10() - log10_tau) / sigma_dex;
                    (-0.5 * z * z).exp()
                })
                .collect(),
        )
    }
}

fn normalise(mut w: Vec<f64>) -> Vec<f64> {
    let s: f64 = w.iter().sum();
    if s > 0.0 {
        w.iter_mut().for_each(|v| *v /= s);
    }
    w
}

/// One fill-and-emit step of a node (module docs).
#[inline]
pub fn step(q: f64, target: f64, capture_per_s: f64, rate_per_s: f64, dt_s: f64) -> f64 {
    if target > q && capture_per_s > 0.0 {
        let r = capture_per_s + rate_per_s;
        let q_eq = capture_per_s * target / r;
        q_eq + (q - q_eq) * (-r * dt_s).exp()
    } else {
        q * (-rate_per_s * dt_s).exp()
    }
}

/// Current (e-/s) of trapped charge `q` on `rates` at `t` s after filling stopped.
pub fn current_at(q: &[f64], rates: &[f64], t_s: f64) -> f64 {
    q.iter()
        .zip(rates)
        .map(|(q, k)| q * k * (-k * t_s).exp())
        .sum()
}

/// Charge (e-) emitted by `q` on `rates` between `t0` and `t1` s after filling stopped.
pub fn released_between(q: &[f64], rates: &[f64], t0_s: f64, t1_s: f64) -> f64 {
    q.iter()
        .zip(rates)
        .map(|(q, k)| q * ((-k * t0_s).exp() - (-k * t1_s).exp()))
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Uniform density in ln k over [k1, k2] (beta = 1) holding N electrons: the exact
    /// current is N / (ln(k2/k1) t) (exp(-k1 t) - exp(-k2 t)) (integral of k e^{-kt}
    /// dk / k over the range).
    #[test]
    fn power_law_one_gives_the_analytic_current() {
        let g = Grid::default();
        let n = 1.0e5;
        let q: Vec<f64> = g.power_law(1.0).iter().map(|w| w * n).collect();
        let (k1, k2) = (1.0 / TAU_MAX_S, 1.0 / TAU_MIN_S);
        for t in [10.0, 300.0, 3000.0, 3.0e4] {
            let exact = n / ((k2 / k1).ln() * t) * ((-k1 * t).exp() - (-k2 * t).exp());
            let got = current_at(&q, &g.rates_per_s, t);
            assert!(
                (got / exact - 1.0).abs() < 0.02,
                "t = {t}: {got} vs analytic {exact}"
            );
        }
    }

    #[test]
    fn capture_approaches_its_equilibrium() {
        // no emission: q -> T (1 - exp(-c t))
        let q = step(0.0, 100.0, 0.01, 0.0, 120.0);
        assert!((q - 100.0 * (1.0 - (-1.2f64).exp())).abs() < 1e-9);
        // emission only when the target is below
        let q = step(50.0, 10.0, 0.5, 0.01, 100.0);
        assert!((q - 50.0 * (-1.0f64).exp()).abs() < 1e-9);
    }
}
