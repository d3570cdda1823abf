//! The parsers of option values that clap does not have.

use persist::units::DetectorId;
use persist::Error;

pub(super) fn positive_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
        _ => Err(format!("`{s}`: expected a number of seconds > 0")),
    }
}

pub(super) fn nonnegative_seconds(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x >= 0.0 => Ok(x),
        _ => Err(format!("`{s}`: expected a number of seconds >= 0")),
    }
}

/// What early release keeps (`early_release.keep` of the model file: `zero` or
/// `threshold`).
pub(super) fn release_keep(s: &str) -> Result<persist::model::ReleaseKeep, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string()))
        .map_err(|_| format!("`{s}`: expected zero or threshold"))
}

/// A flag's value through the library's `FromStr` (whose error names the flag and the
/// values it takes).
pub(super) fn parse_flag<T: std::str::FromStr<Err = Error>>(s: &str) -> Result<T, String> {
    s.parse().map_err(|e: Error| e.to_string())
}

pub(super) fn parse_checkpoint_key(s: &str) -> Result<(DetectorId, u64), String> {
    let (d, i) = s
        .split_once(':')
        .ok_or_else(|| format!("`{s}`: expected DETECTOR:INDEX, e.g. 3:120"))?;
    let d: i64 = d
        .parse()
        .map_err(|_| format!("`{d}`: not a detector number"))?;
    let det = DetectorId::new(d).ok_or_else(|| format!("detector {d}: must be 1..=6"))?;
    let i = i
        .parse()
        .map_err(|_| format!("`{i}`: not an exposure index"))?;
    Ok((det, i))
}
