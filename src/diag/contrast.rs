//! What the data can test, and what the residual of a flexible base depends on.
//!
//! # Contrast classes
//! Each library effect acts on one covariate ([`class_of`]). An effect can only be told
//! from everything else the model gets slightly wrong where its covariate varies among
//! samples that are otherwise alike (same fluence, same time since illumination).
//! [`testability`] decides that from the data alone, class by class:
//!
//! - `illumination_time` (soak): two illumination durations differing by more than
//!   [`REL_DIFFERENT`];
//! - `temperature`: focal-plane temperatures spanning at least [`MIN_TEMPERATURE_SPAN_K`];
//! - `earlier_illuminations` (capacity, refill): a second illumination event;
//! - `integration_length` (linefit_bias): dark integrations of lengths differing by
//!   more than [`REL_DIFFERENT`] (the on-board line fit's bias grows with the length and
//!   the decay's curvature; at one length it is a function of the time since
//!   illumination, which the base takes in);
//! - `neighbour_excess_fluence` (blooming, ipc): at least [`MIN_SHARP_BLOCKS`] sampled
//!   pixel-events whose neighbours' excess over saturation exceeds their own fluence;
//! - `position` (populations): at least [`MIN_SHARP_BLOCKS`] pixel-events in strata of
//!   one event and one fluence bin that span [`MIN_TILES`] tiles of the array (with a
//!   centred spot radius and fluence go together and position has no contrast);
//! - `fluence_x_time` (short_tau_boost, `smooth_shape`): a decay shape that depends on
//!   the fluence, a function of (fluence, time since illumination) alone, which the
//!   base absorbs by construction: measured directly instead, as the tilt of the
//!   decay against the fluence ([`super::shape`]), when two fluence bins each span a
//!   decade of time;
//! - `time_since_illumination` (chord): a function of the time alone: never declared
//!   from contrasts; `compare` and `fit --with` measure it.
//!
//! An untestable class is an answer: it is listed with the measurement that would give
//! it contrast, and its effects are not scored.
//!
//! # The flexible base and its residual
//! The base is the fitted model plus a free offset per cell of (fluence bin, time bin),
//! shared by every illumination event (a free response per fluence bin and a free decay
//! per time bin): `e_i = (d_i - mean_c d) / scale_c`, `d_i = measured - predicted`,
//! `scale_c` the cell's robust spread (1.4826 MAD, at least the median measurement
//! noise), clipped to +-[`CLIP`]. Any misfit of the decay law, of the response around
//! saturation, of the mix of trap populations or of the noise level is a function of
//! (fluence, time) and leaves `e` unchanged on average. For covariates that vary from
//! pixel to pixel within an event the cells are also split by event.
//!
//! # Two bases
//! Pixel-level classes are tested against the flexible base. Event-level classes are
//! tested against the pixel reference ([`super::base::predict_scaled`]): the flexible
//! base times each pixel's own amplitude, decay shape and response in fluence. A
//! pixel's factor is shared by every illumination of that pixel, so it cannot take in
//! what differs between its illuminations of equal fluence (duration, temperature,
//! history), while it takes in the
//! per-pixel trap populations and the misfit of the decay law that otherwise follow the
//! illumination pattern into every event-level covariate. Measured with
//! examples/dependence_scan on the second generator's campaigns (64 x 64, seeds 1-5,
//! nothing hidden, with and without dark pixels): against the flexible base the history
//! explained up to 0.73 % beyond its permutations (z 25); against the pixel reference
//! no event-level class explained more than 0.39 %, while the classes of hidden soak,
//! temperature and capacity explained 0.49-23 % (docs/validation/kinds.md, `make
//! validation PAGES=kinds`). [`MIN_R2_EVENT`] lies between. The pixel reference takes in
//! position (hidden trap-density fields vanish from it), so pixel-level classes stay
//! on the flexible base.
//!
//! # Pixels next to far brighter ones
//! Blooming and inter-pixel capacitance act most where a pixel's neighbours hold far
//! more charge than it does itself: next to a pinhole or the edge of a saturated spot.
//! `T` pools those few pixel-events with every other bin of the neighbours' excess, and
//! the flexible base's misfit inside its cells follows the fluence pattern into the
//! other bins, so a blooming that leaves a clear excess next to the pinholes can
//! explain less than [`MIN_R2`]. For `neighbour_excess_fluence` a second, one-degree
//! test is made ([`SharpExcess`]): `D`, the summed residual of the pixel-events whose
//! neighbours' excess exceeds their own fluence (the contrast of [`testability`]) beyond
//! the mean of their cells, against permutations of that mark among the blocks of each
//! stratum and tile of the array: given the position, so that a field of trap density
//! under clustered sharp pixels (a spot's edge) does not move it. The class also
//! depends when `D` lies farther from the permutations' mean than every permutation
//! and `|z|` reaches [`MIN_SHARP_Z`], in either sign (blooming adds charge next to the
//! bright pixel; coupling in the read moves signal into the neighbours' measured
//! fluence and lowers their persistence against it). Measured with
//! examples/dependence_scan on the second generator (campaigns and single
//! illuminations with the pinhole grid, 64 x 64 and 128 x 128, seeds 1-5, nothing
//! hidden, 13 runs): `|z|` at most 2.7 (mean excess -0.03 to +0.07 of the cells'
//! spread); with hidden blooming by field on campaigns (seeds 1-5 at 64 x 64, seed 1
//! at 128 x 128): `z` 4.4-16.1 (mean excess +0.15 to +0.38; the 4.4, seed 2, is not
//! named), where `T` explained 0.28-0.68 % in four of them; `populations:smooth`
//! (seeds 2 and 3, no pinholes): `z` -2.0 and -0.4, where the same test without the
//! tiles gave -6.4 and -5.0.
//!
//! # Dependence on a covariate, calibrated by permutation
//! The samples are grouped in blocks of one pixel in one event (its whole time series).
//! Each block has a covariate bin `x_b` and a stratum (its fluence bin; with the event
//! for pixel covariates). `T = sum_(c, x) S_(c,x)^2 / n_(c,x)`, `S` the sum of `e` over
//! the samples of cell `c` in blocks of bin `x`: the variance of the base's residual
//! explained by the covariate inside the cells. The null distribution comes from
//! [`PERMUTATIONS`] permutations of `x` among the blocks of each stratum, whole blocks at
//! a time: it keeps every misfit of the base, the correlation of a pixel's residuals in
//! time and the noise, and destroys only the link to the covariate. A class depends on
//! its covariate when `T` exceeds every permutation (p < 1/(P+1)) and the excess over the
//! permutations' mean explains at least [`min_r2`] of the residual's sum of squares
//! ([`MIN_R2`] for pixel-level classes, [`MIN_R2_EVENT`] for event-level ones).
//! The `earlier_illuminations` bin is the previous illumination's fluence in the pixel
//! (half-decades) and the time from its end to this illumination's start
//! (half-decades): a repeat 15 min after a bright illumination meets traps still full,
//! one after an hour meets them mostly empty, and only the time tells them apart from
//! a change of the illumination's duration or flux.
//! Classes that depend come first, ranked by `z = (T - mean) / sd` of the permutations;
//! the event-level ones among them are then reordered, within the places they hold, by
//! effect size (`T - mean` over the sum of squares). Their residuals share one
//! denominator, so the effect size compares them directly, while `z` also follows how
//! many events a covariate splits (measured on capacity:ceiling of the family: the
//! duration at `z` 73.6 explaining 1.7 % beyond the permutations' mean, earlier
//! illuminations at `z` 71.4 explaining 4.5 %). Effect size favours the finer split of
//! the events when two classes explain about as much: on temperature:arrhenius (seed 3)
//! earlier illuminations, whose bins also separate the events, explained 2.4 % against
//! temperature's 2.3 % and came first, where `z` had put temperature first (38.2 against
//! 31.9). A pixel-level class's residual is standardised in cells split by event, so
//! its effect size is on another scale and it keeps its place by `z`. The effects of every
//! event-level class whose `T` exceeds every permutation, and of every pixel-level class
//! that depends, are refitted ([`Dependence::refits`]), and held-out prediction
//! chooses among them ([`super::diagnose`]): event-level classes are often confounded
//! (in a campaign the events differ in duration, flux, temperature and history at once). Two event-level
//! classes whose covariates split the events the same way cannot be told apart; both
//! are reported, with the same `T`. A pixel-level class has hundreds of blocks per
//! stratum and the illumination pattern is spatial, so a base misfit that follows the
//! pattern puts it above every permutation with nothing hidden (measured with
//! examples/family_matrix at 64 x 64, single illumination with nothing hidden: position
//! and neighbours' excess explained 0.5 % more than the permutations' mean, against 3 %
//! and 25 % with hidden blooming and trap density fields): it must also depend.

use super::data::{fluence, Sequence};
use super::eval::{bin_of, Samples};
use crate::stats::median;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use serde::Serialize;
use std::collections::BTreeMap;

/// Two durations (or integration lengths) differ when their ratio exceeds `1 + this`.
pub const REL_DIFFERENT: f64 = 0.1;
/// The focal-plane temperatures must span at least this to test `temperature`.
pub const MIN_TEMPERATURE_SPAN_K: f64 = 1.0;
/// Pixel-events with the contrast needed for a pixel-level class.
pub const MIN_SHARP_BLOCKS: usize = 20;
/// Tiles (of a 4 x 4 grid) one stratum must span for `position`.
pub const MIN_TILES: usize = 4;
/// Permutations of the dependence test.
pub const PERMUTATIONS: usize = 99;
/// Smallest share of the flexible base residual's sum of squares a pixel-level
/// covariate must explain beyond the permutations' mean.
pub const MIN_R2: f64 = 0.01;
/// Smallest share of the pixel reference residual's sum of squares an event-level
/// covariate must explain beyond the permutations' mean.
pub const MIN_R2_EVENT: f64 = 0.0045;
/// `|z|` the residual of the pixel-events next to far brighter pixels must reach
/// beyond their cells' mean for `neighbour_excess_fluence` to depend on it alone
/// (module docs, "Pixels next to far brighter ones").
pub const MIN_SHARP_Z: f64 = 4.5;
/// Clip of the standardised base residual.
pub const CLIP: f64 = 5.0;

/// The contrast class of a library effect (module docs).
/// The bin of a focal-plane temperature `t_k` the temperature class compares (0.5 K):
/// exposures whose temperatures share a bin are held at one temperature.
pub fn temperature_bin(t_k: f64) -> i64 {
    (t_k * 2.0).round() as i64
}

pub fn class_of(effect: &str, covariate: &str) -> &'static str {
    match (effect, covariate) {
        ("linefit_bias", _) => "integration_length",
        (_, "illumination_time") => "illumination_time",
        (_, "temperature") => "temperature",
        (_, "earlier_illuminations") => "earlier_illuminations",
        (_, "neighbour_excess_fluence") => "neighbour_excess_fluence",
        (_, "position") => "position",
        (_, "fluence_x_time") => "fluence_x_time",
        _ => "time_since_illumination",
    }
}

/// Whether a class varies from pixel to pixel inside one event (its cells are split
/// by event) rather than from event to event.
pub(super) fn pixel_level(class: &str) -> bool {
    matches!(class, "neighbour_excess_fluence" | "position")
}

/// Whether the pixel reference can see an effect of this class: one that changes how a
/// pixel's illuminations (or its dark integrations) differ. Its per-pixel factor takes
/// in what varies from pixel to pixel, and its cells what is a function of (fluence,
/// time since illumination) alone.
pub(super) fn seen_by_pixel_reference(class: &str) -> bool {
    !pixel_level(class) && !matches!(class, "fluence_x_time" | "time_since_illumination")
}

/// Whether the data hold contrast for one class.
#[derive(Debug, Clone, Serialize)]
pub struct Testability {
    pub class: String,
    pub effects: Vec<String>,
    pub testable: bool,
    /// What the data hold (testable) or lack (untestable).
    pub why: String,
    /// The measurement that would make it testable.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub needs: Option<String>,
}

/// Distinct values (ratio above `1 + REL_DIFFERENT` apart), sorted.
fn distinct(mut v: Vec<f64>) -> Vec<f64> {
    v.retain(|x| x.is_finite() && *x > 0.0);
    v.sort_by(f64::total_cmp);
    let mut out: Vec<f64> = Vec::new();
    for x in v {
        if out.last().is_none_or(|&l| x > l * (1.0 + REL_DIFFERENT)) {
            out.push(x);
        }
    }
    out
}

fn list_s(v: &[f64]) -> String {
    v.iter()
        .map(|x| format!("{x:.0} s"))
        .collect::<Vec<_>>()
        .join(", ")
}

/// The 4 x 4 tile of a pixel.
pub(super) fn tile(seq: &Sequence, (y, x): (usize, usize)) -> i64 {
    ((y * 4 / seq.ny.max(1)) * 4 + x * 4 / seq.nx.max(1)) as i64
}

/// Pixel-events (blocks) of the samples: `(event, pixel index, fluence bin)`, each once.
pub(super) fn blocks(s: &Samples) -> Vec<(usize, usize, i64)> {
    let np = s.npix();
    let mut seen = std::collections::BTreeSet::new();
    for i in 0..s.len() {
        if !s.measured[i].is_finite() {
            continue;
        }
        let (row, px) = (i / np, i % np);
        if let Some(f) = bin_of(s, "fluence", i) {
            seen.insert((s.event[row], px, f));
        }
    }
    seen.into_iter().collect()
}

/// Whether a class's covariate has contrast in the data, why, and what would give it.
type Contrast = (bool, String, Option<String>);

/// Which classes the data can test (module docs), for the library effects `effects`
/// (name, covariate of the registry).
pub fn testability(seq: &Sequence, s: &Samples, effects: &[(&str, &str)]) -> Vec<Testability> {
    let ev = s.events();
    let mut classes: Vec<(&'static str, Vec<String>)> = Vec::new();
    for &(name, cov) in effects {
        let c = class_of(name, cov);
        match classes.iter_mut().find(|(k, _)| *k == c) {
            Some((_, v)) => v.push(name.to_string()),
            None => classes.push((c, vec![name.to_string()])),
        }
    }
    classes
        .into_iter()
        .map(|(class, effects)| {
            let (testable, why, needs) = match class {
                "illumination_time" => duration_contrast(seq, &ev),
                "temperature" => temperature_contrast(s),
                "earlier_illuminations" => history_contrast(&ev),
                "integration_length" => integration_contrast(seq, s),
                "neighbour_excess_fluence" => neighbour_contrast(s),
                "position" => position_contrast(seq, s),
                "fluence_x_time" => shape_contrast(s),
                _ => no_contrast(),
            };
            Testability {
                class: class.to_string(),
                effects,
                testable,
                why,
                needs,
            }
        })
        .collect()
}

/// Illumination durations: two that differ ([`REL_DIFFERENT`]).
fn duration_contrast(seq: &Sequence, ev: &[usize]) -> Contrast {
    let d = distinct(
        ev.iter()
            .map(|&a| seq.exposures[a].meta.t_illuminated_s())
            .collect(),
    );
    if d.len() >= 2 {
        (true, format!("illumination durations {}", list_s(&d)), None)
    } else {
        (
            false,
            format!("every illumination lasts {}", list_s(&d)),
            Some(
                "illuminations of two durations at equal fluence (for example \
                 120 s and 481 s)"
                    .into(),
            ),
        )
    }
}

/// Focal-plane temperatures spanning [`MIN_TEMPERATURE_SPAN_K`].
fn temperature_contrast(s: &Samples) -> Contrast {
    let t: Vec<f64> = s
        .temperature_k
        .iter()
        .copied()
        .filter(|t| t.is_finite())
        .collect();
    let (lo, hi) = t.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, &x| {
        (a.0.min(x), a.1.max(x))
    });
    let needs = Some(
        "illuminations at focal-plane temperatures at least 2 K apart (for \
         example 78 K and 82 K), with focal_plane_temp_k recorded"
            .into(),
    );
    if t.is_empty() {
        (
            false,
            "no exposure records focal_plane_temp_k".into(),
            needs,
        )
    } else if hi - lo >= MIN_TEMPERATURE_SPAN_K {
        (true, format!("temperatures {lo:.1} to {hi:.1} K"), None)
    } else {
        (
            false,
            format!("temperatures span {lo:.1} to {hi:.1} K only"),
            needs,
        )
    }
}

/// Earlier illuminations: two illumination events or more.
fn history_contrast(ev: &[usize]) -> Contrast {
    if ev.len() >= 2 {
        (true, format!("{} illumination events", ev.len()), None)
    } else {
        (
            false,
            "one illumination event: the traps were empty before it".into(),
            Some(
                "a second illumination while the traps still hold the first's \
                 charge (for example illuminations of 240 s repeated after 15 \
                 min of darks)"
                    .into(),
            ),
        )
    }
}

/// Dark integrations of two lengths.
fn integration_contrast(seq: &Sequence, s: &Samples) -> Contrast {
    let d = distinct(
        s.exposures
            .iter()
            .map(|&k| seq.exposures[k].meta.t_exposure_s)
            .collect(),
    );
    if d.len() >= 2 {
        (true, format!("dark integrations of {}", list_s(&d)), None)
    } else {
        (
            false,
            format!(
                "every dark integration lasts {}: the line fit's bias is then \
                 a function of the time since illumination, which the base \
                 takes in",
                list_s(&d)
            ),
            Some(
                "dark integrations of different lengths after equal \
                 illuminations (for example 60 s and 540 s)"
                    .into(),
            ),
        )
    }
}

/// Sharp features: at least [`MIN_SHARP_BLOCKS`] sampled pixel-events next to far
/// brighter, saturated pixels.
fn neighbour_contrast(s: &Samples) -> Contrast {
    let np = s.npix();
    let mut sharp = std::collections::BTreeSet::new();
    for i in 0..s.len() {
        if s.measured[i].is_finite() && bin_of(s, "neighbour_contrast", i) == Some(1) {
            sharp.insert((s.event[i / np], i % np));
        }
    }
    if sharp.len() >= MIN_SHARP_BLOCKS {
        (
            true,
            format!(
                "{} sampled pixel-events next to far brighter, saturated pixels",
                sharp.len()
            ),
            None,
        )
    } else {
        (
            false,
            format!(
                "{} sampled pixel-events next to far brighter, saturated pixels \
                 (at least {MIN_SHARP_BLOCKS} needed): no sharp features",
                sharp.len()
            ),
            Some(
                "sharp features: pixels below saturation next to saturated ones \
                 (a grid of one-pixel pinholes, or an edge)"
                    .into(),
            ),
        )
    }
}

/// Equal fluence at different positions: at least [`MIN_SHARP_BLOCKS`] pixel-events
/// whose fluence bin spans [`MIN_TILES`] tiles of the array.
fn position_contrast(seq: &Sequence, s: &Samples) -> Contrast {
    let mut strata: BTreeMap<(usize, i64), (usize, Vec<i64>)> = BTreeMap::new();
    for &(e, px, f) in &blocks(s) {
        let t = tile(seq, s.pixels[px]);
        let st = strata.entry((e, f)).or_default();
        st.0 += 1;
        if !st.1.contains(&t) {
            st.1.push(t);
        }
    }
    let spread: usize = strata
        .values()
        .filter(|(_, t)| t.len() >= MIN_TILES)
        .map(|(n, _)| n)
        .sum();
    if spread >= MIN_SHARP_BLOCKS {
        (
            true,
            format!(
                "{spread} sampled pixel-events share their fluence bin with \
                 pixels in {MIN_TILES} or more tiles of the array"
            ),
            None,
        )
    } else {
        (
            false,
            "equal fluences lie in one part of the array only (radius and \
             fluence go together)"
                .into(),
            Some(
                "equal fluence at different positions (the spot moved across \
                 the array, or a flat illumination)"
                    .into(),
            ),
        )
    }
}

/// Fluence bins whose samples span a decade of time ([`super::shape::testable`]).
fn shape_contrast(s: &Samples) -> Contrast {
    if super::shape::testable(s) {
        (
            true,
            "fluence bins spanning a decade of time since illumination: the decay's \
             tilt against the fluence is measured (not a contrast)"
                .into(),
            None,
        )
    } else {
        (
            false,
            "fewer than two fluence bins whose samples span a decade of time since \
             illumination"
                .into(),
            Some(
                "darks for at least an hour after illuminations of fluences a decade apart".into(),
            ),
        )
    }
}

/// A function of the time since illumination alone: never testable.
fn no_contrast() -> Contrast {
    (
        false,
        "a function of the time since illumination alone, which the base \
     absorbs: no contrast can tell it from the base's own misfit"
            .into(),
        Some(
            "no measurement separates it from the decay law; measure it with \
         persist fit --with NAME and compare"
                .into(),
        ),
    )
}

/// The base residual's dependence on one class's covariate (module docs).
#[derive(Debug, Clone, Serialize)]
pub struct Dependence {
    pub class: String,
    pub effects: Vec<String>,
    /// `T` over the residual's sum of squares.
    pub r2: f64,
    /// The permutations' mean of the same.
    pub r2_null_mean: f64,
    /// The permutations' largest.
    pub r2_null_max: f64,
    pub z: f64,
    pub permutations: usize,
    pub depends: bool,
    /// `T` above every permutation (p < 1/(P+1)), whatever the effect size: its effects
    /// are refitted and judged by held-out prediction.
    pub above_permutations: bool,
    /// Mean standardised base residual per covariate bin: (bin, blocks, mean).
    pub by_bin: Vec<(String, usize, f64)>,
    /// `neighbour_excess_fluence` only: the residual of the pixel-events next to far
    /// brighter pixels beyond their cells' mean.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sharp: Option<SharpExcess>,
}

/// The residual of the pixel-events whose neighbours' excess over saturation exceeds
/// their own fluence, beyond the mean of their cells (module docs, "Pixels next to far
/// brighter ones").
#[derive(Debug, Clone, Copy, Serialize)]
pub struct SharpExcess {
    /// Pixel-events next to far brighter pixels.
    pub blocks: usize,
    /// Their mean standardised residual beyond their cells' mean (in units of the
    /// cells' spread).
    pub mean: f64,
    /// `(D - mean) / sd` of the permutations, `D` their summed residual.
    pub z: f64,
    /// `|D - mean|` beyond every permutation's, and `|z|` at least [`MIN_SHARP_Z`].
    pub depends: bool,
}

impl Dependence {
    /// Whether this class's effects are refitted (module docs): `T` above every
    /// permutation, and for a pixel-level class also the effect size of `depends`.
    pub fn refits(&self) -> bool {
        self.above_permutations && (self.depends || !pixel_level(&self.class))
    }
}

/// The standardised residual of the flexible base (module docs), per sample (NaN where
/// unusable), cells split by event when `by_event`.
pub(super) fn base_residual(s: &Samples, pred: &[f64], by_event: bool) -> Vec<f64> {
    cell_residual(s, pred, by_event, false)
}

/// The factors a cell's level may take in [`scaled_residual`]: beyond them a cell's
/// predictions say too little of its measurements to scale them.
pub(super) const CELL_SCALE_RANGE: (f64, f64) = (0.2, 5.0);

/// [`base_residual`] of the predictions scaled per (fluence, time, event) cell by the
/// least-squares factor through the origin, `sum m p / sum p^2` (clamped to
/// [`CELL_SCALE_RANGE`]): a factor on the level, where the additive offset takes in a
/// level misfit only as a shift. A field over the array scales what it multiplies: with
/// the level off by a factor `k` in a cell, an offset leaves `k` of the field's
/// variation to be matched, a factor none.
pub(super) fn scaled_residual(s: &Samples, pred: &[f64], by_event: bool) -> Vec<f64> {
    cell_residual(s, pred, by_event, true)
}

/// The least-squares factor through the origin of a cell's samples `idx`,
/// `sum m p / sum p^2`, clamped to [`CELL_SCALE_RANGE`]; 1 without a positive `sum p^2`.
fn cell_factor(s: &Samples, pred: &[f64], idx: &[usize]) -> f64 {
    let (mp, pp) = idx.iter().fold((0.0, 0.0), |(a, b), &i| {
        (a + s.measured[i] * pred[i], b + pred[i] * pred[i])
    });
    if pp > 0.0 {
        (mp / pp).clamp(CELL_SCALE_RANGE.0, CELL_SCALE_RANGE.1)
    } else {
        1.0
    }
}

/// [`base_residual`], or [`scaled_residual`] when `scaled`.
#[allow(clippy::needless_range_loop)] // i indexes the samples' parallel columns
fn cell_residual(s: &Samples, pred: &[f64], by_event: bool, scaled: bool) -> Vec<f64> {
    let np = s.npix();
    let mut cells: BTreeMap<(i64, i64, usize), Vec<usize>> = BTreeMap::new();
    for i in 0..s.len() {
        if !(s.measured[i].is_finite() && pred[i].is_finite()) {
            continue;
        }
        let row = i / np;
        let (Some(f), Some(t)) = (bin_of(s, "fluence", i), bin_of(s, "time", i)) else {
            continue;
        };
        let e = if by_event { s.event[row] } else { usize::MAX };
        cells.entry((f, t, e)).or_default().push(i);
    }
    let mut out = vec![f64::NAN; s.len()];
    for idx in cells.values() {
        if idx.len() < 4 {
            continue;
        }
        let k = if scaled {
            cell_factor(s, pred, idx)
        } else {
            1.0
        };
        let d: Vec<f64> = idx.iter().map(|&i| s.measured[i] - k * pred[i]).collect();
        let med = median(&d);
        let dev: Vec<f64> = d.iter().map(|x| (x - med).abs()).collect();
        let noise = median(&idx.iter().map(|&i| s.noise[i / np]).collect::<Vec<_>>());
        let scale = (1.4826 * median(&dev)).max(noise).max(1e-12);
        let z: Vec<f64> = d
            .iter()
            .map(|x| ((x - med) / scale).clamp(-CLIP, CLIP))
            .collect();
        let mean = z.iter().sum::<f64>() / z.len() as f64;
        for (&i, v) in idx.iter().zip(z) {
            out[i] = v - mean;
        }
    }
    out
}

/// The `earlier_illuminations` bin of a block with no earlier illumination (or none
/// above 1 e- in its pixel).
const NO_EARLIER: i64 = -100;
/// Half-decade bins of the time between illuminations, from 1 s to 10^10 s.
const GAP_BINS: i64 = 20;

/// The half-decade bin of the time from the end of illumination `a` to the start of
/// illumination `e`: how much of `a`'s charge the traps still hold.
fn gap_bin(seq: &Sequence, a: usize, e: usize) -> i64 {
    let (ma, me) = (&seq.exposures[a].meta, &seq.exposures[e].meta);
    let gap_s = me.t_start.0 - (ma.t_start.0 + ma.t_exposure_s);
    if gap_s.is_finite() && gap_s > 1.0 {
        ((gap_s.log10() * 2.0).floor() as i64).clamp(0, GAP_BINS - 1)
    } else {
        0
    }
}

/// Per-block covariate bin of a class; None leaves the block out.
pub(super) fn covariate_bins(
    seq: &Sequence,
    s: &Samples,
    class: &str,
    blocks: &[(usize, usize, i64)],
) -> Vec<Option<i64>> {
    let np = s.npix();
    // the first row of each event, for the event-level covariates
    let mut first_row: BTreeMap<usize, usize> = BTreeMap::new();
    for (r, &e) in s.event.iter().enumerate() {
        first_row.entry(e).or_insert(r);
    }
    // per event: the median dark integration's bin, computed once
    let mut integration: BTreeMap<usize, Option<i64>> = BTreeMap::new();
    // per event: the fluence map of the illumination before it, for capacity
    let mut prev: BTreeMap<usize, (Option<ndarray::Array2<f64>>, i64)> = BTreeMap::new();
    blocks
        .iter()
        .map(|&(e, px, _)| {
            let row = first_row[&e];
            let i = row * np + px;
            match class {
                "illumination_time" => {
                    let t = seq.exposures[e].meta.t_illuminated_s();
                    (t > 0.0).then(|| (t.log10() * 20.0).round() as i64)
                }
                "temperature" => Some(temperature_bin(seq.exposures[e].meta.focal_plane_temp_k?)),
                "integration_length" => *integration.entry(e).or_insert_with(|| {
                    let rows: Vec<f64> = s
                        .exposures
                        .iter()
                        .zip(&s.event)
                        .filter(|(_, &ev)| ev == e)
                        .map(|(&k, _)| seq.exposures[k].meta.t_exposure_s)
                        .collect();
                    let m = median(&rows);
                    (m > 0.0).then(|| (m.log10() * 20.0).round() as i64)
                }),
                "earlier_illuminations" => {
                    let (f, gap) = prev.entry(e).or_insert_with(|| {
                        seq.illuminations
                            .iter()
                            .rfind(|&&a| a < e)
                            .map_or((None, 0), |&a| {
                                (Some(fluence(&seq.exposures[a])), gap_bin(seq, a, e))
                            })
                    });
                    let (y, x) = s.pixels[px];
                    Some(match f {
                        None => NO_EARLIER,
                        Some(f) => {
                            let v = f[(y, x)];
                            if v.is_finite() && v > 1.0 {
                                (v.log10() * 2.0).floor() as i64 * GAP_BINS + *gap
                            } else {
                                NO_EARLIER
                            }
                        }
                    })
                }
                "neighbour_excess_fluence" | "neighbour_contrast" => bin_of(s, class, i),
                "position" => Some(tile(seq, s.pixels[px])),
                _ => None,
            }
        })
        .collect()
}

/// The predictions each level of class is tested against (module docs, "Two bases").
#[derive(Debug, Clone, Copy)]
pub struct Bases<'a> {
    /// The flexible base ([`super::base::predict`]), per sample: for pixel-level classes.
    pub flexible: &'a [f64],
    /// The pixel reference ([`super::base::predict_scaled`]), per sample: for
    /// event-level classes.
    pub pixel_reference: &'a [f64],
}

impl<'a> Bases<'a> {
    /// The prediction `class` is tested against.
    pub fn of(&self, class: &str) -> &'a [f64] {
        if pixel_level(class) {
            self.flexible
        } else {
            self.pixel_reference
        }
    }
}

/// What `class` is tested against, in words.
pub fn base_name(class: &str) -> &'static str {
    if pixel_level(class) {
        "the flexible base"
    } else {
        "the pixel reference"
    }
}

/// The smallest share of its base's residual sum of squares a class's covariate must
/// explain beyond the permutations' mean (module docs).
pub fn min_r2(class: &str) -> f64 {
    if pixel_level(class) {
        MIN_R2
    } else {
        MIN_R2_EVENT
    }
}

/// The dependence of the base residual on each testable class's covariate, ranked by
/// `z` (module docs). `pred` is the fitted model's prediction of every sample.
pub fn dependences(
    seq: &Sequence,
    s: &Samples,
    bases: Bases,
    classes: &[Testability],
    seed: u64,
) -> Vec<Dependence> {
    let blocks = blocks(s);
    let mut residual: [Option<Vec<f64>>; 2] = [None, None];
    let mut out: Vec<Dependence> = classes
        .iter()
        .filter(|c| c.testable)
        .filter(|c| c.class != "fluence_x_time" && c.class != "time_since_illumination")
        .map(|c| {
            let by_event = pixel_level(&c.class);
            let e = residual[usize::from(by_event)]
                .get_or_insert_with(|| base_residual(s, bases.of(&c.class), by_event))
                .clone();
            let x = covariate_bins(seq, s, &c.class, &blocks);
            let (per_block, ss) = block_sums(s, &e, &x, &blocks, by_event);
            let stat = |xs: &[Option<i64>]| explained(&per_block, xs, None);
            let t = stat(&x);
            let null = permutation_null(&x, &blocks, by_event, None, seed, stat);
            let (mean, sd, max) = null_summary(&null);
            let ss = ss.max(1e-12);
            let z = if sd > 0.0 { (t - mean) / sd } else { 0.0 };
            let sharp = (c.class == "neighbour_excess_fluence").then(|| {
                let next_to_brighter = covariate_bins(seq, s, "neighbour_contrast", &blocks);
                let tiles = covariate_bins(seq, s, "position", &blocks);
                sharp_excess(
                    &per_block,
                    &x,
                    &next_to_brighter,
                    &blocks,
                    Some(&tiles),
                    seed,
                )
            });
            let sharp_depends = sharp.is_some_and(|d| d.depends);
            Dependence {
                class: c.class.clone(),
                effects: c.effects.clone(),
                r2: t / ss,
                r2_null_mean: mean / ss,
                r2_null_max: max / ss,
                z,
                permutations: PERMUTATIONS,
                depends: (t > max && (t - mean) / ss >= min_r2(&c.class)) || sharp_depends,
                above_permutations: t > max || sharp_depends,
                by_bin: residual_by_bin(&per_block, &x)
                    .into_iter()
                    .map(|(k, (nb, a, n))| (bin_label(&c.class, k), nb, a / n.max(1.0)))
                    .collect(),
                sharp,
            }
        })
        .collect();
    rank(&mut out);
    out
}

/// One block's residual summed per cell: (cell id, sum, samples).
pub(super) type CellSums = Vec<(usize, f64, f64)>;

/// Per block (of [`blocks`]), the residual `e` summed in each of its cells: (cell id,
/// sum, samples), in cell order; and the residual's sum of squares. Cells are fluence
/// x time bins, split by event when `by_event`; blocks without a covariate bin in `x`
/// are left out.
pub(super) fn block_sums(
    s: &Samples,
    e: &[f64],
    x: &[Option<i64>],
    blocks: &[(usize, usize, i64)],
    by_event: bool,
) -> (Vec<CellSums>, f64) {
    let np = s.npix();
    let block_of: BTreeMap<(usize, usize), usize> = blocks
        .iter()
        .enumerate()
        .map(|(b, &(e, px, _))| ((e, px), b))
        .collect();
    let mut cell_ids: BTreeMap<(i64, i64, usize), usize> = BTreeMap::new();
    let mut per_block: Vec<BTreeMap<usize, (f64, f64)>> = vec![BTreeMap::new(); blocks.len()];
    let mut ss = 0.0;
    for (i, &v) in e.iter().enumerate() {
        if !v.is_finite() {
            continue;
        }
        let (row, px) = (i / np, i % np);
        let Some(&b) = block_of.get(&(s.event[row], px)) else {
            continue;
        };
        if x[b].is_none() {
            continue;
        }
        let (Some(f), Some(t)) = (bin_of(s, "fluence", i), bin_of(s, "time", i)) else {
            continue;
        };
        let ev = if by_event { s.event[row] } else { usize::MAX };
        let n = cell_ids.len();
        let id = *cell_ids.entry((f, t, ev)).or_insert(n);
        let a = per_block[b].entry(id).or_insert((0.0, 0.0));
        a.0 += v;
        a.1 += 1.0;
        ss += v * v;
    }
    let per_block = per_block
        .into_iter()
        .map(|m| {
            let mut v: Vec<(usize, f64, f64)> =
                m.into_iter().map(|(k, (a, n))| (k, a, n)).collect();
            v.sort_by_key(|p| p.0);
            v
        })
        .collect();
    (per_block, ss)
}

/// `stat` of [`PERMUTATIONS`] permutations of the covariate bins `x` among the blocks
/// of each stratum (fluence bin, event when `by_event`, and the bin of `given` when
/// there is one: the blocks alike in another covariate), whole blocks at a time, from
/// a stream seeded by `seed`. Blocks without a bin in `x` (or in `given`) keep none.
pub(super) fn permutation_null(
    x: &[Option<i64>],
    blocks: &[(usize, usize, i64)],
    by_event: bool,
    given: Option<&[Option<i64>]>,
    seed: u64,
    stat: impl Fn(&[Option<i64>]) -> f64,
) -> Vec<f64> {
    let mut strata: BTreeMap<(i64, usize, i64), Vec<usize>> = BTreeMap::new();
    for (b, &(ev, _, f)) in blocks.iter().enumerate() {
        let g = given.map_or(Some(0), |g| g[b]);
        if let (Some(_), Some(g)) = (x[b], g) {
            strata
                .entry((f, if by_event { ev } else { usize::MAX }, g))
                .or_default()
                .push(b);
        }
    }
    let mut keys: Vec<&(i64, usize, i64)> = strata.keys().collect();
    keys.sort();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x51ed_270b_2a1d_c3f5);
    (0..PERMUTATIONS)
        .map(|_| {
            let mut xp = x.to_vec();
            for k in &keys {
                let members = &strata[k];
                let mut vals: Vec<Option<i64>> = members.iter().map(|&b| x[b]).collect();
                vals.shuffle(&mut rng);
                for (&b, v) in members.iter().zip(vals) {
                    xp[b] = v;
                }
            }
            stat(&xp)
        })
        .collect()
}

/// `T` (module docs): the residual summed per cell and covariate bin `x`, squared over
/// its samples; with `given`, the cells are also split by its bins and blocks without
/// one are left out.
pub(super) fn explained(
    per_block: &[CellSums],
    x: &[Option<i64>],
    given: Option<&[Option<i64>]>,
) -> f64 {
    let mut g: BTreeMap<(usize, i64, i64), (f64, f64)> = BTreeMap::new();
    for (b, entries) in per_block.iter().enumerate() {
        let (Some(xb), Some(gb)) = (x[b], given.map_or(Some(0), |g| g[b])) else {
            continue;
        };
        for &(id, a, n) in entries {
            let q = g.entry((id, gb, xb)).or_insert((0.0, 0.0));
            q.0 += a;
            q.1 += n;
        }
    }
    g.values().map(|(a, n)| a * a / n).sum()
}

/// [`SharpExcess`] of the blocks with `next_to_brighter` bin 1 (module docs): their
/// residual summed beyond their cells' mean, against [`PERMUTATIONS`] permutations of
/// the bin among the blocks of each stratum, split by the bin of `given` (the tile)
/// when there is one. Blocks without a bin in `x` are left out, as in `T`.
fn sharp_excess(
    per_block: &[CellSums],
    x: &[Option<i64>],
    next_to_brighter: &[Option<i64>],
    blocks: &[(usize, usize, i64)],
    given: Option<&[Option<i64>]>,
    seed: u64,
) -> SharpExcess {
    // `block_sums` leaves the blocks without a bin in `x` empty
    let mut cells: BTreeMap<usize, (f64, f64)> = BTreeMap::new();
    for entries in per_block {
        for &(id, a, n) in entries {
            let q = cells.entry(id).or_default();
            q.0 += a;
            q.1 += n;
        }
    }
    // per block: its residual beyond its cells' mean, and its samples
    let beyond: Vec<(f64, f64)> = per_block
        .iter()
        .map(|entries| {
            entries.iter().fold((0.0, 0.0), |(d, m), &(id, a, n)| {
                let (ca, cn) = cells.get(&id).copied().unwrap_or((0.0, 1.0));
                (d + a - n * ca / cn, m + n)
            })
        })
        .collect();
    let bins: Vec<Option<i64>> = (0..blocks.len())
        .map(|b| next_to_brighter[b].filter(|_| x[b].is_some()))
        .collect();
    let stat = |xs: &[Option<i64>]| -> f64 {
        (0..xs.len())
            .filter(|&b| xs[b] == Some(1))
            .map(|b| beyond[b].0)
            .sum()
    };
    let d = stat(&bins);
    let null = permutation_null(&bins, blocks, true, given, seed, stat);
    let (mean, sd, _) = null_summary(&null);
    let widest = null.iter().map(|v| (v - mean).abs()).fold(0.0, f64::max);
    let z = if sd > 0.0 { (d - mean) / sd } else { 0.0 };
    let sharp: Vec<usize> = (0..bins.len()).filter(|&b| bins[b] == Some(1)).collect();
    let samples: f64 = sharp.iter().map(|&b| beyond[b].1).sum();
    SharpExcess {
        blocks: sharp.len(),
        mean: d / samples.max(1.0),
        z,
        depends: (d - mean).abs() > widest && z.abs() >= MIN_SHARP_Z,
    }
}

/// The permutations' mean, standard deviation and largest value.
pub(super) fn null_summary(null: &[f64]) -> (f64, f64, f64) {
    let n = null.len() as f64;
    let mean = null.iter().sum::<f64>() / n;
    let sd = (null.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0)).sqrt();
    let max = null.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    (mean, sd, max)
}

/// Per covariate bin: the blocks in it, and the sum and number of their residual
/// samples.
fn residual_by_bin(per_block: &[CellSums], x: &[Option<i64>]) -> BTreeMap<i64, (usize, f64, f64)> {
    let mut by: BTreeMap<i64, (usize, f64, f64)> = BTreeMap::new();
    for (b, entries) in per_block.iter().enumerate() {
        let Some(xb) = x[b] else { continue };
        let q = by.entry(xb).or_default();
        q.0 += 1;
        for &(_, a, n) in entries {
            q.1 += a;
            q.2 += n;
        }
    }
    by
}

/// The effect size of a dependence: the share of the residual's sum of squares the
/// covariate explains beyond the permutations' mean.
fn excess_r2(d: &Dependence) -> f64 {
    d.r2 - d.r2_null_mean
}

/// Orders the dependences (module docs): those that depend first, by `z`; then the
/// depending event-level classes are reordered among their own places by effect size.
fn rank(out: &mut [Dependence]) {
    out.sort_by(|a, b| {
        b.depends
            .cmp(&a.depends)
            .then(b.z.total_cmp(&a.z))
            .then(a.class.cmp(&b.class))
    });
    let slots: Vec<usize> = (0..out.len())
        .filter(|&i| out[i].depends && !pixel_level(&out[i].class))
        .collect();
    let mut event: Vec<Dependence> = slots.iter().map(|&i| out[i].clone()).collect();
    event.sort_by(|a, b| {
        excess_r2(b)
            .total_cmp(&excess_r2(a))
            .then(a.class.cmp(&b.class))
    });
    for (&i, d) in slots.iter().zip(event) {
        out[i] = d;
    }
}

/// A readable label of a covariate bin of [`covariate_bins`].
fn bin_label(class: &str, b: i64) -> String {
    match class {
        "illumination_time" | "integration_length" => {
            format!("{:.0} s", 10f64.powf(b as f64 / 20.0))
        }
        "temperature" => format!("{:.1} K", b as f64 / 2.0),
        "earlier_illuminations" if b == NO_EARLIER => "no earlier fluence".into(),
        "earlier_illuminations" => {
            let (f, g) = (b.div_euclid(GAP_BINS), b.rem_euclid(GAP_BINS));
            format!(
                "earlier fluence >= {:.2e} e-, {:.0} s or more before",
                10f64.powf(f as f64 / 2.0),
                10f64.powf(g as f64 / 2.0)
            )
        }
        "neighbour_excess_fluence" if b < 0 => "no neighbour excess".into(),
        "neighbour_excess_fluence" => {
            format!("neighbour excess >= {:.2e} e-", 10f64.powf(b as f64 / 2.0))
        }
        "position" => format!("tile (row {}, col {})", b / 4, b % 4),
        _ => b.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn classes_of_the_library() {
        assert_eq!(class_of("soak", "illumination_time"), "illumination_time");
        assert_eq!(
            class_of("linefit_bias", "time_since_illumination"),
            "integration_length"
        );
        assert_eq!(
            class_of("chord", "time_since_illumination"),
            "time_since_illumination"
        );
        assert_eq!(
            class_of("capacity", "earlier_illuminations"),
            "earlier_illuminations"
        );
    }

    fn dep(class: &str, depends: bool, z: f64, r2: f64) -> Dependence {
        Dependence {
            class: class.into(),
            effects: vec![],
            r2,
            r2_null_mean: 0.001,
            r2_null_max: 0.002,
            z,
            permutations: PERMUTATIONS,
            depends,
            above_permutations: depends,
            by_bin: vec![],
            sharp: None,
        }
    }

    #[test]
    fn event_level_classes_rank_by_effect_size_in_their_places() {
        let mut d = vec![
            dep("temperature", false, 90.0, 0.5),
            dep("illumination_time", true, 73.6, 0.018),
            dep("position", true, 80.0, 0.2),
            dep("earlier_illuminations", true, 71.4, 0.046),
        ];
        rank(&mut d);
        let order: Vec<&str> = d.iter().map(|x| x.class.as_str()).collect();
        // position keeps its place by z; the event-level pair swaps by effect size;
        // a class that does not depend comes last whatever its z
        assert_eq!(
            order,
            [
                "position",
                "earlier_illuminations",
                "illumination_time",
                "temperature"
            ]
        );
    }

    /// 400 blocks in four strata (fluence bins) of one event, one cell per stratum, 20
    /// samples each of unit-spread noise; every tenth block next to a far brighter
    /// pixel, its residual shifted by `shift` per sample.
    fn sharp_case(shift: f64) -> SharpExcess {
        sharp_case_in(shift, 0.0, false)
    }

    /// [`sharp_case`] with the blocks in ten tiles of forty (block `b` in tile `b / 40`);
    /// with a `tile_shift`, every block of tile 0 shifted by it per sample and half of
    /// that tile's blocks marked (the marked pixels cluster where the field is high),
    /// the permutations given the tile when `given`.
    fn sharp_case_in(shift: f64, tile_shift: f64, given: bool) -> SharpExcess {
        let mut state = 7u64;
        let mut noise = || {
            // sum of 20 uniform(-0.5, 0.5) draws of a 64-bit LCG: spread sqrt(20/12)
            (0..20)
                .map(|_| {
                    state = state
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    (state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
                })
                .sum::<f64>()
        };
        let tile = |b: usize| b / 40;
        let blocks: Vec<(usize, usize, i64)> = (0..400).map(|b| (0, b, (b % 4) as i64)).collect();
        let is_marked = |b: usize| {
            b.is_multiple_of(10) || (tile_shift != 0.0 && tile(b) == 0 && b.is_multiple_of(2))
        };
        let marked: Vec<Option<i64>> = (0..400).map(|b| Some(i64::from(is_marked(b)))).collect();
        let per_block: Vec<CellSums> = (0..400)
            .map(|b| {
                let mut a = noise();
                if is_marked(b) {
                    a += 20.0 * shift;
                }
                if tile(b) == 0 {
                    a += 20.0 * tile_shift;
                }
                vec![(b % 4, a, 20.0)]
            })
            .collect();
        let x = vec![Some(0); 400];
        let tiles: Vec<Option<i64>> = (0..400).map(|b| Some(tile(b) as i64)).collect();
        let given = given.then_some(tiles.as_slice());
        sharp_excess(&per_block, &x, &marked, &blocks, given, 1)
    }

    #[test]
    fn pixels_next_to_far_brighter_ones_depend_in_either_sign_only_when_shifted() {
        let none = sharp_case(0.0);
        assert_eq!(none.blocks, 40);
        assert!(!none.depends && none.z.abs() < 3.0, "{none:?}");
        let up = sharp_case(0.3);
        assert!(up.depends && up.z >= MIN_SHARP_Z, "{up:?}");
        // the excess beyond the cells' mean: 0.3 less the marked tenth's share of it
        assert!((up.mean - 0.27).abs() < 0.06, "{up:?}");
        let down = sharp_case(-0.3);
        assert!(down.depends && down.z <= -MIN_SHARP_Z, "{down:?}");
    }

    #[test]
    fn a_field_under_clustered_sharp_pixels_moves_them_only_without_the_tiles() {
        let pooled = sharp_case_in(0.0, 0.3, false);
        assert!(pooled.depends && pooled.z > 0.0, "{pooled:?}");
        let given = sharp_case_in(0.0, 0.3, true);
        assert!(!given.depends && given.z.abs() < 3.0, "{given:?}");
        // an excess of the marked pixels themselves still stands out inside the tiles
        let both = sharp_case_in(0.3, 0.3, true);
        assert!(both.depends && both.z >= MIN_SHARP_Z, "{both:?}");
    }

    #[test]
    fn distinct_values_merge_within_ten_percent() {
        assert_eq!(
            distinct(vec![481.0, 120.0, 481.0, 490.0]),
            vec![120.0, 481.0]
        );
        assert_eq!(distinct(vec![f64::NAN, 0.0]), Vec::<f64>::new());
    }
}
