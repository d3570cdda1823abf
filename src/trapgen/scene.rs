//! What each seed draws (the nuisance physics and the illumination pattern) and the
//! sequences of exposures. See the module docs of [`crate::trapgen`] for the ranges.

use crate::sim::rng;
use ndarray::Array2;
use rand::Rng;
use serde::Serialize;

/// Stream purposes of this generator (kept apart from every other generator's by a
/// high tag).
pub mod purpose {
    pub const NUISANCE: u64 = 0x7a_0001;
    pub const PIXEL_MAPS: u64 = 0x7a_0002;
    pub const NOISE: u64 = 0x7a_0003;
    pub const PATCHES: u64 = 0x7a_0004;
}

/// Laboratory temperature of the reference, K.
pub const T_REF_K: f64 = 80.0;
/// Seconds the array stays charged after the shutter closes (the paper's 613 - 481 s).
pub const AFTER_SHUTTER_S: f64 = 132.0;

/// One trap population: a density of emission times and its share of the sites.
#[derive(Debug, Clone, Serialize)]
pub struct Population {
    /// `power_law` (density per ln k proportional to k^(beta-1)) or `log_normal`.
    pub kind: &'static str,
    pub beta: f64,
    pub log10_tau_s: f64,
    pub sigma_dex: f64,
    pub weight: f64,
}

/// The detector and lamp one seed draws.
#[derive(Debug, Clone, Serialize)]
pub struct Nuisance {
    /// Effective decay exponent of the power-law population.
    pub beta: f64,
    pub populations: Vec<Population>,
    /// Trap sites a pixel exposes at full well (all populations), e-.
    pub sites_e: f64,
    /// Per-pixel log-normal scatter of each population's sites.
    pub site_scatter: f64,
    /// Extra exposure fraction added when the pixel saturates (the response's jump).
    pub saturation_jump: f64,
    /// Growth of the exposure fraction with ln(1 + excess / full well) beyond it.
    pub saturation_log_slope: f64,
    pub full_well_e: f64,
    pub full_well_scatter: f64,
    pub read_noise_e: f64,
    pub dark_e_per_s: f64,
    /// Capture rate at high flux, 1/s, and the flux at which it is halved, e-/s.
    pub capture_per_s: f64,
    pub capture_half_flux_e_per_s: f64,
    // illumination pattern
    pub spot_centre: [f64; 2],
    pub spot_peak_e_per_s: f64,
    /// Distance (pixels) over which the spot falls by a decade.
    pub spot_decade_px: f64,
    pub leak_e_per_s: f64,
    pub leak_decade_cols: f64,
    pub floor_e_per_s: f64,
    pub pinholes: bool,
}

/// Uniform draw in [a, b].
fn u(r: &mut impl Rng, a: f64, b: f64) -> f64 {
    a + (b - a) * r.random::<f64>()
}

impl Nuisance {
    /// The seed's draw (`pinholes`: `None` draws it too).
    pub fn draw(seed: u64, size: usize, pinholes: Option<bool>) -> Nuisance {
        let mut r = rng::stream(seed, &[purpose::NUISANCE]);
        let beta = u(&mut r, 0.85, 1.15);
        let three = r.random::<f64>() < 0.5;
        let w_fast = u(&mut r, 0.1, 0.2);
        let w_slow = if three { u(&mut r, 0.1, 0.25) } else { 0.0 };
        let mut populations = vec![
            Population {
                kind: "power_law",
                beta,
                log10_tau_s: f64::NAN,
                sigma_dex: f64::NAN,
                weight: 1.0 - w_fast - w_slow,
            },
            Population {
                kind: "log_normal",
                beta: f64::NAN,
                log10_tau_s: u(&mut r, 2.0, 3.0),
                sigma_dex: u(&mut r, 0.4, 0.7),
                weight: w_fast,
            },
        ];
        let slow_centre = u(&mut r, 3.3, 4.3);
        let slow_sigma = u(&mut r, 0.5, 0.8);
        if three {
            populations.push(Population {
                kind: "log_normal",
                beta: f64::NAN,
                log10_tau_s: slow_centre,
                sigma_dex: slow_sigma,
                weight: w_slow,
            });
        }
        let n = size as f64;
        let centre = [u(&mut r, 0.35, 0.65) * n, u(&mut r, 0.35, 0.65) * n];
        let drawn_pinholes = r.random::<f64>() < 0.5;
        Nuisance {
            beta,
            populations,
            sites_e: u(&mut r, 3.0e3, 8.0e3),
            site_scatter: u(&mut r, 0.05, 0.15),
            saturation_jump: u(&mut r, 0.1, 0.5),
            saturation_log_slope: u(&mut r, 0.05, 0.2),
            full_well_e: u(&mut r, 1.8e5, 2.2e5),
            full_well_scatter: 0.03,
            read_noise_e: u(&mut r, 8.0, 20.0),
            dark_e_per_s: u(&mut r, 0.005, 0.03),
            capture_per_s: u(&mut r, 0.15, 0.4),
            capture_half_flux_e_per_s: u(&mut r, 3.0, 15.0),
            spot_centre: centre,
            spot_peak_e_per_s: u(&mut r, 8.0e4, 1.3e5),
            spot_decade_px: u(&mut r, 0.06, 0.1) * n,
            leak_e_per_s: u(&mut r, 300.0, 3000.0),
            leak_decade_cols: u(&mut r, 3.0, 8.0),
            floor_e_per_s: u(&mut r, 15.0, 60.0),
            pinholes: pinholes.unwrap_or(drawn_pinholes),
        }
    }

    /// The lamp's flux (e-/s) at scale 1: spot + edge leak + floor (+ pinholes), with
    /// the right-hand quarter unlit (0.05 e-/s of scattered light) when `dark_pixels`.
    pub fn flux(&self, size: usize, dark_pixels: bool) -> Array2<f32> {
        let dark_from = size - size / 4;
        Array2::from_shape_fn((size, size), |(y, x)| {
            if dark_pixels && x >= dark_from {
                return 0.05;
            }
            let dy = y as f64 + 0.5 - self.spot_centre[0];
            let dx = x as f64 + 0.5 - self.spot_centre[1];
            let r = (dy * dy + dx * dx).sqrt();
            let spot = self.spot_peak_e_per_s * 10f64.powf(-r / self.spot_decade_px);
            let leak = self.leak_e_per_s * 10f64.powf(-(x as f64) / self.leak_decade_cols);
            let mut f = spot + leak + self.floor_e_per_s;
            if self.pinholes && is_pinhole(y, x, size) {
                f += PINHOLE_E_PER_S[(y / PINHOLE_SPACING_PX + x / PINHOLE_SPACING_PX) % 3];
            }
            f as f32
        })
    }
}

/// Spacing of the pinhole grid, pixels.
pub const PINHOLE_SPACING_PX: usize = 8;
/// Fluxes of the pinholes, in turn, e-/s.
pub const PINHOLE_E_PER_S: [f64; 3] = [2.0e3, 1.0e4, 5.0e4];

fn is_pinhole(y: usize, x: usize, size: usize) -> bool {
    let s = PINHOLE_SPACING_PX;
    y % s == s / 2 && x % s == s / 2 && x >= 2 * s && x + s < size - size / 4
}

/// One illumination and the darks after it.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Illumination {
    pub t_illuminated_s: f64,
    pub flux_scale: f64,
    pub temp_k: f64,
    pub darks_after: usize,
}

/// The sequences.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum SequenceKind {
    Single,
    Campaign,
}

choices!(SequenceKind, "--sequence", Single => "single", Campaign => "campaign");

/// Dark integration length, s ("every ~3 minutes").
pub const DARK_S: f64 = 180.0;

impl SequenceKind {
    /// The illuminations (`darks`: darks after a single illumination).
    pub fn illuminations(self, darks: usize) -> Vec<Illumination> {
        let il = |t, s, k, d| Illumination {
            t_illuminated_s: t,
            flux_scale: s,
            temp_k: k,
            darks_after: d,
        };
        match self {
            SequenceKind::Single => vec![il(481.0, 1.0, T_REF_K, darks)],
            SequenceKind::Campaign => vec![
                il(481.0, 1.0, 80.0, 20),
                il(120.0, 481.0 / 120.0, 80.0, 20),
                il(481.0, 1.0, 80.0, 5),
                il(481.0, 1.0, 80.0, 20),
                il(481.0, 1.0, 78.0, 20),
                il(481.0, 1.0, 82.0, 40),
            ],
        }
    }
}
