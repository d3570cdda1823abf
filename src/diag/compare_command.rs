//! `persist compare`: the comparison of models on one sequence ([`super::compare`]),
//! written as `summary.json` and `report.html` ([`super::report`]), and the lines the
//! command prints. Apart from [`super::compare`] so that the report, which renders the
//! comparison's types, and the comparison do not import each other.

use super::compare::{definitions, summarise_touched, touched_pixels, Options, Summary, STRIDE};
use super::config::Config;
use super::data::Sequence;
use super::eval::Samples;
use super::finding::PixelReference;
use crate::error::{Error, ErrorKind, Result};
use crate::model::params::ModelParams;
use std::path::Path;

/// `persist compare`.
pub fn run(input: &Path, models: &[std::path::PathBuf], out: &Path) -> Result<String> {
    run_with(input, models, out, &Options::default())
}

/// `persist compare` with [`Options`].
/// Why a sequence gives `compare` nothing to compare.
const NOTHING_AFTER_AN_ILLUMINATION: &str =
    "no exposure follows an illumination: compare needs a laboratory sequence \
     (illuminated exposures, which carry `t_illuminated_s`, each followed by darks); \
     on sky data every exposure is an illumination";

pub fn run_with(
    input: &Path,
    models: &[std::path::PathBuf],
    out: &Path,
    opts: &Options,
) -> Result<String> {
    let seq = Sequence::load_with(input, opts.background)?;
    let samples = Samples::new(&seq, STRIDE)
        .with_cells(opts.cells)
        .with_statistic(opts.cell_statistic);
    if samples.exposures.is_empty() {
        return Err(Error::invalid("t_illuminated_s", NOTHING_AFTER_AN_ILLUMINATION).path(input));
    }
    let mut loaded = Vec::new();
    for m in models {
        loaded.push((m.display().to_string(), crate::model_file::load(m)?));
    }
    let touched = match &opts.touched_baseline {
        Some(b) => Some(touched_pixels(
            &seq,
            &samples,
            input,
            b,
            opts.touched_min_e_per_s,
        )?),
        None => None,
    };
    let mut ms = summarise_touched(
        &seq,
        &samples,
        &loaded,
        touched.as_ref().map(|t| t.0.as_slice()),
    )?;
    let reference_samples = diagnose_samples(&seq, opts);
    for (m, (_, params)) in ms.iter_mut().zip(&loaded) {
        m.pixel_reference = Some(pixel_reference(&seq, params, &reference_samples)?);
    }
    let summary = Summary {
        input: input.display().to_string(),
        definitions: definitions(samples.cells, samples.statistic, seq.background),
        cells: samples.cells,
        cell_statistic: samples.statistic,
        background: seq.background,
        exposures_compared: samples.exposures.len(),
        pixels_sampled: samples.npix(),
        pixel_stride: STRIDE,
        samples: samples.len(),
        touched: touched.map(|t| t.1),
        models: ms,
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let text = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    crate::textfile::write_text(&out.join("summary.json"), &(text + "\n"))?;
    let html = super::report::html(&summary).map_err(|e| e.path(out.join("report.html")))?;
    crate::textfile::write_text(&out.join("report.html"), &html)?;
    let mut s = format!(
        "persist compare: {} exposures, {} pixels sampled ({} cells{})\n",
        summary.exposures_compared,
        summary.pixels_sampled,
        summary.cells.describe(),
        summary.cell_statistic.note()
    );
    if let Some(t) = &summary.touched {
        s += &format!(
            "  touched pixels: {} of {} sampled (> {} e-/s from {})\n",
            t.touched_pixels, t.pixels_sampled, t.min_difference_e_per_s, t.baseline
        );
    }
    for m in &summary.models {
        let q = m.flag_quality.get("0.1");
        s += &format!(
            "  {:<40} residual RMS {:>8.2}  missed@0.1 {:.4}  over@0.1 {:.4}",
            m.path,
            m.residual_rms_normalised,
            q.map_or(f64::NAN, |q| q.missed_flag_fraction),
            q.map_or(f64::NAN, |q| q.over_flag_fraction)
        );
        if let Some(t) = m.flag_quality_touched.get("0.1") {
            s += &format!(
                "  missed@0.1 of touched {:.4}",
                t.missed_flag_fraction_touched
            );
        }
        s += "\n";
        if let Some(r) = &m.pixel_reference {
            s += &pixel_reference_line(r);
        }
        s += &coverage_line(&m.flag_quality);
        if let Some(f) = &m.flags_at_first_coverage {
            s += &matched_line(f, &summary.models[0]);
        }
        let sp = &m.spread;
        s += &format!(
            "    pixels moving together: score {:.1} (about N(0, 1) for independent pixels)",
            sp.score
        );
        if let Some(k) = sp.kernel.filter(|k| k.kernel.corr > 0.0) {
            s += &format!(
                "; correlation {:.3} over {:.1} px, RMS {:.2} with it",
                k.kernel.corr, k.kernel.length_px, sp.residual_rms_normalised_correlated
            );
        }
        s += "\n";
        if !m.residual_rms_by_illumination.is_empty() {
            let per: Vec<String> = m
                .residual_rms_by_illumination
                .iter()
                .map(|r| format!("{}: {:.2}", r.illumination, r.residual_rms_normalised))
                .collect();
            s += &format!("    by illumination (exposure: RMS) {}\n", per.join(", "));
        }
        // the cell with the most missed samples at 0.1 e-/s (the first in the map's order
        // among equals)
        let worst = m.flag_quality_by_cell.get("0.1").and_then(|c| {
            c.iter().filter(|c| c.quality.missed > 0).reduce(|a, b| {
                if b.quality.missed > a.quality.missed {
                    b
                } else {
                    a
                }
            })
        });
        if let Some(c) = worst {
            s += &format!(
                "    most missed@0.1 in one cell: {} of {} samples at {}{:.3e} e-, {:.0} s\n",
                c.quality.missed,
                c.quality.samples,
                c.place
                    .illumination
                    .map_or(String::new(), |i| format!("illumination {i}, ")),
                c.place.fluence_e,
                c.place.time_s
            );
        }
    }
    s += &format!("report {}", out.join("report.html").display());
    Ok(s)
}

/// `persist diagnose`'s default samples ([`Config`]'s pixels and seed; the cells and
/// their statistic `opts`'), drawn once for every model's pixel reference.
fn diagnose_samples(seq: &Sequence, opts: &Options) -> Samples {
    let cfg = Config::default();
    Samples::random(seq, cfg.pixels, cfg.seed)
        .with_cells(opts.cells)
        .with_statistic(opts.cell_statistic)
}

/// The pixel reference of `params`' prediction on `samples` ([`diagnose_samples`]), so
/// that its RMS is the one `diagnose` prints for the same model. The noise scales are
/// measured for each model, as `diagnose` does, on a copy of the samples.
fn pixel_reference(
    seq: &Sequence,
    params: &ModelParams,
    samples: &Samples,
) -> Result<PixelReference> {
    let mut samples = samples.clone();
    let pred = super::eval::predict(params, seq, &samples, false)?;
    let view = super::base::View::of_model(params, seq);
    let response = crate::model::response::Response::new(&params.amplitude_knots);
    Ok(PixelReference::fit(seq, &view, &mut samples, &pred.current, &response).0)
}

/// The line of a model's pixel reference.
fn pixel_reference_line(r: &PixelReference) -> String {
    let per_event = r.per_event_rms.map_or(String::new(), |e| {
        format!("; fitted to each illumination event alone {e:.2}")
    });
    let noise = r
        .noise_scale
        .map_or("; noise as measured".to_string(), |n| {
            format!(
                "; noise variances x{:.2} (read), x{:.2} (shot)",
                n.read_var, n.shot_var
            )
        });
    format!(
        "    pixel reference: residual RMS {:.2} over {} cells{per_event}{noise}\n",
        r.residual_rms_normalised, r.cells
    )
}

/// A model's flags at the first model's coverage ([`super::compare::at_coverage_of`]),
/// beside the first model's over-flagging and the difference's noise, paired by pixel.
fn matched_line(f: &super::compare::MatchedFlags, first: &super::compare::ModelSummary) -> String {
    let q = &f.quality;
    let thr = q.threshold_e_per_s;
    let first_over = first
        .flag_quality
        .get(&format!("{thr}"))
        .map_or(0, |q| q.over_flagged);
    let d = &f.over_flagged_vs_first;
    let verdict = d.against_noise();
    format!(
        "    at the first model's coverage at {thr} e-/s (knots x {:.4}): {} missed ({} for \
         the first), over-flagged {:.2} % ({} samples; {} for the first: {:+}, standard \
         error {:.1} from the {} pixels whose counts differ, {verdict})\n",
        f.knot_factor,
        q.missed,
        f.target_missed,
        100.0 * q.over_flag_fraction,
        q.over_flagged,
        first_over,
        d.difference,
        d.standard_error,
        d.pixels_differing,
    )
}

/// The flags' coverage and over-flagging at 0.1 and 0.01 e-/s, as `persist fit` calibrates
/// them (`crate::calib::coverage`): of the samples measured above a threshold by 2 noise
/// sigmas, the share flagged; and the samples flagged while measured below it by 2
/// sigmas, per sample. One line, empty when neither threshold was evaluated.
fn coverage_line(q: &std::collections::BTreeMap<String, super::eval::FlagQuality>) -> String {
    let parts: Vec<String> = ["0.1", "0.01"]
        .iter()
        .filter_map(|t| q.get(*t).map(|q| (t, q)))
        .map(|(t, q)| {
            let cov = if q.measured_above == 0 {
                "-".to_string()
            } else {
                format!("{:.1} %", 100.0 * (1.0 - q.missed_of_measured_above))
            };
            format!(
                "at {t} e-/s coverage {cov} of {} measured above, over-flagged {:.2} %",
                q.measured_above,
                100.0 * q.over_flag_fraction
            )
        })
        .collect();
    if parts.is_empty() {
        String::new()
    } else {
        format!("    flags: {}\n", parts.join("; "))
    }
}
