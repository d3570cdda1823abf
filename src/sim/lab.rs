//! The paper's laboratory test (section 2.1) and a campaign of several illuminations.
//!
//! # Single illumination (default)
//! - exposure 0: a 613 s sample-up-the-ramp integration, illuminated for the first 481 s
//!   (`t_illuminated_s` = 481) through a pinhole;
//! - then `darks` (default 280 = 14 h) dark integrations of 180 s, back to back (the
//!   paper: "every three minutes over the following fourteen hours"); the first keeps
//!   its ramp (`/ramp`, `/ramp_times_s`);
//! - focal plane at 80 K with a slow 5 mK drift (2 h period);
//! - cosmic rays at the laboratory rate (0.02 /cm^2/s).
//!
//! # Pinhole pattern ([`pinhole`])
//! A central spot of 2e5 e-/s (paper Fig. 1: "over 100,000 e-/s") whose flux falls by
//! 10^(-4 r/R) with the distance `r` from the centre (`R` half the array size), i.e. four
//! decades from centre to edge, so every fluence from ~1e4 to ~1e8 e- in 481 s is
//! populated in rings (at 256 x 256 the Table 1 bins hold 150 to 350 pixels each), plus
//! a leak along the left edge (paper Fig. 1: "significant light leakage ... along one
//! edge"): 300 e-/s at the edge falling by a decade every 6 columns, and a floor of
//! 0.05 e-/s of scattered light.
//!
//! # Campaign (`--campaign`)
//! Illuminations of different durations, fluxes (scales of the pinhole pattern) and
//! temperatures, with repeats and shorter dark gaps ([`Illumination::default_campaign`]):
//!
//! | # | illuminated | flux scale | T (K) | darks after |
//! |---|---|---|---|---|
//! | 1 | 481 s | 1 | 80 | 20 (1 h) |
//! | 2 | 240 s | 1 | 80 | 10 (30 min) |
//! | 3 | 240 s | 1 | 80 | 10 (30 min) (repeat of 2) |
//! | 4 | 120 s | 4 | 78 | 20 (1 h) |
//! | 5 | 481 s | 0.25 | 82 | 60 (3 h) |
//!
//! Each illuminated integration lasts `t_illuminated + 132 s` (the paper's 613 - 481);
//! the focal plane changes temperature during the dark gap before the illumination.
//!
//! # Shifted spots (`--spots shifted`, [`Illumination::shifted_campaign`])
//! In the default campaign every illumination is the same pattern, scaled, so a pixel's
//! fluence is a function of its radius from the array centre in every illumination:
//! an effect that differs between illuminations can then be mimicked by a smooth
//! surface over the array (the model's `populations`). The shifted campaign is the same five illuminations with the
//! spot's centre moved for illuminations 2-5, as a laboratory would move the
//! pinhole, so that radius and fluence no longer go together across illuminations:
//!
//! | # | spot centre offset (y, x), fraction of the array size |
//! |---|---|
//! | 1 | (0, 0): the calibration's illumination is the default campaign's |
//! | 2 | (+0.15, -0.20) |
//! | 3 | (+0.15, -0.20) (repeat of 2, same place) |
//! | 4 | (-0.20, -0.15) |
//! | 5 | (+0.20, -0.20) |
//!
//! The leak along the left edge and the scattered-light floor do not move. The spot
//! moves up, down and to the left only, so that the two right-hand corners stay below
//! 3,000 e- (`diag::data::BACKGROUND_FLUENCE_E`) in every illumination: `compare` and
//! `diagnose` measure each exposure's dark level on pixels that were never lit, and a
//! campaign that lights every pixel leaves them none.
//!
//! # Sharp pinholes (`--spots pinholes`, [`Illumination::pinholes_campaign`])
//! The centred spot falls by four decades over half the array, so neighbouring pixels
//! see nearly the same flux and an effect that couples neighbours (the simulator's
//! `ipc`) changes little: of order its coupling times the image's curvature. A
//! laboratory tests coupling with sources smaller than a pixel. This campaign is the
//! default one with a grid of such pinholes added to every illumination
//! ([`point_sources`]): one pixel each, every [`POINT_SPACING_PX`] pixels, fluxes
//! [`POINT_FLUX_E_PER_S`] in turn (0.5 to 7 million e- in the first illumination, every
//! one with a slope),
//! outside the spot's bright centre (above 500 e-/s), the leak's columns and the
//! right-hand quarter that keeps the background pixels.
//!
//! # Dark lengths (`--dark-lengths varied`, [`DarkLengths::apply`])
//! Every dark integration of the default campaign lasts 180 s, and every illumination's
//! first dark starts 132 s after its shutter closes. An effect of the integration's
//! *length*, such as the on-board least-squares line reading a curved ramp lower than
//! its mean current (the simulator's `linefit_bias`: about 2.4 % in such a first dark,
//! 8 % in a 540 s one, 0.5 % in a 60 s one, for a `1/t` decay), is then the same factor
//! in every illumination, which a calibration takes in. The varied campaign changes the
//! darks after illuminations 2 and 3, equal illuminations otherwise:
//!
//! | # | reset after the shutter | darks after |
//! |---|---|---|
//! | 2 | 132 s | 30 of 60 s (30 min, as in the default campaign) |
//! | 3 | 12 s | 10 of 540 s (90 min) |
//!
//! Illumination 3's reset comes 12 s after its shutter, so its first dark starts on the
//! steep part of the decay, where the bias is largest (about 32 % for a `1/t` decay).
//! The others, illumination 1 (the
//! calibration's) included, keep 180 s darks and the 132 s wait.
//!
//! # Temperatures apart (`--temperatures apart`, [`Temperatures::apply`])
//! In the default campaign the two illuminations away from 80 K also differ from the
//! calibration's in length or flux (120 s at x4, 481 s at x1/4), and only the 82 K one
//! is followed by darks of more than an hour. An effect of the illumination's length
//! or of the hours-long tail (the simulator's `soak`) and one of the temperature (its
//! `temperature`) then show in the same illumination, and where they interact (soak's
//! capture time follows the emission time, which the temperature changes) they nearly
//! cancel. The apart campaign moves
//! illumination 4 to 80 K and follows it with 3 h of darks, and adds a sixth
//! illumination, the fifth's twin at 78 K:
//!
//! | # | illuminated | flux scale | T (K) | darks after |
//! |---|---|---|---|---|
//! | 4 | 120 s | 4 | **80** | **60 (3 h)** |
//! | 5 | 481 s | 0.25 | 82 | 60 (3 h) |
//! | 6 | 481 s | 0.25 | **78** | **30 (1.5 h)** |
//!
//! The illuminations away from 80 K are then alike but for the temperature, and the
//! length and the tail show at 80 K on their own. With `--spots shifted` or `pinholes`
//! the sixth illumination takes the fifth's spot.
//!
//! # Durations apart (`--durations apart`, [`Durations::apply`])
//! `diagnose` bins an illumination's history by the fluence of the illumination before
//! it, in the pixel, and the time from that one's end (half-decades of each;
//! `diag::contrast`). In the default campaign no two illuminations of equal fluence and
//! equal history differ in duration: the 120 s x4 illumination (4) shares its history
//! with the 240 s repeat (3), but has twice its fluence (and, at the default
//! temperatures, another temperature), and
//! the 481 s ones (1, 5) have neither the fluence nor the history of any other. An
//! effect of the illumination's duration (the simulator's `soak`: slow capture, so that
//! a longer illumination of the same fluence fills more of the slow traps) and one of
//! the charge the traps still hold (its `capacity`) then split the illuminations alike,
//! and `diagnose` can only call them confounded. The apart campaign appends three
//! illuminations at the reference temperature (illumination 1's):
//!
//! | # | illuminated | flux scale | fluence (x the pattern's e-/s) | darks after |
//! |---|---|---|---|---|
//! | +1 | 481 s | 1 | 481 | 60 (3 h) |
//! | +2 | 120 s | 4 | 480 | 60 (3 h) |
//! | +3 | 481 s | 1 | 481 | 60 (3 h) |
//!
//! +2 and +3 have equal fluence (to 0.2 %) and equal history, each 3 h after an
//! illumination of that fluence, and differ in duration; +1, +3 and illumination 1 have
//! equal duration and fluence and differ in history (illumination 1 has none, +1 comes
//! after the campaign's last illumination), so that each kind also shows on its own.
//! The traps are not emptied in between: their emission times reach 10^6 s
//! (`sim::traps`), so after any gap a laboratory can afford the traps still release the
//! earlier charge, about as `1/t`, and equal history is an equally bright illumination
//! at the same gap. Those two illuminations differ themselves in duration (481 s before
//! +2, 120 s before +3): under an effect of the duration the charge they leave differs
//! too, which the binning of history does not see. With a hidden `soak` (capture 10
//! times slower) the true current over the same seed's without it, array means at 64 x
//! 64 (`examples/truth_ratios --size 64 --durations apart soak`): 1 h after the
//! shutter 0.838 after +2 (120 s) against 0.899 after +3 (481 s) and 0.897 after +1,
//! 3 h after 0.710 against 0.796 and 0.791. The duration moves the current by about 10
//! % at hours; the history, at equal duration, by under 1 %.
//!
//! The three come after every other option's illuminations (after `--temperatures
//! apart`'s sixth and after the `--repeats`), and each is a copy of illumination 1 but
//! for its length, flux and dark count: its temperature, its spot (centred, also with
//! `--spots shifted`), the pinholes of `--spots pinholes`, the floor of `--spots paper`
//! and, with `--dark-lengths varied`, its 180 s darks.
//!
//! # The paper's pattern (`--spots paper`, [`PaperPattern`])
//! The pinhole pattern leaves most of the array below 3,000 e- (its floor is 0.05
//! e-/s), so `fit`, `compare` and `diagnose` find "background pixels" that were never
//! lit and measure each exposure's dark level on them. The paper's laboratory data have
//! none: "flux ranging from tens to hundreds of thousands of electrons per second", a
//! bright pinhole spot, a leak along one edge and tens of e-/s on every other pixel while
//! the source is on. `--spots paper` (with or without `--campaign`) adds
//! [`PAPER_FLOOR_E_PER_S`] = 30 e-/s to every pixel of every illumination (14,430 e- in
//! the 481 s illumination; 3,600 e- in the campaign's dimmest, 481 s at a quarter of the
//! flux), so that no pixel gets less than 3,000 e- in any illumination. With
//! `--dark-pixels` a corner block of `size / 8` x `size / 8` pixels at the top right is
//! masked instead (no floor, no leak; the spot's own tail there is below 1 e-/s), so the
//! same pattern can be measured with and without pixels that were never lit.
//!
//! # Repeated illuminations (`--repeats N`, [`repeat`])
//! In the default campaign the repeated 240 s illuminations (2 and 3) come 1 h and 30
//! min after the one before, when the fast traps are empty. An effect of the charge the
//! traps still hold (the simulator's `capacity`: every bin's capacity divided by
//! `1 + (C_tot + H) / n_max`, `H` the held charge) then lowers the second of two saturating
//! illuminations 30 min apart by about 7 % (`tests/sim_effects.rs`). `--repeats
//! N` adds N more 240 s illuminations at the reference temperature after illumination
//! 3, each followed by five darks (15 min), so that each begins while the pixel holds the
//! last one's charge; illumination 1, from which `fit` calibrates, is never changed.
//! With `--temperatures apart` the repeats still come before illumination 4.

use super::detector::DetectorParams;
use super::effect::{EffectSet, EffectSpec};
use super::engine::{ExposureSpec, SimDetector};
use super::traps::TrapParams;
use super::{epoch, meta, SimExposure};
use crate::product::Exposure;
use crate::units::Seconds;
use ndarray::Array2;
use serde::Serialize;
use std::sync::Arc;

/// One illumination of a campaign.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Illumination {
    pub t_illuminated_s: f64,
    pub flux_scale: f64,
    pub temp_k: f64,
    pub darks_after: usize,
    /// Offset of the spot's centre from its default place, (y, x) in fractions of the
    /// array size ([`pinhole_at`]); (0, 0) in the default campaign (and then not
    /// written to `truth.json`, which stays as it was).
    #[serde(skip_serializing_if = "is_centred")]
    pub spot_offset: [f64; 2],
    /// Add the grid of sharp pinholes ([`point_sources`]; module docs, "Sharp
    /// pinholes"); false in the default campaign (and then not written to `truth.json`).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub points: bool,
    /// Length of each dark integration after this illumination, s; `None` (the default
    /// campaign, and then not written to `truth.json`) takes the configuration's
    /// `dark_s` (module docs, "Dark lengths").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub dark_s: Option<f64>,
    /// Time from the shutter closing to the end of the illuminated integration (the
    /// reset), s; `None` (the default campaign, and then not written to `truth.json`)
    /// takes the configuration's `after_shutter_s` (module docs, "Dark lengths").
    #[serde(skip_serializing_if = "Option::is_none")]
    pub after_shutter_s: Option<f64>,
}

fn is_centred(o: &[f64; 2]) -> bool {
    *o == [0.0, 0.0]
}

impl Illumination {
    pub fn default_campaign() -> Vec<Illumination> {
        let i = |t, s, k, d| Illumination {
            t_illuminated_s: t,
            flux_scale: s,
            temp_k: k,
            darks_after: d,
            spot_offset: [0.0, 0.0],
            points: false,
            dark_s: None,
            after_shutter_s: None,
        };
        vec![
            i(481.0, 1.0, 80.0, 20),
            i(240.0, 1.0, 80.0, 10),
            i(240.0, 1.0, 80.0, 10),
            i(120.0, 4.0, 78.0, 20),
            i(481.0, 0.25, 82.0, 60),
        ]
    }

    /// The default campaign with the spot moved for illuminations 2-5 (module docs,
    /// "Shifted spots").
    pub fn shifted_campaign() -> Vec<Illumination> {
        const OFFSETS: [[f64; 2]; 5] = [
            [0.0, 0.0],
            [0.15, -0.20],
            [0.15, -0.20],
            [-0.20, -0.15],
            [0.20, -0.20],
        ];
        Self::default_campaign()
            .into_iter()
            .zip(OFFSETS)
            .map(|(i, spot_offset)| Illumination { spot_offset, ..i })
            .collect()
    }

    /// What this illumination shines on an `n` x `n` array, e-/s: the spot at its place
    /// ([`pinhole_at`]), the sharp pinholes if asked ([`point_sources`]), times the flux
    /// scale.
    pub fn flux(&self, n: usize) -> Array2<f32> {
        self.flux_in(n, None)
    }

    /// [`Illumination::flux`] with the paper's pattern applied before the flux scale
    /// (the floor scales with the source, as the rest of the pattern does).
    pub fn flux_in(&self, n: usize, paper: Option<PaperPattern>) -> Array2<f32> {
        let mut flux = pinhole_at(n, self.spot_offset);
        if self.points {
            for (y, x, f) in point_sources(n) {
                flux[[y, x]] += f;
            }
        }
        if let Some(p) = paper {
            flux = p.apply(flux);
        }
        flux.mapv(|v| v * self.flux_scale as f32)
    }

    /// The default campaign with the grid of sharp pinholes added to every
    /// illumination (module docs, "Sharp pinholes").
    pub fn pinholes_campaign() -> Vec<Illumination> {
        Self::default_campaign()
            .into_iter()
            .map(|i| Illumination { points: true, ..i })
            .collect()
    }
}

/// Where a campaign's spot is (`persist simulate lab --spots`; module docs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Spots {
    /// Every illumination the same pattern, scaled ([`Illumination::default_campaign`]).
    #[default]
    Centred,
    /// The spot moved for illuminations 2-5 ([`Illumination::shifted_campaign`]).
    Shifted,
    /// The default campaign plus a grid of sharp pinholes
    /// ([`Illumination::pinholes_campaign`]).
    Pinholes,
    /// The centred spots with every pixel lit at tens of e-/s (module docs, "The paper's
    /// pattern"; [`PaperPattern`]).
    Paper,
}

impl Spots {
    /// The campaign's illuminations (the paper's pattern is the centred campaign's
    /// spots; [`LabConfig::paper_pattern`] adds its floor).
    pub fn campaign(self) -> Vec<Illumination> {
        match self {
            Spots::Centred | Spots::Paper => Illumination::default_campaign(),
            Spots::Shifted => Illumination::shifted_campaign(),
            Spots::Pinholes => Illumination::pinholes_campaign(),
        }
    }
}

choices!(Spots, "--spots", Centred => "centred", Shifted => "shifted", Pinholes => "pinholes", Paper => "paper");

/// The flux added to every pixel by the paper's pattern while the source is on, e-/s
/// (module docs, "The paper's pattern").
pub const PAPER_FLOOR_E_PER_S: f32 = 30.0;

/// The paper's illumination pattern (module docs, "The paper's pattern"): every pixel
/// lit at [`PAPER_FLOOR_E_PER_S`] or more, except, with `dark_pixels`, a masked corner.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct PaperPattern {
    /// Keep a `size / 8` square at the top right unlit (masked: no floor, no leak).
    pub dark_pixels: bool,
}

impl PaperPattern {
    /// `flux` (e-/s, an illumination's pattern before its flux scale) with the floor
    /// added, and the corner masked if asked.
    pub fn apply(self, mut flux: Array2<f32>) -> Array2<f32> {
        let n = flux.nrows().min(flux.ncols());
        let corner = (n / 8).max(1);
        let nx = flux.ncols();
        for ((y, x), v) in flux.indexed_iter_mut() {
            if self.dark_pixels && y < corner && x >= nx - corner {
                let spot = pinhole_spot_only(*v, x);
                *v = spot;
            } else {
                *v += PAPER_FLOOR_E_PER_S;
            }
        }
        flux
    }
}

/// What is left of the pinhole pattern's value `v` at column `x` once its leak and
/// floor are masked ([`pinhole_at`]).
fn pinhole_spot_only(v: f32, x: usize) -> f32 {
    let leak = 300.0 * 10f64.powf(-(x as f64) / 6.0);
    (f64::from(v) - leak - 0.05).max(0.0) as f32
}

/// How long the campaign's dark integrations are (`persist simulate lab --dark-lengths`;
/// module docs, "Dark lengths").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum DarkLengths {
    /// Every dark integration lasts the configuration's `dark_s` (180 s).
    #[default]
    Uniform,
    /// Illumination 2's darks last 60 s; its repeat's (3) 540 s, after a reset 12 s
    /// after the shutter (`VARIED_DARKS`).
    Varied,
}

/// The darks `--dark-lengths varied` gives one illumination.
struct VariedDarks {
    /// Index of the illumination in the campaign (0 is the calibration's).
    illumination: usize,
    dark_s: f64,
    darks_after: usize,
    after_shutter_s: f64,
}

/// `--dark-lengths varied` (module docs, "Dark lengths"); illumination 2 keeps its 30
/// minute gap.
const VARIED_DARKS: [VariedDarks; 2] = [
    VariedDarks {
        illumination: 1,
        dark_s: 60.0,
        darks_after: 30,
        after_shutter_s: AFTER_SHUTTER_S,
    },
    VariedDarks {
        illumination: 2,
        dark_s: 540.0,
        darks_after: 10,
        after_shutter_s: 12.0,
    },
];

/// The paper's time from the shutter closing to the reset, 613 - 481 s.
const AFTER_SHUTTER_S: f64 = 132.0;

impl DarkLengths {
    /// `campaign` with this choice of dark lengths. Illumination 1, from which `fit`
    /// calibrates, is never changed.
    pub fn apply(self, campaign: Vec<Illumination>) -> Vec<Illumination> {
        match self {
            DarkLengths::Uniform => campaign,
            DarkLengths::Varied => campaign
                .into_iter()
                .enumerate()
                .map(
                    |(k, i)| match VARIED_DARKS.iter().find(|v| v.illumination == k) {
                        Some(v) => Illumination {
                            dark_s: Some(v.dark_s),
                            darks_after: v.darks_after,
                            after_shutter_s: Some(v.after_shutter_s),
                            ..i
                        },
                        None => i,
                    },
                )
                .collect(),
        }
    }
}

choices!(DarkLengths, "--dark-lengths", Uniform => "uniform", Varied => "varied");

/// Where the campaign's temperatures are (`persist simulate lab --temperatures`; module
/// docs, "Temperatures apart").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Temperatures {
    /// The default campaign's: illumination 4 at 78 K, 5 at 82 K, each also of another
    /// length or flux than the calibration's.
    #[default]
    Mixed,
    /// Illumination 4 at 80 K with 3 h of darks; a sixth illumination, 5's twin at
    /// 78 K ([`Temperatures::apply`]).
    Apart,
}

/// `--temperatures apart`: the dark integrations after illumination 4 (3 h) and after
/// the added sixth illumination (1.5 h).
const APART_DARKS_AFTER_4: usize = 60;
const APART_DARKS_AFTER_6: usize = 30;

impl Temperatures {
    /// `campaign` with this choice of temperatures. Illumination 1, from which `fit`
    /// calibrates, is never changed; a campaign of fewer than five illuminations is
    /// returned as it is.
    pub fn apply(self, mut campaign: Vec<Illumination>) -> Vec<Illumination> {
        if self == Temperatures::Mixed || campaign.len() < 5 {
            return campaign;
        }
        let reference_k = campaign[0].temp_k;
        campaign[3].temp_k = reference_k;
        campaign[3].darks_after = APART_DARKS_AFTER_4;
        let cold_k = 2.0 * reference_k - campaign[4].temp_k;
        let twin = Illumination {
            temp_k: cold_k,
            darks_after: APART_DARKS_AFTER_6,
            ..campaign[4].clone()
        };
        campaign.push(twin);
        campaign
    }
}

choices!(Temperatures, "--temperatures", Mixed => "mixed", Apart => "apart");

/// Whether the campaign tells the illumination's duration from its history (`persist
/// simulate lab --durations`; module docs, "Durations apart").
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Durations {
    /// The campaign as the other options make it.
    #[default]
    Mixed,
    /// Three illuminations appended: 481 s x1, 120 s x4 and 481 s x1 at the reference
    /// temperature, each followed by 3 h of darks, the last two of equal fluence after
    /// equally bright ones at the same gap ([`Durations::apply`]).
    Apart,
}

/// One illumination `--durations apart` appends (module docs, "Durations apart").
struct Appended {
    t_illuminated_s: f64,
    flux_scale: f64,
}

/// `--durations apart`: 481 s x1, then 120 s x4 (480 s x1's fluence) and 481 s x1,
/// each followed by [`DURATIONS_DARKS`].
const DURATIONS_APART: [Appended; 3] = [
    Appended {
        t_illuminated_s: 481.0,
        flux_scale: 1.0,
    },
    Appended {
        t_illuminated_s: 120.0,
        flux_scale: 4.0,
    },
    Appended {
        t_illuminated_s: 481.0,
        flux_scale: 1.0,
    },
];
/// The dark integrations after each illumination `--durations apart` appends (3 h of
/// 180 s darks): the gap before the next and the hours over which the slow traps
/// release what a longer illumination put in them.
const DURATIONS_DARKS: usize = 60;

impl Durations {
    /// `campaign` with this choice of durations: with `Apart`, `DURATIONS_APART`
    /// appended, each illumination 1's copy (its temperature, spot, pinholes and darks)
    /// but for its length, flux and dark count. Nothing before them is changed; an
    /// empty campaign is returned as it is.
    pub fn apply(self, mut campaign: Vec<Illumination>) -> Vec<Illumination> {
        let Some(first) = campaign.first().cloned() else {
            return campaign;
        };
        if self == Durations::Apart {
            campaign.extend(DURATIONS_APART.iter().map(|a| Illumination {
                t_illuminated_s: a.t_illuminated_s,
                flux_scale: a.flux_scale,
                darks_after: DURATIONS_DARKS,
                ..first.clone()
            }));
        }
        campaign
    }
}

choices!(Durations, "--durations", Mixed => "mixed", Apart => "apart");

/// `--repeats N` (module docs, "Repeated illuminations"): what each added illumination
/// is, and its dark gap.
const REPEAT_T_ILLUMINATED_S: f64 = 240.0;
const REPEAT_DARKS_AFTER: usize = 5;
/// The campaign's illumination after which the repeats come (the 240 s repeat, 3).
const REPEATS_AFTER: usize = 2;
/// The most `--repeats` takes.
pub const MAX_REPEATS: usize = 20;

/// `campaign` with `n` more 240 s illuminations at the reference temperature after
/// illumination 3, each followed by five darks (module docs, "Repeated illuminations").
/// Illumination 1, from which `fit` calibrates, is never changed; a campaign of fewer
/// than three illuminations is returned as it is.
pub fn repeat(mut campaign: Vec<Illumination>, n: usize) -> Vec<Illumination> {
    if n == 0 || campaign.len() <= REPEATS_AFTER {
        return campaign;
    }
    let template = Illumination {
        t_illuminated_s: REPEAT_T_ILLUMINATED_S,
        temp_k: campaign[0].temp_k,
        darks_after: REPEAT_DARKS_AFTER,
        ..campaign[REPEATS_AFTER].clone()
    };
    let at = REPEATS_AFTER + 1;
    campaign.splice(at..at, std::iter::repeat_n(template, n));
    campaign
}

/// The campaign options of `persist simulate lab --campaign` together: where the
/// spot is, how long the darks are, where the temperatures are, how many repeats and
/// whether the durations are apart. One place that builds the campaign they describe
/// and names them back as flags.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct CampaignOptions {
    pub spots: Spots,
    pub dark_lengths: DarkLengths,
    pub temperatures: Temperatures,
    pub repeats: usize,
    pub durations: Durations,
}

impl CampaignOptions {
    /// The campaign's illuminations: the spots' campaign, then the dark lengths, the
    /// temperatures, the repeats and the durations applied in that order.
    pub fn illuminations(&self) -> Vec<Illumination> {
        self.durations.apply(repeat(
            self.temperatures
                .apply(self.dark_lengths.apply(self.spots.campaign())),
            self.repeats,
        ))
    }

    /// The `persist simulate lab` flags beyond `--campaign` that give these options,
    /// each after a space; empty at the defaults.
    pub fn flags(&self) -> String {
        let d = CampaignOptions::default();
        let mut f = String::new();
        if self.spots != d.spots {
            f += &format!(" --spots {}", self.spots);
        }
        if self.dark_lengths != d.dark_lengths {
            f += &format!(" --dark-lengths {}", self.dark_lengths);
        }
        if self.temperatures != d.temperatures {
            f += &format!(" --temperatures {}", self.temperatures);
        }
        if self.repeats != d.repeats {
            f += &format!(" --repeats {}", self.repeats);
        }
        if self.durations != d.durations {
            f += &format!(" --durations {}", self.durations);
        }
        f
    }
}

/// Laboratory scenario configuration.
#[derive(Debug, Clone, Serialize)]
pub struct LabConfig {
    pub size: usize,
    pub seed: u64,
    /// Dark integrations after a single illumination (ignored with a campaign).
    pub darks: usize,
    pub dark_s: f64,
    /// Time the array stays dark-but-charged after the shutter closes (613 - 481 s).
    pub after_shutter_s: f64,
    pub t_illuminated_s: f64,
    pub temp_k: f64,
    pub campaign: Option<Vec<Illumination>>,
    /// The paper's pattern on every illumination (`--spots paper`; module docs, "The
    /// paper's pattern"); `None`, the pinhole pattern alone, is not written to
    /// `truth.json`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub paper_pattern: Option<PaperPattern>,
    #[serde(skip)]
    pub effects: Vec<EffectSpec>,
    pub traps: TrapParams,
    pub detector: DetectorParams,
}

impl Default for LabConfig {
    fn default() -> Self {
        LabConfig {
            size: 256,
            seed: 1,
            darks: 280,
            dark_s: 180.0,
            after_shutter_s: AFTER_SHUTTER_S,
            t_illuminated_s: 481.0,
            temp_k: 80.0,
            campaign: None,
            paper_pattern: None,
            effects: Vec::new(),
            traps: TrapParams::default(),
            detector: DetectorParams {
                cosmic_rate_per_cm2_s: 0.02,
                ..DetectorParams::default()
            },
        }
    }
}

/// The pinhole illumination, e-/s.
pub fn pinhole(size: usize) -> Array2<f32> {
    pinhole_at(size, [0.0, 0.0])
}

/// The pinhole illumination with the spot's centre moved by `offset` (y, x) times the
/// array size; the leak and the floor stay.
pub fn pinhole_at(size: usize, offset: [f64; 2]) -> Array2<f32> {
    let c = (size as f64 - 1.0) / 2.0 + 0.3;
    let (cy, cx) = (c + offset[0] * size as f64, c + offset[1] * size as f64);
    let r0 = size as f64 / 2.0;
    Array2::from_shape_fn((size, size), |(y, x)| {
        let r = ((y as f64 - cy).powi(2) + (x as f64 - cx).powi(2)).sqrt();
        let spot = 2e5 * 10f64.powf(-4.0 * r / r0);
        let leak = 300.0 * 10f64.powf(-(x as f64) / 6.0);
        (spot + leak + 0.05) as f32
    })
}

/// Spacing of the sharp pinholes, pixels (even: every pinhole keeps the parity below).
pub const POINT_SPACING_PX: usize = 4;
/// The pinholes' fluxes, e-/s, taken in turn along the grid.
/// All below ~22,000 e-/s, above which the on-board fit has fewer than three samples
/// under half the full well and the pinhole has no slope and no fluence
/// (`sim::detector`), so that the model knows what each pinhole received.
pub const POINT_FLUX_E_PER_S: [f32; 4] = [1e3, 3e3, 7e3, 15e3];

/// The grid of sharp pinholes (module docs, "Sharp pinholes"): `(y, x, flux e-/s)`, all
/// the light of each pinhole in one pixel. Rows are even and columns odd, so two of each
/// pinhole's four nearest neighbours are on the stride-2 sample of `fit` (even rows and
/// columns) and the pinhole itself is not. Left out where the centred spot is above
/// 500 e-/s, in the leak's eight columns and in the right-hand quarter (the corners
/// that stay dark).
pub fn point_sources(size: usize) -> Vec<(usize, usize, f32)> {
    let spot = pinhole(size);
    let mut out = Vec::new();
    let mut k = 0;
    for y in (2..size).step_by(POINT_SPACING_PX) {
        for x in (9..size * 3 / 4).step_by(POINT_SPACING_PX) {
            if spot[[y, x]] > 500.0 {
                continue;
            }
            out.push((y, x, POINT_FLUX_E_PER_S[k % POINT_FLUX_E_PER_S.len()]));
            k += 1;
        }
    }
    out
}

fn temp_at(base: f64, t: f64) -> f64 {
    base + 0.005 * (2.0 * std::f64::consts::PI * t / 7200.0).sin()
}

/// Check the configuration (and the effects) before anything is written.
pub fn validate(cfg: &LabConfig) -> crate::Result<()> {
    steps(cfg).map(|_| ())
}

fn steps(cfg: &LabConfig) -> crate::Result<Vec<Illumination>> {
    if cfg.size < 4 || cfg.size > 8192 {
        return Err(crate::Error::invalid(
            "--size",
            format!("must be 4..=8192, got {}", cfg.size),
        ));
    }
    let short = |d: f64| !(d >= 3.0 * cfg.detector.frame_time_s && d.is_finite());
    if short(cfg.dark_s) {
        return Err(crate::Error::invalid("dark_s", "shorter than three frames"));
    }
    let steps = match &cfg.campaign {
        Some(c) if c.is_empty() => {
            return Err(crate::Error::invalid("--campaign", "no illumination given"))
        }
        Some(c) => c.clone(),
        None => vec![Illumination {
            t_illuminated_s: cfg.t_illuminated_s,
            flux_scale: 1.0,
            temp_k: cfg.temp_k,
            darks_after: cfg.darks,
            spot_offset: [0.0, 0.0],
            points: false,
            dark_s: None,
            after_shutter_s: None,
        }],
    };
    for s in &steps {
        if !(s.t_illuminated_s > 0.0
            && s.flux_scale >= 0.0
            && s.temp_k > 0.0
            && s.spot_offset.iter().all(|o| o.abs() <= 1.0))
        {
            return Err(crate::Error::invalid(
                "--campaign",
                "each illumination needs t > 0, flux scale >= 0, temperature > 0, \
                 spot offsets within [-1, 1]",
            ));
        }
        if s.after_shutter_s
            .is_some_and(|a| !(a >= 0.0 && a.is_finite()))
        {
            return Err(crate::Error::invalid(
                "--campaign",
                "an illumination's time after the shutter is negative",
            ));
        }
        if s.dark_s.is_some_and(short) {
            return Err(crate::Error::invalid(
                "--campaign",
                "an illumination's dark integrations are shorter than three frames",
            ));
        }
    }
    EffectSet::from_specs(&cfg.effects)?;
    Ok(steps)
}

/// Run the laboratory scenario, handing each exposure to `sink` as it is made.
/// Returns the scenario description for `truth.json`.
pub fn run(
    cfg: &LabConfig,
    mut sink: impl FnMut(SimExposure) -> crate::Result<()>,
) -> crate::Result<serde_json::Value> {
    let steps = steps(cfg)?;
    let effects = Arc::new(EffectSet::from_specs(&cfg.effects)?);
    let n = cfg.size;
    let mut sim = SimDetector::new(
        cfg.traps.clone(),
        cfg.detector.clone(),
        effects.clone(),
        n,
        n,
        cfg.seed,
        1,
    )?;
    let zero = Array2::<f32>::zeros((n, n));
    let t0 = epoch();
    let mut t = 0.0f64; // seconds since t0 of the next integration's start
    let mut index = 0u64;
    let mut first_dark = true;
    for s in &steps {
        let flux = s.flux_in(n, cfg.paper_pattern);
        let t_exp = s.t_illuminated_s + s.after_shutter_s.unwrap_or(cfg.after_shutter_s);
        let temp = temp_at(s.temp_k, t);
        let out = sim.expose(&ExposureSpec {
            index,
            flux: &flux,
            t_exposure_s: t_exp,
            t_on_s: s.t_illuminated_s,
            temp_k: temp,
            write_ramp: false,
        })?;
        sink(SimExposure {
            exposure: Exposure {
                meta: meta(
                    1,
                    index,
                    t0.plus(Seconds(t)),
                    t_exp,
                    temp,
                    Some(s.t_illuminated_s),
                ),
                image: out.image,
                flags: out.flags,
                ramp: None,
                ramp_times_s: None,
            },
            true_persistence: out.true_persistence,
            true_flux: out.flux,
            kind: "illuminated".into(),
        })?;
        index += 1;
        t += t_exp;
        let dark_s = s.dark_s.unwrap_or(cfg.dark_s);
        for _ in 0..s.darks_after {
            let temp = temp_at(s.temp_k, t);
            let out = sim.expose(&ExposureSpec {
                index,
                flux: &zero,
                t_exposure_s: dark_s,
                t_on_s: dark_s,
                temp_k: temp,
                write_ramp: first_dark,
            })?;
            sink(SimExposure {
                exposure: Exposure {
                    meta: meta(1, index, t0.plus(Seconds(t)), dark_s, temp, None),
                    image: out.image,
                    flags: out.flags,
                    ramp: out.ramp,
                    ramp_times_s: out.ramp_times_s,
                },
                true_persistence: out.true_persistence,
                true_flux: out.flux,
                kind: "dark".into(),
            })?;
            first_dark = false;
            index += 1;
            t += dark_s;
        }
    }
    Ok(serde_json::json!({
        "scenario": "lab",
        "config": cfg,
        "effects": effects.describe(),
        "illumination": "sim::lab::pinhole",
    }))
}

/// Calibration (traps module docs): first-dark slope per unit density for a pixel of
/// extrapolated fluence `fluence_e` in the laboratory history, `(g_lin, g_sat)`, noise
/// off, full well exactly 200,000 e-, chord slope (effects off).
pub fn calibrate(fluence_e: f64) -> (f64, f64) {
    let det = DetectorParams {
        noise: false,
        nonfunc_fraction: 0.0,
        full_well_scatter: 0.0,
        ..DetectorParams::default()
    };
    let sim = SimDetector::new(
        TrapParams::default(),
        det,
        Arc::new(EffectSet::default()),
        1,
        2,
        0,
        1,
    )
    .expect("valid");
    let mut px = sim.pixels.clone();
    px.d_lin = Array2::from_shape_vec((1, 2), vec![1.0, 0.0]).expect("shape");
    px.d_sat = Array2::from_shape_vec((1, 2), vec![0.0, 1.0]).expect("shape");
    let mut sim = sim.with_pixels(px);
    let phi = (fluence_e / 481.0) as f32;
    let flux = Array2::from_elem((1, 2), phi);
    sim.expose(&ExposureSpec::paper_illumination(0, &flux))
        .expect("valid");
    let zero = Array2::<f32>::zeros((1, 2));
    let out = sim
        .expose(&ExposureSpec::paper_dark(1, &zero))
        .expect("valid");
    let dark = 0.01;
    (
        f64::from(out.image[[0, 0]]) - dark,
        f64::from(out.image[[0, 1]]) - dark,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::traps::{D_LIN_DEFAULT, D_SAT_HIGH, D_SAT_MID};

    /// Re-derive the default densities (traps module docs, "Calibration").
    #[test]
    fn calibration_matches_defaults() {
        let (g_lin, _) = calibrate(400_000.0);
        let (_, g_sat) = calibrate(265_000.0);
        let d_lin = 3.1 / g_lin;
        let lin = D_LIN_DEFAULT * g_lin;
        let d_mid = (17.0 - lin) / g_sat;
        let d_high = (22.5 - lin) / g_sat;
        println!(
            "g_lin {g_lin:.6} g_sat {g_sat:.6} d_lin {d_lin:.1} mid {d_mid:.1} high {d_high:.1}"
        );
        assert!((d_lin / D_LIN_DEFAULT - 1.0).abs() < 0.01, "d_lin {d_lin}");
        assert!((d_mid / D_SAT_MID - 1.0).abs() < 0.01, "mid {d_mid}");
        assert!((d_high / D_SAT_HIGH - 1.0).abs() < 0.01, "high {d_high}");
    }

    #[test]
    fn shifted_spots_move_the_centre_and_keep_the_first_illumination() {
        let n = 64;
        let argmax = |p: &Array2<f32>| {
            let (i, _) = p
                .iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .unwrap();
            (i / n, i % n)
        };
        let shifted = Illumination::shifted_campaign();
        let centred = Illumination::default_campaign();
        assert_eq!(shifted.len(), centred.len());
        // the calibration's illumination is the default campaign's, bit for bit
        assert_eq!(shifted[0], centred[0]);
        assert_eq!(pinhole_at(n, shifted[0].spot_offset), pinhole(n));
        // the spot's brightest pixel moves by the offset (centre 31.8 + 64 * offset)
        assert_eq!(argmax(&pinhole(n)), (32, 32));
        assert_eq!(argmax(&pinhole_at(n, shifted[1].spot_offset)), (41, 19));
        assert_eq!(argmax(&pinhole_at(n, shifted[3].spot_offset)), (19, 22));
        assert_eq!(argmax(&pinhole_at(n, shifted[4].spot_offset)), (45, 19));
        // the repeat stays where the illumination it repeats was
        assert_eq!(shifted[1], shifted[2]);
        // the right-hand corners stay dark enough to be background pixels in every
        // illumination (module docs), at the matrix's size and the issue's
        for size in [64, 256] {
            for s in &shifted {
                let f = pinhole_at(size, s.spot_offset);
                for y in [0, size - 1] {
                    let fluence = f64::from(f[[y, size - 1]]) * s.flux_scale * s.t_illuminated_s;
                    assert!(
                        fluence < crate::diag::data::BACKGROUND_FLUENCE_E,
                        "{size}: {s:?} corner {y}: {fluence} e-"
                    );
                }
            }
        }
        // everything but the spot's place is the default campaign's
        for (s, c) in shifted.iter().zip(&centred) {
            assert_eq!(
                Illumination {
                    spot_offset: [0.0, 0.0],
                    points: false,
                    ..s.clone()
                },
                *c
            );
        }
    }

    #[test]
    fn sharp_pinholes_keep_their_sampled_neighbours_and_the_dark_corners() {
        for size in [64, 256] {
            let pts = point_sources(size);
            let spot = pinhole(size);
            assert!(pts.len() >= size / 2, "{size}: {} pinholes", pts.len());
            for &(y, x, f) in &pts {
                // two nearest neighbours on the stride-2 sample, the pinhole off it
                assert!(y % 2 == 0 && x % 2 == 1, "{y} {x}");
                assert!(spot[[y, x]] <= 500.0 && x >= 8 && x < size * 3 / 4);
                assert!(POINT_FLUX_E_PER_S.contains(&f));
            }
            // every flux level is used
            for f in POINT_FLUX_E_PER_S {
                assert!(pts.iter().any(|p| p.2 == f), "{size}: {f}");
            }
        }
        // the campaign is the default one with the pinholes added; illumination 1, from
        // which `fit` calibrates, too
        let c = Illumination::pinholes_campaign();
        for (p, d) in c.iter().zip(Illumination::default_campaign()) {
            assert!(p.points);
            assert_eq!(
                Illumination {
                    points: false,
                    ..p.clone()
                },
                d
            );
        }
        // the right-hand corners stay background pixels
        let cfg = LabConfig {
            size: 64,
            campaign: Some(c.clone()),
            ..LabConfig::default()
        };
        let n = cfg.size;
        for s in &steps(&cfg).unwrap() {
            let flux = s.flux(n);
            for y in [0, n - 1] {
                let fluence = f64::from(flux[[y, n - 1]]) * s.t_illuminated_s;
                assert!(fluence < crate::diag::data::BACKGROUND_FLUENCE_E);
            }
        }
    }

    #[test]
    fn a_spot_offset_outside_the_array_is_refused() {
        let mut c = Illumination::shifted_campaign();
        c[2].spot_offset = [0.0, 1.5];
        let cfg = LabConfig {
            size: 16,
            campaign: Some(c),
            ..LabConfig::default()
        };
        let e = validate(&cfg).unwrap_err().to_string();
        assert!(
            e.contains("--campaign") && e.contains("spot offsets"),
            "{e}"
        );
    }

    /// `--repeats 3`: three copies of illumination 3 at the reference temperature, each
    /// with five darks, between illuminations 3 and 4; the rest as it was.
    #[test]
    fn repeats_follow_illumination_3_with_short_gaps_and_change_nothing_else() {
        let base = Illumination::default_campaign();
        let r = repeat(base.clone(), 3);
        assert_eq!(r.len(), 8);
        assert_eq!(r[..3], base[..3]);
        assert_eq!(r[6..], base[3..]);
        for i in &r[3..6] {
            assert_eq!(
                *i,
                Illumination {
                    darks_after: 5,
                    ..base[2].clone()
                }
            );
        }
        // with the temperatures apart the repeats still come before illumination 4
        let apart = repeat(Temperatures::Apart.apply(base.clone()), 2);
        assert_eq!(apart.len(), 8);
        assert_eq!(apart[3].temp_k, 80.0);
        assert_eq!(apart[3].t_illuminated_s, 240.0);
        assert_eq!(apart[5].t_illuminated_s, 120.0);
        assert_eq!(repeat(base.clone(), 0), base);
        assert_eq!(repeat(base[..2].to_vec(), 4), base[..2]);
    }

    #[test]
    fn campaign_options_build_in_order_and_name_what_is_not_the_default() {
        let d = CampaignOptions::default();
        assert_eq!(d.illuminations(), Illumination::default_campaign());
        assert_eq!(d.flags(), "");
        let o = CampaignOptions {
            spots: Spots::Shifted,
            temperatures: Temperatures::Apart,
            repeats: 2,
            ..d
        };
        assert_eq!(
            o.illuminations(),
            repeat(Temperatures::Apart.apply(Spots::Shifted.campaign()), 2)
        );
        assert_eq!(
            o.flags(),
            " --spots shifted --temperatures apart --repeats 2"
        );
        // the durations come last, after the temperatures' sixth and the repeats
        let o = CampaignOptions {
            durations: Durations::Apart,
            ..o
        };
        assert_eq!(
            o.illuminations(),
            Durations::Apart.apply(repeat(
                Temperatures::Apart.apply(Spots::Shifted.campaign()),
                2
            ))
        );
        assert_eq!(
            o.flags(),
            " --spots shifted --temperatures apart --repeats 2 --durations apart"
        );
    }

    /// `--durations apart`: two appended illuminations of equal fluence and equal
    /// history (as `diagnose` bins it: the fluence before and the gap) that differ in
    /// duration, and three of equal duration and fluence that differ in history.
    #[test]
    fn durations_apart_append_equal_fluence_and_history_of_different_durations() {
        let mixed = Illumination::default_campaign();
        let apart = Durations::Apart.apply(mixed.clone());
        assert_eq!(apart.len(), 8);
        assert_eq!(apart[..5], mixed[..5]);
        // each appended one is illumination 1 but for its length, flux and darks
        for a in &apart[5..] {
            assert_eq!(
                a.clone(),
                Illumination {
                    t_illuminated_s: a.t_illuminated_s,
                    flux_scale: a.flux_scale,
                    darks_after: 60,
                    ..mixed[0].clone()
                }
            );
        }
        let fluence = |i: &Illumination| i.t_illuminated_s * i.flux_scale;
        let gap_s = |i: &Illumination| i.darks_after as f64 * i.dark_s.unwrap_or(180.0);
        let (before, pair) = (&apart[5..7], &apart[6..8]);
        // the pair: fluence within 0.5 %, durations four times apart
        assert!((fluence(&pair[0]) / fluence(&pair[1]) - 1.0).abs() < 0.005);
        assert_eq!(
            (pair[0].t_illuminated_s, pair[1].t_illuminated_s),
            (120.0, 481.0)
        );
        // its history: equally bright illuminations, 3 h before each
        assert!((fluence(&before[0]) / fluence(&before[1]) - 1.0).abs() < 0.005);
        assert_eq!((gap_s(&before[0]), gap_s(&before[1])), (10800.0, 10800.0));
        // equal duration and fluence, other histories: illumination 1 (none), +1 (after
        // the 481 s x1/4 one), +3 (after the 120 s x4 one)
        for k in [5, 7] {
            assert_eq!(
                (apart[k].t_illuminated_s, fluence(&apart[k])),
                (481.0, fluence(&mixed[0]))
            );
        }
        assert_ne!(fluence(&apart[4]), fluence(&apart[6]));
        assert_eq!(Durations::Mixed.apply(mixed.clone()), mixed);
        assert_eq!(Durations::Apart.apply(Vec::new()), Vec::new());
        assert_eq!("apart".parse::<Durations>().unwrap(), Durations::Apart);
        assert!("long".parse::<Durations>().is_err());
        // with the other options: illumination 1's temperature, spot, pinholes and darks
        for (spots, lengths) in [
            (Spots::Shifted, DarkLengths::Varied),
            (Spots::Pinholes, DarkLengths::Uniform),
        ] {
            let o = CampaignOptions {
                spots,
                dark_lengths: lengths,
                temperatures: Temperatures::Apart,
                repeats: 1,
                durations: Durations::Apart,
            };
            let c = o.illuminations();
            let n = c.len();
            assert_eq!(
                c[..n - 3],
                CampaignOptions {
                    durations: Durations::Mixed,
                    ..o
                }
                .illuminations()[..]
            );
            for a in &c[n - 3..] {
                assert_eq!(
                    (
                        a.temp_k,
                        a.spot_offset,
                        a.points,
                        a.dark_s,
                        a.after_shutter_s
                    ),
                    (80.0, [0.0, 0.0], spots == Spots::Pinholes, None, None)
                );
            }
        }
    }

    /// The exposures of `--durations apart` carry the durations, and the time from the
    /// end of each of the pair's earlier illuminations to its start is the same.
    #[test]
    fn durations_apart_exposures_keep_the_pair_at_the_same_gap() {
        let cfg = LabConfig {
            size: 8,
            campaign: Some(Durations::Apart.apply(Illumination::default_campaign())),
            ..LabConfig::default()
        };
        let mut ill = Vec::new();
        run(&cfg, |e| {
            if e.kind == "illuminated" {
                let m = &e.exposure.meta;
                ill.push((m.t_start.0, m.t_exposure_s, m.t_illuminated_s()));
            }
            Ok(())
        })
        .unwrap();
        let t: Vec<f64> = ill.iter().map(|i| i.2).collect();
        assert_eq!(
            t,
            vec![481.0, 240.0, 240.0, 120.0, 481.0, 481.0, 120.0, 481.0]
        );
        let gap = |k: usize| ill[k + 1].0 - (ill[k].0 + ill[k].1);
        assert!((gap(5) - 10800.0).abs() < 1e-6 && (gap(6) - 10800.0).abs() < 1e-6);
    }

    #[test]
    fn temperatures_apart_keep_the_reference_temperature_off_the_length_and_flux_changes() {
        let mixed = Illumination::default_campaign();
        let apart = Temperatures::Apart.apply(mixed.clone());
        assert_eq!(apart.len(), 6);
        assert_eq!(apart[..3], mixed[..3]);
        // illumination 4 (120 s, x4): now at the calibration's 80 K, with 3 h of darks
        assert_eq!(
            apart[3],
            Illumination {
                temp_k: 80.0,
                darks_after: 60,
                ..mixed[3].clone()
            }
        );
        assert_eq!(apart[4], mixed[4]);
        // the sixth: the fifth's length and flux at 78 K, 1.5 h of darks
        assert_eq!(
            apart[5],
            Illumination {
                temp_k: 78.0,
                darks_after: 30,
                ..mixed[4].clone()
            }
        );
        // every illumination away from 80 K has the same length and flux
        let off: Vec<(f64, f64)> = apart
            .iter()
            .filter(|i| i.temp_k != 80.0)
            .map(|i| (i.t_illuminated_s, i.flux_scale))
            .collect();
        assert_eq!(off, vec![(481.0, 0.25); 2]);
        assert_eq!(Temperatures::Mixed.apply(mixed.clone()), mixed);
        // a single illumination is left alone
        assert_eq!(Temperatures::Apart.apply(mixed[..1].to_vec()), mixed[..1]);
        assert_eq!(
            "apart".parse::<Temperatures>().unwrap(),
            Temperatures::Apart
        );
        assert!("warm".parse::<Temperatures>().is_err());
    }

    #[test]
    fn varied_dark_lengths_change_only_the_darks_of_illuminations_2_and_3() {
        let centred = Illumination::default_campaign();
        let varied = DarkLengths::Varied.apply(centred.clone());
        let gap = |i: &Illumination| i.dark_s.unwrap_or(180.0) * i.darks_after as f64;
        for (k, (v, c)) in varied.iter().zip(&centred).enumerate() {
            assert_eq!(
                Illumination {
                    dark_s: None,
                    darks_after: c.darks_after,
                    after_shutter_s: None,
                    ..v.clone()
                },
                *c,
                "{k}"
            );
            match k {
                1 => assert_eq!(
                    (v.dark_s, gap(v), v.after_shutter_s),
                    (Some(60.0), gap(c), Some(132.0))
                ),
                2 => assert_eq!(
                    (v.dark_s, v.darks_after, v.after_shutter_s),
                    (Some(540.0), 10, Some(12.0))
                ),
                _ => assert_eq!(v, c),
            }
        }
        assert_eq!(DarkLengths::Uniform.apply(centred.clone()), centred);
        // the exposures carry the lengths, and time runs on by them
        let cfg = LabConfig {
            size: 8,
            campaign: Some(varied),
            ..LabConfig::default()
        };
        let mut seen = Vec::new();
        run(&cfg, |e| {
            seen.push((
                e.kind.clone(),
                e.exposure.meta.t_exposure_s,
                e.exposure.meta.t_start,
            ));
            Ok(())
        })
        .unwrap();
        let darks_of = |k: usize| {
            let ill: Vec<usize> = (0..seen.len())
                .filter(|&i| seen[i].0 == "illuminated")
                .collect();
            let end = ill.get(k + 1).copied().unwrap_or(seen.len());
            seen[ill[k] + 1..end]
                .iter()
                .map(|e| e.1)
                .collect::<Vec<f64>>()
        };
        assert_eq!(darks_of(0), vec![180.0; 20]);
        assert_eq!(darks_of(1), vec![60.0; 30]);
        assert_eq!(darks_of(2), vec![540.0; 10]);
        // illumination 3's integration ends 12 s after its shutter
        let ill: Vec<f64> = seen
            .iter()
            .filter(|e| e.0 == "illuminated")
            .map(|e| e.1)
            .collect();
        assert_eq!(ill, vec![613.0, 372.0, 252.0, 252.0, 613.0]);
        for w in seen.windows(2) {
            let dt = w[1].2 .0 - w[0].2 .0;
            assert!((dt - w[0].1).abs() < 1e-6, "{dt} vs {}", w[0].1);
        }
    }

    #[test]
    fn a_dark_shorter_than_three_frames_is_refused() {
        let mut c = Illumination::default_campaign();
        c[3].dark_s = Some(2.0);
        let cfg = LabConfig {
            size: 8,
            campaign: Some(c),
            ..LabConfig::default()
        };
        let e = validate(&cfg).unwrap_err().to_string();
        assert!(
            e.contains("--campaign") && e.contains("three frames"),
            "{e}"
        );
    }

    #[test]
    fn pinhole_covers_the_fluence_bins() {
        let p = pinhole(256);
        let f = |lo: f64, hi: f64| {
            p.iter()
                .filter(|v| {
                    let q = f64::from(**v) * 481.0;
                    q >= lo && q < hi
                })
                .count()
        };
        assert!(p[[128, 128]] > 1e5);
        assert!(f(260e3, 270e3) > 150);
        assert!(f(3.75e6, 3.92e6) > 100);
    }
}
