//! Following bright events through later sky exposures, pixel by pixel (pure array code:
//! no files, no clock).
//!
//! # What is measured
//! An **event** is a pixel whose extrapolated fluence in an exposure (the line-fit current
//! times the illuminated time: [`crate::model::fluence`], the rule the stage uses) reaches
//! [`TrackParams::event_fluence_e`] (default: the paper's saturation level, 200,000 e-),
//! or that the on-board processing flagged `OVERFLOW`. From the reset that ends that
//! exposure on, the pixel carries a **track**: in each later exposure its **excess
//! current** is its measured current minus an estimate of the sky it saw in that same
//! exposure.
//!
//! # The sky estimate, and why it is not the pixel's own history
//! SPHEREx has no shutter and points elsewhere every exposure, so a pixel's own earlier or
//! later exposures see other sky: they cannot give its sky now. The estimate is the
//! median of the pixels of a square annulus around it (Chebyshev distance
//! [`TrackParams::annulus_inner_px`] to [`TrackParams::annulus_outer_px`]) in the same
//! exposure, leaving out every pixel that itself carries a track (a recent event: its own
//! persistence would bias the sky high) and every pixel without a usable slope. The annulus
//! starts three pixels out so that the event's own point-spread function (and its
//! persistence, which has the same shape) is not in it. The median is robust to the few
//! annulus pixels that hold a star in this exposure. What it leaves: the annulus pixels'
//! own persistence floor (faint sources and zodiacal light, ~0.001-0.004 e-/s in the
//! simulator) is subtracted with the sky, so the excess is the persistence above that floor.
//!
//! The prediction and (in simulations) the truth go through the same operator: each minus
//! its median over the same annulus pixels, so the three are compared like for like.
//!
//! # Stars in the measured pixel
//! A star that falls on the measured pixel in a later exposure adds to its excess. Charge
//! released from one event only decays, so a track's excess cannot rise by more than noise:
//! a sample more than [`TrackParams::spike_nsigma`] standard deviations of the difference
//! (its and the last accepted sample's annulus noise) above the last accepted excess
//! floored at zero is rejected as a source and counted ([`passes_screen`]: why floored).
//! Fainter sources pass that screen, and on average add to the excess. Sources fall where
//! they fall whether or not a pixel saw an event, so **control pixels** (a grid of pixels
//! with no track and no fluence above [`TrackParams::control_lit_fluence_e`] within
//! [`TrackParams::control_quiet_s`], every [`CONTROL_STRIDE`]-th in each direction) are
//! measured and screened the same way; their weighted mean excess in each exposure
//! ([`Control`]) is what the
//! sources add, and the stacked means subtract it. A new event at the pixel ends the
//! track and starts another; a cosmic ray (`TRANSIENT`) ends it (the fluence is unknown).
//!
//! A track ends at its pixel's cosmic ray or when it grows older than
//! [`TrackParams::max_time_s`], before any pixel of the exposure is measured: an ended
//! track's pixel is sky for every annulus of that exposure.
//!
//! # Cosmic-ray hits
//! A pixel the on-board processing flagged `TRANSIENT` (with a slope: not `SUR_ERROR`,
//! not `NONFUNC`) that carries no track and that the stage predicted quiet in that
//! exposure (at most [`TrackParams::hit_quiet_e_per_s`], so that what follows is the
//! hit's and not an earlier event's) starts a **hit**: from the reset that ends the
//! exposure on, it is measured like a track (same sky annulus, same source screen,
//! same control), and its samples ([`Tracker::take_hit_samples`]) carry an unknown
//! (NaN) event fluence. Its first sample has no earlier one to screen a source against,
//! and the rule is read there ([`super::transient`]), so a source is screened by its
//! extent instead: a star's light reaches the pixel's neighbours, a hit's persistence
//! stays in the pixels it hit. The first sample is a source when the mean excess of its
//! 4-neighbours without a track or hit of their own, predicted quiet, stands more than
//! [`TrackParams::spike_nsigma`] noise sigmas of that mean above the sky; the next sample
//! is then the hit's first. A hit ends at its pixel's next `TRANSIENT`, at an event of its
//! pixel, or after [`TrackParams::hit_max_time_s`]. A hit's pixel stays sky for the
//! annuli: it was quiet before the hit, and its persistence is what is measured.
//!
//! Invariants: every [`Sample`] has a finite excess, prediction and time (a hit's has a
//! NaN event fluence, every other a finite one); samples come out
//! in pixel order, and the control grid's sums are taken in pixel order, so the result
//! does not depend on threads (rows are measured in parallel on the rayon pool, the
//! state is updated after them in pixel order).

use crate::flags::{bits, pbits};
use crate::model::fluence::{fluence_map_e, FlagBits};
use crate::stats::median_in_place;
use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;

/// How events are found and tracks measured.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TrackParams {
    /// Extrapolated fluence at or above which a pixel's exposure is an event, e-.
    pub event_fluence_e: f64,
    /// Inner Chebyshev radius of the sky annulus, pixels.
    pub annulus_inner_px: usize,
    /// Outer Chebyshev radius of the sky annulus, pixels.
    pub annulus_outer_px: usize,
    /// Fewest usable annulus pixels for a sky estimate.
    pub annulus_min_pixels: usize,
    /// A rise above the track's last accepted excess of more than this many noise
    /// standard deviations is a source in the measured pixel, not persistence.
    pub spike_nsigma: f64,
    /// Tracks end this long after their event, s.
    pub max_time_s: f64,
    /// A control pixel must not have seen this fluence (e-) within the last
    /// `control_quiet_s`: its own persistence would otherwise be subtracted with the
    /// sources' excess (module docs).
    pub control_lit_fluence_e: f64,
    /// How long a control pixel must have stayed below `control_lit_fluence_e`, s.
    pub control_quiet_s: f64,
    /// A `TRANSIENT` pixel starts a hit when the stage predicted at most this current
    /// for it in the hit's exposure, e-/s (module docs, "Cosmic-ray hits"; default the
    /// low threshold, 0.01).
    pub hit_quiet_e_per_s: f64,
    /// Hits end this long after the hit, s: the rule is measured at the first exposure
    /// after it, and by 10,000 s the paper's terms bring the knot table's maximum below
    /// 0.1 e-/s. Following every hit to `max_time_s` would measure fourteen times the
    /// events' samples on the demo sky (8.1 million) and make `verify` five times
    /// slower.
    pub hit_max_time_s: f64,
}

impl Default for TrackParams {
    fn default() -> Self {
        TrackParams {
            event_fluence_e: 2.0e5,
            annulus_inner_px: 3,
            annulus_outer_px: 6,
            annulus_min_pixels: 12,
            spike_nsigma: 3.0,
            max_time_s: 2.0e5,
            control_lit_fluence_e: 2.0e4,
            control_quiet_s: 2.0e4,
            hit_quiet_e_per_s: crate::model::params::Thresholds::default().low_e_per_s,
            hit_max_time_s: 1.0e4,
        }
    }
}

/// One exposure, as `verify` sees it.
#[derive(Debug, Clone, Copy)]
pub struct Frame<'a> {
    /// Line-fit current, e-/s.
    pub image: ArrayView2<'a, f32>,
    /// On-board flags.
    pub flags: ArrayView2<'a, u32>,
    /// The stage's predicted persistence current, e-/s.
    pub predicted: ArrayView2<'a, f32>,
    /// The stage's persistence flags.
    pub pflags: ArrayView2<'a, u8>,
    /// The simulator's true persistence current, when known, e-/s.
    pub truth: Option<ArrayView2<'a, f32>>,
    /// Seconds of illumination that turn the current into fluence.
    pub t_illuminated_s: f64,
    /// Middle of the integration, s on the run's clock.
    pub t_mid_s: f64,
    /// The reset that ends the integration, s on the same clock.
    pub t_reset_s: f64,
}

impl<'a> Frame<'a> {
    /// The frame of exposure `e` with the stage's predicted current and flags for it.
    pub fn of(
        e: &'a crate::product::Exposure,
        predicted: ArrayView2<'a, f32>,
        pflags: ArrayView2<'a, u8>,
        truth: Option<ArrayView2<'a, f32>>,
    ) -> Frame<'a> {
        let start = e.meta.t_start.0;
        Frame {
            image: e.image.view(),
            flags: e.flags.view(),
            predicted,
            pflags,
            truth,
            t_illuminated_s: e.meta.t_illuminated_s(),
            t_mid_s: start + 0.5 * e.meta.t_exposure_s,
            t_reset_s: start + e.meta.t_exposure_s,
        }
    }
}

/// One measured point of a track.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sample {
    pub y: usize,
    pub x: usize,
    /// The event that started the track: a cluster of adjacent event pixels of one exposure.
    pub cluster: u64,
    pub event_fluence_e: f64,
    /// From the reset ending the event's exposure to the middle of this one, s.
    pub time_s: f64,
    pub excess_e_per_s: f64,
    /// Noise standard deviation of one pixel's current here (the annulus's), e-/s.
    pub sigma_e_per_s: f64,
    /// The control pixels' mean screened excess in the same exposure: what sources that
    /// pass the screen add on average, to subtract from stacked means. A track's first
    /// sample has no earlier value to be screened against, so a bright source on it stays
    /// in; such sources are rare, and they widen the bootstrap interval of the bins they
    /// fall in rather than shift every bin (the unscreened control mean, dominated by the
    /// rare brightest sources, would).
    pub control_e_per_s: f64,
    /// In simulations, the control pixels' mean true persistence above their annuli's
    /// in the same exposure ([`Control::truth`]).
    pub control_true_e_per_s: f64,
    pub predicted_e_per_s: f64,
    /// The prediction minus its median over the same annulus pixels.
    pub predicted_excess_e_per_s: f64,
    /// Above the high threshold in the stage's output.
    pub flagged: bool,
    /// The truth minus its median over the same annulus pixels: the true persistence
    /// above the surroundings', which is what the excess measures.
    pub true_excess_e_per_s: Option<f64>,
    /// The first sample of its track.
    pub first: bool,
}

#[derive(Debug, Clone, Copy)]
struct Track {
    reset_s: f64,
    /// NaN for a hit.
    fluence_e: f64,
    cluster: u64,
    last_excess: f64,
    last_sigma: f64,
    samples: u32,
}

/// Per-pixel track state of one detector, carried from exposure to exposure.
#[derive(Debug)]
pub struct Tracker {
    params: TrackParams,
    tracks: Array2<Option<Track>>,
    next_cluster: u64,
    /// Each control pixel's last screened excess and its noise.
    control_last: Array2<(f64, f64)>,
    /// Reset ending the last exposure in which the pixel saw `control_lit_fluence_e`.
    lit_s: Array2<f64>,
    last_control: Control,
    /// Samples rejected as sources in the measured pixel.
    pub rejected: u64,
    /// Samples without a sky estimate (too few usable annulus pixels).
    pub no_sky: u64,
    /// Per-pixel hit state (module docs, "Cosmic-ray hits").
    hits: Array2<Option<Track>>,
    /// Hits started so far (each its own cluster).
    pub hits_started: u64,
    /// Hit samples rejected as sources.
    pub hit_rejected: u64,
    /// Hit samples of the frames observed since the last [`Tracker::take_hit_samples`].
    hit_samples: Vec<Sample>,
}

/// The mean excess of the control pixels in one frame, e-/s.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct Control {
    /// Every control pixel.
    pub raw: f64,
    /// Control pixels that pass the source screening against their own last value.
    pub screened: f64,
    pub pixels: usize,
    /// In simulations, the control pixels' true persistence above their annuli's
    /// (what the control would wrongly subtract; 0 without a truth).
    pub truth: f64,
}

/// One control pixel every this many pixels in each direction.
pub const CONTROL_STRIDE: usize = 4;

/// The source screen (module docs): a sample passes unless it rises above the level
/// its track can still hold, the last accepted excess floored at zero, by more than
/// `nsigma` standard deviations of the difference of the two samples. `last`: the last
/// accepted excess and its noise (`None`: nothing to compare with, the sample passes).
///
/// Why floored and why both noises: a screen against the last noisy sample alone is a
/// ratchet. After a sample drawn low (a crowded field's sky estimate can be 1 e-/s too
/// high), every later sample of a quiet field sits more than `nsigma` above it and is
/// rejected until another low one comes: the track keeps only its low draws and its
/// mean is biased low. Persistence is never negative and only decays, so zero and the
/// last accepted level bound what the track can hold.
pub fn passes_screen(last: Option<(f64, f64)>, excess: f64, sigma: f64, nsigma: f64) -> bool {
    match last {
        None => true,
        Some((l, ls)) => excess <= l.max(0.0) + nsigma * (sigma * sigma + ls * ls).sqrt(),
    }
}

const UNUSABLE: u32 = bits::TRANSIENT | bits::SUR_ERROR | bits::NONFUNC;

/// What one tracked pixel gave in one exposure (a pixel it skips gives nothing).
enum Measured {
    Sample(Sample),
    /// Too few usable annulus pixels.
    NoSky,
    /// Rejected by the source screen.
    Source,
}

/// One control pixel measured in one exposure.
struct ControlPixel {
    y: usize,
    x: usize,
    excess: f64,
    sigma: f64,
    /// The truth minus its median over the same annulus.
    truth: Option<f64>,
    /// Passes the source screen against its own last value.
    passes: bool,
}

/// A track's (or hit's) state after its sample `s` was accepted.
fn advance(track: &mut Option<Track>, s: &Sample) {
    if let Some(tr) = track.as_mut() {
        tr.last_excess = s.excess_e_per_s;
        tr.last_sigma = s.sigma_e_per_s;
        tr.samples += 1;
    }
}

/// Buffers of one worker: the annulus of the pixel last measured and its values.
#[derive(Default)]
struct Scratch {
    ring: Vec<(usize, usize)>,
    values: Vec<f64>,
}

impl Scratch {
    /// `plane` at `(y, x)` minus its median over the annulus of the last sky estimate.
    fn around(&mut self, plane: ArrayView2<f32>, y: usize, x: usize) -> f64 {
        self.values.clear();
        self.values
            .extend(self.ring.iter().map(|&(a, b)| f64::from(plane[[a, b]])));
        f64::from(plane[[y, x]]) - median_in_place(&mut self.values)
    }
}

impl Tracker {
    pub fn new(params: TrackParams, ny: usize, nx: usize) -> Self {
        Tracker {
            params,
            tracks: Array2::from_elem((ny, nx), None),
            next_cluster: 0,
            control_last: Array2::from_elem((ny, nx), (f64::NAN, f64::NAN)),
            lit_s: Array2::from_elem((ny, nx), f64::NEG_INFINITY),
            last_control: Control::default(),
            rejected: 0,
            no_sky: 0,
            hits: Array2::from_elem((ny, nx), None),
            hits_started: 0,
            hit_rejected: 0,
            hit_samples: Vec::new(),
        }
    }

    pub fn params(&self) -> &TrackParams {
        &self.params
    }

    /// The detector's shape, `(ny, nx)`.
    pub fn shape(&self) -> (usize, usize) {
        self.tracks.dim()
    }

    /// Events (clusters of adjacent event pixels) started so far.
    pub fn clusters_started(&self) -> u64 {
        self.next_cluster
    }

    /// Pixels currently carrying a track.
    pub fn active(&self) -> usize {
        self.tracks.iter().filter(|t| t.is_some()).count()
    }

    /// The samples of the hits measured by the frames observed since the last call, in
    /// frame then pixel order (module docs, "Cosmic-ray hits").
    pub fn take_hit_samples(&mut self) -> Vec<Sample> {
        std::mem::take(&mut self.hit_samples)
    }

    /// Measure every track and hit in `frame`, then start the tracks of its events and
    /// its hits. Returns the tracks' samples; the hits' are kept for
    /// [`Tracker::take_hit_samples`].
    pub fn observe(&mut self, frame: &Frame) -> Vec<Sample> {
        let (ny, nx) = frame.image.dim();
        assert_eq!(
            self.tracks.dim(),
            (ny, nx),
            "frame shape changed within a detector"
        );
        let fluence = fluence_map_e(
            frame.image,
            frame.flags,
            &FlagBits::default(),
            frame.t_illuminated_s,
        );
        let threshold = self.params.event_fluence_e;
        let mut event = Array2::from_elem((ny, nx), false);
        Zip::from(&mut event)
            .and(frame.flags)
            .and(&fluence)
            .par_for_each(|e, &f, &fl| {
                *e = f & UNUSABLE == 0 && (f & bits::OVERFLOW != 0 || fl >= threshold);
            });
        let control = self.controls(frame, &event);
        let hit_starts = self.hit_starts(frame);
        // Tracks end at their pixel's cosmic ray or when too old (module docs).
        let max_time_s = self.params.max_time_s;
        let hit_max_time_s = self.params.hit_max_time_s;
        Zip::from(&mut self.hits)
            .and(frame.flags)
            .and(&event)
            .par_for_each(|t, &f, &e| {
                if t.is_some_and(|tr| {
                    e || f & bits::TRANSIENT != 0 || frame.t_mid_s - tr.reset_s > hit_max_time_s
                }) {
                    *t = None;
                }
            });
        Zip::from(&mut self.tracks)
            .and(frame.flags)
            .par_for_each(|t, &f| {
                if t.is_some_and(|tr| {
                    f & bits::TRANSIENT != 0 || frame.t_mid_s - tr.reset_s > max_time_s
                }) {
                    *t = None;
                }
            });
        let this = &*self;
        let rows: Vec<(Vec<Measured>, Vec<Measured>)> = (0..ny)
            .into_par_iter()
            .map_init(Scratch::default, |scratch, y| {
                let (mut tracks, mut hits) = (Vec::new(), Vec::new());
                for x in 0..nx {
                    for (state, out) in [(&this.tracks, &mut tracks), (&this.hits, &mut hits)] {
                        if let Some(tr) = state[[y, x]] {
                            out.extend(this.measure(frame, &event, &control, (y, x), &tr, scratch));
                        }
                    }
                }
                (tracks, hits)
            })
            .collect();
        let (tracks, hits): (Vec<_>, Vec<_>) = rows.into_iter().unzip();
        let mut samples = Vec::new();
        for m in tracks.into_iter().flatten() {
            match m {
                Measured::NoSky => self.no_sky += 1,
                Measured::Source => self.rejected += 1,
                Measured::Sample(s) => {
                    advance(&mut self.tracks[[s.y, s.x]], &s);
                    samples.push(s);
                }
            }
        }
        for m in hits.into_iter().flatten() {
            match m {
                Measured::NoSky => {}
                Measured::Source => self.hit_rejected += 1,
                Measured::Sample(s) => {
                    advance(&mut self.hits[[s.y, s.x]], &s);
                    self.hit_samples.push(s);
                }
            }
        }
        self.start_events(frame.t_reset_s, &fluence, &event);
        for (y, x) in hit_starts {
            self.hits[[y, x]] = Some(Track {
                reset_s: frame.t_reset_s,
                fluence_e: f64::NAN,
                cluster: self.hits_started,
                last_excess: f64::NAN,
                last_sigma: f64::NAN,
                samples: 0,
            });
            self.hits_started += 1;
        }
        let lit = self.params.control_lit_fluence_e;
        Zip::from(&mut self.lit_s)
            .and(&fluence)
            .and(frame.flags)
            .par_for_each(|t, &f, &fl| {
                if f >= lit || f.is_nan() || fl & bits::OVERFLOW != 0 {
                    *t = frame.t_reset_s;
                }
            });
        self.last_control = control;
        samples
    }

    /// The pixels where `frame` starts a hit (module docs, "Cosmic-ray hits"), in pixel
    /// order: read before this frame ends any track.
    fn hit_starts(&self, frame: &Frame) -> Vec<(usize, usize)> {
        let quiet = self.params.hit_quiet_e_per_s;
        let mut out = Vec::new();
        for ((y, x), &f) in frame.flags.indexed_iter() {
            if f & bits::TRANSIENT != 0
                && f & (bits::SUR_ERROR | bits::NONFUNC) == 0
                && self.tracks[[y, x]].is_none()
                && f64::from(frame.predicted[[y, x]]) <= quiet
            {
                out.push((y, x));
            }
        }
        out
    }

    /// A source on a hit's pixel at its first sample (module docs, "Cosmic-ray hits"):
    /// the mean excess over the sky `sky` of its 4-neighbours that carry no track or
    /// hit, are usable and were predicted quiet, above `spike_nsigma` times the noise
    /// `sigma` of that mean. Fewer than two such neighbours: no screen.
    fn lit_neighbours(&self, frame: &Frame, (y, x): (usize, usize), sky: f64, sigma: f64) -> bool {
        let (ny, nx) = frame.image.dim();
        let quiet = self.params.hit_quiet_e_per_s;
        let (mut sum, mut n) = (0.0, 0usize);
        let near = [
            (y.wrapping_sub(1), x),
            (y + 1, x),
            (y, x.wrapping_sub(1)),
            (y, x + 1),
        ];
        for (yy, xx) in near.into_iter().filter(|&(a, b)| a < ny && b < nx) {
            let v = f64::from(frame.image[[yy, xx]]);
            let usable = frame.flags[[yy, xx]] & UNUSABLE == 0
                && self.tracks[[yy, xx]].is_none()
                && self.hits[[yy, xx]].is_none()
                && f64::from(frame.predicted[[yy, xx]]) <= quiet
                && v.is_finite();
            if usable {
                sum += v - sky;
                n += 1;
            }
        }
        n >= 2 && sum / n as f64 > self.params.spike_nsigma * sigma / (n as f64).sqrt()
    }

    /// One tracked pixel in `frame` (the track not ended): its sample, or why none.
    fn measure(
        &self,
        frame: &Frame,
        event: &Array2<bool>,
        control: &Control,
        (y, x): (usize, usize),
        tr: &Track,
        scratch: &mut Scratch,
    ) -> Option<Measured> {
        let f = frame.flags[[y, x]];
        let v = f64::from(frame.image[[y, x]]);
        let pred = f64::from(frame.predicted[[y, x]]);
        if f & UNUSABLE != 0 || event[[y, x]] || !v.is_finite() || !pred.is_finite() {
            return None;
        }
        let Some((sky, sigma)) = self.sky(frame, y, x, scratch) else {
            return Some(Measured::NoSky);
        };
        let excess = v - sky;
        let first = tr.samples == 0;
        let last = (!first).then_some((tr.last_excess, tr.last_sigma));
        if !passes_screen(last, excess, sigma, self.params.spike_nsigma) {
            return Some(Measured::Source);
        }
        if first && tr.fluence_e.is_nan() && self.lit_neighbours(frame, (y, x), sky, sigma) {
            return Some(Measured::Source);
        }
        Some(Measured::Sample(Sample {
            y,
            x,
            cluster: tr.cluster,
            event_fluence_e: tr.fluence_e,
            time_s: frame.t_mid_s - tr.reset_s,
            excess_e_per_s: excess,
            sigma_e_per_s: sigma,
            control_e_per_s: control.screened,
            control_true_e_per_s: control.truth,
            predicted_e_per_s: pred,
            predicted_excess_e_per_s: scratch.around(frame.predicted, y, x),
            flagged: frame.pflags[[y, x]] & pbits::HIGH != 0,
            true_excess_e_per_s: frame.truth.map(|t| scratch.around(t, y, x)),
            first,
        }))
    }

    /// The control pixels' mean excess in this frame (see the module docs).
    pub fn last_control(&self) -> Control {
        self.last_control
    }

    /// Measure the control grid: every [`CONTROL_STRIDE`]-th pixel in each direction that
    /// carries no track and is no event, measured like a track's pixel. Rows in parallel;
    /// the sums and each control pixel's last value in pixel order.
    fn controls(&mut self, frame: &Frame, event: &Array2<bool>) -> Control {
        let (ny, nx) = frame.image.dim();
        let this = &*self;
        let ys: Vec<usize> = (CONTROL_STRIDE / 2..ny).step_by(CONTROL_STRIDE).collect();
        let rows: Vec<Vec<ControlPixel>> = ys
            .par_iter()
            .map_init(Scratch::default, |scratch, &y| {
                let mut out = Vec::new();
                for x in (CONTROL_STRIDE / 2..nx).step_by(CONTROL_STRIDE) {
                    let v = f64::from(frame.image[[y, x]]);
                    let f = frame.flags[[y, x]];
                    if this.tracks[[y, x]].is_some()
                        || event[[y, x]]
                        || frame.t_mid_s - this.lit_s[[y, x]] < this.params.control_quiet_s
                        || f & (UNUSABLE | bits::OVERFLOW) != 0
                        || !v.is_finite()
                    {
                        continue;
                    }
                    let Some((sky, sigma)) = this.sky(frame, y, x, scratch) else {
                        continue;
                    };
                    let excess = v - sky;
                    let last = this.control_last[[y, x]];
                    let prev = (!last.0.is_nan()).then_some(last);
                    out.push(ControlPixel {
                        y,
                        x,
                        excess,
                        sigma,
                        truth: frame.truth.map(|t| scratch.around(t, y, x)),
                        passes: passes_screen(prev, excess, sigma, this.params.spike_nsigma),
                    });
                }
                out
            })
            .collect();
        let (mut raw, mut truth) = ((0.0, 0usize), (0.0, 0usize));
        let mut screened = (0.0, 0.0);
        for c in rows.iter().flatten() {
            raw.0 += c.excess;
            raw.1 += 1;
            if let Some(t) = c.truth {
                truth.0 += t;
                truth.1 += 1;
            }
            if c.passes {
                let w = crate::verify::sample_weight(c.sigma);
                screened.0 += w * c.excess;
                screened.1 += w;
                self.control_last[[c.y, c.x]] = (c.excess, c.sigma);
            }
        }
        let mean = |(s, n): (f64, usize)| if n > 0 { s / n as f64 } else { 0.0 };
        let screened = if screened.1 > 0.0 {
            screened.0 / screened.1
        } else {
            0.0
        };
        Control {
            raw: mean(raw),
            screened,
            pixels: raw.1,
            truth: mean(truth),
        }
    }

    /// Median and robust standard deviation of the usable, track-free annulus pixels,
    /// whose positions are left in `scratch` (for [`Scratch::around`]).
    fn sky(&self, frame: &Frame, y: usize, x: usize, scratch: &mut Scratch) -> Option<(f64, f64)> {
        let (ny, nx) = frame.image.dim();
        let (r0, r1) = (self.params.annulus_inner_px, self.params.annulus_outer_px);
        let ring = &mut scratch.ring;
        ring.clear();
        for yy in y.saturating_sub(r1)..(y + r1 + 1).min(ny) {
            for xx in x.saturating_sub(r1)..(x + r1 + 1).min(nx) {
                if yy.abs_diff(y).max(xx.abs_diff(x)) < r0 {
                    continue;
                }
                let v = frame.image[[yy, xx]];
                let usable = frame.flags[[yy, xx]] & (UNUSABLE | bits::OVERFLOW) == 0;
                if usable && v.is_finite() && self.tracks[[yy, xx]].is_none() {
                    ring.push((yy, xx));
                }
            }
        }
        if ring.len() < self.params.annulus_min_pixels {
            return None;
        }
        let vals = &mut scratch.values;
        vals.clear();
        vals.extend(ring.iter().map(|&(a, b)| f64::from(frame.image[[a, b]])));
        let med = median_in_place(vals);
        for v in vals.iter_mut() {
            *v = (*v - med).abs();
        }
        Some((med, (1.4826 * median_in_place(vals)).max(1e-6)))
    }

    /// New tracks at this frame's events; adjacent event pixels (4-connected) share a
    /// cluster, so that an event's pixels are resampled together.
    fn start_events(&mut self, t_reset_s: f64, fluence: &Array2<f64>, event: &Array2<bool>) {
        let (ny, nx) = event.dim();
        // Only the event pixels are labelled (a few thousand of millions), in pixel
        // order: clusters are numbered by their first pixel.
        let events: Vec<usize> = event
            .as_slice()
            .map(|e| {
                e.par_iter()
                    .enumerate()
                    .filter_map(|(i, &b)| b.then_some(i))
                    .collect()
            })
            .unwrap_or_else(|| {
                event
                    .indexed_iter()
                    .filter_map(|((y, x), &b)| b.then_some(y * nx + x))
                    .collect()
            });
        let mut label: std::collections::HashMap<usize, u64> =
            std::collections::HashMap::with_capacity(events.len());
        let mut stack = Vec::new();
        for &i in &events {
            if label.contains_key(&i) {
                continue;
            }
            let id = self.next_cluster;
            self.next_cluster += 1;
            label.insert(i, id);
            stack.push((i / nx, i % nx));
            while let Some((cy, cx)) = stack.pop() {
                let near = [
                    (cy.wrapping_sub(1), cx),
                    (cy + 1, cx),
                    (cy, cx.wrapping_sub(1)),
                    (cy, cx + 1),
                ];
                for (y, x) in near {
                    if y < ny && x < nx && event[[y, x]] && !label.contains_key(&(y * nx + x)) {
                        label.insert(y * nx + x, id);
                        stack.push((y, x));
                    }
                }
            }
        }
        for (i, cluster) in label {
            let (y, x) = (i / nx, i % nx);
            let f = fluence[[y, x]];
            self.tracks[[y, x]] = Some(Track {
                reset_s: t_reset_s,
                fluence_e: if f.is_finite() {
                    f.max(self.params.event_fluence_e)
                } else {
                    self.params.event_fluence_e
                },
                cluster,
                last_excess: f64::NAN,
                last_sigma: f64::NAN,
                samples: 0,
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    struct Owned {
        image: Array2<f32>,
        flags: Array2<u32>,
        pred: Array2<f32>,
        pflags: Array2<u8>,
    }

    fn frame(o: &Owned, t_mid_s: f64) -> Frame<'_> {
        Frame {
            image: o.image.view(),
            flags: o.flags.view(),
            predicted: o.pred.view(),
            pflags: o.pflags.view(),
            truth: None,
            t_illuminated_s: 100.0,
            t_mid_s,
            t_reset_s: t_mid_s + 50.0,
        }
    }

    fn sky(v: f32) -> Owned {
        Owned {
            image: Array2::from_elem((20, 20), v),
            flags: Array2::zeros((20, 20)),
            pred: Array2::zeros((20, 20)),
            pflags: Array2::zeros((20, 20)),
        }
    }

    #[test]
    fn an_event_is_followed_and_its_excess_is_measured_against_the_annulus() {
        let mut t = Tracker::new(TrackParams::default(), 20, 20);
        let mut a = sky(1.0);
        a.image[[10, 10]] = 5000.0; // 5e5 e- in 100 s: an event
        assert!(t.observe(&frame(&a, 0.0)).is_empty());
        assert_eq!(t.active(), 1);
        let mut b = sky(1.5);
        b.image[[10, 10]] = 1.5 + 0.8;
        b.pred[[10, 10]] = 0.9;
        b.pflags[[10, 10]] = pbits::HIGH;
        let s = t.observe(&frame(&b, 200.0));
        assert_eq!(s.len(), 1);
        assert!((s[0].excess_e_per_s - 0.8).abs() < 1e-6, "{s:?}");
        assert!((s[0].time_s - 150.0).abs() < 1e-9);
        assert!(s[0].flagged && s[0].first);
        assert!((s[0].event_fluence_e - 5e5).abs() < 1.0);
    }

    #[test]
    fn a_rise_far_above_the_track_is_a_source_and_a_cosmic_ray_ends_the_track() {
        let mut t = Tracker::new(TrackParams::default(), 20, 20);
        let mut a = sky(1.0);
        a.image[[10, 10]] = 5000.0;
        t.observe(&frame(&a, 0.0));
        // Noisy annulus so that sigma is known: alternate 0.9 / 1.1 -> MAD 0.1.
        let mut b = sky(1.0);
        for ((y, x), v) in b.image.indexed_iter_mut() {
            *v = if (y + x) % 2 == 0 { 0.9 } else { 1.1 };
        }
        b.image[[10, 10]] = 2.0;
        assert_eq!(t.observe(&frame(&b, 200.0)).len(), 1);
        b.image[[10, 10]] = 30.0; // a star: +29 against sigma ~0.15
        assert!(t.observe(&frame(&b, 400.0)).is_empty());
        assert_eq!(t.rejected, 1);
        b.image[[10, 10]] = 1.9;
        assert_eq!(t.observe(&frame(&b, 600.0)).len(), 1);
        b.flags[[10, 10]] = bits::TRANSIENT;
        assert!(t.observe(&frame(&b, 800.0)).is_empty());
        assert_eq!(t.active(), 0);
    }

    /// A `TRANSIENT` pixel the stage predicted quiet starts a hit, measured in the next
    /// frames like a track (NaN fluence, first sample marked) and handed out apart from
    /// the tracks' samples; one predicted above the quiet level, or without a slope,
    /// does not; the pixel's next `TRANSIENT` ends its hit.
    #[test]
    fn a_quiet_cosmic_ray_hit_is_followed_apart_from_the_tracks() {
        let mut t = Tracker::new(TrackParams::default(), 20, 20);
        let mut a = sky(1.0);
        a.flags[[10, 10]] = bits::TRANSIENT;
        a.flags[[5, 5]] = bits::TRANSIENT;
        a.pred[[5, 5]] = 0.5; // an earlier event's persistence: not the hit's
        a.flags[[15, 15]] = bits::TRANSIENT | bits::SUR_ERROR;
        assert!(t.observe(&frame(&a, 0.0)).is_empty());
        assert_eq!(t.hits_started, 1);
        let mut b = sky(1.0);
        b.image[[10, 10]] = 1.3;
        b.pred[[10, 10]] = 6.0;
        assert!(t.observe(&frame(&b, 200.0)).is_empty(), "no track's sample");
        let s = t.take_hit_samples();
        assert_eq!(s.len(), 1);
        assert_eq!((s[0].y, s[0].x), (10, 10));
        assert!(s[0].first && s[0].event_fluence_e.is_nan());
        assert!((s[0].excess_e_per_s - 0.3).abs() < 1e-6, "{s:?}");
        assert!((s[0].time_s - 150.0).abs() < 1e-9);
        t.observe(&frame(&b, 400.0));
        let s = t.take_hit_samples();
        assert!(s.len() == 1 && !s[0].first);
        b.flags[[10, 10]] = bits::TRANSIENT;
        b.pred[[10, 10]] = 0.5;
        t.observe(&frame(&b, 600.0));
        assert!(t.take_hit_samples().is_empty());
        assert_eq!(
            t.hits_started, 1,
            "predicted above the quiet level: no new hit"
        );
    }

    /// A hit's first sample is a source when its neighbours are lit too (a star's
    /// light spreads, a hit's persistence does not): rejected, and the hit's next sample
    /// is its first; a hit whose excess stays in its pixel is measured.
    #[test]
    fn a_hit_s_first_sample_with_lit_neighbours_is_a_source() {
        let mut t = Tracker::new(TrackParams::default(), 20, 20);
        let mut a = sky(1.0);
        a.flags[[10, 10]] = bits::TRANSIENT;
        a.flags[[4, 4]] = bits::TRANSIENT;
        t.observe(&frame(&a, 0.0));
        assert_eq!(t.hits_started, 2);
        // alternate 0.9 / 1.1: sigma about 0.15
        let mut b = sky(1.0);
        for ((y, x), v) in b.image.indexed_iter_mut() {
            *v = if (y + x) % 2 == 0 { 0.9 } else { 1.1 };
        }
        let quiet = b.image.clone();
        b.image[[4, 4]] = 2.0; // persistence: the pixel alone
        b.image[[10, 10]] = 3.0; // a star: its neighbours lit by about 1 e-/s
        for (y, x) in [(9, 10), (11, 10), (10, 9), (10, 11)] {
            b.image[[y, x]] += 1.0;
        }
        b.pred[[4, 4]] = 6.0;
        b.pred[[10, 10]] = 6.0;
        t.observe(&frame(&b, 200.0));
        let s = t.take_hit_samples();
        assert_eq!(s.len(), 1, "{s:?}");
        assert_eq!((s[0].y, s[0].x), (4, 4));
        assert!(s[0].first);
        assert_eq!(t.hit_rejected, 1);
        let mut c = sky(1.0);
        c.image = quiet;
        c.image[[10, 10]] = 1.5;
        t.observe(&frame(&c, 400.0));
        let s = t.take_hit_samples();
        let star = s.iter().find(|s| (s.y, s.x) == (10, 10)).unwrap();
        assert!(star.first, "{s:?}");
    }

    #[test]
    fn adjacent_event_pixels_share_a_cluster_and_tracked_pixels_are_not_sky() {
        let mut t = Tracker::new(TrackParams::default(), 20, 20);
        let mut a = sky(1.0);
        a.image[[10, 10]] = 5000.0;
        a.image[[10, 11]] = 5000.0;
        a.flags[[2, 2]] = bits::OVERFLOW;
        t.observe(&frame(&a, 0.0));
        let mut b = sky(1.0);
        b.image[[10, 10]] = 3.0;
        b.image[[10, 11]] = 3.0;
        b.image[[2, 2]] = 3.0;
        let s = t.observe(&frame(&b, 200.0));
        assert_eq!(s.len(), 3);
        let c: Vec<u64> = s.iter().map(|s| s.cluster).collect();
        assert_eq!(c[1], c[2], "{c:?}");
        assert_ne!(c[0], c[1]);
        assert!(s.iter().all(|s| (s.excess_e_per_s - 2.0).abs() < 1e-6));
    }
}
