//! One Level-1 exposure product in memory (ICD "Input"), and the persistence planes
//! the stage appends to it (ICD "Output").

use crate::units::{DetectorId, ExposureIndex, Seconds, UtcSeconds};
use ndarray::{Array1, Array2, Array3};

pub use crate::flags::{bits, pbits};

pub const PRODUCT_L1: &str = "spherex.l1.exposure";
pub const SCHEMA_VERSION: &str = "1.0";

/// Root attributes of an exposure product.
#[derive(Debug, Clone, PartialEq)]
pub struct ExposureMeta {
    pub detector: DetectorId,
    pub exposure_index: ExposureIndex,
    /// Exactly as written in the file (carried through unchanged).
    pub t_start_utc: String,
    /// `t_start_utc` parsed.
    pub t_start: UtcSeconds,
    pub t_exposure_s: f64,
    pub focal_plane_temp_k: Option<f64>,
    pub t_illuminated_s: Option<f64>,
}

impl ExposureMeta {
    /// The reset that ends this exposure: `t_start + t_exposure` (ICD "Timing").
    pub fn t_reset(&self) -> UtcSeconds {
        self.t_start.plus(Seconds(self.t_exposure_s))
    }

    /// Seconds of illumination used for the extrapolated fluence (ICD "Timing").
    pub fn t_illuminated_s(&self) -> f64 {
        self.t_illuminated_s.unwrap_or(self.t_exposure_s)
    }
}

/// A whole input product.
#[derive(Debug, Clone, PartialEq)]
pub struct Exposure {
    pub meta: ExposureMeta,
    /// Line-fit current, e-/s; NaN where no value. [ny, nx]
    pub image: Array2<f32>,
    /// On-board flag bits. [ny, nx]
    pub flags: Array2<u32>,
    /// Sample-up-the-ramp charge, electrons [nsamp, ny, nx] (laboratory data only).
    pub ramp: Option<Array3<f32>>,
    /// Sample times after the reset that started the integration, seconds `[nsamp]`.
    pub ramp_times_s: Option<Array1<f64>>,
}

/// What the stage adds to an output product.
#[derive(Debug, Clone, PartialEq)]
pub struct PersistencePlanes {
    /// Predicted persistence current at `t_meas`, e-/s. [ny, nx]
    pub current_e_per_s: Array2<f32>,
    /// `pbits` per pixel. [ny, nx]
    pub flags: Array2<u8>,
}

/// Attributes of `/persistence` in an output product (ICD "Output").
#[derive(Debug, Clone, PartialEq)]
pub struct PersistenceAttrs {
    /// SHA-256 (hex) of the model file in canonical form.
    pub model_id: String,
    pub model_name: String,
    pub threshold_high_e_per_s: f64,
    pub threshold_low_e_per_s: f64,
    /// Time after the previous reset at which the prediction was evaluated; NaN when
    /// there is no previous exposure.
    pub t_meas_s: f64,
    /// The previous exposure index whose state was used, or -1 for none.
    pub previous_exposure_index: i64,
    pub software_version: String,
    /// UTC time of processing. Excluded from byte-identity comparisons by construction:
    /// tests compare the datasets; the stage can pin it with `--processing-time`.
    pub processed_utc: String,
    /// What this exposure flagged (`None`: an output written before these attributes).
    pub stats: Option<FlagStats>,
    /// Set on an output of a time-split span that started from zero with a warm-up
    /// ([`crate::timesplit`]); `None` on every output computed from the whole history.
    pub warmup: Option<WarmupAttrs>,
}

/// What an output computed after a warm-up (not from the whole history) records
/// (attributes of `/persistence`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WarmupAttrs {
    /// Seconds of data stepped from a zero state before the first published exposure.
    pub warmup_s: f64,
    /// The most persistence current, e-/s, the history before the warm-up could still
    /// add to any pixel of this output (the model's bound, [`crate::timesplit`]).
    pub carry_in_bound_e_per_s: f64,
}

/// Per-exposure statistics of an output's persistence flags (attributes of
/// `/persistence`). Invariant: they are counts of `/persistence/flags` itself, so a
/// reader recounts them from the plane ([`FlagStats::of_plane`]) and finds the same.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FlagStats {
    /// Fraction of the pixels with bit 0 (above the high threshold), in [0, 1].
    pub fraction_above_high: f64,
    /// Fraction of the pixels with bit 1 (above the low threshold), in [0, 1].
    pub fraction_above_low: f64,
    /// Pixels flagged `PERSIST` (bit 0; `PERSIST` in `/flags` is set exactly there).
    pub n_flagged: u64,
}

impl FlagStats {
    /// From counts of pixels with bit 0 and bit 1 among `pixels`.
    pub fn from_counts(pixels: u64, above_high: u64, above_low: u64) -> FlagStats {
        let fraction = |n: u64| n as f64 / pixels.max(1) as f64;
        FlagStats {
            fraction_above_high: fraction(above_high),
            fraction_above_low: fraction(above_low),
            n_flagged: above_high,
        }
    }

    /// Counted from a persistence flag plane.
    pub fn of_plane(pflags: &Array2<u8>) -> FlagStats {
        use rayon::prelude::*;
        let block = |c: &[u8]| {
            c.iter().fold((0u64, 0u64), |(h, l), &f| {
                (
                    h + u64::from(f & pbits::HIGH != 0),
                    l + u64::from(f & pbits::LOW != 0),
                )
            })
        };
        let (high, low) = match pflags.as_slice() {
            Some(s) => s
                .par_chunks(1 << 16)
                .map(block)
                .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1)),
            None => block(&pflags.iter().copied().collect::<Vec<u8>>()),
        };
        FlagStats::from_counts(pflags.len() as u64, high, low)
    }
}
