//! `persist simulate family`: a second, independent truth generator, written from
//! another physical description than [`crate::sim`] and than the model's effects, to
//! prove the diagnostics on physics they were not built against.
//!
//! It shares with the rest of the crate only the product layer (Level-1 products are
//! written by [`crate::product::write`] through [`crate::sim::output::Writer`], so the
//! layout and the truth files are exactly those of `persist simulate lab`), the random
//! sub-streams ([`crate::sim::rng`]) and the metadata helper ([`crate::sim::meta`]). No
//! trap, detector or effect code of [`crate::sim`] or [`crate::model`] is used.
//!
//! # Physics
//!
//! **Traps.** Each pixel holds two or three populations of traps. A population is a
//! *continuous* density of emission rates `k` (1/s) over emission times 1 s to 10^6 s:
//! - the main population: density per `ln k` proportional to `k^(beta - 1)`, which
//!   alone gives a current falling as `t^-beta` between the ends;
//! - a fast population: log-normal in emission time, centre 10^2..10^3 s, width
//!   0.4..0.7 decade;
//! - (half of the seeds) a slow population: log-normal, centre 10^3.3..10^4.3 s,
//!   width 0.5..0.8 decade.
//!
//! The densities are integrated on a private quadrature grid ([`traps`]: 12 nodes per
//! decade, midpoint rule in `ln k`; the analytic current of a `1/k` density is matched
//! to 2 %, a test).
//!
//! **Filling.** The charge `Q(t)` collected on the node exposes a fraction
//! `f = Q / FW` of each population's sites (`FW` the pixel's full well, ~2e5 e-). When
//! the pixel saturates (`Q` would exceed `FW`), forward bias exposes more: `f = 1 + J +
//! s ln(1 + E / FW)` with `E` the charge above full well, `J` the saturation jump and
//! `s` the slope beyond it. Traps capture at a *finite* rate
//! `c = c0 phi / (phi + phi_half)` (the photo-current `phi`: carriers to capture),
//! towards the exposed sites, and emit at their own rate at the same time
//! ([`traps::step`], exact for a piecewise-constant target; 60 steps while lit, 6 after
//! the shutter, while the charge stays on the node until the reset). After the reset
//! the traps only emit: node `j` releases `q_j (1 - exp(-k_j t))` by time `t`.
//!
//! **Readout** ([`readout`]): samples every 1.5 s, the least-squares slope of the
//! samples below half of full well (lit samples only in an illuminated integration),
//! `OVERFLOW` (bit 1) when the pixel reached full well; Poisson arrivals, white read
//! noise per sample, dark current. The first dark after each illumination keeps its
//! ramp (`/ramp`, `/ramp_times_s`), as the on-board data of a laboratory test would.
//! Trap emission during an illuminated integration is added as its mean current; the
//! charge captured from the signal is not subtracted from it (it is a fraction of a
//! percent).
//!
//! **Truth** (`OUT/truth/*.truth.hdf5`, the layout `persist compare
//! --touched-baseline` reads): `/true_persistence`, the mean over the integration of
//! the current released by charge trapped before it began, through the readout's
//! capacitive coupling when `ipc:*` is hidden; `/true_flux`, the lamp's flux. The
//! `truth.json` records `scenario = "family"`, the configuration (`config.campaign` is
//! the sequence's name), `effects = []` (no effect of [`crate::sim`]), the hidden
//! forms and every nuisance draw.
//!
//! # Nuisance physics (drawn per seed, [`scene::Nuisance::draw`])
//! Decay exponent `beta` 0.85..1.15; saturation jump `J` 0.1..0.5 and slope `s`
//! 0.05..0.2; populations (two or three) and their weights (fast 0.1..0.2, slow
//! 0.1..0.25); sites at full well 3e3..8e3 e- with a per-pixel log-normal scatter of
//! 5..15 %; full well 1.8e5..2.2e5 e- (3 % per pixel); read noise 8..20 e- per sample;
//! dark current 0.005..0.03 e-/s; capture rate 0.15..0.4 /s, halved at 3..15 e-/s.
//! Illumination: a spot of 8e4..1.3e5 e-/s at its centre (placed in the middle 30 % of
//! the array) falling by a decade every 0.06..0.1 array sizes, a leak along the left
//! edge of 300..3000 e-/s falling by a decade every 3..8 columns, every other pixel lit
//! at 15..60 e-/s, and (half of the seeds, or `--pinholes`) a grid of one-pixel
//! pinholes of 2e3, 1e4 and 5e4 e-/s every 8 pixels. `--dark-pixels` leaves the
//! right-hand quarter unlit (0.05 e-/s of scattered light).
//!
//! # Sequences ([`scene::SequenceKind`])
//! - `single` (the paper's): a 613 s integration lit for 481 s at 80 K, then `--darks`
//!   (default 120, 6 h) dark integrations of 180 s.
//! - `campaign`: six illuminations, each followed by 180 s darks:
//!
//! | # | lit | flux scale | T (K) | darks after | contrast |
//! |---|---|---|---|---|---|
//! | 1 | 481 s | 1 | 80 | 20 | |
//! | 2 | 120 s | 481/120 | 80 | 20 | duration at equal fluence |
//! | 3 | 481 s | 1 | 80 | 5 | |
//! | 4 | 481 s | 1 | 80 | 20 | repeat 15 min after 3: traps still full |
//! | 5 | 481 s | 1 | 78 | 20 | temperature |
//! | 6 | 481 s | 1 | 82 | 40 | temperature |
//!
//! The single sequence has none of these contrasts: soak, capacity and temperature are
//! untestable on it; blooming and ipc need the pinholes.
//!
//! # Hidden effects ([`hidden::Hidden`], `--hidden CLASS:FORM`), constants in [`engine`]
//! - `soak:capture`: nodes slower than 10^3 s capture at most at 1/400 s, so their
//!   filling is limited by the time the charge is on the node: 120 s lit (252 s
//!   charged) fills them to 47 %, 481 s (613 s) to 78 %.
//! - `soak:diffusion`: an extra deep population (35 % of the sites, emission times
//!   log-normal at 10^3.7 s, 0.5 decade) that charge reaches by diffusion: its
//!   occupancy is `sqrt(t / 2000 s)` of the exposed sites, `t` the time since the
//!   illumination began (no capture kinetics; emission as the others).
//! - `capacity:ceiling`: a hard ceiling on a pixel's total trapped charge (60 % of its
//!   sites): capture stops at it, whatever the exposure, within an illumination or
//!   across repeats.
//! - `capacity:langmuir`: sites are a shared pool (80 % of the sites); the fraction
//!   still occupied by earlier charge when an illumination begins is blocked
//!   (Langmuir blocking): a repeat fills `1 - held / pool` of what a fresh pixel would.
//! - `temperature:arrhenius`: every emission rate scales as `exp(1500 K (1/80 K - 1/T))` (x1.6
//!   from 80 to 82 K). A decay close to `1/t` is nearly scale-free, so this shows mostly
//!   through the log-normal populations and the ends of the density.
//! - `temperature:weight`: the main population's sites scale with the temperature at
//!   filling, `1 + 0.12 (T - 80 K)` (a thermally activated capture cross-section);
//!   emission rates do not change.
//! - `blooming:spill`: a quarter of 10^-3 of a neighbour's charge above full well
//!   spills into each of its four neighbours' wells (they collect it, and their ramps
//!   show it), along the trap-rich surface, so it exposes four times more sites than
//!   bulk charge.
//! - `blooming:field`: a saturated pixel's forward bias reaches its eight neighbours'
//!   traps: their exposure grows by `0.01 ln(1 + E / FW)` per cardinal neighbour (half
//!   per diagonal one); no charge moves.
//! - `ipc:cross4`: the read signal couples 2 % into each of the four neighbours.
//! - `ipc:aniso8`: 2.5 % along rows, 1 % along columns, 0.4 % to each diagonal.
//! - `populations:smooth`: sites times `1 + 0.4 (cos th u + sin th v) + 0.25 (u^2 -
//!   1/3)` over the array (`u, v` in -1..1, `th` drawn).
//! - `populations:patches`: five disks (radius 6..12 % of the array) of 2.5 times the
//!   sites.
//! - `shape:fill_depth`: the main population's weights at filling tilt towards slow
//!   nodes as `(k / 0.01)^(-0.1 u)`, `u = ln(1 + fluence / FW)`: brighter pixels decay
//!   more slowly.
//! - `shape:fast_ceiling`: the fast population's exposure never exceeds 0.15: it is
//!   full at low fluence, so the decay's shape changes with fluence.
//!
//! # Held aside for the final proof
//! The forms `temperature:weight`, `populations:patches` and `shape:fast_ceiling`
//! ([`hidden::HELD_ASIDE`]) and every seed from 100 on
//! ([`hidden::HELD_ASIDE_FIRST_SEED`]): the family matrix runs them only with
//! `--held-out`.
//!
//! Determinism: every random draw comes from a sub-stream keyed by (seed, purpose,
//! exposure, pixel), so the same seed gives byte-identical files, and a hidden effect
//! leaves the noise of the pixels it does not touch unchanged.

pub mod engine;
pub mod hidden;
pub mod readout;
pub mod scene;
pub mod traps;

use crate::error::{Error, Result};
use crate::product::Exposure;
use crate::sim::SimExposure;
use crate::units::Seconds;
use hidden::Hidden;
use scene::{Nuisance, SequenceKind, AFTER_SHUTTER_S, DARK_S};

/// Default darks after a single illumination (6 h).
pub const DEFAULT_DARKS: usize = 120;

/// What to generate.
#[derive(Debug, Clone)]
pub struct FamilyConfig {
    pub size: usize,
    pub seed: u64,
    pub sequence: SequenceKind,
    /// Darks after a single illumination (ignored by the campaign).
    pub darks: usize,
    pub dark_pixels: bool,
    /// `None`: drawn by the seed.
    pub pinholes: Option<bool>,
    pub hidden: Vec<Hidden>,
}

impl Default for FamilyConfig {
    fn default() -> Self {
        FamilyConfig {
            size: 64,
            seed: 1,
            sequence: SequenceKind::Single,
            darks: DEFAULT_DARKS,
            dark_pixels: false,
            pinholes: None,
            hidden: Vec::new(),
        }
    }
}

/// Check a configuration before anything is written.
pub fn validate(cfg: &FamilyConfig) -> Result<()> {
    if !(16..=2048).contains(&cfg.size) {
        return Err(Error::invalid(
            "--size",
            format!("{} is outside 16..=2048 pixels", cfg.size),
        ));
    }
    if !(1..=5000).contains(&cfg.darks) {
        return Err(Error::invalid(
            "--darks",
            format!("{} is outside 1..=5000", cfg.darks),
        ));
    }
    Ok(())
}

/// Run the sequence, handing each exposure to `sink`; returns the `truth.json`
/// description.
pub fn run(
    cfg: &FamilyConfig,
    mut sink: impl FnMut(SimExposure) -> Result<()>,
) -> Result<serde_json::Value> {
    validate(cfg)?;
    let n = cfg.size;
    let nu = Nuisance::draw(cfg.seed, n, cfg.pinholes);
    let flux1 = nu.flux(n, cfg.dark_pixels);
    let mut hidden = cfg.hidden.clone();
    hidden.sort();
    hidden.dedup();
    let mut eng = engine::Engine::new(nu.clone(), n, cfg.seed, &hidden);
    let t0 = crate::sim::epoch();
    let mut t = 0.0f64;
    let mut index = 0u64;
    let ills = cfg.sequence.illuminations(cfg.darks);
    for il in &ills {
        let flux = flux1.mapv(|v| (f64::from(v) * il.flux_scale) as f32);
        let t_exp = il.t_illuminated_s + AFTER_SHUTTER_S;
        let o = eng.illuminate(index, &flux, il.t_illuminated_s, t_exp, il.temp_k);
        sink(SimExposure {
            exposure: Exposure {
                meta: crate::sim::meta(
                    1,
                    index,
                    t0.plus(Seconds(t)),
                    t_exp,
                    il.temp_k,
                    Some(il.t_illuminated_s),
                ),
                image: o.image,
                flags: o.flags,
                ramp: None,
                ramp_times_s: None,
            },
            true_persistence: o.true_persistence,
            true_flux: flux,
            kind: "illuminated".into(),
        })?;
        index += 1;
        t += t_exp;
        for d in 0..il.darks_after {
            let o = eng.dark(index, DARK_S, il.temp_k, d == 0);
            sink(SimExposure {
                exposure: Exposure {
                    meta: crate::sim::meta(1, index, t0.plus(Seconds(t)), DARK_S, il.temp_k, None),
                    image: o.image,
                    flags: o.flags,
                    ramp: o.ramp,
                    ramp_times_s: o.ramp_times_s,
                },
                true_persistence: o.true_persistence,
                true_flux: ndarray::Array2::zeros((n, n)),
                kind: "dark".into(),
            })?;
            index += 1;
            t += DARK_S;
        }
    }
    Ok(serde_json::json!({
        "scenario": "family",
        "generator": "persist::trapgen",
        "config": {
            "size": n,
            "seed": cfg.seed,
            "campaign": cfg.sequence.to_string(),
            "darks": cfg.darks,
            "dark_pixels": cfg.dark_pixels,
            "pinholes": nu.pinholes,
        },
        "effects": [],
        "hidden": hidden.iter().map(|h| h.to_string()).collect::<Vec<_>>(),
        "held_aside": hidden.iter().any(|h| h.held_aside()) || cfg.seed >= hidden::HELD_ASIDE_FIRST_SEED,
        "illuminations": ills,
        "nuisance": nu,
    }))
}
