//! The paper's analysis of laboratory data, for tests and reports.
//!
//! - sigma-clipped median (3 sigma, iterated to convergence) of the line-fit current of
//!   the first dark integration, per bin of extrapolated fluence (paper section 2.2,
//!   Fig. 4a, Table 1);
//! - peaks of the current histogram within one fluence bin (paper Fig. 4b), from a
//!   Gaussian kernel density;
//! - the log-log slope of the median current against time since the reset (paper Fig. 5
//!   right).

/// Median of finite values (NaN when none).
pub fn median(v: &[f64]) -> f64 {
    let mut a: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
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

/// Local maxima of a Gaussian kernel density of `v` on `[lo, hi]`, higher than
/// `min_rel` times the highest one, in increasing order.
pub fn density_peaks(v: &[f64], bandwidth: f64, lo: f64, hi: f64, min_rel: f64) -> Vec<f64> {
    let n = 400;
    let xs: Vec<f64> = (0..=n)
        .map(|i| lo + (hi - lo) * i as f64 / n as f64)
        .collect();
    let d: Vec<f64> = xs
        .iter()
        .map(|x| {
            v.iter()
                .filter(|u| u.is_finite())
                .map(|u| (-0.5 * ((x - u) / bandwidth).powi(2)).exp())
                .sum()
        })
        .collect();
    let top = d.iter().copied().fold(0.0, f64::max);
    (1..n)
        .filter(|&i| d[i] > d[i - 1] && d[i] >= d[i + 1] && d[i] > min_rel * top)
        .map(|i| xs[i])
        .collect()
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

/// One box pass of half-width `h` along x then y (each mean over the pixels within
/// `h`, fewer at the edges): three passes make the simulator's smooth fields
/// ([`crate::sim::effects::populations::field`]) and `diag::spatial`'s maps.
pub fn box_blur(a: &ndarray::Array2<f64>, h: usize) -> ndarray::Array2<f64> {
    let (ny, nx) = a.dim();
    let mut b = ndarray::Array2::<f64>::zeros((ny, nx));
    for y in 0..ny {
        for x in 0..nx {
            let (x0, x1) = (x.saturating_sub(h), (x + h).min(nx - 1));
            b[[y, x]] = (x0..=x1).map(|i| a[[y, i]]).sum::<f64>() / (x1 - x0 + 1) as f64;
        }
    }
    let mut c = ndarray::Array2::<f64>::zeros((ny, nx));
    for y in 0..ny {
        let (y0, y1) = (y.saturating_sub(h), (y + h).min(ny - 1));
        for x in 0..nx {
            c[[y, x]] = (y0..=y1).map(|i| b[[i, x]]).sum::<f64>() / (y1 - y0 + 1) as f64;
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clipping_drops_outliers() {
        let mut v: Vec<f64> = (0..100).map(|i| 10.0 + (i % 5) as f64 * 0.1).collect();
        v.push(1e6);
        let (m, _) = clipped_median(&v, 3.0);
        assert!((m - 10.2).abs() < 1e-9);
    }

    #[test]
    fn finds_two_peaks() {
        let mut v: Vec<f64> = (0..200).map(|i| 3.0 + 0.01 * (i % 20) as f64).collect();
        v.extend((0..200).map(|i| 17.0 + 0.01 * (i % 20) as f64));
        let p = density_peaks(&v, 0.5, 0.0, 30.0, 0.1);
        assert_eq!(p.len(), 2);
    }

    #[test]
    fn slope_of_power_law() {
        let x: Vec<f64> = (1..50).map(|i| i as f64 * 100.0).collect();
        let y: Vec<f64> = x.iter().map(|t| 5.0 / t).collect();
        assert!((loglog_slope(&x, &y) + 1.0).abs() < 1e-9);
    }
}
