//! A SPHEREx-like survey: integrations, slews, zodiacal light, stars.
//!
//! # Timing
//! Integrations of `t_exposure_s` = 112 s (SPHEREx's ~112 s; Crill et al. 2020), read
//! every 1.5 s, separated by slews of 20 to 60 s ("tens of seconds") during which the
//! arrays are reset frequently (no charge collected: traps only emit, paper section 5).
//! Defaults: 2040 x 2040 pixels, six detectors (independent histories, each its own
//! part of the sky), 1143 exposures (the paper's two simulated days).
//!
//! # Fields ([`plan`])
//! Each exposure points at one field: every 6th exposure revisits one of two deep fields
//! (the ecliptic poles; alternating every 12 visits), so the same stars fall on the same
//! pixels within half a pixel; 10 % of the others are bright Galactic-plane fields (30x
//! the star density); the rest are ordinary fields seen once.
//!
//! # Sky
//! - Zodiacal light: uniform in 0.5 to 2 e-/s per field (0.5 to 0.7 at the deep fields,
//!   1 to 2 in the plane), with a 5 % gradient across the array (paper section 5:
//!   zodiacal light is always present).
//! - Stars: cumulative counts `N(<m) = n12 10^(0.35 (m - 12))` per array, `n12` = 30
//!   stars brighter than m = 12 at high latitude (2.5 per deg^2 over the 12.2 deg^2 of
//!   an array), from m = 3 to m = 18. The scale is anchored at saturation (below), so
//!   `n12` is the number of stars that fill a pixel's well in one integration: a photon
//!   budget for SPHEREx (20 cm, lambda/41 channels) puts that at AB ~ 9 (Ks ~ 7.2), where
//!   2MASS counts extrapolated with their 0.32 dex/mag slope give 30 to 60 per array;
//!   `docs/validation/floor_scan.md` gives the derivation and scans `--n12`, `--count-slope`,
//!   `--plane-fraction`, `--plane-density` and `--cosmic-rate`. Total flux
//!   `F(m) = F12 10^(-0.4 (m - 12))` with `F12` set so that a star of magnitude 12
//!   centred on a pixel just fills the well in one integration (paper section 5: "sources
//!   brighter than a magnitude of 12 will saturate"). PSF: 95 % in a Gaussian of
//!   sigma 0.8 px, 5 % in a halo of sigma 3 px, integrated over pixels.
//! - Focal plane: 80 K + 20 mK orbital (94 min) oscillation + 10 mK per detector.
//!
//! # Truth
//! Per exposure the true sky flux (zodi + stars, e-/s) and the true persistence current
//! ([`super::engine`]), written beside the products.

use super::detector::DetectorParams;
use super::effect::{EffectSet, EffectSpec};
use super::effects::populations::norm_cdf;
use super::engine::{ExposureSpec, SimDetector};
use super::rng::{purpose, stream};
use super::traps::TrapParams;
use super::{epoch, meta, SimExposure};
use crate::product::Exposure;
use crate::units::Seconds;
use ndarray::Array2;
use rand::Rng;
use serde::Serialize;
use std::sync::Arc;

#[derive(Debug, Clone, Serialize)]
pub struct SkyConfig {
    pub size: usize,
    pub detectors: u8,
    pub exposures: u64,
    pub seed: u64,
    pub t_exposure_s: f64,
    pub slew_min_s: f64,
    pub slew_max_s: f64,
    pub deep_every: u64,
    pub plane_fraction: f64,
    /// Stars brighter than m = 12 per 2040 x 2040 array at high latitude.
    pub n12_per_array: f64,
    pub plane_density: f64,
    pub m_bright: f64,
    pub m_faint: f64,
    pub count_slope: f64,
    #[serde(skip)]
    pub effects: Vec<EffectSpec>,
    pub traps: TrapParams,
    pub detector: DetectorParams,
}

impl Default for SkyConfig {
    fn default() -> Self {
        SkyConfig {
            size: 2040,
            detectors: 6,
            exposures: 1143,
            seed: 1,
            t_exposure_s: 112.0,
            slew_min_s: 20.0,
            slew_max_s: 60.0,
            deep_every: 6,
            plane_fraction: 0.1,
            n12_per_array: 30.0,
            plane_density: 30.0,
            m_bright: 3.0,
            m_faint: 18.0,
            count_slope: 0.35,
            effects: Vec::new(),
            traps: TrapParams::default(),
            detector: DetectorParams::default(),
        }
    }
}

/// Kind of field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldKind {
    Normal,
    Deep,
    Plane,
}

/// One pointing of the survey (the same for all detectors).
#[derive(Debug, Clone, Serialize)]
pub struct Pointing {
    pub kind: FieldKind,
    pub field_id: u64,
    /// Slew (reset interval) before the integration, s.
    pub slew_s: f64,
    pub zodi_e_per_s: f64,
    /// Pointing offset, px.
    pub dx: f64,
    pub dy: f64,
}

/// The survey plan.
pub fn plan(cfg: &SkyConfig) -> Vec<Pointing> {
    let mut r = stream(cfg.seed, &[purpose::PLAN]);
    let mut next_id = 2u64;
    let mut deep_visits = 0u64;
    (0..cfg.exposures)
        .map(|k| {
            let slew_s = cfg.slew_min_s + (cfg.slew_max_s - cfg.slew_min_s) * r.random::<f64>();
            let (dx, dy) = (r.random::<f64>() - 0.5, r.random::<f64>() - 0.5);
            let u: f64 = r.random();
            let z: f64 = r.random();
            if cfg.deep_every > 0 && k % cfg.deep_every == cfg.deep_every - 1 {
                let id = (deep_visits / 12) % 2;
                deep_visits += 1;
                Pointing {
                    kind: FieldKind::Deep,
                    field_id: id,
                    slew_s,
                    zodi_e_per_s: 0.5 + 0.2 * z,
                    dx,
                    dy,
                }
            } else {
                let id = next_id;
                next_id += 1;
                let plane = u < cfg.plane_fraction;
                Pointing {
                    kind: if plane {
                        FieldKind::Plane
                    } else {
                        FieldKind::Normal
                    },
                    field_id: id,
                    slew_s,
                    zodi_e_per_s: if plane { 1.0 + z } else { 0.5 + 1.5 * z },
                    dx,
                    dy,
                }
            }
        })
        .collect()
}

/// Check the configuration (and the effects) before anything is written.
pub fn validate(cfg: &SkyConfig) -> crate::Result<()> {
    let bad = |f: &str, m: String| Err(crate::Error::invalid(f, m));
    if cfg.size < 4 || cfg.size > 8192 {
        return bad("--size", format!("must be 4..=8192, got {}", cfg.size));
    }
    if cfg.detectors < 1 || cfg.detectors > 6 {
        return bad(
            "--detectors",
            format!("must be 1..=6, got {}", cfg.detectors),
        );
    }
    if cfg.exposures < 1 {
        return bad("--exposures", "must be >= 1".into());
    }
    if cfg.t_exposure_s.is_nan() || cfg.t_exposure_s < 3.0 * cfg.detector.frame_time_s {
        return bad("t_exposure_s", "shorter than three frames".into());
    }
    if !(cfg.slew_min_s >= 0.0 && cfg.slew_max_s >= cfg.slew_min_s) {
        return bad("slew_min_s", "need 0 <= slew_min_s <= slew_max_s".into());
    }
    if cfg.m_faint.is_nan() || cfg.m_bright.is_nan() || cfg.m_faint <= cfg.m_bright {
        return bad("m_faint", "must exceed m_bright".into());
    }
    if !(cfg.n12_per_array.is_finite() && cfg.n12_per_array >= 0.0) {
        return bad(
            "--n12",
            format!("must be finite and >= 0, got {}", cfg.n12_per_array),
        );
    }
    if !(cfg.count_slope.is_finite() && cfg.count_slope > 0.0) {
        return bad(
            "--count-slope",
            format!("must be finite and > 0, got {}", cfg.count_slope),
        );
    }
    if !(0.0..=1.0).contains(&cfg.plane_fraction) {
        return bad(
            "--plane-fraction",
            format!("must be in 0..=1, got {}", cfg.plane_fraction),
        );
    }
    if !(cfg.plane_density.is_finite() && cfg.plane_density >= 0.0) {
        return bad(
            "--plane-density",
            format!("must be finite and >= 0, got {}", cfg.plane_density),
        );
    }
    let cr = cfg.detector.cosmic_rate_per_cm2_s;
    if !(cr.is_finite() && cr >= 0.0) {
        return bad(
            "--cosmic-rate",
            format!("must be finite and >= 0, got {cr}"),
        );
    }
    EffectSet::from_specs(&cfg.effects)?;
    Ok(())
}

/// Total flux of a magnitude-12 star, e-/s: its centred peak pixel fills the well.
pub fn f12(cfg: &SkyConfig) -> f64 {
    let c = 2.0 * norm_cdf(0.5 / 0.8) - 1.0;
    let h = 2.0 * norm_cdf(0.5 / 3.0) - 1.0;
    let peak = 0.95 * c * c + 0.05 * h * h;
    cfg.detector.full_well_e / cfg.t_exposure_s / peak
}

/// The true sky (zodi + stars) of detector `det` at pointing `p`, e-/s.
pub fn sky_flux(cfg: &SkyConfig, det: u8, p: &Pointing) -> Array2<f32> {
    let n = cfg.size;
    let mut f = Array2::from_shape_fn((n, n), |(_, x)| {
        (p.zodi_e_per_s * (1.0 + 0.05 * (x as f64 / n as f64 - 0.5))) as f32
    });
    let area = (n as f64 / 2040.0).powi(2);
    let density = match p.kind {
        FieldKind::Plane => cfg.plane_density,
        FieldKind::Deep => 0.7,
        FieldKind::Normal => 1.0,
    };
    let a = cfg.count_slope;
    let n_tot = cfg.n12_per_array * area * density * 10f64.powf(a * (cfg.m_faint - 12.0));
    let mut r = stream(cfg.seed, &[purpose::STARS, u64::from(det), p.field_id]);
    // Poisson count via the normal approximation for large means, exact-ish for small
    let count = {
        let mut k = 0u64;
        if n_tot < 50.0 {
            let l = (-n_tot).exp();
            let mut prod: f64 = r.random();
            while prod > l {
                k += 1;
                prod *= r.random::<f64>();
            }
            k
        } else {
            let z: f64 = rand_distr::Distribution::sample(&rand_distr::StandardNormal, &mut r);
            (n_tot + z * n_tot.sqrt()).round().max(0.0) as u64
        }
    };
    let u_min = 10f64.powf(a * (cfg.m_bright - cfg.m_faint));
    let f12 = f12(cfg);
    for _ in 0..count {
        let xc = r.random::<f64>() * n as f64 + p.dx;
        let yc = r.random::<f64>() * n as f64 + p.dy;
        let u = u_min + (1.0 - u_min) * r.random::<f64>();
        let m = cfg.m_faint + u.log10() / a;
        let flux = f12 * 10f64.powf(-0.4 * (m - 12.0));
        let rad = if m > 12.0 {
            4
        } else {
            (4.0 + 2.0 * (12.0 - m)).min(24.0) as i64
        };
        stamp(&mut f, xc - 0.5, yc - 0.5, flux, rad);
    }
    f
}

fn stamp(f: &mut Array2<f32>, xc: f64, yc: f64, flux: f64, rad: i64) {
    let (ny, nx) = f.dim();
    let (ix, iy) = (xc.round() as i64, yc.round() as i64);
    let frac = |d: f64, s: f64| norm_cdf((d + 0.5) / s) - norm_cdf((d - 0.5) / s);
    for y in (iy - rad).max(0)..=(iy + rad).min(ny as i64 - 1) {
        let (cy, hy) = (frac(y as f64 - yc, 0.8), frac(y as f64 - yc, 3.0));
        for x in (ix - rad).max(0)..=(ix + rad).min(nx as i64 - 1) {
            let (cx, hx) = (frac(x as f64 - xc, 0.8), frac(x as f64 - xc, 3.0));
            let v = flux * (0.95 * cy * cx + 0.05 * hy * hx);
            f[[y as usize, x as usize]] += v as f32;
        }
    }
}

fn temp_at(det: u8, t: f64) -> f64 {
    80.0 + 0.02 * (2.0 * std::f64::consts::PI * t / 5640.0).sin() + 0.01 * f64::from(det - 1)
}

/// [`run`] written as products with their truth into `dir` ([`super::output::Writer`]):
/// the number of products written.
pub fn write(cfg: &SkyConfig, dir: &std::path::Path) -> crate::Result<usize> {
    let mut w = super::output::Writer::new(dir)?;
    let description = run(cfg, |e| w.write(&e))?;
    w.finish(description)
}

/// Run the survey, detector by detector, handing each exposure to `sink`.
pub fn run(
    cfg: &SkyConfig,
    mut sink: impl FnMut(SimExposure) -> crate::Result<()>,
) -> crate::Result<serde_json::Value> {
    validate(cfg)?;
    let effects = Arc::new(EffectSet::from_specs(&cfg.effects)?);
    let pl = plan(cfg);
    let t0 = epoch();
    for det in 1..=cfg.detectors {
        let mut sim = SimDetector::new(
            cfg.traps.clone(),
            cfg.detector.clone(),
            effects.clone(),
            cfg.size,
            cfg.size,
            cfg.seed,
            det,
        )?;
        let mut t = 0.0f64;
        for (k, p) in pl.iter().enumerate() {
            let temp = temp_at(det, t);
            sim.gap(p.slew_s, temp);
            t += p.slew_s;
            let flux = sky_flux(cfg, det, p);
            let out = sim.expose(&ExposureSpec {
                index: k as u64,
                flux: &flux,
                t_exposure_s: cfg.t_exposure_s,
                t_on_s: cfg.t_exposure_s,
                temp_k: temp,
                write_ramp: false,
            })?;
            sink(SimExposure {
                exposure: Exposure {
                    meta: meta(
                        det,
                        k as u64,
                        t0.plus(Seconds(t)),
                        cfg.t_exposure_s,
                        temp,
                        None,
                    ),
                    image: out.image,
                    flags: out.flags,
                    ramp: None,
                    ramp_times_s: None,
                },
                true_persistence: out.true_persistence,
                true_flux: out.flux,
                kind: match p.kind {
                    FieldKind::Normal => "normal",
                    FieldKind::Deep => "deep_field",
                    FieldKind::Plane => "galactic_plane",
                }
                .into(),
            })?;
            t += cfg.t_exposure_s;
        }
    }
    Ok(serde_json::json!({
        "scenario": "sky",
        "config": cfg,
        "effects": effects.describe(),
        "f12_e_per_s": f12(cfg),
        "plan": pl,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn magnitude_12_just_saturates() {
        let cfg = SkyConfig::default();
        let mut f = Array2::<f32>::zeros((21, 21));
        stamp(&mut f, 10.0, 10.0, f12(&cfg), 10);
        let q = f64::from(f[[10, 10]]) * cfg.t_exposure_s;
        assert!((q / 2e5 - 1.0).abs() < 0.01, "{q}");
        assert!((f.sum() as f64 / f12(&cfg) - 1.0).abs() < 0.02);
    }

    #[test]
    fn validate_names_the_bad_sky_option() {
        let bad = [
            (
                "--n12",
                SkyConfig {
                    n12_per_array: -1.0,
                    ..SkyConfig::default()
                },
            ),
            (
                "--count-slope",
                SkyConfig {
                    count_slope: f64::NAN,
                    ..SkyConfig::default()
                },
            ),
            (
                "--plane-fraction",
                SkyConfig {
                    plane_fraction: 1.5,
                    ..SkyConfig::default()
                },
            ),
            (
                "--plane-density",
                SkyConfig {
                    plane_density: -2.0,
                    ..SkyConfig::default()
                },
            ),
        ];
        for (field, cfg) in bad {
            let e = validate(&cfg).unwrap_err().to_string();
            assert!(e.contains(field), "{field}: {e}");
        }
        let mut cfg = SkyConfig::default();
        cfg.detector.cosmic_rate_per_cm2_s = f64::INFINITY;
        assert!(validate(&cfg)
            .unwrap_err()
            .to_string()
            .contains("--cosmic-rate"));
        assert!(validate(&SkyConfig::default()).is_ok());
    }

    #[test]
    fn plan_has_deep_repeats_and_plane_fields() {
        let cfg = SkyConfig {
            exposures: 200,
            ..SkyConfig::default()
        };
        let p = plan(&cfg);
        assert!(p.iter().filter(|q| q.kind == FieldKind::Deep).count() >= 30);
        assert!(p.iter().any(|q| q.kind == FieldKind::Plane));
        assert!(p.iter().all(|q| (20.0..=60.0).contains(&q.slew_s)));
    }
}
