//! The paper's analysis of laboratory data, for tests and reports.
//!
//! - sigma-clipped median (3 sigma, iterated to convergence) of the line-fit current of
//!   the first dark integration, per bin of extrapolated fluence (paper section 2.2,
//!   Fig. 4a, Table 1);
//! - peaks of the current histogram within one fluence bin (paper Fig. 4b), from a
//!   Gaussian kernel density;
//! - the log-log slope of the median current against time since the reset (paper Fig. 5
//!   right).
//!
//! The statistics themselves ([`median`], [`clipped_median`], [`loglog_slope`]) live in
//! [`crate::stats`]; they are re-exported here for the code that still names them
//! through this module.

pub use crate::stats::{clipped_median, loglog_slope, median};

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
    fn finds_two_peaks() {
        let mut v: Vec<f64> = (0..200).map(|i| 3.0 + 0.01 * (i % 20) as f64).collect();
        v.extend((0..200).map(|i| 17.0 + 0.01 * (i % 20) as f64));
        let p = density_peaks(&v, 0.5, 0.0, 30.0, 0.1);
        assert_eq!(p.len(), 2);
    }
}
