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
//! target/release/examples/populations_map LAB_DIR MODEL.json [L_PX]
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
    let ratio = |row: usize| -> Vec<f64> {
        (0..np)
            .map(|p| {
                let (m, q) = (s.measured[row * np + p], pr.current[row * np + p]);
                if q > MIN_PRED_E_PER_S && m > 0.0 && m.is_finite() {
                    (m / q).ln()
                } else {
                    f64::NAN
                }
            })
            .collect()
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
