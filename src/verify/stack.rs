//! Stacking track samples into binned means with uncertainties that respect how the
//! samples are correlated (pure code).
//!
//! Samples of one event are not independent: the pixels of one star share its fluence
//! pattern and their sky annuli overlap, and one pixel appears at many times. So every
//! mean is a ratio `sum / count` over **clusters** (the adjacent event pixels of one
//! exposure, [`super::track`]), and its uncertainty is a bootstrap over clusters: clusters
//! are drawn with replacement, whole, [`BOOTSTRAP_REPLICAS`] times, from a generator seeded
//! by the bin, so the result is deterministic. A bin needs [`MIN_CLUSTERS`] clusters.

use crate::stats::quantile;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::BTreeMap;

pub const BOOTSTRAP_REPLICAS: usize = 200;
pub const MIN_CLUSTERS: usize = 5;

/// Sums of `N` columns and a count, per cluster.
#[derive(Debug, Clone)]
pub struct Sums<const N: usize> {
    /// Sum of the weights.
    pub n: f64,
    /// Samples.
    pub count: usize,
    pub s: [f64; N],
}

impl<const N: usize> Default for Sums<N> {
    fn default() -> Self {
        Sums {
            n: 0.0,
            count: 0,
            s: [0.0; N],
        }
    }
}

/// Per-cluster sums of one bin.
#[derive(Debug, Clone)]
pub struct Bin<const N: usize> {
    clusters: BTreeMap<u64, Sums<N>>,
}

impl<const N: usize> Default for Bin<N> {
    fn default() -> Self {
        Bin {
            clusters: BTreeMap::new(),
        }
    }
}

/// A mean and its bootstrap standard error.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Mean {
    pub mean: f64,
    pub se: f64,
}

impl<const N: usize> Bin<N> {
    pub fn add(&mut self, cluster: u64, values: [f64; N]) {
        self.add_weighted(cluster, 1.0, values);
    }

    /// Add one sample of weight `w` (> 0, finite): the means become weighted means.
    pub fn add_weighted(&mut self, cluster: u64, w: f64, values: [f64; N]) {
        let c = self.clusters.entry(cluster).or_default();
        c.n += w;
        c.count += 1;
        for (a, v) in c.s.iter_mut().zip(values) {
            *a += w * v;
        }
    }

    pub fn samples(&self) -> usize {
        self.clusters.values().map(|c| c.count).sum()
    }

    pub fn clusters(&self) -> usize {
        self.clusters.len()
    }

    /// Means of `f(column sums) / (sum of weights)` for each requested linear combination of
    /// columns, with bootstrap standard errors; `None` with too few clusters.
    pub fn means<const K: usize>(&self, weights: [[f64; N]; K], seed: u64) -> Option<[Mean; K]> {
        if self.clusters.len() < MIN_CLUSTERS {
            return None;
        }
        let cl: Vec<&Sums<N>> = self.clusters.values().collect();
        let combine = |pick: &mut dyn FnMut() -> usize| {
            let mut n = 0.0;
            let mut s = [0.0; N];
            for _ in 0..cl.len() {
                let c = cl[pick()];
                n += c.n;
                for (a, v) in s.iter_mut().zip(c.s) {
                    *a += v;
                }
            }
            weights.map(|w| w.iter().zip(s).map(|(w, s)| w * s).sum::<f64>() / n)
        };
        let mut i = 0;
        let full = combine(&mut || {
            i += 1;
            i - 1
        });
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut acc = [(0.0, 0.0); K];
        for _ in 0..BOOTSTRAP_REPLICAS {
            let r = combine(&mut || rng.random_range(0..cl.len()));
            for (a, v) in acc.iter_mut().zip(r) {
                a.0 += v;
                a.1 += v * v;
            }
        }
        let b = BOOTSTRAP_REPLICAS as f64;
        let mut out = [Mean { mean: 0.0, se: 0.0 }; K];
        for k in 0..K {
            let m = acc[k].0 / b;
            out[k] = Mean {
                mean: full[k],
                se: (acc[k].1 / b - m * m).max(0.0).sqrt(),
            };
        }
        Some(out)
    }
}

/// Per-cluster lists of one value, for quantiles.
#[derive(Debug, Clone, Default)]
pub struct QuantileBin {
    clusters: BTreeMap<u64, Vec<f64>>,
}

impl QuantileBin {
    pub fn add(&mut self, cluster: u64, v: f64) {
        if v.is_finite() {
            self.clusters.entry(cluster).or_default().push(v);
        }
    }

    pub fn samples(&self) -> usize {
        self.clusters.values().map(Vec::len).sum()
    }

    /// The `q` quantile and its bootstrap 2.5 % and 97.5 % points (clusters resampled).
    pub fn quantile(&self, q: f64, seed: u64) -> Option<(f64, f64, f64)> {
        if self.clusters.len() < MIN_CLUSTERS {
            return None;
        }
        let cl: Vec<&Vec<f64>> = self.clusters.values().collect();
        let all: Vec<f64> = cl.iter().flat_map(|c| c.iter().copied()).collect();
        let est = quantile(&all, q);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut reps: Vec<f64> = (0..BOOTSTRAP_REPLICAS)
            .map(|_| {
                let mut v = Vec::with_capacity(all_len(&cl));
                for _ in 0..cl.len() {
                    v.extend_from_slice(cl[rng.random_range(0..cl.len())]);
                }
                quantile(&v, q)
            })
            .collect();
        reps.sort_by(f64::total_cmp);
        let at =
            |p: f64| reps[((p * (reps.len() - 1) as f64).round() as usize).min(reps.len() - 1)];
        Some((est, at(0.025), at(0.975)))
    }
}

fn all_len(cl: &[&Vec<f64>]) -> usize {
    cl.iter().map(|c| c.len()).sum()
}

/// Which bin of `edges` (ascending) holds `v`: `edges[i] <= v < edges[i + 1]`.
pub fn bin_of(edges: &[f64], v: f64) -> Option<usize> {
    if v.is_nan() || v < edges[0] {
        return None;
    }
    edges.windows(2).position(|w| v >= w[0] && v < w[1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mean_over_clusters_weights_samples_and_its_error_shrinks_with_clusters() {
        let mut b: Bin<1> = Bin::default();
        for c in 0..4 {
            b.add(c, [1.0]);
        }
        assert!(b.means([[1.0]], 1).is_none(), "four clusters are too few");
        b.add(4, [3.0]);
        b.add(4, [3.0]);
        let [m] = b.means([[1.0]], 1).unwrap();
        assert!((m.mean - 10.0 / 6.0).abs() < 1e-12);
        let mut big: Bin<1> = Bin::default();
        for c in 0..400 {
            big.add(c, [if c % 2 == 0 { 1.0 } else { 3.0 }]);
        }
        let [m2] = big.means([[1.0]], 1).unwrap();
        // sd 1 over 400 clusters: se 0.05
        assert!((m2.se - 0.05).abs() < 0.012, "{m2:?}");
    }

    #[test]
    fn quantiles_and_bins() {
        assert_eq!(quantile(&[3.0, 1.0, 2.0], 0.5), 2.0);
        assert_eq!(quantile(&[0.0, 10.0], 0.95), 9.5);
        assert_eq!(bin_of(&[1.0, 2.0, f64::INFINITY], 5.0), Some(1));
        assert_eq!(bin_of(&[1.0, 2.0], 0.5), None);
    }
}
