//! `persist compare`: every model of `--model` against the measurements of a sequence.
//!
//! Definitions (measured current, background, samples, normalised residuals, flag
//! quality) are those of [`super::data`] and [`super::eval`]. Writes
//! `OUT/summary.json` (every number of the report) and `OUT/report.html`
//! (self-contained; [`super::report`]).

use super::data::Sequence;
use super::eval::{self, FlagQuality, GroupStat, Samples};
use crate::error::{Error, ErrorKind, Result};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::Path;

/// Pixel stride of the sample (eval docs): every 2nd pixel in x and y.
pub const STRIDE: usize = 2;

#[derive(Debug, Clone, Serialize)]
pub struct Bin {
    pub bin: i64,
    /// Lower edge of the bin in the covariate's unit.
    pub value: f64,
    #[serde(flatten)]
    pub stat: GroupStat,
}

#[derive(Debug, Clone, Serialize)]
pub struct Cell {
    pub fluence_e: f64,
    pub time_s: f64,
    #[serde(flatten)]
    pub stat: GroupStat,
}

#[derive(Debug, Clone, Serialize)]
pub struct ModelSummary {
    pub path: String,
    pub name: String,
    pub identity: String,
    pub effects: Vec<String>,
    pub residual_rms_normalised: f64,
    pub cells: usize,
    pub map: Vec<Cell>,
    pub breakdown: BTreeMap<String, Vec<Bin>>,
    /// Keyed by the threshold in e-/s, e.g. "0.1".
    pub flag_quality: BTreeMap<String, FlagQuality>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub input: String,
    pub definitions: BTreeMap<String, String>,
    pub exposures_compared: usize,
    pub pixels_sampled: usize,
    pub pixel_stride: usize,
    pub samples: usize,
    pub models: Vec<ModelSummary>,
}

pub const BREAKDOWNS: [&str; 7] = [
    "time",
    "fluence",
    "neighbour_excess_fluence",
    "illumination_time",
    "temperature",
    "earlier_illuminations",
    "position",
];

/// Compare already-loaded models (used by the CLI, `diagnose` and tests).
pub fn summarise(
    seq: &Sequence,
    samples: &Samples,
    models: &[(String, crate::model::ModelParams)],
) -> Result<Vec<ModelSummary>> {
    let mut out = Vec::new();
    for (path, params) in models {
        let pr = eval::predict(params, seq, samples, false)?;
        let fl = eval::predict(params, seq, samples, true)?;
        let cells = eval::cell_z(samples, &pr.current);
        let map = cells
            .iter()
            .map(|(k, g)| Cell {
                fluence_e: eval::bin_value("fluence", k[0]),
                time_s: eval::bin_value("time", k[1]),
                stat: *g,
            })
            .collect();
        let mut breakdown = BTreeMap::new();
        for c in BREAKDOWNS {
            let g = eval::groups(samples, &pr.current, &[c]);
            breakdown.insert(
                c.to_string(),
                g.into_iter()
                    .map(|(k, st)| Bin {
                        bin: k[0],
                        value: eval::bin_value(c, k[0]),
                        stat: st,
                    })
                    .collect(),
            );
        }
        let mut fq = BTreeMap::new();
        let high = params.thresholds.high_e_per_s;
        let mut ths = vec![0.1, 0.01, high, params.thresholds.low_e_per_s];
        ths.sort_by(|a, b| a.total_cmp(b));
        ths.dedup();
        for t in ths {
            let flags = (t == high).then_some(fl.flagged.as_slice());
            fq.insert(
                format!("{t}"),
                eval::flag_quality(samples, &pr.current, flags, t),
            );
        }
        out.push(ModelSummary {
            path: path.clone(),
            name: params.name.clone(),
            identity: params.identity(),
            effects: params.effects.iter().map(|e| e.name.clone()).collect(),
            residual_rms_normalised: eval::rms(&cells),
            cells: cells.len(),
            map,
            breakdown,
            flag_quality: fq,
        });
    }
    Ok(out)
}

pub fn definitions() -> BTreeMap<String, String> {
    BTreeMap::from([
        ("measured".into(), "image minus the median of the background pixels of the same exposure (fluence < 3000 e- in every illumination so far, no on-board flag); noise 1.4826 MAD of the same pixels".into()),
        ("samples".into(), "every 2nd pixel in x and y with fluence > 3000 e- in the last illumination, every exposure after an illumination".into()),
        ("z".into(), "(P95 of measured signal - P95 of predicted) / (2.12 s / sqrt(n)), s = 1.4826 MAD of measured, at least the noise".into()),
        ("residual_rms_normalised".into(), "RMS of z over cells fluence (5 per decade) x time since illumination (4 per decade)".into()),
        ("missed".into(), "measured > threshold + 2 noise and not flagged".into()),
        ("over_flagged".into(), "flagged and measured < threshold - 2 noise".into()),
        ("flags".into(), "at the model's high threshold from the model as the stage runs it (early release on); other thresholds: prediction > threshold with early release off".into()),
    ])
}

/// `persist compare`.
pub fn run(input: &Path, models: &[std::path::PathBuf], out: &Path) -> Result<String> {
    let seq = Sequence::load(input)?;
    let samples = Samples::new(&seq, STRIDE);
    let mut loaded = Vec::new();
    for m in models {
        loaded.push((m.display().to_string(), crate::model_file::load(m)?));
    }
    let ms = summarise(&seq, &samples, &loaded)?;
    let summary = Summary {
        input: input.display().to_string(),
        definitions: definitions(),
        exposures_compared: samples.exposures.len(),
        pixels_sampled: samples.npix(),
        pixel_stride: STRIDE,
        samples: samples.len(),
        models: ms,
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let text = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
    crate::calib::write_text(&out.join("summary.json"), &(text + "\n"))?;
    let html = super::report::html(&summary).map_err(|e| e.path(out.join("report.html")))?;
    crate::calib::write_text(&out.join("report.html"), &html)?;
    let mut s = format!(
        "persist compare: {} exposures, {} pixels sampled\n",
        summary.exposures_compared, summary.pixels_sampled
    );
    for m in &summary.models {
        let q = m.flag_quality.get("0.1");
        s += &format!(
            "  {:<40} residual RMS {:>8.2}  missed@0.1 {:.4}  over@0.1 {:.4}\n",
            m.path,
            m.residual_rms_normalised,
            q.map_or(f64::NAN, |q| q.missed_flag_fraction),
            q.map_or(f64::NAN, |q| q.over_flag_fraction)
        );
    }
    s += &format!("report {}", out.join("report.html").display());
    Ok(s)
}
