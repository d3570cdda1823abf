//! Tiny products for tests and examples, deterministic (no random numbers).

use super::exposure::{bits, Exposure, ExposureMeta};
use crate::units::{DetectorId, UtcSeconds};
use ndarray::Array2;

/// A small valid input product: a faint ramp of currents (0.5 e-/s and up) with one
/// bright pixel, one NaN pixel, one `TRANSIENT` and one `NONFUNC` flag.
///
/// `t_start` is kept as given; when it does not parse, `meta.t_start` is NaN (so tests
/// can build invalid products on purpose). Likewise `detector` is not range-checked.
pub fn tiny_exposure(
    detector: u8,
    index: u64,
    ny: usize,
    nx: usize,
    t_start: &str,
    t_exposure_s: f64,
) -> Exposure {
    let mut image = Array2::from_shape_fn((ny, nx), |(y, x)| 0.5 + ((y * 7 + x * 3) % 11) as f32);
    let mut flags = Array2::<u32>::zeros((ny, nx));
    if ny > 2 && nx > 2 {
        image[[1, 1]] = 5.0e4;
        image[[ny - 1, nx - 1]] = f32::NAN;
        flags[[2, 1]] = bits::TRANSIENT;
        flags[[0, nx - 1]] = bits::NONFUNC;
    }
    Exposure {
        meta: ExposureMeta {
            detector: DetectorId(detector),
            exposure_index: index,
            t_start_utc: t_start.to_owned(),
            t_start: UtcSeconds::parse(t_start).unwrap_or(UtcSeconds(f64::NAN)),
            t_exposure_s,
            focal_plane_temp_k: Some(80.0),
            t_illuminated_s: None,
        },
        image,
        flags,
        ramp: None,
        ramp_times_s: None,
    }
}
