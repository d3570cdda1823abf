//! Writes the committed fixtures: 2 detectors x 12 exposures of 64 x 64 pixels.
//!
//! `cargo run --example make_fixtures -- fixtures/` (see fixtures/README.md). The scene is
//! hand-made, not the simulator: a flat sky with Gaussian noise, a bright star seen in
//! three exposures, a saturated patch, a cosmic-ray transient, dead pixels, then a
//! dark stretch. Deterministic: the same bytes every time (a test checks it).

use ndarray::Array2;
use persist::flags::bits;
use persist::product::synthetic::tiny_exposure;
use persist::product::Exposure;
use persist::units::UtcSeconds;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use std::path::{Path, PathBuf};

pub const N: usize = 64;
pub const EXPOSURES: u64 = 12;
const T_EXPOSURE_S: f64 = 112.0;
/// Slews between exposures, seconds: mostly 30 s, one long one (exposure 6).
const SLEWS_S: [f64; 12] = [
    0.0, 30.0, 28.0, 35.0, 30.0, 32.0, 900.0, 30.0, 31.0, 29.0, 30.0, 33.0,
];

fn exposure(det: u8, k: u64, t_start: f64) -> Exposure {
    let mut rng = ChaCha8Rng::seed_from_u64(1000 * u64::from(det) + k);
    let dark = k >= 6;
    // Sky 1.2 e-/s with 0.1 e-/s noise; the dark stretch (k >= 6) has 0.02 e-/s.
    let (level, sigma) = if dark { (0.02, 0.02) } else { (1.2, 0.1) };
    let noise = Normal::new(level, sigma).expect("valid normal");
    let mut image = Array2::from_shape_fn((N, N), |_| noise.sample(&mut rng) as f32);
    let mut flags = Array2::<u32>::zeros((N, N));
    let off = if det == 1 { 0 } else { 7 };
    // A bright star (peak 3000 e-/s, sigma 2 px) in exposures 0, 1, 2.
    if k <= 2 {
        let (cy, cx) = (18.0 + off as f64, 20.0);
        for ((y, x), v) in image.indexed_iter_mut() {
            let r2 = (y as f64 - cy).powi(2) + (x as f64 - cx).powi(2);
            *v += (3000.0 * (-r2 / 8.0).exp()) as f32;
        }
    }
    // A saturated patch in exposure 3: 20,000 e-/s over 6 x 6 pixels (OVERFLOW), the
    // middle 2 x 2 without a usable slope (SUR_ERROR, NaN).
    if k == 3 {
        for y in 40..46 {
            for x in (40 - off)..(46 - off) {
                image[(y, x)] = 20_000.0;
                flags[(y, x)] |= bits::OVERFLOW;
            }
        }
        for y in 42..44 {
            for x in (42 - off)..(44 - off) {
                image[(y, x)] = f32::NAN;
                flags[(y, x)] |= bits::SUR_ERROR;
            }
        }
    }
    // A cosmic ray in exposure 5 (TRANSIENT) at one pixel.
    if k == 5 {
        image[(10, 50)] = 40.0;
        flags[(10, 50)] |= bits::TRANSIENT;
    }
    // Two dead pixels throughout.
    for (y, x) in [(5, 5), (60, 33 + off)] {
        image[(y, x)] = f32::NAN;
        flags[(y, x)] |= bits::NONFUNC;
    }
    let mut e = tiny_exposure(det, k, N, N, &UtcSeconds(t_start).to_iso(), T_EXPOSURE_S);
    e.image = image;
    e.flags = flags;
    e
}

/// Write all fixtures into `dir`; returns the paths written.
pub fn write_all(dir: &Path) -> persist::Result<Vec<PathBuf>> {
    std::fs::create_dir_all(dir).map_err(|e| persist::Error::io(dir, e))?;
    let t0 = UtcSeconds::parse("2026-03-01T00:00:00Z")
        .expect("valid time")
        .0;
    let mut paths = Vec::new();
    for det in [1u8, 2] {
        let mut t = t0 + f64::from(det) * 7.5;
        for k in 0..EXPOSURES {
            t += SLEWS_S[k as usize];
            let e = exposure(det, k, t);
            let path = dir.join(format!("l1_det{det}_exp{k:04}.h5"));
            persist::product::write::write_exposure(&path, &e)?;
            paths.push(path);
            t += T_EXPOSURE_S;
        }
    }
    Ok(paths)
}

#[allow(dead_code)]
fn main() {
    let dir = std::env::args().nth(1).unwrap_or_else(|| "fixtures".into());
    match write_all(Path::new(&dir)) {
        Ok(p) => println!("wrote {} products to {dir}", p.len()),
        Err(e) => {
            eprintln!("make_fixtures: {e}");
            std::process::exit(1);
        }
    }
}
