//! `persist pixelmap`: measure a detector's per-pixel response map from a laboratory
//! sequence against a model, write it, and optionally write the model file naming it.

use super::{build, file, MapConfig};
use crate::error::{Error, Result};
use crate::measure::data::Sequence;
use std::path::PathBuf;

/// Arguments of `persist pixelmap`.
#[derive(clap::Args, Debug)]
pub struct PixelmapArgs {
    /// Laboratory sequence of one detector (Level-1 products; the first detector found).
    #[arg(long)]
    pub input: PathBuf,
    /// The model the ratios are measured against (normally `persist fit`'s on the same
    /// sequence).
    #[arg(long)]
    pub model: PathBuf,
    /// The map to write (HDF5, `schemas/pixel_map.schema.json`).
    #[arg(long)]
    pub out: PathBuf,
    /// Also write this model file: the model naming the map (its SHA-256) with
    /// `--margin` (written beside the map, the map's path relative to it).
    #[arg(long)]
    pub write_model: Option<PathBuf>,
    /// Factor on each pixel's upper posterior ratio in the model written
    /// (docs/pixel_map.md, "Margin"; 1: on the simulator's sky no band of true current
    /// is missed more often than with the global model).
    #[arg(long, default_value_t = 1.0)]
    pub margin: f64,
    /// Fluence range 0 (linear) ends here, e-.
    #[arg(long, default_value_t = 150_000.0)]
    pub linear_below_e: f64,
    /// Fluence range 1 (saturated) starts here, e-.
    #[arg(long, default_value_t = 250_000.0)]
    pub saturated_above_e: f64,
    /// Posterior quantile stored as `/ratio_upper`.
    #[arg(long, default_value_t = 0.95)]
    pub upper_quantile: f64,
}

/// Run `persist pixelmap`; returns the lines to print.
pub fn run(a: &PixelmapArgs) -> Result<Vec<String>> {
    let params = crate::model_file::load(&a.model)?;
    let seq = Sequence::load(&a.input)?;
    let cfg = MapConfig {
        linear_below_e: a.linear_below_e,
        saturated_above_e: a.saturated_above_e,
        upper_quantile: a.upper_quantile,
    };
    let mut map = build(&seq, &params, &cfg).map_err(|e| e.path(&a.input))?;
    map.source = a.input.display().to_string();
    if let Some(d) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    file::write(&a.out, &map)?;
    let [lin, sat] = file::observed(&map);
    let mut lines = vec![format!(
        "persist pixelmap: detector {} ({} x {}), {lin} pixels measured in the linear range, {sat} in the saturated range -> {}",
        map.detector,
        map.ratio.dim().1,
        map.ratio.dim().2,
        a.out.display()
    )];
    if let Some(m) = &a.write_model {
        if !(a.margin.is_finite() && a.margin > 0.0) {
            return Err(Error::invalid("--margin", "must be finite and > 0"));
        }
        let written = relative_to(m, &a.out);
        let p = file::name_maps(params, &[(map.detector, written, a.out.clone())], a.margin)?;
        crate::textfile::write_text(m, &(p.to_json_pretty() + "\n"))?;
        lines.push(format!(
            "model with the map (margin {}): {} (identity {})",
            a.margin,
            m.display(),
            &p.identity()[..12]
        ));
    }
    Ok(lines)
}

/// `target` as the model file `model` will name it: relative to the model's directory
/// when both are in the same directory, else absolute.
fn relative_to(model: &std::path::Path, target: &std::path::Path) -> String {
    let abs = |p: &std::path::Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
    let (m, t) = (abs(model), abs(target));
    match (m.parent(), t.parent(), t.file_name()) {
        (Some(a), Some(b), Some(n)) if a == b => n.to_string_lossy().into_owned(),
        _ => t.display().to_string(),
    }
}
