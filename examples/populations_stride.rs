//! Where the residual of a campaign with hidden `populations` comes from (the
//! `populations` row of `examples/diagnose_matrix`). Under `--cell-statistic population
//! --background line`:
//!
//! 1. the cell RMS with the pixels sampled every 2, 4 and 8 pixels (two offsets each):
//!    if the residual is the cells' 95th percentiles moving together because
//!    neighbouring pixels share their traps (the truth's field), the excess over a
//!    campaign without the field falls as the samples grow apart;
//! 2. a per-pixel map learnt from the data: the first dark's log ratio of measured to
//!    predicted (`persist::diag::spatial::log_ratios`), of the first illumination or
//!    averaged over all, smoothed over `L_PX`, applied to the predictions as
//!    `exp(strength (M - mean M))` with the knots' level refitted on a grid, and the
//!    population's spread measured anew about it (the measured current divided by the
//!    map, [`PopulationSpread::measure`]), so that the reference follows the map.
//! 3. the stride-2 cells with each cell's `sigma_q` widened by its design effect for
//!    pixels whose spread is correlated as the truth's field is (`L_PX` as the
//!    simulator's `length_px`: three box passes of half-width `L/2`, a Gaussian of
//!    `sigma^2 = L (L + 2) / 4`; correlation `exp(-d^2 / (4 sigma^2))` at `d` pixels):
//!    `deff = 1 + mean over pairs of rho_ij s_i s_j / (sd_i sd_j) * (n - 1)`, from 20,000
//!    random pairs per cell, `s` the population part of each sample's spread and `sd`
//!    its whole ([`Samples::null_of`]). The RMS such a statistic would give, had the
//!    model said the pixels' spread is correlated over `L_PX`; and the score test of a
//!    correlated fraction `f` of that spread at this length (`deff(f) = 1 + f (deff -
//!    1)`, Gaussian cells): `sum (deff_c - 1) (z_c^2 - 1) / sqrt(2 sum (deff_c - 1)^2)`,
//!    standard normal when the cells' `z` are.
//!
//! 4. the design effect measured from the data alone (no kernel, no length): in each
//!    stride-2 cell, the samples standardised by their reference (`e = (d - mean) /
//!    sd`, [`Samples::null_of`]) and the indicator `J` of the cell's top 5 % of `e`;
//!    the correlation of `J` between pairs of samples of one cell, pooled over the
//!    cells by class (same exposure or not, distance rounded to a pixel, up to
//!    `MAX_LAG_PX`; the same pixel at two exposures is the class "other exposure,
//!    distance 0"); then per cell `deff = 1 + (2 / n) sum over its pairs of rho(class)`
//!    (the variance of a 95th percentile is that of the mean of its indicators), and
//!    the RMS of `z / sqrt(deff)`: with every class, with the same exposure's
//!    neighbours alone (the spatial part) and with the other exposures alone.
//!
//! ```sh
//! target/release/examples/populations_stride LAB_DIR MODEL.json [L_PX] [--measured-only]
//! ```
use persist::diag::data::{fluence, Background, PopulationSpread, Sequence};
use persist::diag::eval::{self, Samples};
use persist::diag::{spatial, spread};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    if a.len() < 3 {
        eprintln!("usage: populations_stride LAB_DIR MODEL.json [L_PX]");
        std::process::exit(2);
    }
    let seq = Sequence::load_with(Path::new(&a[1]), Background::Line).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let length_px: f64 = a
        .get(3)
        .filter(|s| !s.starts_with("--"))
        .map_or(8.0, |s| s.parse().expect("L_PX"));
    let measured_only = a.iter().any(|s| s == "--measured-only");
    let cells = |s: Samples| {
        s.with_cells(eval::Cells::Illumination)
            .with_statistic(eval::CellStatistic::Population)
    };
    if measured_only {
        let s0 = cells(Samples::new(&seq, 2));
        let pr = eval::predict(&model, &seq, &s0, false).expect("predict");
        measured_design_effect(&s0, &pr.current);
        return;
    }
    println!("stride  offset  cells  RMS");
    for stride in [2usize, 4, 8] {
        for off in [0usize, 1] {
            let pixels: Vec<(usize, usize)> = (0..seq.ny)
                .filter(|y| y % stride == off)
                .flat_map(|y| {
                    (0..seq.nx)
                        .filter(|x| x % stride == off)
                        .map(move |x| (y, x))
                })
                .collect();
            let s = cells(Samples::with_pixels(&seq, pixels, stride));
            let pr = eval::predict(&model, &seq, &s, false).expect("predict");
            let z = eval::cell_z(&s, &pr.current);
            println!("{stride:6}  {off:6}  {:5}  {:.3}", z.len(), eval::rms(&z));
        }
    }
    let s0 = cells(Samples::new(&seq, 2));
    let pr = eval::predict(&model, &seq, &s0, false).expect("predict");
    design_effect(&s0, &pr.current, length_px);
    measured_design_effect(&s0, &pr.current);
    let ratios = spatial::log_ratios(&seq, &model).expect("ratios");
    let Some(first) = ratios.first() else {
        return;
    };
    let a0 = seq.illuminations[0];
    let k = a0 + 1;
    let np = s0.npix();
    println!("map     L_px  strength  RMS    level");
    for (label, base) in [
        ("first", first.ratio.clone()),
        ("mean", spatial::mean_ratio(&ratios)),
    ] {
        let map = spatial::smooth(&base, length_px).mapv(|v| if v.is_finite() { v } else { 0.0 });
        let mu = map.iter().sum::<f64>() / map.len() as f64;
        for strength in [0.0, 0.5, 1.0, 2.0] {
            let scale = map.mapv(|m| (strength * (m - mu)).exp());
            let spread = PopulationSpread::measure(
                &fluence(&seq.exposures[a0]),
                &(&seq.measured(k) / &scale),
                seq.noise_e_per_s[k],
                seq.shot_var_per_e_per_s(k),
            );
            let mut s = s0.clone();
            for i in 0..s.len() {
                s.spread_rel[i] = spread.at(s.fluence_e[i]);
            }
            let mut best = (f64::INFINITY, 0.0);
            for j in 0..=40 {
                let level = 0.8 + 0.4 * f64::from(j) / 40.0;
                let scaled: Vec<f64> = pr
                    .current
                    .iter()
                    .enumerate()
                    .map(|(i, q)| {
                        let (y, x) = s.pixels[i % np];
                        level * q * scale[[y, x]]
                    })
                    .collect();
                let r = eval::rms(&eval::cell_z(&s, &scaled));
                if r < best.0 {
                    best = (r, level);
                }
            }
            println!(
                "{label:6}  {length_px:4}  {strength:8}  {:.3}  {:.3}",
                best.0, best.1
            );
        }
    }
}

/// Section 3 (module docs), on the stride-2 population cells `s` and their predictions.
fn design_effect(s: &Samples, pred: &[f64], length_px: f64) {
    let h = (length_px / 2.0).round().max(1.0);
    // one box pass of half-width h has variance h (h + 1) / 3; three passes
    let var = h * (h + 1.0);
    let g = cell_members(s, pred);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
    let (mut plain, mut widened, mut deffs) = (Vec::new(), Vec::new(), Vec::new());
    let (mut num, mut den) = (0.0, 0.0);
    for members in g.values() {
        let meas: Vec<f64> = members.iter().map(|&i| s.measured[i]).collect();
        let p: Vec<f64> = members.iter().map(|&i| pred[i]).collect();
        let nulls: Vec<(f64, f64, f64)> = members
            .iter()
            .zip(&p)
            .map(|(&i, &q)| s.null_of(i, q))
            .collect();
        let offset: Vec<f64> = nulls.iter().map(|n| n.0).collect();
        let sd: Vec<f64> = nulls.iter().map(|n| n.1).collect();
        let mut noise: Vec<f64> = nulls.iter().map(|n| n.2).collect();
        noise.sort_by(f64::total_cmp);
        let Some(st) =
            eval::cell_stat_null(s.statistic, &meas, &p, &offset, &sd, noise[noise.len() / 2])
        else {
            continue;
        };
        let n = members.len();
        let mut acc = 0.0;
        let pairs = 20_000;
        for _ in 0..pairs {
            let a = rng.random_range(0..n);
            let mut b = rng.random_range(0..n - 1);
            if b >= a {
                b += 1;
            }
            let (ya, xa) = s.pixels[members[a] % s.npix()];
            let (yb, xb) = s.pixels[members[b] % s.npix()];
            let d2 = (ya as f64 - yb as f64).powi(2) + (xa as f64 - xb as f64).powi(2);
            let pop = |k: usize| (-offset[k] / 1.645) / sd[k].max(1e-300);
            acc += (-d2 / (4.0 * var)).exp() * pop(a) * pop(b);
        }
        let deff = 1.0 + acc / f64::from(pairs) * (n - 1) as f64;
        // the score of a correlated fraction f at this length, deff(f) = 1 + f (deff - 1)
        num += (deff - 1.0) * (st.z * st.z - 1.0);
        den += 2.0 * (deff - 1.0).powi(2);
        plain.push(st.z);
        widened.push(st.z / deff.sqrt());
        deffs.push(deff);
    }
    let rms = rms_of;
    deffs.sort_by(f64::total_cmp);
    println!(
        "design effect, L {length_px} px: {} cells, RMS {:.3} -> {:.3}; deff median {:.2}, \
         10-90 % {:.2}-{:.2}; score of a correlated fraction (N(0,1) under the null) {:.1}",
        plain.len(),
        rms(&plain),
        rms(&widened),
        deffs[deffs.len() / 2],
        deffs[deffs.len() / 10],
        deffs[deffs.len() * 9 / 10],
        num / den.sqrt()
    );
}

/// The samples of each cell of `s` with a finite measurement and prediction.
fn cell_members(s: &Samples, pred: &[f64]) -> std::collections::BTreeMap<Vec<i64>, Vec<usize>> {
    let mut g: std::collections::BTreeMap<Vec<i64>, Vec<usize>> = Default::default();
    for (i, q) in pred.iter().enumerate().take(s.len()) {
        if s.measured[i].is_finite() && q.is_finite() {
            if let Some(k) = eval::key_of(s, s.cells.keys(), i) {
                g.entry(k).or_default().push(i);
            }
        }
    }
    g
}

/// Section 4 (module docs), on the stride-2 population cells `s` and their predictions.
fn measured_design_effect(s: &Samples, pred: &[f64]) {
    let pc = spread::pair_correlation(s, pred);
    println!("indicator correlation (centred, pairs): distance px, same exposure, other exposures");
    for d in 1..=spread::MAX_LAG_PX {
        let (a, b) = (pc.same_exposure_pairs[d], pc.other_exposures_pairs[d]);
        if a + b > 0 {
            println!(
                "  {d:3}  {:+.4} ({a:8})  {:+.4} ({b:8})",
                pc.same_exposure[d], pc.other_exposures[d]
            );
        }
    }
    let z = eval::cell_z(s, pred);
    let c = spread::check(s, pred, &z);
    if let Some(kf) = c.kernel {
        println!(
            "kernel: corr {:.4} +- {:.4}, length {:.2} +- {:.2} px, level {:+.4}, weighted RMS \
             {:.2}, converged {}",
            kf.kernel.corr,
            kf.sigma_corr,
            kf.kernel.length_px,
            kf.sigma_length_px,
            kf.level,
            kf.rms_weighted,
            kf.converged
        );
    }
    println!(
        "design effect of the fitted kernel: {} cells, RMS {:.3} -> {:.3}; deff median {:.2}",
        z.len(),
        eval::rms(&z),
        c.residual_rms_normalised_correlated,
        c.design_effect_median
    );
    let (t, n) = (c.score, c.score_pairs);
    // the same score on replicas drawn from the reference (independent samples)
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    let mut rep = s.clone();
    let ts: Vec<f64> = (0..20)
        .map(|_| {
            for (i, &q) in pred.iter().enumerate().take(s.len()) {
                if s.measured[i].is_finite() && q.is_finite() {
                    let (o, sd, _) = s.null_of(i, q);
                    rep.measured[i] = q + o + sd * rng.sample::<f64, _>(StandardNormal);
                }
            }
            spread::score(&rep, pred, spread::SCORE_LENGTH_PX).0
        })
        .collect();
    println!(
        "score T at {} px: {t:.2} over {n} pairs; 20 replicas from the reference: mean {:.2}, \
         sd {:.2}, max {:.2}",
        spread::SCORE_LENGTH_PX,
        ts.iter().sum::<f64>() / ts.len() as f64,
        (ts.iter().map(|v| v * v).sum::<f64>() / ts.len() as f64
            - (ts.iter().sum::<f64>() / ts.len() as f64).powi(2))
        .sqrt(),
        ts.iter().copied().fold(f64::NEG_INFINITY, f64::max)
    );
}

fn rms_of(v: &[f64]) -> f64 {
    (v.iter().map(|z| z * z).sum::<f64>() / v.len().max(1) as f64).sqrt()
}
