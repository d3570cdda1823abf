//! `persist verify`, `persist export` and `persist validate`: commands over products.

use clap::Args;
use persist::{Error, ErrorKind};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args, Debug)]
pub struct ExportArgs {
    /// HDF5 products to export (`NAME.h5` -> `OUT/NAME.fits`).
    #[arg(long = "fits", required = true, num_args = 1..)]
    pub files: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Write the image of detector D in MJy/sr, FACTOR e-/s per MJy/sr (recorded as
    /// ESCONV); repeatable. Without it the image is written in e-/s.
    #[arg(long = "fits-gain", value_parser = persist::fits::parse_gain)]
    pub fits_gain: Vec<(u8, f64)>,
    /// Add VARIANCE, ZODI, PSF and WCS-WAVE placeholders and a spatial WCS (SPHEREx's
    /// full layout, synthetic values).
    #[arg(long)]
    pub placeholders: bool,
}

#[derive(Args, Debug)]
pub struct VerifyArgs {
    /// The stage's input directory (sky exposures; a simulator's `truth/` in it is used).
    #[arg(long)]
    pub input: PathBuf,
    /// The stage's output directory (its products carry the input image and flags).
    #[arg(long)]
    pub output: PathBuf,
    /// Where to write report.html and report.json.
    #[arg(long)]
    pub report: PathBuf,
    /// Extrapolated fluence from which a pixel's exposure is an event, e- [default: 2e5,
    /// the paper's saturation level; OVERFLOW pixels always are].
    #[arg(long)]
    pub event_fluence_e: Option<f64>,
    /// Reject a track's sample that rises more than this many standard deviations of the
    /// difference above its last accepted one floored at zero (a source in the pixel).
    #[arg(long, default_value_t = 3.0)]
    pub spike_nsigma: f64,
    /// Inner and outer Chebyshev radii of the sky annulus, pixels.
    #[arg(long, value_delimiter = ',', default_values_t = [3, 6])]
    pub annulus_px: Vec<usize>,
    /// Seed of the bootstrap over events.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The quantile of the transient rule: of measured / predicted at the first exposure
    /// after a cosmic-ray hit (docs/verify.md, "The transient rule").
    #[arg(long, default_value_t = persist::verify::transient::DEFAULT_QUANTILE)]
    pub transient_quantile: f64,
    /// Also learn each pixel's response from the tracks and write it as a per-pixel map
    /// (HDF5, the laboratory map's format; one detector: the first found). Needs
    /// `--map-model`.
    #[arg(long)]
    pub flight_map: Option<PathBuf>,
    /// The model the stage ran with, without a map: the flight map is measured against it.
    #[arg(long)]
    pub map_model: Option<PathBuf>,
    /// A laboratory map of the same detector to start the flight map from.
    #[arg(long)]
    pub prior_map: Option<PathBuf>,
}

/// `persist verify`: exit code 1 when a check disagrees or a file could not be read.
pub(super) fn verify(a: &VerifyArgs) -> persist::Result<ExitCode> {
    if !(a.transient_quantile > 0.0 && a.transient_quantile < 1.0) {
        return Err(Error::new(
            ErrorKind::Usage,
            format!(
                "--transient-quantile {}: need 0 < q < 1",
                a.transient_quantile
            ),
        ));
    }
    let mut p = persist::verify::VerifyParams {
        seed: a.seed,
        transient_quantile: a.transient_quantile,
        ..Default::default()
    };
    if let Some(f) = a.event_fluence_e {
        p.track.event_fluence_e = f;
    }
    p.track.spike_nsigma = a.spike_nsigma;
    if let [inner, outer] = a.annulus_px[..] {
        if inner == 0 || outer < inner {
            return Err(Error::new(
                ErrorKind::Usage,
                format!("--annulus-px {inner},{outer}: need 0 < inner <= outer"),
            ));
        }
        p.track.annulus_inner_px = inner;
        p.track.annulus_outer_px = outer;
    }
    let r = match &a.flight_map {
        None => persist::verify::run(&a.input, &a.output, &p)?,
        Some(out) => persist::pixmap::flight::learn_and_write(
            &a.input,
            &a.output,
            &p,
            out,
            a.map_model.as_deref(),
            a.prior_map.as_deref(),
        )?,
    };
    persist::verify::write_report(&r, &a.report)?;
    let c = &r.checks;
    out!(
        "{} exposures, {} events, {} samples; {}",
        r.exposures,
        r.events,
        r.samples,
        c.verdict()
    );
    if let Some((inside, n)) = c.truth_inside {
        out!("truth inside the measured 95 % interval in {inside} of {n} bins");
    }
    out!(
        "{} cosmic-ray hits followed; transient rule: {}",
        r.transients.hits,
        r.transients.rule
    );
    if let Some(q) = &r.flag_quality {
        out!(
            "flags against the truth, pixel-exposures from exposure {} on:\n{}",
            q.from_exposure,
            q.table().trim_end()
        );
    }
    for e in &r.errors {
        eprintln!("unreadable: {}: {}", e.file.display(), e.reason);
    }
    out!("report: {}", a.report.join("report.html").display());
    let ok = c.agree() && r.errors.is_empty();
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

/// `persist export --fits FILE... --out DIR`.
pub(super) fn export(a: &ExportArgs) -> persist::Result<ExitCode> {
    std::fs::create_dir_all(&a.out).map_err(|e| Error::io(&a.out, e))?;
    let opts = persist::fits::export::ExportOptions {
        gains: a.fits_gain.iter().copied().collect(),
        placeholders: a.placeholders,
    };
    let mut failed = false;
    for f in &a.files {
        match persist::fits::export::export_file(f, &a.out, &opts) {
            Ok(p) => out!("{} -> {}", f.display(), p.display()),
            Err(e) => {
                failed = true;
                tracing::error!("{e}");
            }
        }
    }
    Ok(if failed {
        ExitCode::FAILURE
    } else {
        ExitCode::SUCCESS
    })
}

/// `persist validate FILE...`: every file is checked; exit 1 if any failed.
pub(super) fn validate(files: &[PathBuf]) -> ExitCode {
    let mut failed = false;
    for path in files {
        match persist::validate::validate_path(path) {
            Ok(kind) => out!("ok {kind} {}", path.display()),
            Err(errors) => {
                failed = true;
                for e in errors {
                    // Every error names its file; make sure of it.
                    eprintln!("{}", e.path(path));
                }
            }
        }
    }
    if failed {
        ExitCode::from(1)
    } else {
        ExitCode::SUCCESS
    }
}
