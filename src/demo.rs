//! `persist demo`: the main job on a built-in default. Simulate a small SPHEREx-like
//! sky sequence from the trap-level truth ([`crate::sim`]), run the stage on it with the
//! default model, and show what the flagging does: the fraction of pixels above each
//! threshold versus time, and one pixel's predicted and true persistence through a
//! saturating event (two PNG plots and a printed summary).
//!
//! The default is the paper's two days (1143 exposures of 112 s) on one detector at
//! 128 x 128 pixels: the star density per pixel is the full array's, so the statistics
//! are those of a 128 x 128 patch of the sky.
//!
//! # The paper's workflow
//! Without a model file the demo first measures the same simulated detector (same size
//! and seed: the same pixels) in the laboratory ([`crate::pixmap::eval::lab_sequence`]:
//! the paper's pattern with a dark corner for the dark level and noise, three
//! illuminations and 1.5 h of darks after the first), fits
//! it as `persist fit` does by default ([`crate::calib::Preset::Paper`]: the paper's
//! calibration with `refill` fitted, then the flags calibrated to 95 % coverage,
//! [`crate::calib::coverage`], and early release keeping the threshold; written to
//! `lab_model.json`). In flight, the sky's first [`crate::flag_quality::FROM_EXPOSURE`]
//! exposures are flagged with it and `persist verify` measures what follows the
//! cosmic-ray hits; `persist fit --from-verify` writes the transient rule it measured
//! into the model ([`crate::verify::transient::measure_in_flight`]; `model.json`), and
//! the sky is flagged with that model. Then it counts the flags against the simulator's truth
//! ([`crate::flag_quality`], from exposure [`crate::flag_quality::FROM_EXPOSURE`] on)
//! and runs `persist verify` on the stage's outputs.

use crate::checkpoint::Retention;
use crate::error::{Error, Result};
use crate::model::{Model, ModelParams};
use crate::plot::{line_chart_png, Chart, Series};
use crate::sim::{output::Writer, sky};
use crate::stage::{self, ExposureReport, RunConfig};
use crate::stats::median;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone)]
pub struct DemoConfig {
    pub out: PathBuf,
    pub size: usize,
    pub exposures: u64,
    pub seed: u64,
    /// The model; None: fitted on the laboratory sequence (module docs, "The paper's
    /// workflow").
    pub model: Option<ModelParams>,
    /// The sky survey's parameters (star counts, cosmic rays, ...); `size`, `detectors`,
    /// `exposures` and `seed` are taken from the fields above.
    pub sky: sky::SkyConfig,
}

impl Default for DemoConfig {
    fn default() -> Self {
        DemoConfig {
            out: PathBuf::from("demo-out"),
            size: 128,
            exposures: 1143,
            seed: 1,
            model: None,
            sky: sky::SkyConfig::default(),
        }
    }
}

/// Per exposure: hours since the start, the fractions predicted above each threshold
/// (what the stage flags), the same fractions of the simulator's true persistence
/// current, and the fractions of pixels saturated (`OVERFLOW`) and hit by a cosmic ray
/// (`TRANSIENT`) in that exposure.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Row {
    pub exposure_index: u64,
    pub t_hours: f64,
    pub frac_high: f64,
    pub frac_low: f64,
    pub true_frac_high: f64,
    pub true_frac_low: f64,
    pub frac_saturated: f64,
    pub frac_transient: f64,
    /// The median pixel's true and predicted persistence current, e-/s (the "floor").
    pub median_true_e_per_s: f64,
    pub median_pred_e_per_s: f64,
}

/// Per exposure, from the simulation (index order).
#[derive(Debug, Clone, Copy, Default)]
struct SimCounts {
    true_high: f64,
    true_low: f64,
    saturated: f64,
    transient: f64,
    median_true: f64,
}

/// What the demo found.
#[derive(Debug, Clone, serde::Serialize)]
pub struct DemoReport {
    pub rows: Vec<Row>,
    /// The pixel traced through its brightest (saturating) exposure.
    pub pixel: (usize, usize),
    pub pixel_event_index: u64,
    pub pixel_event_fluence_e: f64,
    /// (hours, predicted e-/s, true e-/s) for that pixel, every exposure.
    pub pixel_trace: Vec<(f64, f64, f64)>,
    /// Median over exposures after the first 6 h of the fraction above 0.1 / 0.01 e-/s.
    pub steady_frac_high: f64,
    pub steady_frac_low: f64,
    /// The same medians of the true persistence current (simulator truth).
    pub steady_true_frac_high: f64,
    pub steady_true_frac_low: f64,
    /// Median over exposures after 6 h of the median pixel's true / predicted current.
    pub steady_median_true_e_per_s: f64,
    pub steady_median_pred_e_per_s: f64,
    pub plots: Vec<PathBuf>,
    pub errors: usize,
    /// Where the model came from (the fit's summary when the demo fitted it).
    pub model_source: String,
    /// The flags against the simulator's truth.
    pub flag_quality: crate::flag_quality::TruthTally,
    /// `persist verify` on the stage's outputs.
    pub verify: crate::verify::Checks,
}

fn read_plane(path: &Path, dataset: &str) -> Result<ndarray::Array2<f32>> {
    let f = crate::h5io::open(path)?;
    f.dataset(dataset)
        .and_then(|d| d.read_2d())
        .map_err(|e| Error::from(e).path(path).field(dataset))
}

/// Median of a plane's finite values, e-/s.
fn plane_median(a: &ndarray::Array2<f32>) -> f64 {
    let v: Vec<f64> = a.iter().map(|v| f64::from(*v)).collect();
    median(&v)
}

/// Draw a chart, on a linear axis if a log axis would have nothing to show (a sky with
/// no stars and no cosmic rays: every fraction zero).
fn draw(path: &Path, chart: &Chart, width: u32, height: u32) -> Result<()> {
    let positive = chart
        .series
        .iter()
        .any(|s| s.points.iter().any(|p| p.1 > 0.0 && p.1.is_finite()));
    let mut c = chart.clone();
    c.log_y &= positive;
    line_chart_png(path, &c, width, height)
}

/// The demo's model: `cfg.model`, or fitted on the laboratory sequence of the same
/// detector (module docs), with a summary of where it came from.
fn model_of(cfg: &DemoConfig, progress: &dyn Fn(&str)) -> Result<(ModelParams, String)> {
    if let Some(m) = &cfg.model {
        return Ok((m.clone(), format!("model `{}` (given)", m.name)));
    }
    progress(&format!(
        "simulating the laboratory sequence of the same detector ({}x{}, seed {})",
        cfg.size, cfg.size, cfg.seed
    ));
    let (_, seq) = crate::pixmap::eval::lab_sequence(cfg.size, cfg.seed, true)?;
    progress(
        "fitting it as `persist fit` does by default (the paper's calibration with `refill`, \
         the flags' coverage, early release keeping the threshold)",
    );
    let preset = crate::calib::Preset::Paper;
    let calib = preset.config();
    let fit = crate::calib::command::fit_model(
        &seq,
        &calib,
        &preset.with(&[]),
        Default::default(),
        preset.release_keep(),
        false,
    )?;
    let covered = crate::calib::command::describe_coverage(
        fit.coverage.as_ref(),
        fit.not_covered.as_deref(),
        &calib,
    );
    let text = format!(
        "fitted on the laboratory sequence: {} knots, then\n{}",
        fit.calibration.knots.len(),
        covered.trim_end()
    );
    let params = fit.params;
    let path = cfg.out.join("lab_model.json");
    crate::textfile::write_text(&path, &(params.to_json_pretty() + "\n"))?;
    Ok((params, text))
}

/// The transient rule measured in flight (module docs, "The paper's workflow"): the
/// stage and `persist verify` on the sky's first exposures (written again into
/// `in_flight/sim`: the survey's draws are sequential, so they are the full run's
/// first ones) flagged with the laboratory model `lab`, then `persist fit
/// --from-verify`. The model to flag the sky with (written to `model.json`) and what
/// was measured, in words.
fn in_flight_rule(
    cfg: &DemoConfig,
    sky_cfg: &sky::SkyConfig,
    lab: &ModelParams,
    progress: &dyn Fn(&str),
) -> Result<(ModelParams, String)> {
    let n = crate::flag_quality::FROM_EXPOSURE.min(cfg.exposures);
    progress(&format!(
        "measuring the transient rule in flight: the stage and `persist verify` on the \
         sky's first {n} exposures, then `persist fit --from-verify`"
    ));
    let dir = cfg.out.join("in_flight");
    let sim = dir.join("sim");
    let span = sky::SkyConfig {
        exposures: n,
        ..sky_cfg.clone()
    };
    sky::write(&span, &sim)?;
    let m = crate::verify::transient::measure_in_flight(&sim, lab, &dir)?;
    let text = match (&m.params.transient, &m.refused) {
        (Some(t), _) => format!(
            "transient rule measured in flight on the sky's first {n} exposures: {:.1} e- \
             (the laboratory model's {:.1} e- x {:.4}, from {} hits at their first exposure)",
            t.amplitude_e, t.measured.flown_amplitude_e, t.measured.ratio, t.measured.events
        ),
        (None, why) => format!(
            "no transient rule measured in flight ({}): the table's maximum stays",
            why.as_deref().unwrap_or("no rule")
        ),
    };
    let path = cfg.out.join("model.json");
    crate::textfile::write_text(&path, &(m.params.to_json_pretty() + "\n"))?;
    Ok((m.params, text))
}

/// Simulate, run the stage, analyse, plot. `progress` is told what happens.
pub fn run(cfg: &DemoConfig, progress: &dyn Fn(&str)) -> Result<DemoReport> {
    if cfg.out.exists() {
        std::fs::remove_dir_all(&cfg.out).map_err(|e| Error::io(&cfg.out, e))?;
    }
    let (model, mut model_source) = model_of(cfg, progress)?;
    let sim_dir = cfg.out.join("sim");
    let sky_cfg = sky::SkyConfig {
        size: cfg.size,
        detectors: 1,
        exposures: cfg.exposures,
        seed: cfg.seed,
        ..cfg.sky.clone()
    };
    progress(&format!(
        "simulating {} sky exposures of {}x{} (seed {}) into {}",
        cfg.exposures,
        cfg.size,
        cfg.size,
        cfg.seed,
        sim_dir.display()
    ));
    let mut writer = Writer::new(&sim_dir)?;
    // The brightest exposure of any pixel in the middle half of the run: its event.
    let (lo, hi) = (cfg.exposures / 4, 3 * cfg.exposures / 4);
    let mut event: (f64, u64, (usize, usize)) = (0.0, 0, (0, 0));
    let mut counts: Vec<SimCounts> = Vec::new();
    // The true current is counted against the model's own thresholds.
    let (high, low) = (model.thresholds.high_e_per_s, model.thresholds.low_e_per_s);
    let description = sky::run(&sky_cfg, |s| {
        let k = s.exposure.meta.exposure_index;
        let n = s.true_persistence.len().max(1) as f64;
        let frac = |p: &dyn Fn(f32) -> bool| {
            s.true_persistence.iter().filter(|v| p(**v)).count() as f64 / n
        };
        let flagged = |b: u32| s.exposure.flags.iter().filter(|f| **f & b != 0).count() as f64 / n;
        counts.push(SimCounts {
            true_high: frac(&|v| f64::from(v) > high),
            true_low: frac(&|v| f64::from(v) > low),
            saturated: flagged(crate::flags::bits::OVERFLOW),
            transient: flagged(crate::flags::bits::TRANSIENT),
            median_true: plane_median(&s.true_persistence),
        });
        if (lo..hi).contains(&k) {
            let t = s.exposure.meta.t_exposure_s;
            for ((y, x), f) in s.true_flux.indexed_iter() {
                let fluence = f64::from(*f) * t;
                if fluence > event.0 {
                    event = (fluence, k, (y, x));
                }
            }
        }
        writer.write(&s)
    })?;
    writer.finish(description)?;
    let model = if cfg.model.is_none() {
        let (with_rule, text) = in_flight_rule(cfg, &sky_cfg, &model, progress)?;
        model_source = format!("{model_source}\n{text}");
        with_rule
    } else {
        model
    };

    progress(&format!("running the stage with model `{}`", model.name));
    let run_cfg = RunConfig {
        input: sim_dir.clone(),
        output: cfg.out.join("output"),
        checkpoints: cfg.out.join("checkpoints"),
        model: Model::new(model.clone())?,
        from_checkpoint: None,
        allow_model_change: false,
        checkpoint_every: 1,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: Retention::default(),
        processed_utc: stage::processing_time(),
    };
    let report = stage::run(&run_cfg, &|_| {});
    let mut exposures: Vec<&ExposureReport> = report.exposures.iter().collect();
    exposures.sort_by_key(|r| r.exposure_index);

    let t0 = crate::sim::epoch().0;
    let mut rows = Vec::new();
    let mut trace = Vec::new();
    let mut flag_quality =
        crate::flag_quality::TruthTally::new(high, low, crate::flag_quality::FROM_EXPOSURE);
    for r in &exposures {
        let n = r.summary.pixels.max(1) as f64;
        let c = counts
            .get(r.exposure_index as usize)
            .copied()
            .unwrap_or_default();
        let out = run_cfg.output.join(r.path.file_name().unwrap_or_default());
        let truth = read_plane(
            &crate::sim::output::truth_path(&sim_dir, 1, r.exposure_index),
            "true_persistence",
        )?;
        let (e, planes, _) = crate::product::read::read_output(&out)?;
        let meta = &e.meta;
        let t_hours = (meta.t_start.0 + 0.5 * meta.t_exposure_s - t0) / 3600.0;
        flag_quality.add_pflags(r.exposure_index, &planes.flags, &truth, &e.flags);
        let predicted = planes.current_e_per_s;
        rows.push(Row {
            exposure_index: r.exposure_index,
            t_hours,
            frac_high: r.summary.above_high as f64 / n,
            frac_low: r.summary.above_low as f64 / n,
            true_frac_high: c.true_high,
            true_frac_low: c.true_low,
            frac_saturated: c.saturated,
            frac_transient: c.transient,
            median_true_e_per_s: c.median_true,
            median_pred_e_per_s: plane_median(&predicted),
        });
        trace.push((
            t_hours,
            f64::from(predicted[event.2]),
            f64::from(truth[event.2]),
        ));
    }
    let steady = |f: fn(&Row) -> f64| {
        let v: Vec<f64> = rows.iter().filter(|r| r.t_hours > 6.0).map(f).collect();
        median(&v)
    };
    let steady_frac_high = steady(|r| r.frac_high);
    let steady_frac_low = steady(|r| r.frac_low);
    let steady_true_frac_high = steady(|r| r.true_frac_high);
    let steady_true_frac_low = steady(|r| r.true_frac_low);
    let steady_median_true = steady(|r| r.median_true_e_per_s);
    let steady_median_pred = steady(|r| r.median_pred_e_per_s);

    let plots = vec![
        cfg.out.join("flagged_fraction.png"),
        cfg.out.join("pixel_trace.png"),
    ];
    draw(
        &plots[0],
        &Chart {
            title: format!(
                "Pixels above threshold, model `{}` and truth ({}x{}, seed {})",
                model.name, cfg.size, cfg.size, cfg.seed
            ),
            x_label: "time since start [h]".into(),
            y_label: "pixels above threshold [%]".into(),
            log_y: true,
            series: vec![
                Series {
                    name: "predicted > 0.01 e-/s".into(),
                    points: rows
                        .iter()
                        .map(|r| (r.t_hours, 100.0 * r.frac_low))
                        .collect(),
                },
                Series {
                    name: "predicted > 0.1 e-/s (flagged)".into(),
                    points: rows
                        .iter()
                        .map(|r| (r.t_hours, 100.0 * r.frac_high))
                        .collect(),
                },
                Series {
                    name: "true > 0.01 e-/s (simulator)".into(),
                    points: rows
                        .iter()
                        .map(|r| (r.t_hours, 100.0 * r.true_frac_low))
                        .collect(),
                },
                Series {
                    name: "true > 0.1 e-/s (simulator)".into(),
                    points: rows
                        .iter()
                        .map(|r| (r.t_hours, 100.0 * r.true_frac_high))
                        .collect(),
                },
            ],
            hlines: vec![(2.0, "paper: ~2% above 0.1 e-/s".into())],
        },
        1000,
        560,
    )?;
    draw(
        &plots[1],
        &Chart {
            title: format!(
                "Pixel ({}, {}): brightest exposure {} ({:.2e} e-)",
                event.2 .0, event.2 .1, event.1, event.0
            ),
            x_label: "time since start [h]".into(),
            y_label: "persistence current [e-/s]".into(),
            log_y: true,
            series: vec![
                Series {
                    name: "predicted (default model)".into(),
                    points: trace.iter().map(|t| (t.0, t.1)).collect(),
                },
                Series {
                    name: "true (simulator)".into(),
                    points: trace.iter().map(|t| (t.0, t.2)).collect(),
                },
            ],
            hlines: vec![(0.1, "0.1 e-/s".into()), (0.01, "0.01 e-/s".into())],
        },
        1000,
        560,
    )?;
    for e in &report.errors {
        progress(&format!("error: {e}"));
    }
    progress("running persist verify on the outputs");
    let verified = crate::verify::run(
        &sim_dir,
        &run_cfg.output,
        &crate::verify::VerifyParams::default(),
    )?;
    Ok(DemoReport {
        rows,
        pixel: event.2,
        pixel_event_index: event.1,
        pixel_event_fluence_e: event.0,
        pixel_trace: trace,
        steady_frac_high,
        steady_frac_low,
        steady_true_frac_high,
        steady_true_frac_low,
        steady_median_true_e_per_s: steady_median_true,
        steady_median_pred_e_per_s: steady_median_pred,
        plots,
        errors: report.errors.len() + verified.errors.len(),
        model_source,
        flag_quality,
        verify: verified.checks,
    })
}
