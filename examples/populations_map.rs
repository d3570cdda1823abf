//! Can a map of the trap density be learnt from one illumination and carried to another,
//! and does carrying it lower the residual? The per-event log ratios, their smoothing
//! and the pairwise `R^2` are `persist::diag::spatial`'s (its module docs); this prints
//! them per pair, then applies the mean map of all events to the predictions as a scale
//! `exp(strength * (M - mean M))` with the knots' level refitted on a grid, and prints
//! the cell RMS (the per-illumination fluence x time cells of `persist fit`, or those
//! also split by position tiles of `TILE_PX` on a side).
//!
//! ```sh
//! target/release/examples/populations_map LAB_DIR MODEL.json [L_PX [TILE_PX]]
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::diag::spatial;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let length_px: f64 = a.get(3).map_or(8.0, |s| s.parse().expect("L_PX"));
    // cells also split by square position tiles of this side (0: the usual cells)
    let tile_px: usize = a.get(4).map_or(0, |s| s.parse().expect("TILE_PX"));
    let ratios = spatial::log_ratios(&seq, &model).expect("ratios");
    println!("event  pixels  rms_log_ratio");
    for e in &ratios {
        let v: Vec<f64> = e.ratio.iter().copied().filter(|v| v.is_finite()).collect();
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt();
        println!(
            "{:5}  {:6}  {sd:.3}",
            e.illumination_exposure_index,
            v.len()
        );
    }
    let maps: Vec<_> = ratios
        .iter()
        .map(|e| spatial::smooth(&e.ratio, length_px))
        .collect();
    println!("A  B  R2_raw  R2_smoothed(L={length_px})");
    for (i, ea) in ratios.iter().enumerate() {
        for (j, eb) in ratios.iter().enumerate() {
            if i != j {
                println!(
                    "{i}  {j}  {:.3}  {:.3}",
                    spatial::r2(&ea.ratio, &eb.ratio),
                    spatial::r2(&maps[i], &eb.ratio)
                );
            }
        }
    }
    println!("{:?}", spatial::coherence_of(&ratios));
    // the map of all events (mean of the first darks' log ratios, smoothed), applied to
    // every prediction as a scale `exp(strength * map)`: the cell RMS of the stride-2
    // paired cells (`persist fit`'s report) as the strength grows
    let mean = spatial::mean_ratio(&ratios);
    let map = spatial::smooth(&mean, length_px).mapv(|v| if v.is_finite() { v } else { 0.0 });
    let lit = mean.iter().filter(|v| v.is_finite()).count();
    let s2 = Samples::new(&seq, 2)
        .with_cells(eval::Cells::Illumination)
        .with_statistic(eval::CellStatistic::Paired);
    let np2 = s2.npix();
    let pr2 = eval::predict(&model, &seq, &s2, false).expect("predict");
    // demeaned: the level is the knots'; the map only moves pixels against each other
    let mu = map.iter().sum::<f64>() / map.len() as f64;
    let sd_map = (map.iter().map(|v| (v - mu).powi(2)).sum::<f64>() / map.len() as f64).sqrt();
    println!("map: mean {mu:.3}, sd {sd_map:.3} ({lit} pixels with a ratio)");
    for strength in [0.0, 1.0, 2.0, 3.0, 4.0, 6.0] {
        let mut best = (f64::INFINITY, 0.0);
        for j in 0..=30 {
            let level = 0.5 * (1.0 + j as f64 / 30.0);
            let scaled: Vec<f64> = pr2
                .current
                .iter()
                .enumerate()
                .map(|(i, q)| {
                    let (y, x) = s2.pixels[i % np2];
                    level * q * (strength * (map[[y, x]] - mu)).exp()
                })
                .collect();
            let r = if tile_px > 0 {
                tile_rms(&s2, &scaled, tile_px)
            } else {
                eval::rms(&eval::cell_z(&s2, &scaled))
            };
            if r < best.0 {
                best = (r, level);
            }
        }
        println!(
            "strength {strength}: best cell RMS {:.3} at level {:.3}",
            best.0, best.1
        );
    }
}

/// The cell RMS with the per-illumination fluence x time cells also split by position
/// tiles `tile_px` on a side.
fn tile_rms(s: &Samples, pred: &[f64], tile_px: usize) -> f64 {
    use std::collections::BTreeMap;
    type Cell = (Vec<f64>, Vec<f64>, Vec<f64>);
    let mut g: BTreeMap<Vec<i64>, Cell> = BTreeMap::new();
    for (i, &p) in pred.iter().enumerate().take(s.len()) {
        let m = s.measured[i];
        if !m.is_finite() || !p.is_finite() {
            continue;
        }
        let (y, x) = s.pixels[i % s.npix()];
        let mut key = vec![(y / tile_px) as i64, (x / tile_px) as i64];
        for k in ["event", "fluence", "time"] {
            match eval::bin_of(s, k, i) {
                Some(b) => key.push(b),
                None => break,
            }
        }
        if key.len() != 5 {
            continue;
        }
        let e = g.entry(key).or_default();
        e.0.push(m);
        e.1.push(p);
        e.2.push(s.noise[i / s.npix()]);
    }
    let z: Vec<(Vec<i64>, eval::GroupStat)> = g
        .into_iter()
        .filter_map(|(k, (m, p, n))| {
            let mut sorted = n.clone();
            sorted.sort_by(f64::total_cmp);
            let med = sorted[sorted.len() / 2];
            eval::cell_stat(s.statistic, &m, &p, &n, med).map(|st| (k, st))
        })
        .collect();
    eval::rms(&z)
}
