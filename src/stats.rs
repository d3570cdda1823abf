//! Robust statistics shared by the simulator's checks, the fitter, the diagnostics,
//! the demo and the benchmarks: medians, sigma-clipped medians, quantiles and the
//! log-log slope of a power law.
//!
//! Invariants: medians and quantiles ignore values that are not finite (NaN, +-Inf)
//! and are NaN when nothing finite is left; they are found by selection (O(n)) and
//! equal, bit for bit, what a full sort would give, so they do not depend on the order
//! of their input. [`loglog_slope`] uses the pairs where both values are positive.

/// Median of finite values (NaN when none).
pub fn median(v: &[f64]) -> f64 {
    median_in_place(&mut v.to_vec())
}

/// [`median`] of `a`, reordering it (and dropping its values that are not finite)
/// instead of copying it: the same value.
pub fn median_in_place(a: &mut Vec<f64>) -> f64 {
    a.retain(|x| x.is_finite());
    if a.is_empty() {
        return f64::NAN;
    }
    let n = a.len();
    // the middle value(s) by selection (the values a full sort would give)
    let (low, mid, _) = a.select_nth_unstable_by(n / 2, |x, y| x.total_cmp(y));
    let mid = *mid;
    if n % 2 == 1 {
        mid
    } else {
        let below = low
            .iter()
            .copied()
            .max_by(|x, y| x.total_cmp(y))
            .unwrap_or(mid);
        0.5 * (below + mid)
    }
}

/// Sigma-clipped median and standard deviation (clip at `nsigma` about the median).
pub fn clipped_median(v: &[f64], nsigma: f64) -> (f64, f64) {
    let mut a: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    for _ in 0..20 {
        if a.is_empty() {
            return (f64::NAN, f64::NAN);
        }
        let med = median(&a);
        let n = a.len() as f64;
        let mean = a.iter().sum::<f64>() / n;
        let sd = (a.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
        let kept: Vec<f64> = a
            .iter()
            .copied()
            .filter(|x| (x - med).abs() <= nsigma * sd)
            .collect();
        if kept.len() == a.len() {
            return (med, sd);
        }
        a = kept;
    }
    let med = median(&a);
    (med, f64::NAN)
}

/// Least-squares slope of `ln y` against `ln x`.
pub fn loglog_slope(x: &[f64], y: &[f64]) -> f64 {
    let p: Vec<(f64, f64)> = x
        .iter()
        .zip(y)
        .filter(|(a, b)| **a > 0.0 && **b > 0.0)
        .map(|(a, b)| (a.ln(), b.ln()))
        .collect();
    let n = p.len() as f64;
    let mx = p.iter().map(|q| q.0).sum::<f64>() / n;
    let my = p.iter().map(|q| q.1).sum::<f64>() / n;
    let sxy: f64 = p.iter().map(|q| (q.0 - mx) * (q.1 - my)).sum();
    let sxx: f64 = p.iter().map(|q| (q.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// The `q`-quantile (0..1) of finite values, linear interpolation between the two
/// nearest order statistics; NaN when none.
pub fn quantile(v: &[f64], q: f64) -> f64 {
    quantile_in_place(&mut v.to_vec(), q)
}

/// [`quantile`] of `a`, reordering it (and dropping its values that are not finite)
/// instead of copying it: the same value.
pub fn quantile_in_place(a: &mut Vec<f64>, q: f64) -> f64 {
    a.retain(|x| x.is_finite());
    if a.is_empty() {
        return f64::NAN;
    }
    let pos = q.clamp(0.0, 1.0) * (a.len() - 1) as f64;
    let i = pos.floor() as usize;
    // the i-th and (i+1)-th smallest by selection (the values a full sort would give)
    let (_, ai, rest) = a.select_nth_unstable_by(i, |x, y| x.total_cmp(y));
    let ai = *ai;
    let aj = rest
        .iter()
        .copied()
        .min_by(|x, y| x.total_cmp(y))
        .unwrap_or(ai);
    ai + (aj - ai) * (pos - i as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_counts_ignores_non_finite_values() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, f64::NAN, 3.0, 2.0, f64::INFINITY]), 2.5);
        assert!(median(&[f64::NAN]).is_nan());
        assert!(median(&[]).is_nan());
    }

    #[test]
    fn clipping_drops_outliers() {
        let mut v: Vec<f64> = (0..100).map(|i| 10.0 + (i % 5) as f64 * 0.1).collect();
        v.push(1e6);
        let (m, _) = clipped_median(&v, 3.0);
        assert!((m - 10.2).abs() < 1e-9);
    }

    #[test]
    fn quantile_interpolates_between_order_statistics_as_a_sort_would() {
        // 0..=10 shuffled: the q-quantile is 10 q exactly
        let v: Vec<f64> = (0..11).map(|i| ((i * 7) % 11) as f64).collect();
        for q in [0.0, 0.05, 0.5, 0.95, 1.0] {
            assert!((quantile(&v, q) - 10.0 * q).abs() < 1e-12, "q {q}");
        }
        assert_eq!(quantile(&[1.0, f64::NAN, 3.0], 0.5), 2.0);
        assert!(quantile(&[f64::NAN], 0.5).is_nan());
        // out-of-range q is clamped
        assert_eq!(quantile(&v, 2.0), 10.0);
    }

    #[test]
    fn slope_of_power_law() {
        let x: Vec<f64> = (1..50).map(|i| i as f64 * 100.0).collect();
        let y: Vec<f64> = x.iter().map(|t| 5.0 / t).collect();
        assert!((loglog_slope(&x, &y) + 1.0).abs() < 1e-9);
    }
}
