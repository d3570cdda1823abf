//! The flexible base that effects are tested against.
//!
//! What every detector does is not an effect: a response that is some function of the
//! fluence and a decay that is some sum of exponentials. The base is
//!
//! `b(p, k) = m(p, k) + sum_(a <= k) sum_j A_j(F_a(p)) exp(-t(a, k) / tau_j)`
//!
//! with `m` the fitted model's prediction (so the model's own effects, such as
//! `refill`, stay in the base)
//! over the illuminations `a` before exposure `k` (`F_a(p)` the pixel's extrapolated
//! fluence in `a`, `t(a, k)` the time from the end of `a` to the middle of `k`), with
//! `tau_j` a fixed grid of [`TAU_S`] and `A_j(F)` free (a correction of the model's response and decay), piecewise linear in `log10 F`
//! between knots every fifth of a decade: a free response per fluence bin and free
//! weights over a fixed grid of rates, shared by every illumination event and
//! superposed linearly. It follows a t^-0.85 ... t^-1.15 decay, any shape of the
//! response around saturation and any mix of trap populations; what it cannot make is a
//! dependence on anything but the fluence and the time since each illumination (the
//! illumination's duration, the temperature, how full the traps were, the neighbours,
//! the position). It is linear in the `A_j`, fitted once by weighted least squares
//! (weights `1 / (sigma_k^2 + (0.1 p)^2)`, `p` the model's prediction; a small ridge
//! keeps unused knots at 0) on at most [`MAX_FIT_SAMPLES`] samples taken at a fixed
//! stride (deterministic).

use super::data::{fluence, Sequence, BACKGROUND_FLUENCE_E};
use super::eval::Samples;
use ndarray::Array2;
use rayon::prelude::*;

/// The fixed grid of decay times, s.
pub const TAU_S: [f64; 9] = [10.0, 30.0, 100.0, 300.0, 1e3, 3e3, 1e4, 3e4, 1e5];
/// Response knots per decade of fluence.
const KNOTS_PER_DECADE: f64 = 5.0;
/// Knots from 10^LOG_F_MIN to 10^LOG_F_MAX e-.
const LOG_F_MIN: f64 = 3.0;
const LOG_F_MAX: f64 = 7.0;
/// Samples used in the fit at most.
pub const MAX_FIT_SAMPLES: usize = 300_000;

fn n_knots() -> usize {
    ((LOG_F_MAX - LOG_F_MIN) * KNOTS_PER_DECADE).round() as usize + 1
}

/// The (knot, weight) pairs of the response at fluence `f` (two neighbouring knots).
fn knots_of(f: f64) -> Option<[(usize, f64); 2]> {
    if !(f.is_finite() && f > BACKGROUND_FLUENCE_E) {
        return None;
    }
    let u = ((f.log10() - LOG_F_MIN) * KNOTS_PER_DECADE).clamp(0.0, (n_knots() - 1) as f64);
    let k0 = (u.floor() as usize).min(n_knots() - 2);
    let w = u - k0 as f64;
    Some([(k0, 1.0 - w), (k0 + 1, w)])
}

/// Sparse features of sample `i`: (parameter index, value).
fn features(
    seq: &Sequence,
    s: &Samples,
    maps: &[(usize, Array2<f64>)],
    i: usize,
    out: &mut Vec<(usize, f64)>,
) {
    out.clear();
    let np = s.npix();
    let (row, px) = (i / np, i % np);
    let k = s.exposures[row];
    let (y, x) = s.pixels[px];
    for (a, f) in maps.iter().filter(|(a, _)| *a < k) {
        let Some(kn) = knots_of(f[(y, x)]) else {
            continue;
        };
        let t = seq.t_mid_after_s(*a, k).max(0.0);
        for (j, tau) in TAU_S.iter().enumerate() {
            let d = (-t / tau).exp();
            if d < 1e-9 {
                continue;
            }
            for &(kk, w) in &kn {
                if w > 0.0 {
                    out.push((kk * TAU_S.len() + j, w * d));
                }
            }
        }
    }
}

/// The base's prediction of every sample: the model's prediction `pred` plus the
/// correction fitted on `s` (module docs); `pred` itself when the fit fails.
pub fn predict(seq: &Sequence, s: &Samples, pred: &[f64]) -> Vec<f64> {
    let maps: Vec<(usize, Array2<f64>)> = seq
        .illuminations
        .iter()
        .map(|&a| (a, fluence(&seq.exposures[a])))
        .collect();
    let np = s.npix().max(1);
    let p = n_knots() * TAU_S.len();
    let usable: Vec<usize> = (0..s.len())
        .filter(|&i| s.measured[i].is_finite() && pred[i].is_finite())
        .collect();
    let stride = usable.len().div_ceil(MAX_FIT_SAMPLES).max(1);
    let fit: Vec<usize> = usable.iter().copied().step_by(stride).collect();
    let (ata, atb) = fit
        .par_chunks(4096)
        .map(|chunk| {
            let mut ata = vec![0.0; p * p];
            let mut atb = vec![0.0; p];
            let mut f = Vec::new();
            for &i in chunk {
                features(seq, s, &maps, i, &mut f);
                if f.is_empty() {
                    continue;
                }
                let sig = s.noise[i / np];
                let w = 1.0 / (sig * sig + (0.1 * pred[i]).powi(2)).max(1e-12);
                let y = s.measured[i] - pred[i];
                for &(a, va) in &f {
                    atb[a] += w * va * y;
                    for &(b, vb) in &f {
                        ata[a * p + b] += w * va * vb;
                    }
                }
            }
            (ata, atb)
        })
        .reduce(
            || (vec![0.0; p * p], vec![0.0; p]),
            |(mut a, mut b), (c, d)| {
                a.iter_mut().zip(c).for_each(|(x, y)| *x += y);
                b.iter_mut().zip(d).for_each(|(x, y)| *x += y);
                (a, b)
            },
        );
    let trace: f64 = (0..p).map(|j| ata[j * p + j]).sum::<f64>() / p as f64;
    let mut m = ata;
    for j in 0..p {
        m[j * p + j] += 1e-6 * trace.max(1e-300);
    }
    let Some(coef) = solve_spd(&mut m, atb, p) else {
        return pred.to_vec();
    };
    (0..s.len())
        .into_par_iter()
        .map_init(Vec::new, |f, i| {
            features(seq, s, &maps, i, f);
            pred[i] + f.iter().map(|&(a, v)| coef[a] * v).sum::<f64>()
        })
        .collect()
}

/// Solves `m x = b` for a symmetric positive definite `m` (n x n, row major) by
/// Cholesky; None when it is not positive definite.
fn solve_spd(m: &mut [f64], mut b: Vec<f64>, n: usize) -> Option<Vec<f64>> {
    for j in 0..n {
        let mut d = m[j * n + j];
        for k in 0..j {
            d -= m[j * n + k] * m[j * n + k];
        }
        if d <= 0.0 || !d.is_finite() {
            return None;
        }
        let d = d.sqrt();
        m[j * n + j] = d;
        for i in j + 1..n {
            let mut v = m[i * n + j];
            for k in 0..j {
                v -= m[i * n + k] * m[j * n + k];
            }
            m[i * n + j] = v / d;
        }
    }
    for i in 0..n {
        let mut v = b[i];
        for k in 0..i {
            v -= m[i * n + k] * b[k];
        }
        b[i] = v / m[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = b[i];
        for k in i + 1..n {
            v -= m[k * n + i] * b[k];
        }
        b[i] = v / m[i * n + i];
    }
    Some(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cholesky_solves_a_small_system() {
        // [[4, 2], [2, 3]] x = [2, 1] -> x = [0.5, 0]
        let mut m = vec![4.0, 2.0, 2.0, 3.0];
        let x = solve_spd(&mut m, vec![2.0, 1.0], 2).unwrap();
        assert!((x[0] - 0.5).abs() < 1e-12 && x[1].abs() < 1e-12, "{x:?}");
        let mut bad = vec![0.0, 1.0, 1.0, 0.0];
        assert!(solve_spd(&mut bad, vec![1.0, 1.0], 2).is_none());
    }

    #[test]
    fn response_knots_interpolate_in_log_fluence() {
        assert!(knots_of(100.0).is_none());
        let k = knots_of(1e4).unwrap();
        assert_eq!(k[0].0 + 1, k[1].0);
        assert!((k[0].1 + k[1].1 - 1.0).abs() < 1e-12);
    }
}
