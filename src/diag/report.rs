//! The self-contained HTML report of `persist compare`: inline SVG plots (plotters' SVG
//! backend, no fonts needed), every model of a figure side by side, no external
//! resource, no script.

use super::compare::{Summary, BREAKDOWNS};
use crate::error::{Error, ErrorKind, Result};
use plotters::prelude::*;

fn perr<E: std::fmt::Display>(e: E) -> Error {
    Error::new(ErrorKind::Io, format!("plot: {e}"))
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Heat map of z over fluence x time. Per-illumination cells (`--cells illumination`)
/// share a fluence x time square: the one with the largest |z| is drawn.
fn map_svg(m: &super::compare::ModelSummary) -> Result<String> {
    if m.map.is_empty() {
        return Ok(String::new());
    }
    let mut shown: std::collections::BTreeMap<(u64, u64), &super::compare::Cell> =
        Default::default();
    for c in &m.map {
        let e = shown
            .entry((c.place.fluence_e.to_bits(), c.place.time_s.to_bits()))
            .or_insert(c);
        if c.stat.z.abs() > e.stat.z.abs() {
            *e = c;
        }
    }
    let (fx0, fx1) = m.map.iter().fold((f64::MAX, f64::MIN), |a, c| {
        (
            a.0.min(c.place.fluence_e.log10()),
            a.1.max(c.place.fluence_e.log10() + 0.2),
        )
    });
    let (ty0, ty1) = m.map.iter().fold((f64::MAX, f64::MIN), |a, c| {
        (
            a.0.min(c.place.time_s.log10()),
            a.1.max(c.place.time_s.log10() + 0.25),
        )
    });
    heat_svg(
        (420, 320),
        "z: fluence x time",
        (fx0..fx1, ty0..ty1),
        ("log10 fluence (e-)", "log10 t (s)"),
        shown.values().map(|c| {
            let (x, y) = (c.place.fluence_e.log10(), c.place.time_s.log10());
            ([(x, y), (x + 0.2, y + 0.25)], diverging(c.stat.z / 10.0))
        }),
    )
}

/// A heat map: `rects` (corners, colour) on axes `ranges` (x, y; a reversed range runs
/// down or left), described by `desc` (x, y).
fn heat_svg(
    size: (u32, u32),
    caption: &str,
    ranges: (std::ops::Range<f64>, std::ops::Range<f64>),
    desc: (&str, &str),
    rects: impl Iterator<Item = ([(f64, f64); 2], RGBColor)>,
) -> Result<String> {
    crate::plot::ensure_font();
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, size).into_drawing_area();
        root.fill(&WHITE).map_err(perr)?;
        let mut ch = ChartBuilder::on(&root)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(45)
            .caption(caption, ("sans-serif", 16))
            .build_cartesian_2d(ranges.0, ranges.1)
            .map_err(perr)?;
        ch.configure_mesh()
            .x_desc(desc.0)
            .y_desc(desc.1)
            .disable_mesh()
            .draw()
            .map_err(perr)?;
        ch.draw_series(rects.map(|(corners, col)| Rectangle::new(corners, col.filled())))
            .map_err(perr)?;
        root.present().map_err(perr)?;
    }
    Ok(s)
}

/// White at 0, red towards +1, blue towards -1 (`t` clamped to [-1, 1]).
fn diverging(t: f64) -> RGBColor {
    let t = t.clamp(-1.0, 1.0);
    if t >= 0.0 {
        RGBColor(255, (255.0 * (1.0 - t)) as u8, (255.0 * (1.0 - t)) as u8)
    } else {
        RGBColor((255.0 * (1.0 + t)) as u8, (255.0 * (1.0 + t)) as u8, 255)
    }
}

/// Where the residual field is on the array: the spatial check's map
/// ([`crate::diag::spatial::FieldMap`]), `ln(measured / predicted)` relative to its
/// fluence bin, red where the model under-predicts; colour full at +-0.5. Empty
/// without the check (one illumination).
fn field_svg(m: &super::compare::ModelSummary) -> Result<String> {
    let Some(c) = &m.spatial else {
        return Ok(String::new());
    };
    let f = &c.field;
    let b = f.block_px as f64;
    let (w, h) = (f.cols as f64 * b, f.rows as f64 * b);
    heat_svg(
        (420, 400),
        &format!(
            "ln(measured/predicted), {:.0} px; R^2 {:.2}{}",
            c.best_length_px,
            c.best_r2,
            if c.coherent { ": a field" } else { "" }
        ),
        (0.0..w, h..0.0),
        ("x (px)", "y (px)"),
        f.log_ratio.iter().enumerate().filter_map(|(i, v)| {
            let (r, col) = ((i / f.cols) as f64, (i % f.cols) as f64);
            v.map(|v| {
                (
                    [(col * b, r * b), ((col + 1.0) * b, (r + 1.0) * b)],
                    diverging(v / 0.5),
                )
            })
        }),
    )
}

/// z against one covariate.
fn line_svg(m: &super::compare::ModelSummary, cov: &str) -> Result<String> {
    let Some(bins) = m.breakdown.get(cov).filter(|b| !b.is_empty()) else {
        return Ok("<p>no data</p>".into());
    };
    let logx = matches!(cov, "time" | "fluence" | "neighbour_excess_fluence");
    let xs: Vec<f64> = bins
        .iter()
        .map(|b| {
            if logx {
                b.value.max(1.0).log10()
            } else {
                b.value
            }
        })
        .collect();
    let (x0, x1) = xs
        .iter()
        .fold((f64::MAX, f64::MIN), |a, v| (a.0.min(*v), a.1.max(*v)));
    let (y0, y1) = bins.iter().fold((-1.0f64, 1.0f64), |a, b| {
        (a.0.min(b.stat.z.max(-1e3)), a.1.max(b.stat.z.min(1e3)))
    });
    let pad = ((x1 - x0).abs() * 0.05).max(0.5);
    crate::plot::ensure_font();
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, (420, 260)).into_drawing_area();
        root.fill(&WHITE).map_err(perr)?;
        let mut ch = ChartBuilder::on(&root)
            .margin(10)
            .x_label_area_size(35)
            .y_label_area_size(45)
            .caption(format!("z by {cov}"), ("sans-serif", 16))
            .build_cartesian_2d((x0 - pad)..(x1 + pad), (y0 * 1.1)..(y1 * 1.1))
            .map_err(perr)?;
        ch.configure_mesh()
            .x_desc(if logx {
                format!("log10 {cov}")
            } else {
                cov.to_string()
            })
            .y_desc("z")
            .draw()
            .map_err(perr)?;
        let pts: Vec<(f64, f64)> = xs
            .iter()
            .zip(bins)
            .map(|(x, b)| (*x, b.stat.z.clamp(-1e3, 1e3)))
            .collect();
        ch.draw_series(LineSeries::new(pts.clone(), &BLUE))
            .map_err(perr)?;
        ch.draw_series(pts.iter().map(|p| Circle::new(*p, 3, BLUE.filled())))
            .map_err(perr)?;
        ch.draw_series(LineSeries::new(
            vec![(x0 - pad, 0.0), (x1 + pad, 0.0)],
            &BLACK,
        ))
        .map_err(perr)?;
        root.present().map_err(perr)?;
    }
    Ok(s)
}

/// The cells with the most missed, then the most over-flagged, samples at 0.1 e-/s
/// (`flag_quality_by_cell`), ten of each.
fn flag_cells_html(m: &super::compare::ModelSummary) -> Result<String> {
    let Some(cells) = m.flag_quality_by_cell.get("0.1") else {
        return Ok("<p>-</p>".into());
    };
    let mut h = String::new();
    type Count = fn(&crate::diag::eval::FlagQuality) -> usize;
    let parts: [(&str, Count); 2] = [
        ("most missed", |q| q.missed),
        ("most over-flagged", |q| q.over_flagged),
    ];
    for (title, count) in parts {
        let mut top: Vec<_> = cells.iter().filter(|c| count(&c.quality) > 0).collect();
        // most first; the map's order among equals (a stable sort)
        top.sort_by_key(|c| std::cmp::Reverse(count(&c.quality)));
        let total: usize = top.iter().map(|c| count(&c.quality)).sum();
        h += &format!("<p>{title}: {total} samples in {} cells</p>", top.len());
        if top.is_empty() {
            continue;
        }
        h += "<table><tr><th>illumination</th><th>fluence (e-)</th><th>time (s)</th>\
<th>samples</th><th>measured above</th><th>flagged</th><th>missed</th><th>over-flagged</th></tr>";
        for c in top.iter().take(10) {
            let q = &c.quality;
            h += &format!(
                "<tr><td>{}{}</td><td>{:.3e}</td><td>{:.0}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
                c.place.illumination.map_or("-".into(), |i| i.to_string()),
                if c.place.next_to_brighter { " (next to brighter)" } else { "" },
                c.place.fluence_e,
                c.place.time_s,
                q.samples,
                q.measured_above,
                q.flagged,
                q.missed,
                q.over_flagged
            );
        }
        h += "</table>";
    }
    Ok(h)
}

pub fn html(sum: &Summary) -> Result<String> {
    let mut h = String::from(
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>persist compare</title>\
<style>body{font-family:sans-serif;margin:1em}.row{display:flex;flex-wrap:wrap;gap:1em}\
.col{flex:1;min-width:420px}table{border-collapse:collapse}td,th{border:1px solid #999;padding:2px 6px}</style>\
</head><body>",
    );
    h += &format!(
        "<h1>persist compare</h1><p>input {} : {} exposures compared, {} pixels sampled (stride {}), {} samples</p>",
        esc(&sum.input),
        sum.exposures_compared,
        sum.pixels_sampled,
        sum.pixel_stride,
        sum.samples
    );
    let touched = sum.touched.as_ref();
    if let Some(t) = touched {
        h += &format!(
            "<p>touched pixels: {} of {} sampled ({}; baseline {})</p>",
            t.touched_pixels,
            t.pixels_sampled,
            esc(&t.definition),
            esc(&t.baseline)
        );
    }
    h += "<h2>Models</h2><table><tr><th>model</th><th>effects</th><th>residual RMS (normalised)</th><th>cells</th><th>missed @0.1</th><th>over @0.1</th><th>missed @0.01</th><th>over @0.01</th>";
    if touched.is_some() {
        h += "<th>missed @0.1 of touched</th><th>over @0.1 of touched</th><th>missed @0.01 of touched</th>";
    }
    h += "<th>spatial coherence (R^2, best smoothing)</th></tr>";
    for m in &sum.models {
        let q = |t: &str, f: fn(&crate::diag::eval::FlagQuality) -> f64| {
            m.flag_quality
                .get(t)
                .map_or("-".to_string(), |q| format!("{:.4}", f(q)))
        };
        h += &format!(
            "<tr><td>{}</td><td>{}</td><td>{:.3}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}</td>",
            esc(&m.path),
            esc(&m.effects.join(", ")),
            m.residual_rms_normalised,
            m.cells,
            q("0.1", |q| q.missed_flag_fraction),
            q("0.1", |q| q.over_flag_fraction),
            q("0.01", |q| q.missed_flag_fraction),
            q("0.01", |q| q.over_flag_fraction),
        );
        if touched.is_some() {
            let t = |th: &str, f: fn(&super::compare::TouchedQuality) -> f64| {
                m.flag_quality_touched
                    .get(th)
                    .map_or("-".to_string(), |q| format!("{:.4}", f(q)))
            };
            h += &format!(
                "<td>{}</td><td>{}</td><td>{}</td>",
                t("0.1", |q| q.missed_flag_fraction_touched),
                t("0.1", |q| q.over_flag_fraction_touched),
                t("0.01", |q| q.missed_flag_fraction_touched),
            );
        }
        h += &format!(
            "<td>{}</td></tr>",
            m.spatial.as_ref().map_or("-".to_string(), |c| format!(
                "{:.2} at {:.0} px{}",
                c.best_r2,
                c.best_length_px,
                if c.coherent {
                    ": a field shared by neighbours"
                } else {
                    ""
                }
            ))
        );
    }
    h += "</table>";
    let mut figure =
        |title: &str, f: &dyn Fn(&super::compare::ModelSummary) -> Result<String>| -> Result<()> {
            h += &format!("<h2>{}</h2><div class=\"row\">", esc(title));
            for m in &sum.models {
                h += &format!(
                    "<div class=\"col\"><h3>{}</h3>{}</div>",
                    esc(&m.path),
                    f(m)?
                );
            }
            h += "</div>";
            Ok(())
        };
    figure(
        "Normalised residual map: fluence bin x time since illumination",
        &map_svg,
    )?;
    for c in BREAKDOWNS {
        figure(&format!("Normalised residual by {c}"), &|m| line_svg(m, c))?;
    }
    figure(
        "Where the flags at 0.1 e-/s fail: cells of the map by missed and over-flagged samples",
        &flag_cells_html,
    )?;
    if sum.models.iter().any(|m| m.spatial.is_some()) {
        figure(
            "Where the residual is on the array (spatial check; red: measured above predicted)",
            &field_svg,
        )?;
    }
    h += "<h2>Definitions</h2><dl>";
    for (k, v) in &sum.definitions {
        h += &format!("<dt>{}</dt><dd>{}</dd>", esc(k), esc(v));
    }
    h += "</dl></body></html>\n";
    Ok(h)
}
