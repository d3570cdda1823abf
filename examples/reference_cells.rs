//! Per cell of the pixel reference (`persist diagnose`'s "pixel reference" line,
//! `persist::diag::base::predict_scaled`) with `diagnose`'s default sampling: n, the
//! samples' noise (RMS of `sigma_i sqrt(1 - h_i)`), the median of the residuals
//! `d = measured - reference`, their spread (1.4826 MAD) over the noise, the median
//! prediction, and the cell's `z`. Sorted by |z|, largest first.
//!
//! ```sh
//! target/release/examples/reference_cells LAB_DIR MODEL.json [ROWS]
//! ```
//!
//! `XP_CELL="[EVENT, FLUENCE BIN, TIME BIN]"` also prints every sample of that cell:
//! its pixel's fluence in each illumination (`S`: flagged `OVERFLOW`), the measured
//! and reference currents, the noise and the leverage.
use persist::diag::config::Config;
use persist::diag::data::Sequence;
use persist::diag::eval::{self, Samples};
use persist::stats::median;
use std::path::Path;

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let seq = Sequence::load(Path::new(&a[1])).expect("sequence");
    let model = persist::model_file::load(Path::new(&a[2])).expect("model");
    let rows: usize = a.get(3).map_or(25, |r| r.parse().expect("rows"));
    let cfg = Config::default();
    let mut s = Samples::random(&seq, cfg.pixels, cfg.seed)
        .with_cells(cfg.cells)
        .with_statistic(cfg.cell_statistic);
    let model = if std::env::var("XP_MODEL").is_ok() {
        model
    } else {
        persist::diag::reference::describe(&model, &seq, &cfg).expect("description")
    };
    let base = eval::predict(&model, &seq, &s, false).expect("predict");
    let view = persist::diag::base::View::of_model(&model, &seq);
    let response = persist::model::response::Response::new(&model.amplitude_knots);
    // the noise as `diagnose` scales it
    persist::diag::base::scale_noise(&seq, &view, &mut s, &base.current, &response);
    let r = persist::diag::base::predict_scaled(&seq, &view, &s, &base.current, &response);
    let cells = r.cells(&s);
    let mut groups: std::collections::BTreeMap<Vec<i64>, Vec<usize>> = Default::default();
    for i in 0..s.len() {
        if s.measured[i].is_finite() && r.prediction[i].is_finite() {
            if let Some(key) = eval::key_of(&s, s.cells.keys(), i) {
                groups.entry(key).or_default().push(i);
            }
        }
    }
    let mut out = Vec::new();
    for (key, g) in &cells {
        let Some(members) = groups.get(key) else {
            continue;
        };
        let d: Vec<f64> = members
            .iter()
            .map(|&i| s.measured[i] - r.prediction[i])
            .collect();
        let sd: Vec<f64> = members
            .iter()
            .map(|&i| r.sigma[i] * (1.0 - r.leverage[i]).max(0.0).sqrt())
            .collect();
        let norm: Vec<f64> = d.iter().zip(&sd).map(|(d, s)| d / s).collect();
        let mn = median(&norm);
        let dev: Vec<f64> = norm.iter().map(|x| (x - mn).abs()).collect();
        let pred: Vec<f64> = members.iter().map(|&i| r.prediction[i]).collect();
        let sig = (sd.iter().map(|v| v * v).sum::<f64>() / sd.len() as f64).sqrt();
        let p95 = persist::stats::quantile(&norm, 0.95);
        let tail = norm.iter().filter(|v| v.abs() > 4.0).count() as f64 / norm.len() as f64;
        out.push((
            key.clone(),
            g.n,
            sig,
            median(&d),
            1.4826 * median(&dev),
            median(&pred),
            g.z,
            p95,
            tail,
        ));
    }
    out.sort_by(|a, b| b.6.abs().total_cmp(&a.6.abs()));
    println!("key                 n      sigma    med(d)   sd(d/s)  med(pred)  z   P95(d/s) share|d/s|>4");
    for (k, n, sig, md, sdn, mp, z, p95, tail) in out.iter().take(rows) {
        println!(
            "{:18} {:6} {:8.4} {:9.5} {:7.3} {:9.4} {:7.2} {:6.2} {:6.3}",
            format!("{k:?}"),
            n,
            sig,
            md,
            sdn,
            mp,
            z,
            p95,
            tail
        );
    }
    if let Ok(k) = std::env::var("XP_CELL") {
        for (key, m) in &groups {
            if format!("{key:?}") == k {
                for &i in m {
                    let (y, x) = s.pixels[i % s.npix()];
                    let hist: Vec<String> = seq
                        .illuminations
                        .iter()
                        .map(|&a| {
                            let e = &seq.exposures[a];
                            let f = persist::diag::data::fluence(e)[(y, x)];
                            let o = e.flags[(y, x)] & persist::flags::bits::OVERFLOW != 0;
                            format!("{a}:{:.0}k{}", f / 1e3, if o { "S" } else { "" })
                        })
                        .collect();
                    println!("{}", hist.join(" "));
                    println!("i {i} px {:?} meas {:.4} pred {:.4} sigma {:.4} h {:.3} noise {:.4} shot {:.5}", s.pixels[i % s.npix()], s.measured[i], r.prediction[i], r.sigma[i], r.leverage[i], s.noise[i / s.npix()], s.shot_var_per_e_per_s[i / s.npix()]);
                }
            }
        }
    }
    println!("rms {:.2} over {} cells", eval::rms(&cells), cells.len());
}
