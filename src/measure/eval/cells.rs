//! The cells: each sample's bin of every covariate ([`bin_of`]), the groups the bins
//! key ([`groups`], [`cell_z`]), the index the fits evaluate many predictions with
//! ([`CellIndex`]) and the sums over the cells ([`rss`], [`rms`]).

use super::group::{
    cell_stat_null, group_stat, group_stat_p95, noise_p95, paired_stat, CellStatistic, GroupStat,
};
use super::samples::Samples;
use crate::measure::data::noisy_quantile;
use crate::stats::median;
use rayon::prelude::*;

/// Lower edges (e-, s) of the fluence and time bins of a cell key of either
/// [`super::Cells`] kind (the last two elements).
pub fn cell_fluence_time(key: &[i64]) -> (f64, f64) {
    let n = key.len();
    if n < 2 {
        return (f64::NAN, f64::NAN);
    }
    (
        bin_value("fluence", key[n - 2]),
        bin_value("time", key[n - 1]),
    )
}

/// The illumination (position in the sequence's exposures, not the products' exposure
/// index) of a per-illumination cell key (either kind); None for a pooled one.
pub fn cell_illumination(key: &[i64]) -> Option<usize> {
    (key.len() >= 3).then(|| key[0] as usize)
}

/// Whether a cell key of [`super::Cells::Neighbours`] holds the pixels next to a far brighter
/// one ([`super::samples`] docs, "Neighbour contrast"); false for the other kinds.
pub fn cell_next_to_brighter(key: &[i64]) -> bool {
    key.len() == 4 && key[1] == 1
}

/// Sample `i`'s group key: its bin of each covariate in `keys` ([`bin_of`]), or None
/// when one has none. The key of [`groups`], [`CellIndex`] and [`super::flag_quality_by_cell`].
pub fn key_of(s: &Samples, keys: &[&str], i: usize) -> Option<Vec<i64>> {
    keys.iter().map(|k| bin_of(s, k, i)).collect()
}

/// Bin index of a sample for a covariate; None to leave it out.
pub fn bin_of(s: &Samples, covariate: &str, i: usize) -> Option<i64> {
    let (row, px) = (i / s.npix(), i % s.npix());
    let lg =
        |v: f64, per: f64| (v > 0.0 && v.is_finite()).then(|| (v.log10() * per).floor() as i64);
    match covariate {
        "fluence" => lg(s.fluence_e[i], 5.0),
        "time" => lg(s.t_since_s[row], 4.0),
        "neighbour_excess_fluence" => {
            let v = s.neighbour_excess_e[i];
            Some(if v <= 0.0 {
                -1
            } else {
                (v.log10() * 2.0).floor() as i64
            })
        }
        // 1 where the neighbours' excess over saturation exceeds the pixel's own fluence
        // (`samples.rs`, "Neighbour contrast")
        "neighbour_contrast" => {
            let (v, f) = (s.neighbour_excess_e[i], s.fluence_e[i]);
            Some(i64::from(v > f.max(0.0)))
        }
        "illumination_time" => Some(s.illumination_time_s[row].round() as i64),
        "temperature" => {
            let t = s.temperature_k[row];
            t.is_finite().then(|| (t * 2.0).round() as i64)
        }
        "earlier_illuminations" => Some(s.earlier_illuminations[row] as i64),
        "event" => Some(s.event[row] as i64),
        "position" => Some((s.radius[px] * 5.0).floor() as i64),
        _ => None,
    }
}

/// Lower edge (in the covariate's unit) of a bin from [`bin_of`].
pub fn bin_value(covariate: &str, b: i64) -> f64 {
    match covariate {
        "fluence" => 10f64.powf(b as f64 / 5.0),
        "time" => 10f64.powf(b as f64 / 4.0),
        "neighbour_excess_fluence" => {
            if b < 0 {
                0.0
            } else {
                10f64.powf(b as f64 / 2.0)
            }
        }
        "temperature" => b as f64 / 2.0,
        "position" => b as f64 / 5.0,
        _ => b as f64,
    }
}

/// Groups keyed by bins of the given covariates (in their order).
pub fn groups(s: &Samples, pred: &[f64], keys: &[&str]) -> Vec<(Vec<i64>, GroupStat)> {
    groups_by(s, pred, keys, s.statistic, |i| s.null_of(i, pred[i]))
}

/// [`groups`] with each sample's null `(offset, sd, noise)` given by `null` (sample
/// index) and the groups compared by `statistic`.
pub fn groups_by(
    s: &Samples,
    pred: &[f64],
    keys: &[&str],
    statistic: CellStatistic,
    null: impl Fn(usize) -> (f64, f64, f64),
) -> Vec<(Vec<i64>, GroupStat)> {
    use std::collections::BTreeMap;
    /// Per group: measured, predicted, and per sample the null's offset, standard
    /// deviation and measurement noise ([`Samples::null_of`]).
    #[derive(Default)]
    struct Group {
        m: Vec<f64>,
        p: Vec<f64>,
        offset: Vec<f64>,
        sd: Vec<f64>,
        noise: Vec<f64>,
    }
    let mut g: BTreeMap<Vec<i64>, Group> = BTreeMap::new();
    #[allow(clippy::needless_range_loop)]
    for i in 0..s.len() {
        let m = s.measured[i];
        if !m.is_finite() || !pred[i].is_finite() {
            continue;
        }
        let Some(key) = key_of(s, keys, i) else {
            continue;
        };
        let e = g.entry(key).or_default();
        let (offset, sd, noise) = null(i);
        e.m.push(m);
        e.p.push(pred[i]);
        e.offset.push(offset);
        e.sd.push(sd);
        e.noise.push(noise);
    }
    // the groups' statistics in parallel, collected in key order
    let g: Vec<_> = g.into_iter().collect();
    g.into_par_iter()
        .filter_map(|(k, c)| {
            cell_stat_null(statistic, &c.m, &c.p, &c.offset, &c.sd, median(&c.noise))
                .map(|st| (k, st))
        })
        .collect()
}

/// The cells (fluence x time, per illumination when `s.cells` says so) and their `z`
/// ([`super::group`] docs).
pub fn cell_z(s: &Samples, pred: &[f64]) -> Vec<(Vec<i64>, GroupStat)> {
    groups(s, pred, s.cells.keys())
}

/// The cells ([`super::Cells`]) of one sample set with their measured side computed once:
/// for fits that evaluate [`cell_z`] for many predictions of the same samples.
/// [`CellIndex::z`] returns exactly what [`cell_z`] returns (a cell where some
/// prediction is not finite is recomputed from its remaining samples, as [`groups`]
/// would).
#[derive(Debug, Clone)]
pub struct CellIndex {
    cells: Vec<IndexedCell>,
}

#[derive(Debug, Clone)]
struct IndexedCell {
    key: Vec<i64>,
    /// Samples with a finite measurement, in sample order.
    members: Vec<usize>,
    /// Their exposures' noise, e-/s.
    sigma: Vec<f64>,
    /// Zeros, one per member (the paired statistic's offsets).
    zero: Vec<f64>,
    /// The median of `sigma`.
    noise: f64,
    /// [`noise_p95`] of `sigma` (the paired statistic's reference, whatever the
    /// predictions; NaN with the levels statistic).
    noise_p95: f64,
    /// [`group_stat_p95`] of all members (its `predicted_p95_e_per_s` unused); None
    /// when fewer than 10, and with the paired statistic (not used there).
    measured: Option<GroupStat>,
}

impl CellIndex {
    pub fn new(s: &Samples) -> CellIndex {
        let all = vec![0.0; s.len()];
        let mut g: std::collections::BTreeMap<Vec<i64>, Vec<usize>> = Default::default();
        for i in 0..s.len() {
            if !s.measured[i].is_finite() {
                continue;
            }
            // the keys of `groups` (same covariates, same order)
            if let Some(key) = key_of(s, s.cells.keys(), i) {
                g.entry(key).or_default().push(i);
            }
        }
        let cells = g
            .into_iter()
            .map(|(key, members)| {
                let (meas, sigma) = Self::gather(s, &members, &all);
                let noise = median(&sigma);
                let (measured, noise_p95) = match s.statistic {
                    CellStatistic::Levels => (group_stat_p95(&meas, 0.0, noise), f64::NAN),
                    CellStatistic::Paired => (None, noise_p95(&sigma)),
                    // depends on the predictions: computed in `z`
                    CellStatistic::Population => (None, f64::NAN),
                };
                IndexedCell {
                    key,
                    zero: vec![0.0; members.len()],
                    members,
                    sigma,
                    noise,
                    noise_p95,
                    measured,
                }
            })
            .collect();
        CellIndex { cells }
    }

    fn gather(s: &Samples, members: &[usize], pred: &[f64]) -> (Vec<f64>, Vec<f64>) {
        members
            .iter()
            .filter(|&&i| pred[i].is_finite())
            .map(|&i| (s.measured[i], s.noise[i / s.npix()]))
            .unzip()
    }

    /// [`cell_z`] of `pred` on the samples this index was built from.
    pub fn z(&self, s: &Samples, pred: &[f64]) -> Vec<(Vec<i64>, GroupStat)> {
        let mut buf = Vec::new();
        let mut meas = Vec::new();
        self.cells
            .iter()
            .filter_map(|c| {
                buf.clear();
                buf.extend(c.members.iter().map(|&i| pred[i]));
                let all_finite = buf.iter().all(|v| v.is_finite());
                let st = if s.statistic == CellStatistic::Population {
                    meas.clear();
                    meas.extend(c.members.iter().map(|&i| s.measured[i]));
                    let (mut offset, mut sd, mut noise) = (Vec::new(), Vec::new(), Vec::new());
                    for (&i, p) in c.members.iter().zip(&buf) {
                        let (o, d, n) = s.null_of(i, *p);
                        offset.push(o);
                        sd.push(d);
                        if p.is_finite() {
                            noise.push(n);
                        }
                    }
                    paired_stat(&meas, &buf, &offset, &sd, median(&noise), None)
                } else if s.statistic == CellStatistic::Paired {
                    meas.clear();
                    meas.extend(c.members.iter().map(|&i| s.measured[i]));
                    // the typical noise of the samples `groups` keeps
                    let noise = if all_finite {
                        c.noise
                    } else {
                        median(&Self::gather(s, &c.members, pred).1)
                    };
                    paired_stat(&meas, &buf, &c.zero, &c.sigma, noise, Some(c.noise_p95))
                } else if all_finite {
                    let m = c.measured?;
                    let pp = noisy_quantile(&buf, &c.sigma, 0.95).0;
                    Some(GroupStat {
                        predicted_p95_e_per_s: pp,
                        z: (m.measured_p95_e_per_s - pp) / m.sigma_e_per_s,
                        ..m
                    })
                } else {
                    let (meas, noise) = Self::gather(s, &c.members, pred);
                    // non-finite predictions drop out with their sigma
                    group_stat(&meas, &buf, &c.sigma, median(&noise))
                };
                st.map(|st| (c.key.clone(), st))
            })
            .collect()
    }
}

/// Sum of squared `z` over the cells, and their number.
pub fn rss(z: &[(Vec<i64>, GroupStat)]) -> (f64, usize) {
    (z.iter().map(|(_, g)| g.z * g.z).sum(), z.len())
}

/// `sqrt(mean z^2)` over the cells.
pub fn rms(z: &[(Vec<i64>, GroupStat)]) -> f64 {
    if z.is_empty() {
        return f64::NAN;
    }
    (z.iter().map(|(_, g)| g.z * g.z).sum::<f64>() / z.len() as f64).sqrt()
}
