//! The judges of the candidates the pixel reference cannot see, against the flexible
//! base: a candidate acting on the neighbours (`neighbour_excess_fluence`) on the pixels
//! next to far brighter ones, a candidate acting on the position (`position`) by tile
//! of the array.
//!
//! # Why not the pixel reference
//! The pixel reference ([`super::base::predict_scaled`]) gives each pixel its own
//! amplitude, decay shape and response in fluence. A pixel beside a pinhole sees the
//! same bright neighbour in every illumination, so what the neighbour does to it
//! (charge spilled in, traps exposed by its field, signal coupled in the read) is a
//! factor of that pixel, and the pixel's own terms take it in: on the second
//! generator's `blooming:field` campaign (64 x 64, seed 1) the pixel reference's RMS
//! is 1.13, the nothing-hidden campaign's 1.11, while the pixels next to the
//! pinholes lie +0.21 of their cells' spread above the flexible base (z 6.9,
//! [`super::contrast::SharpExcess`]). A field of trap density over the array is such a
//! factor too. A candidate of these kinds is therefore judged where the kind was
//! named: against the flexible base ([`super::base::predict`], a response per fluence
//! and a decay per time shared by every pixel), on the pixel-events whose neighbours'
//! excess over saturation exceeds their own fluence, or on every pixel-event, grouped
//! by the 4 x 4 tile of the array the position's dependence is tested on.
//!
//! # The cells
//! Each sample's standardised residual beyond the mean of its (fluence, time, event)
//! cell: of the flexible base for [`Judge::NextToBrighter`]
//! (`super::contrast::base_residual`), of the prediction times the cell's own
//! least-squares factor for [`Judge::Position`] (`super::contrast::scaled_residual`).
//! A field over the array multiplies the response, and where the description's level
//! is off by a factor `k` in a cell, an offset per cell leaves `k` times the field's
//! variation to be matched: measured on the second generator's `populations:smooth`
//! campaign (64 x 64, seed 1, gradient 0.4 along `y`; `examples/per_event_floor` with
//! `JUDGE=position`), the tiles' RMS with an offset was 2.69 at the null, 1.54 at `gy`
//! 0.25 and 2.20 at 0.40; with the factor, 2.75, 1.81 and 1.66, and 1.28 at the
//! surface measured directly (`gy` 0.40, [`super::polish`]). The samples grouped
//! by (group, event, fluence, time), the group the tile ([`Judge::Position`]) or, for
//! [`Judge::NextToBrighter`], the marked samples alone (`neighbour_contrast` 1,
//! [`crate::measure::eval::bin_of`]); a group's `z` is its residuals' sum over the
//! square root of their number (unit variance each, up to the clip). A candidate that
//! predicts what the neighbours, or the place on the array, do brings these `z`
//! towards 0; the gate ([`super::refit::held_out`]) compares its held-out gain with
//! those of its change moved to other pixels, on the same cells.
//!
//! Invariants: the cells depend on the samples, the mark, the tiles and which
//! predictions are finite, never on the measurements' values; a group has at least
//! [`MIN_MARKED`] samples; nothing here fits but the flexible base and the cells'
//! factors.

use super::base::View;
use super::data::Sequence;
use super::eval::{self, Samples};
use std::collections::BTreeMap;

/// The fewest marked samples a cell of the judge holds.
pub const MIN_MARKED: usize = 4;

/// What a held-out check is judged against ([`super::refit::PixelHeldOut::judge`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Judge {
    /// The pixel reference ([`super::base::predict_scaled`]) over every cell.
    PixelReference,
    /// The flexible base on the pixels next to far brighter ones (module docs): for a
    /// candidate acting on the neighbours, which each pixel's own terms in the pixel
    /// reference would take in.
    NextToBrighter,
    /// The flexible base by tile of the array (module docs): for a candidate acting on
    /// the position, which each pixel's own amplitude in the pixel reference takes in.
    Position,
}

impl Judge {
    /// The judge of the candidates `names`.
    pub fn of(names: &[&str]) -> Judge {
        if acts_on(names, NEIGHBOURS) {
            Judge::NextToBrighter
        } else if acts_on(names, POSITION) {
            Judge::Position
        } else {
            Judge::PixelReference
        }
    }

    /// The judge of the candidates acting on `covariate` (a dependence's class).
    pub fn of_covariate(covariate: &str) -> Judge {
        match covariate {
            NEIGHBOURS => Judge::NextToBrighter,
            POSITION => Judge::Position,
            _ => Judge::PixelReference,
        }
    }

    /// "the pixel reference", as the verdict says it.
    pub fn phrase(self) -> &'static str {
        match self {
            Judge::PixelReference => "the pixel reference",
            Judge::NextToBrighter => "the flexible base on the pixels next to far brighter ones",
            Judge::Position => "the flexible base by tile of the array",
        }
    }
}

/// The covariate of the effects judged on the pixels next to far brighter ones.
pub const NEIGHBOURS: &str = "neighbour_excess_fluence";

/// The covariate of the effects judged by tile of the array.
pub const POSITION: &str = "position";

/// Whether the candidates `names` (`--with` arguments allowed) act on the neighbours:
/// their library definition's covariate is [`NEIGHBOURS`].
pub fn acts_on_neighbours(names: &[&str]) -> bool {
    acts_on(names, NEIGHBOURS)
}

/// Whether one of the candidates `names` (`--with` arguments allowed) is a library
/// effect whose covariate is `covariate`.
pub fn acts_on(names: &[&str], covariate: &str) -> bool {
    names.iter().any(|n| {
        crate::model::effects::lookup(n.split(':').next().unwrap_or(n))
            .is_some_and(|d| d.covariate == covariate)
    })
}

/// The cells of `judge` (one of the flexible base's: [`Judge::NextToBrighter`] or
/// [`Judge::Position`]) for `pred` over `s` (module docs), keyed by (group, event,
/// fluence bin, time bin); the flexible base fitted on `s` with `view`'s clock and
/// readout. Empty for [`Judge::PixelReference`].
pub fn cells(
    judge: Judge,
    seq: &Sequence,
    view: &View,
    s: &Samples,
    pred: &[f64],
) -> Vec<(Vec<i64>, eval::GroupStat)> {
    if judge == Judge::PixelReference {
        return Vec::new();
    }
    let np = s.npix().max(1);
    let group = |i: usize| -> Option<i64> {
        match judge {
            Judge::PixelReference => None,
            Judge::NextToBrighter => marked(s, i),
            Judge::Position => Some(super::contrast::tile(seq, s.pixels[i % np])),
        }
    };
    let e = match judge {
        Judge::Position => super::contrast::scaled_residual(s, pred, true),
        _ => super::contrast::base_residual(s, &super::base::predict(seq, view, s, pred), true),
    };
    grouped_cells(s, &e, group)
}

/// The normalised residual RMS of `m`'s prediction over the cells of `judge` on `s`
/// ([`cells`]); NaN without a cell.
pub fn rms(
    judge: Judge,
    m: &crate::model::params::ModelParams,
    seq: &Sequence,
    s: &Samples,
) -> crate::error::Result<f64> {
    let pred = eval::predict(m, seq, s, false)?.current;
    let cells = cells(judge, seq, &View::of_model(m, seq), s, &pred);
    Ok(eval::rms(&cells))
}

/// The group of sample `i` on the pixels next to far brighter ones: 0 when marked
/// (`neighbour_contrast` 1), else none.
fn marked(s: &Samples, i: usize) -> Option<i64> {
    (eval::bin_of(s, "neighbour_contrast", i) == Some(1)).then_some(0)
}

/// The residuals `e` (per sample, NaN unusable) of the samples `group` gives a group
/// (None: no group), grouped into cells by (group, event, fluence bin, time bin).
fn grouped_cells(
    s: &Samples,
    e: &[f64],
    group: impl Fn(usize) -> Option<i64>,
) -> Vec<(Vec<i64>, eval::GroupStat)> {
    let np = s.npix().max(1);
    let mut sums: BTreeMap<Vec<i64>, (f64, usize)> = BTreeMap::new();
    for (i, &v) in e.iter().enumerate() {
        if !v.is_finite() {
            continue;
        }
        let Some(g) = group(i) else { continue };
        let (Some(f), Some(t)) = (eval::bin_of(s, "fluence", i), eval::bin_of(s, "time", i)) else {
            continue;
        };
        let q = sums
            .entry(vec![g, s.event[i / np] as i64, f, t])
            .or_default();
        q.0 += v;
        q.1 += 1;
    }
    sums.into_iter()
        .filter(|(_, (_, n))| *n >= MIN_MARKED)
        .map(|(key, (sum, n))| {
            let stat = eval::GroupStat {
                n,
                measured_p95_e_per_s: f64::NAN,
                predicted_p95_e_per_s: f64::NAN,
                measured_median_e_per_s: f64::NAN,
                sigma_e_per_s: f64::NAN,
                z: sum / (n as f64).sqrt(),
            };
            (key, stat)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Eight pixels in one row after one illumination, every fluence 1e4 e-; pixels 0-5
    /// have neighbours 1e6 e- over saturation (marked), 6-7 none.
    fn row() -> Samples {
        let np = 8;
        Samples {
            cells: eval::Cells::Illumination,
            statistic: eval::CellStatistic::Levels,
            stride: 0,
            pixels: (0..np).map(|x| (0, x)).collect(),
            exposures: vec![0],
            measured: vec![1.0; np],
            noise: vec![0.01],
            shot_var_per_e_per_s: vec![0.0],
            noise_scale: Default::default(),
            spread_rel: vec![0.0; np],
            fluence_e: vec![1e4; np],
            neighbour_excess_e: (0..np).map(|x| if x < 6 { 1e6 } else { 0.0 }).collect(),
            t_since_s: vec![100.0],
            event: vec![0],
            illumination_time_s: vec![481.0],
            temperature_k: vec![80.0],
            earlier_illuminations: vec![0.0],
            radius: vec![0.5; np],
        }
    }

    /// One cell whose measurements follow a field `1 + g_x` over the row at half the
    /// prediction's level: the scaled residual of the prediction with the right field
    /// is 0 everywhere; with the field at half its size it is not, and an offset per
    /// cell (the flexible base's residual) prefers the half-size field.
    #[test]
    fn a_factor_per_cell_matches_a_field_at_its_size_whatever_the_level() {
        let mut s = row();
        let g: Vec<f64> = (0..8).map(|x| 0.05 * (f64::from(x) - 3.5)).collect();
        s.measured = g.iter().map(|g| 0.5 * (1.0 + g)).collect();
        let pred = |c: f64| -> Vec<f64> { g.iter().map(|g| 1.0 + c * g).collect() };
        let size = |e: Vec<f64>| e.iter().map(|v| v * v).sum::<f64>();
        let right = size(super::super::contrast::scaled_residual(
            &s,
            &pred(1.0),
            true,
        ));
        let half = size(super::super::contrast::scaled_residual(
            &s,
            &pred(0.5),
            true,
        ));
        assert!(right < 1e-12 && half > 1.0, "{right} {half}");
        let right = size(super::super::contrast::base_residual(&s, &pred(1.0), true));
        let half = size(super::super::contrast::base_residual(&s, &pred(0.5), true));
        assert!(half < 1e-12 && right > 1.0, "{right} {half}");
    }

    /// A group's `z` is its marked residuals' sum over the root of their number; the
    /// unmarked samples and those without a residual do not count, and a group under
    /// [`MIN_MARKED`] is left out.
    #[test]
    fn marked_cells_sum_the_marked_residuals_per_event_fluence_and_time() {
        let s = row();
        let e = [0.5, 0.5, f64::NAN, 0.5, 0.5, 0.5, 9.0, 9.0];
        let cells = grouped_cells(&s, &e, |i| marked(&s, i));
        assert_eq!(cells.len(), 1);
        let (key, c) = &cells[0];
        assert_eq!(key[..2], [0, 0]);
        assert_eq!(c.n, 5);
        assert!((c.z - 2.5 / 5f64.sqrt()).abs() < 1e-12);
        let few = [0.5, f64::NAN, f64::NAN, 0.5, 0.5, f64::NAN, 9.0, 9.0];
        assert!(grouped_cells(&s, &few, |i| marked(&s, i)).is_empty());
    }

    /// Every sample counts in its own group's cell (a tile, for the position): two
    /// groups of four pixels, each its own sum over the root of its number.
    #[test]
    fn grouped_cells_keep_each_group_apart() {
        let s = row();
        let e = [1.0, 1.0, 1.0, 1.0, -0.5, -0.5, -0.5, -0.5];
        let cells = grouped_cells(&s, &e, |i| Some(i64::from(i >= 4)));
        assert_eq!(cells.len(), 2);
        assert_eq!((cells[0].0[0], cells[1].0[0]), (0, 1));
        assert!((cells[0].1.z - 2.0).abs() < 1e-12);
        assert!((cells[1].1.z + 1.0).abs() < 1e-12);
    }

    /// Only effects on `neighbour_excess_fluence` are judged here.
    #[test]
    fn the_neighbour_effects_are_judged_on_the_marked_pixels() {
        assert!(acts_on_neighbours(&["blooming:fraction=0.001"]));
        assert!(acts_on_neighbours(&["smooth_neighbour"]));
        assert!(acts_on_neighbours(&["ipc"]));
        assert!(!acts_on_neighbours(&["soak", "capacity"]));
        assert_eq!(Judge::of(&["populations"]), Judge::Position);
        assert_eq!(Judge::of_covariate(POSITION), Judge::Position);
        assert_eq!(Judge::of(&["soak"]), Judge::PixelReference);
    }
}
