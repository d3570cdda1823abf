//! Can a map of the trap density be learnt from one illumination and carried to another?
//! The feasibility check for a map-carrying `populations` effect (issue 4): per
//! illumination event, the log ratio `r = ln(measured / predicted)` of the first dark
//! exposure after it, at pixels predicted above `MIN_PRED_E_PER_S` and measured above 0
//! (the model's misfit per pixel, mostly the trap density it does not know). For every
//! ordered pair of events (A, B): how much of B's per-pixel ratio the ratio of A explains
//! (`R^2` of the least-squares line), raw and smoothed over `L` pixels (three masked box
//! passes of half-width `L/2`, the simulator's own smoothing of its `populations`
//! field). A pixel's own traps are the same in every event, so the raw `R^2` is high
//! whatever the campaign; what a smooth map can carry is the part shared by
//! neighbours, which only a spatially correlated truth has.
//!
//! ```sh
//! target/release/examples/populations_map LAB_DIR MODEL.json [L_PX [TILE_PX]]
//! ```
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use std::path::Path;

/// Pixels predicted below this in the first dark are left out (noise dominated), e-/s.
const MIN_PRED_E_PER_S: f64 = 1.0;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let length_px: f64 = a.get(3).map_or(8.0, |s| s.parse().expect("L_PX"));
    // cells also split by square position tiles of this side (0: the usual cells)
    let tile_px: usize = a.get(4).map_or(0, |s| s.parse().expect("TILE_PX"));
    let s = Samples::new(&seq, 1);
    let pr = eval::predict(&model, &seq, &s, false).expect("predict");
    let np = s.npix();
    let (ny, nx) = (seq.ny, seq.nx);
    // the first row after each event
    let mut firsts: Vec<usize> = Vec::new();
    for (row, &e) in s.event.iter().enumerate() {
        if row == 0 || s.event[row - 1] != e {
            firsts.push(row);
        }
    }
    // the log ratio less the median of its fluence bin (20 per decade) in the same
    // event: what is a function of fluence is the knots' to take
    let ratio = |row: usize| -> Vec<f64> {
        let mut r: Vec<f64> = (0..np)
            .map(|p| {
                let (m, q) = (s.measured[row * np + p], pr.current[row * np + p]);
                if q > MIN_PRED_E_PER_S && m > 0.0 && m.is_finite() {
                    (m / q).ln()
                } else {
                    f64::NAN
                }
            })
            .collect();
        let bin = |p: usize| (20.0 * s.fluence_e[row * np + p].max(1.0).log10()).floor() as i64;
        let mut groups: std::collections::BTreeMap<i64, Vec<usize>> = Default::default();
        for p in (0..np).filter(|&p| r[p].is_finite()) {
            groups.entry(bin(p)).or_default().push(p);
        }
        for members in groups.values() {
            let mut v: Vec<f64> = members.iter().map(|&p| r[p]).collect();
            v.sort_by(f64::total_cmp);
            let med = v[v.len() / 2];
            for &p in members {
                r[p] -= med;
            }
        }
        r
    };
    let maps: Vec<(Vec<f64>, Vec<f64>)> = firsts
        .iter()
        .map(|&row| {
            let r = ratio(row);
            let sm = smooth(&r, ny, nx, length_px);
            (r, sm)
        })
        .collect();
    println!("event  t_since_s  pixels  rms_log_ratio");
    for (i, &row) in firsts.iter().enumerate() {
        let v: Vec<f64> = maps[i]
            .0
            .iter()
            .copied()
            .filter(|v| v.is_finite())
            .collect();
        let m = v.iter().sum::<f64>() / v.len().max(1) as f64;
        let sd = (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt();
        println!("{i:5}  {:9.1}  {:6}  {sd:.3}", s.t_since_s[row], v.len());
    }
    let (mut raw, mut smoothed, mut n) = (0.0, 0.0, 0);
    println!("A  B  R2_raw  R2_smoothed(L={length_px})");
    for i in 0..maps.len() {
        for j in 0..maps.len() {
            if i == j {
                continue;
            }
            let (r1, r2) = (r2(&maps[i].0, &maps[j].0), r2(&maps[i].1, &maps[j].0));
            println!("{i}  {j}  {r1:.3}  {r2:.3}");
            raw += r1;
            smoothed += r2;
            n += 1;
        }
    }
    let n = f64::from(n.max(1));
    println!(
        "mean over pairs: R2_raw {:.3}, R2_smoothed {:.3}",
        raw / n,
        smoothed / n
    );
    // the map of all events (mean of the first darks' log ratios, smoothed), applied to
    // every prediction as a scale `exp(strength * map)`: the cell RMS of the stride-2
    // paired cells (`persist fit`'s report) as the strength grows
    let mut sum = vec![0.0; np];
    let mut cnt = vec![0.0; np];
    for (r, _) in &maps {
        for p in 0..np {
            if r[p].is_finite() {
                sum[p] += r[p];
                cnt[p] += 1.0;
            }
        }
    }
    let mean: Vec<f64> = (0..np)
        .map(|p| {
            if cnt[p] > 0.0 {
                sum[p] / cnt[p]
            } else {
                f64::NAN
            }
        })
        .collect();
    let map: Vec<f64> = smooth(&mean, ny, nx, length_px)
        .into_iter()
        .map(|v| if v.is_finite() { v } else { 0.0 })
        .collect();
    let s2 = Samples::new(&seq, 2)
        .with_cells(eval::Cells::Illumination)
        .with_statistic(eval::CellStatistic::Paired);
    let np2 = s2.npix();
    let pr2 = eval::predict(&model, &seq, &s2, false).expect("predict");
    // demeaned: the level is the knots'; the map only moves pixels against each other
    let lit: Vec<f64> = mean.iter().copied().filter(|v| v.is_finite()).collect();
    let mu = map.iter().sum::<f64>() / map.len() as f64;
    let sd_map = (map.iter().map(|v| (v - mu).powi(2)).sum::<f64>() / map.len() as f64).sqrt();
    println!(
        "map: mean {mu:.3}, sd {sd_map:.3} ({} pixels with a ratio)",
        lit.len()
    );
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
                    level * q * (strength * (map[y * nx + x] - mu)).exp()
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

/// `R^2` of the least-squares line of `y` on `x` over the pixels where both are finite.
fn r2(x: &[f64], y: &[f64]) -> f64 {
    let pts: Vec<(f64, f64)> = x
        .iter()
        .zip(y)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| (*a, *b))
        .collect();
    let n = pts.len() as f64;
    if n < 3.0 {
        return f64::NAN;
    }
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in &pts {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx).powi(2);
        syy += (b - my).powi(2);
    }
    if sxx == 0.0 || syy == 0.0 {
        return 0.0;
    }
    sxy * sxy / (sxx * syy)
}

/// Three masked box passes of half-width `round(L/2)` (NaN = no value); NaN where no
/// value is within reach.
fn smooth(v: &[f64], ny: usize, nx: usize, length_px: f64) -> Vec<f64> {
    let h = (length_px / 2.0).round().max(1.0) as usize;
    let mut val: Vec<f64> = v
        .iter()
        .map(|x| if x.is_finite() { *x } else { 0.0 })
        .collect();
    let mut w: Vec<f64> = v
        .iter()
        .map(|x| f64::from(u8::from(x.is_finite())))
        .collect();
    for _ in 0..3 {
        val = blur(&val, ny, nx, h);
        w = blur(&w, ny, nx, h);
    }
    val.iter()
        .zip(&w)
        .map(|(a, b)| if *b > 1e-6 { a / b } else { f64::NAN })
        .collect()
}

fn blur(a: &[f64], ny: usize, nx: usize, h: usize) -> Vec<f64> {
    let mut b = vec![0.0; a.len()];
    for y in 0..ny {
        for x in 0..nx {
            let (x0, x1) = (x.saturating_sub(h), (x + h).min(nx - 1));
            b[y * nx + x] = (x0..=x1).map(|i| a[y * nx + i]).sum::<f64>() / (x1 - x0 + 1) as f64;
        }
    }
    let mut c = vec![0.0; a.len()];
    for y in 0..ny {
        let (y0, y1) = (y.saturating_sub(h), (y + h).min(ny - 1));
        for x in 0..nx {
            c[y * nx + x] = (y0..=y1).map(|i| b[i * nx + x]).sum::<f64>() / (y1 - y0 + 1) as f64;
        }
    }
    c
}
