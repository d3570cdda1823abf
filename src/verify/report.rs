//! The self-contained HTML page of `persist verify`: per fluence bin the measured decay
//! (points with 95 % intervals), the prediction and, when known, the truth, on log-log
//! axes (inline SVG, plotters' SVG backend, no external resource); then the checks and the
//! flags table.

use super::{DecayBin, Report};
use crate::error::{Error, ErrorKind, Result};
use plotters::prelude::*;
use std::fmt::Write as _;

fn perr<E: std::fmt::Display>(e: E) -> Error {
    Error::new(ErrorKind::Io, format!("plot: {e}"))
}

/// The decay plot of one fluence bin; `None` when its values give no finite axis range.
fn decay_svg(bins: &[&DecayBin]) -> Result<Option<String>> {
    let lg = |v: f64| v.max(1e-4).log10();
    let xs: Vec<f64> = bins.iter().map(|b| b.mean_time_s.log10()).collect();
    let ys = bins.iter().flat_map(|b| {
        [
            b.measured.mean - 1.96 * b.measured.se,
            b.measured.mean + 1.96 * b.measured.se,
            b.predicted.mean,
        ]
    });
    let (x0, x1) = xs
        .iter()
        .fold((f64::MAX, f64::MIN), |a, v| (a.0.min(*v), a.1.max(*v)));
    let (y0, y1) = ys.fold((f64::MAX, f64::MIN), |a, v| {
        (a.0.min(lg(v)), a.1.max(lg(v)))
    });
    // (a NaN is skipped by min and max: all NaN leaves the folds' starting values)
    let finite = [x0, x1, y0, y1]
        .iter()
        .all(|v| v.is_finite() && v.abs() < 1e6);
    if !(finite && x0 <= x1 && y0 <= y1) {
        return Ok(None);
    }
    crate::plot::ensure_font();
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, (460, 300)).into_drawing_area();
        root.fill(&WHITE).map_err(perr)?;
        let b0 = bins[0];
        let mut ch = ChartBuilder::on(&root)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(50)
            .caption(
                format!(
                    "fluence {:.1e} - {:.1e} e-",
                    b0.fluence_lo_e, b0.fluence_hi_e
                ),
                ("sans-serif", 15),
            )
            .build_cartesian_2d((x0 - 0.2)..(x1 + 0.2), (y0 - 0.2)..(y1 + 0.2))
            .map_err(perr)?;
        ch.configure_mesh()
            .x_desc("log10 time since the event, s")
            .y_desc("log10 current, e-/s")
            .draw()
            .map_err(perr)?;
        let pred: Vec<(f64, f64)> = xs
            .iter()
            .zip(bins)
            .map(|(x, b)| (*x, lg(b.predicted.mean)))
            .collect();
        ch.draw_series(LineSeries::new(pred, &RED))
            .map_err(perr)?
            .label("predicted")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 15, y)], RED));
        if bins.iter().all(|b| b.truth.is_some()) {
            let tr: Vec<(f64, f64)> = xs
                .iter()
                .zip(bins)
                .filter_map(|(x, b)| b.truth.map(|t| (*x, lg(t.mean))))
                .collect();
            ch.draw_series(LineSeries::new(tr, &GREEN))
                .map_err(perr)?
                .label("truth")
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 15, y)], GREEN));
        }
        for (x, b) in xs.iter().zip(bins) {
            let (lo, hi) = (
                b.measured.mean - 1.96 * b.measured.se,
                b.measured.mean + 1.96 * b.measured.se,
            );
            ch.draw_series(std::iter::once(PathElement::new(
                vec![(*x, lg(lo)), (*x, lg(hi))],
                BLUE,
            )))
            .map_err(perr)?;
        }
        ch.draw_series(
            xs.iter()
                .zip(bins)
                .map(|(x, b)| Circle::new((*x, lg(b.measured.mean)), 3, BLUE.filled())),
        )
        .map_err(perr)?
        .label("measured (95 %)")
        .legend(|(x, y)| Circle::new((x + 7, y), 3, BLUE.filled()));
        ch.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(perr)?;
        root.present().map_err(perr)?;
    }
    Ok(Some(s))
}

/// The page.
pub fn html(r: &Report) -> Result<String> {
    let mut h = String::from(
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>persist verify</title>\
         <style>body{font-family:sans-serif;max-width:1000px;margin:auto}\
         table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}\
         svg{display:inline-block}</style></head><body><h1>Persistence measured in flight</h1>",
    );
    let c = &r.checks;
    let _ = write!(
        h,
        "<p>{} exposures of detector(s) {:?}; {} events; {} samples ({} rejected as sources in the \
         pixel, {} without a sky estimate); {} unreadable file(s).</p>\
         <h2>Checks</h2><ul>\
         <li>decay: predicted minus measured log-log slope {:.3} &plusmn; {:.3}: <b>{}</b></li>\
         <li>margin (prediction over the measured 95th percentile of the first-exposure response): \
         {:.2} (95 %: {:.2} - {:.2}): <b>{}</b></li>",
        r.exposures,
        r.detectors,
        r.events,
        r.samples,
        r.rejected_as_sources,
        r.without_sky,
        r.errors.len(),
        c.slope_difference.mean,
        c.slope_difference.se,
        if c.decay_agrees { "agrees" } else { "disagrees" },
        c.margin.0,
        c.margin.1,
        c.margin.2,
        c.margin_verdict,
    );
    if let Some((inside, n)) = c.truth_inside {
        let _ = write!(
            h,
            "<li>truth inside the measured 95 % interval in {inside} of {n} bins</li>"
        );
    }
    h.push_str("</ul><h2>Decay by fluence</h2>");
    let mut i = 0;
    while i < r.decay.len() {
        let f = r.decay[i].fluence_lo_e;
        let group: Vec<&DecayBin> = r.decay[i..]
            .iter()
            .take_while(|b| b.fluence_lo_e == f)
            .collect();
        i += group.len();
        match decay_svg(&group)? {
            Some(svg) => h.push_str(&svg),
            None => {
                let _ = write!(
                    h,
                    "<p>fluence {f:.1e} e-: no finite measured means to plot.</p>"
                );
            }
        }
    }
    h.push_str(
        "<h2>Flags</h2><table><tr><th>time since event, s</th><th>flagged</th><th>samples</th>\
         <th>measured excess, e-/s</th><th>truth, e-/s</th><th>measured above threshold (2 sigma)</th></tr>",
    );
    for b in &r.flags {
        let _ = write!(
            h,
            "<tr><td>{:.0} - {:.0}</td><td>{}</td><td>{}</td><td>{:.4} &plusmn; {:.4}</td><td>{}</td><td>{:.3}</td></tr>",
            b.time_lo_s,
            b.time_hi_s,
            if b.flagged { "yes" } else { "no" },
            b.samples,
            b.measured.mean,
            b.measured.se,
            b.truth.map_or("-".into(), |t| format!("{:.4}", t.mean)),
            b.above_threshold_fraction,
        );
    }
    h.push_str("</table>");
    transients_html(&mut h, &r.transients);
    for e in &r.errors {
        let _ = write!(
            h,
            "<p>unreadable: {} ({})</p>",
            e.file.display(),
            esc(&e.reason)
        );
    }
    h.push_str("</body></html>\n");
    Ok(h)
}

/// The transient section: the rule, then the decay by time since the hit.
fn transients_html(h: &mut String, t: &super::transient::TransientReport) {
    let f = &t.first;
    let _ = write!(
        h,
        "<h2>Cosmic-ray hits</h2><p>{} hits followed, {} samples ({} rejected as sources). \
         First exposure after a hit, measured / predicted: median {}, {:.0}th percentile {} \
         over {} hits{}.</p><p>Transient rule: {}. Without a rule measured in flight, the \
         exposure after a hit is flagged whatever the prediction.</p>\
         <table><tr><th>time since hit, s</th><th>hits</th><th>samples</th>\
         <th>measured excess, e-/s</th><th>predicted, e-/s</th><th>truth, e-/s</th></tr>",
        t.hits,
        t.samples,
        t.rejected_as_sources,
        f.median_ratio.map_or("-".into(), |v| format!("{v:.4}")),
        100.0 * f.quantile,
        f.ratio.map_or("-".into(), |(q, lo, hi)| format!(
            "{q:.4} (95 %: {lo:.4} - {hi:.4})"
        )),
        f.events,
        f.true_ratio
            .map_or(String::new(), |v| format!(" (truth: {v:.4})")),
        esc(&t.rule),
    );
    for b in &t.decay {
        let _ = write!(
            h,
            "<tr><td>{:.0} - {:.0}</td><td>{}</td><td>{}</td><td>{:.4} &plusmn; {:.4}</td>\
             <td>{:.4}</td><td>{}</td></tr>",
            b.time_lo_s,
            b.time_hi_s,
            b.events,
            b.samples,
            b.measured.mean,
            b.measured.se,
            b.predicted.mean,
            b.truth.map_or("-".into(), |t| format!("{:.4}", t.mean)),
        );
    }
    h.push_str("</table>");
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}
