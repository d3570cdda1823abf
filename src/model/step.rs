//! One exposure through the model, fused into one pass over the state.
//!
//! For each pixel, in this order (ARCHITECTURE.md, "The data path"):
//! 1. **predict** `i_p(t_meas) = sum_n A_n C_n exp(-t_meas/tau_n)` from the state left by
//!    the previous exposure, `t_meas = t_slew + 0.5 t_exposure` after its reset;
//! 2. **flag**: above the high / low thresholds (strictly greater). A pixel whose
//!    previous response used the maximum amplitude (unknown fluence) is flagged high
//!    whatever the prediction, and marked `MAX_AMPLITUDE`;
//! 3. **early release**: a pixel flagged high whose measured current, less the
//!    exposure's background (sky + dark, [`background_e_per_s`], when the model asks for
//!    it: by default the median over the pixels the model predicts quiet), is finite
//!    and below the early-release threshold counts one more; at `consecutive` it is
//!    released: its amplitudes become zero, it is not flagged in this exposure, it is marked
//!    `RELEASED` (with `keep: threshold`, [`super::params::ReleaseKeep`], its amplitudes
//!    are scaled so that its prediction is the high threshold instead). A non-finite
//!    measurement or an unflagged pixel resets the count;
//! 4. **decay** the amplitudes over `t_elapsed = t_reset(k+1) - t_reset(k)`;
//! 5. **respond**: add this exposure's `A_k` to every term.
//!
//! What enters the state (so that NaN, Inf or negative currents never do):
//! each pixel's fluence follows [`super::fluence::pixel_fluence`]:
//! - `NONFUNC` pixels add nothing (a dead pixel collects no charge);
//! - `TRANSIENT` or `SUR_ERROR` pixels, and pixels whose current is NaN or infinite, have
//!   an unknown fluence: they add the maximum amplitude of the knot table (conservative,
//!   as the paper does for transients), and the next exposure flags them whatever the
//!   prediction; a `TRANSIENT` pixel with a finite slope and without `SUR_ERROR` adds
//!   the model's transient rule instead ([`ModelParams::transient_amplitude_e`]: the
//!   maximum unless the model file holds an amplitude measured in flight) or its
//!   slope's amplitude, the larger; the next exposure flags it whatever the prediction
//!   unless the rule was measured in flight (`persist verify` measures it at that very
//!   exposure, so there the prediction decides);
//! - a negative current counts as zero fluence (it is noise about zero);
//! - otherwise the fluence is `current * t_illuminated` (ICD "Timing").
//!
//! `/persistence/current` holds the prediction of step 1 for every pixel, released or
//! not. The arithmetic is identical, operation for operation, to the plain multi-pass
//! [`crate::model::reference`] implementation, so the two agree bit for bit.

use super::decay::ExpSum;
pub use super::fluence::FlagBits;
use super::fluence::{extrapolated_fluence_e, pixel_fluence, PixelFluence};
use super::params::{BackgroundEstimate, ModelParams, ReleaseKeep, ReleaseRule};
use super::pixel_response::PixelResponse;
use super::response::Response;
use super::state::{State, PENDING_MAX_AMPLITUDE};
use crate::error::{Error, ErrorKind};
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;

/// A validated model, ready to step.
#[derive(Debug, Clone)]
pub struct Model {
    params: ModelParams,
    sum: ExpSum,
    response: Response,
    identity: String,
    bits: FlagBits,
    /// The model file's effects, built once (empty: the fused paper kernel below).
    effects: std::sync::Arc<Vec<Box<dyn super::effect::Effect>>>,
    /// Per-pixel response maps by detector ([`Model::with_pixel_maps`]).
    pixel_maps: std::sync::Arc<std::collections::BTreeMap<u8, std::sync::Arc<PixelResponse>>>,
    /// The map this model applies ([`Model::for_detector`]), among its effects.
    pixel_response: Option<std::sync::Arc<PixelResponse>>,
}

impl Model {
    pub fn new(params: ModelParams) -> Result<Self, Error> {
        params
            .validate()
            .map_err(|m| Error::new(ErrorKind::Model, m))?;
        let effects = params
            .effects
            .iter()
            .map(super::effects::build)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|m| Error::new(ErrorKind::Model, m))?;
        Ok(Model {
            effects: std::sync::Arc::new(effects),
            sum: ExpSum::new(&params.terms),
            response: Response::new(&params.amplitude_knots),
            identity: params.identity(),
            params,
            bits: FlagBits::default(),
            pixel_maps: Default::default(),
            pixel_response: None,
        })
    }

    /// The same model with per-pixel response maps by detector (a detector's map is
    /// applied by the model [`Model::for_detector`] returns).
    pub fn with_pixel_maps(mut self, maps: std::collections::BTreeMap<u8, PixelResponse>) -> Self {
        self.pixel_maps = std::sync::Arc::new(
            maps.into_iter()
                .map(|(d, r)| (d, std::sync::Arc::new(r)))
                .collect(),
        );
        self
    }

    /// The detectors with a per-pixel response map.
    pub fn pixel_map_detectors(&self) -> Vec<u8> {
        self.pixel_maps.keys().copied().collect()
    }

    /// The map this model applies, if any.
    pub fn pixel_response(&self) -> Option<&PixelResponse> {
        self.pixel_response.as_deref()
    }

    /// The model that steps `detector`: this one with that detector's per-pixel map
    /// applied after the model file's effects ([`super::pixel_response`]), or this one
    /// when it has no map for it.
    pub fn for_detector(&self, detector: u8) -> Result<Model, Error> {
        let Some(map) = self.pixel_maps.get(&detector) else {
            return Ok(self.clone());
        };
        let mut effects = self
            .params
            .effects
            .iter()
            .map(super::effects::build)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|m| Error::new(ErrorKind::Model, m))?;
        effects.push(Box::new(super::pixel_response::PixelScale(map.clone())));
        let mut m = self.clone();
        m.effects = std::sync::Arc::new(effects);
        m.pixel_response = Some(map.clone());
        Ok(m)
    }

    /// A model applying a per-pixel map steps only arrays of the map's shape.
    pub(super) fn check_pixel_response(&self, state: &State) -> Result<(), Error> {
        match &self.pixel_response {
            Some(r) if r.dim() != state.shape() => Err(Error::invalid(
                "pixel_map",
                format!(
                    "the per-pixel map is {:?}, the detector's array {:?}",
                    r.dim(),
                    state.shape()
                ),
            )),
            _ => Ok(()),
        }
    }

    pub fn with_flag_bits(mut self, bits: FlagBits) -> Self {
        self.bits = bits;
        self
    }

    /// The row stride of the early-release background's sample when this exposure's
    /// background is estimated from the model's own quiet pixels
    /// ([`BackgroundEstimate::QuietPixels`], no background given in `input`): those rows'
    /// states are read, so a step that advances only some pixels must advance them too.
    /// `None` when the background reads no state.
    pub fn quiet_rows(&self, input: &Input<'_>) -> Option<usize> {
        let er = &self.params.early_release;
        let reads_state = er.enabled
            && er.background == BackgroundEstimate::QuietPixels
            && ((er.subtract_background && input.background_e_per_s.is_none())
                || er.rule == ReleaseRule::Evidence);
        reads_state.then(|| {
            let (ny, nx) = input.image_e_per_s.dim();
            quiet_row_stride(ny, nx)
        })
    }

    pub fn params(&self) -> &ModelParams {
        &self.params
    }
    pub fn identity(&self) -> &str {
        &self.identity
    }
    pub fn exp_sum(&self) -> &ExpSum {
        &self.sum
    }
    pub fn response(&self) -> &Response {
        &self.response
    }
    /// How long the largest response takes to decay below the low threshold, s
    /// (infinite if it never does): after a gap, how long a missing exposure could still
    /// change a flag, so how long outputs carry "history incomplete".
    pub fn carry_over_s(&self) -> f64 {
        self.sum
            .crossing_time_s(
                self.largest_response_e(),
                self.params.thresholds.low_e_per_s,
            )
            .unwrap_or(f64::INFINITY)
    }
    /// The largest current, e-/s, that one exposure's response (at most the knot table's
    /// maximum amplitude or the transient rule's, on every term) can still give `age_s`
    /// after the reset that ended it: the current [`Model::carry_over_s`] brings down to
    /// the low threshold. Decreasing in `age_s`.
    pub fn carry_over_e_per_s(&self, age_s: f64) -> f64 {
        self.largest_response_e() * self.sum.unit_current_per_s(age_s.max(0.0))
    }
    /// The largest amplitude one exposure adds to a term, e-.
    fn largest_response_e(&self) -> f64 {
        self.response
            .max_e()
            .max(self.params.transient_amplitude_e())
    }
    pub fn flag_bits(&self) -> FlagBits {
        self.bits
    }
    pub fn n_terms(&self) -> usize {
        self.sum.len()
    }

    pub fn new_state(&self, ny: usize, nx: usize) -> State {
        State::zeros(ny, nx, self.n_terms())
    }

    /// The effects of the model file, in file order.
    pub fn effects(&self) -> &[Box<dyn super::effect::Effect>] {
        &self.effects
    }

    /// True if each pixel's prediction depends on that pixel's own history alone: every
    /// effect is [`super::effect::Effect::is_pixel_local`] and early release subtracts
    /// no background (which is estimated over the whole array). Such a model predicts
    /// any selection of pixels, laid out in an array of its own, bit for bit as it
    /// would on the whole array.
    pub fn is_pixel_local(&self) -> bool {
        let er = &self.params.early_release;
        let array_wide = er.subtract_background || er.rule == ReleaseRule::Evidence;
        !(er.enabled && array_wide) && self.effects.iter().all(|e| e.is_pixel_local())
    }

    /// The paper's fused kernel: one exposure of a model without effects (module
    /// documentation). [`Model::step`] and [`Model::step_with`] (in
    /// [`super::effect_step`], which also steps the models with effects) call it.
    /// Nothing is changed on error.
    pub(super) fn step_fused(
        &self,
        state: &mut State,
        input: &Input<'_>,
        out: &mut Output<'_>,
    ) -> Result<StepSummary, Error> {
        let k = self.prepare(state, input, out)?;
        let (ny, nx) = state.shape();
        let n = k.n;
        let image = input.image_e_per_s.as_standard_layout();
        let image = image.as_slice().expect("standard layout");
        let amps = state.amplitudes_e.as_slice_mut().expect("owned state");
        let count = state.release_count.as_slice_mut().expect("owned state");
        let pending = state.pending.as_slice_mut().expect("owned state");
        let flags = contiguous(out.flags);
        let current = contiguous(out.current_e_per_s);
        let pflags = contiguous(out.pflags);
        debug_assert_eq!(amps.len(), ny * nx * n);
        let mut summary = (
            amps.par_chunks_mut(nx * n),
            count.par_chunks_mut(nx),
            pending.par_chunks_mut(nx),
            image.par_chunks(nx),
            flags.par_chunks_mut(nx),
            current.par_chunks_mut(nx),
            pflags.par_chunks_mut(nx),
        )
            .into_par_iter()
            .map(|(a, c, p, img, f, cur, pf)| k.row(a, c, p, img, f, cur, pf))
            .reduce(StepSummary::default, StepSummary::add);
        summary.t_meas_s = k.t_meas_s;
        summary.previous_index = state.last_index;
        state.t_reset_unix_s = Some(input.t_start_unix_s + input.t_exposure_s);
        state.last_index = Some(input.exposure_index);
        Ok(summary)
    }

    /// Check the input against the state and precompute the per-exposure factors.
    pub(crate) fn prepare(
        &self,
        state: &State,
        input: &Input<'_>,
        out: &Output<'_>,
    ) -> Result<Kernel<'_>, Error> {
        let seq = |field: &str, msg: String| {
            Error::new(ErrorKind::Sequence, msg)
                .field(field)
                .exposure(input.exposure_index)
        };
        let shape = state.shape();
        if state.n_terms() != self.n_terms() {
            return Err(Error::new(
                ErrorKind::Checkpoint,
                format!(
                    "state has {} terms, the model {}",
                    state.n_terms(),
                    self.n_terms()
                ),
            ));
        }
        if input.image_e_per_s.dim() != shape {
            return Err(Error::invalid(
                "image",
                format!(
                    "shape {:?} differs from the detector's state {:?}",
                    input.image_e_per_s.dim(),
                    shape
                ),
            ));
        }
        for (name, dim) in [
            ("flags", out.flags.dim()),
            ("persistence/current", out.current_e_per_s.dim()),
            ("persistence/flags", out.pflags.dim()),
        ] {
            if dim != shape {
                return Err(Error::invalid(
                    name,
                    format!("shape {dim:?} differs from {shape:?}"),
                ));
            }
        }
        if !(input.t_exposure_s.is_finite() && input.t_exposure_s > 0.0) {
            return Err(Error::invalid(
                "t_exposure_s",
                format!("must be finite and > 0, got {}", input.t_exposure_s),
            ));
        }
        let t_illum = input.t_illuminated_s;
        if !(t_illum.is_finite() && t_illum > 0.0 && t_illum <= input.t_exposure_s) {
            return Err(Error::invalid(
                "t_illuminated_s",
                format!("must be in (0, t_exposure_s], got {t_illum}"),
            ));
        }
        if !input.t_start_unix_s.is_finite() {
            return Err(Error::invalid("t_start_utc", "not a finite time"));
        }
        if let Some(last) = state.last_index {
            if input.exposure_index <= last {
                return Err(seq(
                    "exposure_index",
                    format!(
                        "{} does not follow the last processed index {last}",
                        input.exposure_index
                    ),
                ));
            }
        }
        let (w, decay, t_meas_s) = match state.t_reset_unix_s {
            None => (vec![0.0; self.n_terms()], vec![1.0; self.n_terms()], None),
            Some(t_reset) => {
                let t_slew = input.t_start_unix_s - t_reset;
                if t_slew < 0.0 {
                    return Err(seq(
                        "t_start_utc",
                        format!(
                            "starts {:.6} s before the reset ending the previous exposure",
                            -t_slew
                        ),
                    ));
                }
                let t_meas = t_slew + 0.5 * input.t_exposure_s;
                let t_elapsed = t_slew + input.t_exposure_s;
                (
                    self.sum.weights_at(t_meas),
                    self.sum.decay_over(t_elapsed),
                    Some(t_meas),
                )
            }
        };
        let er = &self.params.early_release;
        // The sample of quiet pixels gives the background (when not given) and the noise
        // (when the rule asks for it); computed only when used.
        let needs_background = er.enabled && er.subtract_background;
        let needs_noise = er.enabled && er.rule == ReleaseRule::Evidence;
        let given = input.background_e_per_s.filter(|_| needs_background);
        let mut sample = if (needs_background && given.is_none()) || needs_noise {
            quiet_sample(
                er.background,
                &input.image_e_per_s,
                &state.amplitudes_e,
                &w,
                self.params.thresholds.low_e_per_s,
            )
        } else {
            Vec::new()
        };
        // Comparing `m - background < threshold` is comparing `m < threshold + background`.
        let background = match (needs_background, given) {
            (false, _) => 0.0,
            (true, Some(b)) => b,
            (true, None) => median_f32(&mut sample),
        };
        if !background.is_finite() {
            return Err(Error::invalid(
                "background_e_per_s",
                format!("must be finite, got {background}"),
            ));
        }
        let noise_e_per_s = if needs_noise {
            robust_sigma_f32(&mut sample)
        } else {
            0.0
        };
        Ok(Kernel {
            n: self.n_terms(),
            w,
            decay,
            t_meas_s,
            high: self.params.thresholds.high_e_per_s,
            low: self.params.thresholds.low_e_per_s,
            er_enabled: er.enabled,
            er_threshold: er.threshold_e_per_s + background,
            er_background: background,
            er_noise: noise_e_per_s.max(f64::MIN_POSITIVE),
            er_rule: er.rule,
            er_keep: er.keep,
            er_release_at: match er.rule {
                ReleaseRule::Consecutive => er.consecutive,
                ReleaseRule::Evidence => er.evidence_quarter_sigmas(),
            },
            response: &self.response,
            a_max: self.response.max_e(),
            a_transient: self.params.transient_amplitude_e(),
            transient_measured: self.params.transient.is_some(),
            first: self.response.first_segment(),
            t_illuminated_s: t_illum,
            history: if input.history_incomplete {
                self.bits.history_incomplete
            } else {
                0
            },
            bits: self.bits,
        })
    }
}

fn contiguous<T: Clone>(a: &mut Array2<T>) -> &mut [T] {
    if !a.is_standard_layout() {
        *a = a.as_standard_layout().into_owned();
    }
    a.as_slice_mut().expect("standard layout")
}

/// One exposure's data as the model needs it.
#[derive(Debug, Clone)]
pub struct Input<'a> {
    /// Line-fit current, e-/s. `[ny, nx]`
    pub image_e_per_s: ArrayView2<'a, f32>,
    pub exposure_index: u64,
    /// Start of the integration, seconds since the Unix epoch.
    pub t_start_unix_s: f64,
    pub t_exposure_s: f64,
    pub t_illuminated_s: f64,
    /// Set bit `HISTORY_INCOMPLETE` on every pixel of this exposure.
    pub history_incomplete: bool,
    /// The sky + dark level of this exposure, e-/s, subtracted from the measured current
    /// before the early-release comparison (when the model asks for it). `None`: the
    /// step estimates it with [`background_e_per_s`].
    pub background_e_per_s: Option<f64>,
}

/// Pixels of the regular sample the background estimates look at, at most.
const BACKGROUND_SAMPLE: usize = 65_536;

/// The rows [`background_e_per_s`] samples with `quiet_pixels`: every
/// `quiet_row_stride(ny, nx)`-th row from row 0.
pub fn quiet_row_stride(ny: usize, nx: usize) -> usize {
    (ny * nx).div_ceil(BACKGROUND_SAMPLE).max(1)
}

/// A robust estimate of an exposure's background (sky + dark), e-/s: the median of the
/// finite pixels, on a regular sample of at most 65,536 of them (the zodiacal light
/// varies slowly across an array; stars and persistence are a minority of pixels).
/// 0 when no pixel is finite. [`BackgroundEstimate::ImageMedian`].
pub fn sky_level_e_per_s(image: &ArrayView2<'_, f32>) -> f64 {
    median_f32(&mut sky_sample(image))
}

/// The finite pixels of the regular sample [`sky_level_e_per_s`] takes the median of.
fn sky_sample(image: &ArrayView2<'_, f32>) -> Vec<f32> {
    let stride = image.len().div_ceil(BACKGROUND_SAMPLE).max(1);
    image
        .iter()
        .step_by(stride)
        .copied()
        .filter(|v| v.is_finite())
        .collect()
}

/// The early-release background of an exposure, e-/s ([`BackgroundEstimate`]):
/// `amplitudes_e` the state before this exposure (`[ny, nx, n]`, standard layout as
/// [`State`] keeps it), `w` the weights `C_n exp(-t_meas/tau_n)` of its prediction.
/// On a sample of at most 65,536 pixels in whole rows (every pixel below 256 x 256);
/// 0 when no sampled pixel is finite.
pub fn background_e_per_s(
    estimate: BackgroundEstimate,
    image: &ArrayView2<'_, f32>,
    amplitudes_e: &ndarray::Array3<f64>,
    w: &[f64],
    low_e_per_s: f64,
) -> f64 {
    median_f32(&mut quiet_sample(
        estimate,
        image,
        amplitudes_e,
        w,
        low_e_per_s,
    ))
}

/// The noise of an exposure's measured currents, e-/s: the robust standard deviation
/// (1.4826 x the median absolute deviation from the median) of the pixels whose median
/// is [`background_e_per_s`] (same arguments). 0 when no sampled pixel is finite.
pub fn noise_e_per_s(
    estimate: BackgroundEstimate,
    image: &ArrayView2<'_, f32>,
    amplitudes_e: &ndarray::Array3<f64>,
    w: &[f64],
    low_e_per_s: f64,
) -> f64 {
    robust_sigma_f32(&mut quiet_sample(
        estimate,
        image,
        amplitudes_e,
        w,
        low_e_per_s,
    ))
}

/// The finite measured currents [`background_e_per_s`] takes the median of.
fn quiet_sample(
    estimate: BackgroundEstimate,
    image: &ArrayView2<'_, f32>,
    amplitudes_e: &ndarray::Array3<f64>,
    w: &[f64],
    low_e_per_s: f64,
) -> Vec<f32> {
    let amps = match (estimate, amplitudes_e.as_slice()) {
        (BackgroundEstimate::QuietPixels, Some(a))
            if !w.is_empty() && a.len() == image.len() * w.len() =>
        {
            a
        }
        _ => return sky_sample(image),
    };
    let n = w.len();
    let (ny, nx) = image.dim();
    // Whole rows, every `row_stride`-th: the rows' amplitudes are contiguous in the
    // state, so the sample's predictions stream through memory (a pixel sample spread
    // over the array costs a cache miss per pixel: 15 % of the step at 2040 x 2040).
    let row_stride = quiet_row_stride(ny, nx);
    // (predicted current, measured current) of the finite sampled pixels
    let mut sample: Vec<(f64, f32)> = Vec::with_capacity(ny.div_ceil(row_stride) * nx);
    for y in (0..ny).step_by(row_stride) {
        let a = &amps[y * nx * n..(y + 1) * nx * n];
        for (x, a) in a.chunks_exact(n).enumerate() {
            let v = image[[y, x]];
            if v.is_finite() {
                sample.push((super::decay::weighted_sum(a, w), v));
            }
        }
    }
    if sample.is_empty() {
        return Vec::new();
    }
    // at least the 1/256 of the sample (and 16 pixels) with the lowest prediction
    let m = (sample.len() / 256).max(16).min(sample.len());
    let (_, mth, _) = sample.select_nth_unstable_by(m - 1, |a, b| a.0.total_cmp(&b.0));
    let cut = mth.0.max(low_e_per_s);
    sample
        .iter()
        .filter(|(p, _)| *p <= cut)
        .map(|(_, v)| *v)
        .collect()
}

/// 1.4826 x the median absolute deviation of `v` from its median (the standard
/// deviation of normal noise), `v` reordered; 0 when empty.
fn robust_sigma_f32(v: &mut [f32]) -> f64 {
    let m = median_f32(v);
    let mut dev: Vec<f32> = v.iter().map(|&x| (f64::from(x) - m).abs() as f32).collect();
    1.4826 * median_f32(&mut dev)
}

/// The median (upper middle element) of `v`, reordered; 0 when empty.
fn median_f32(v: &mut [f32]) -> f64 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, f32::total_cmp);
    f64::from(*m)
}

/// Where the step writes. `flags` holds the on-board flags on entry; on return the
/// `PERSIST` bit is set exactly where `pflags` has `HIGH` (any upstream `PERSIST` is
/// cleared). The buffers may be reused from exposure to exposure.
pub struct Output<'a> {
    pub flags: &'a mut Array2<u32>,
    pub current_e_per_s: &'a mut Array2<f32>,
    pub pflags: &'a mut Array2<u8>,
}

/// Counts of one exposure, for logs and the per-exposure summary.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StepSummary {
    pub pixels: u64,
    pub above_high: u64,
    pub above_low: u64,
    pub released: u64,
    pub max_amplitude: u64,
    /// Time after the previous reset the prediction was made at (None: first exposure).
    pub t_meas_s: Option<f64>,
    pub previous_index: Option<u64>,
}

impl StepSummary {
    pub(crate) fn add(self, o: StepSummary) -> StepSummary {
        StepSummary {
            pixels: self.pixels + o.pixels,
            above_high: self.above_high + o.above_high,
            above_low: self.above_low + o.above_low,
            released: self.released + o.released,
            max_amplitude: self.max_amplitude + o.max_amplitude,
            t_meas_s: self.t_meas_s.or(o.t_meas_s),
            previous_index: self.previous_index.or(o.previous_index),
        }
    }
}

/// Everything the per-pixel loop needs, computed once per exposure.
pub(crate) struct Kernel<'m> {
    pub n: usize,
    /// `C_n exp(-t_meas/tau_n)`; zeros for a first exposure.
    pub w: Vec<f64>,
    /// `exp(-t_elapsed/tau_n)`; ones for a first exposure.
    pub decay: Vec<f64>,
    pub t_meas_s: Option<f64>,
    pub high: f64,
    pub low: f64,
    pub er_enabled: bool,
    pub er_threshold: f64,
    /// The background the threshold includes, e-/s.
    pub er_background: f64,
    /// The exposure's noise ([`noise_e_per_s`]; 0 when the rule does not use it), at
    /// least the smallest positive `f64`.
    pub er_noise: f64,
    pub er_rule: ReleaseRule,
    pub er_keep: ReleaseKeep,
    /// The release count that releases: `consecutive`, or the evidence in quarter sigmas.
    pub er_release_at: u8,
    pub response: &'m Response,
    pub a_max: f64,
    /// `A_k` of a `TRANSIENT` pixel ([`ModelParams::transient_amplitude_e`]).
    pub a_transient: f64,
    /// The transient rule was measured in flight ([`ModelParams::transient`]): the
    /// exposure after a hit follows the prediction instead of being flagged whatever it.
    pub transient_measured: bool,
    /// [`Response::first_segment`].
    pub first: (f64, f64, f64, f64),
    pub t_illuminated_s: f64,
    pub history: u8,
    pub bits: FlagBits,
}

impl Kernel<'_> {
    /// A `TRANSIENT` pixel with a finite slope and without `SUR_ERROR`: it takes the
    /// transient rule ([`Kernel::response_of`]).
    #[inline(always)]
    pub fn transient_with_slope(&self, current: f32, flags: u32) -> bool {
        flags & self.bits.transient != 0 && flags & self.bits.sur_error == 0 && current.is_finite()
    }

    /// An unknown fluence whose next exposure is not flagged whatever the prediction: a
    /// transient with a slope under a rule measured in flight ([`Kernel::response_of`]).
    #[inline(always)]
    pub fn transient_ruled(&self, current: f32, flags: u32) -> bool {
        self.transient_measured && self.transient_with_slope(current, flags)
    }

    /// `A_k` for one pixel and whether the next exposure is flagged whatever the
    /// prediction (`MAX_AMPLITUDE`): a transient with a finite slope (and not a fit
    /// error) takes the transient rule's amplitude or its slope's, the larger (a source
    /// bright enough to saturate keeps its own response when a cosmic ray also hits),
    /// any other unknown fluence the maximum. Every unknown fluence forces the next
    /// exposure's flag, except a transient under a rule measured in flight: the rule was
    /// measured at that exposure, so its prediction decides.
    #[inline(always)]
    pub fn response_of(&self, current: f32, flags: u32) -> (f64, bool) {
        match pixel_fluence(current, flags, &self.bits, self.t_illuminated_s) {
            PixelFluence::Unknown => {
                let transient_only = self.transient_with_slope(current, flags);
                let a = if transient_only {
                    let slope = self
                        .response
                        .amplitude_e(extrapolated_fluence_e(current, self.t_illuminated_s));
                    self.a_transient.max(slope)
                } else {
                    self.a_max
                };
                (a, !self.transient_ruled(current, flags))
            }
            PixelFluence::NonFunctional => (0.0, false),
            PixelFluence::Known(fluence_e) => {
                // The first segment, where faint pixels fall, without a table look-up:
                // the same operations as `Response::amplitude_e` there.
                let (x1, y0, slope0, x0) = self.first;
                if fluence_e > 0.0 && fluence_e < x1 {
                    (y0 + slope0 * (fluence_e - x0), false)
                } else {
                    (self.response.amplitude_e(fluence_e), false)
                }
            }
        }
    }

    /// One row of pixels: dispatch to a loop specialised for the common term counts
    /// (the per-pixel arithmetic is the same code, [`Kernel::pixel`], in every case).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn row(
        &self,
        amps: &mut [f64],
        count: &mut [u8],
        pending: &mut [u8],
        image: &[f32],
        flags: &mut [u32],
        current: &mut [f32],
        pflags: &mut [u8],
    ) -> StepSummary {
        match self.n {
            6 => self.row_n::<6>(amps, count, pending, image, flags, current, pflags),
            4 => self.row_n::<4>(amps, count, pending, image, flags, current, pflags),
            _ => self.row_dyn(amps, count, pending, image, flags, current, pflags),
        }
    }

    /// `N` terms known at compile time: the term loops unroll, no bounds checks.
    #[allow(clippy::too_many_arguments)]
    fn row_n<const N: usize>(
        &self,
        amps: &mut [f64],
        count: &mut [u8],
        pending: &mut [u8],
        image: &[f32],
        flags: &mut [u32],
        current: &mut [f32],
        pflags: &mut [u8],
    ) -> StepSummary {
        let (Ok(w), Ok(decay)) = (
            <[f64; N]>::try_from(&self.w[..]),
            <[f64; N]>::try_from(&self.decay[..]),
        ) else {
            return self.row_dyn(amps, count, pending, image, flags, current, pflags);
        };
        // Equal lengths up front, so that the indexed accesses below need no checks.
        let nx = image.len();
        let (amps, count, pending) = (&mut amps[..nx * N], &mut count[..nx], &mut pending[..nx]);
        let (flags, current, pflags) = (&mut flags[..nx], &mut current[..nx], &mut pflags[..nx]);
        let (amps, _) = amps.as_chunks_mut::<N>();
        let amps = &mut amps[..nx];
        let base = amps.as_ptr();
        for x in 0..nx {
            if x % 4 == 0 {
                // Four pixels' amplitudes: three cache lines with 6 terms (two with 4).
                let ahead = base.wrapping_add(x + PREFETCH_PIXELS);
                prefetch(ahead);
                prefetch(ahead.wrapping_add(2));
                prefetch(ahead.wrapping_add(3));
            }
            self.pixel(
                &mut amps[x],
                &w,
                &decay,
                &mut count[x],
                &mut pending[x],
                image[x],
                &mut flags[x],
                &mut current[x],
                &mut pflags[x],
            );
        }
        Counts::of_row(pflags, &self.bits).summary(nx)
    }

    /// Any number of terms.
    #[allow(clippy::too_many_arguments)]
    fn row_dyn(
        &self,
        amps: &mut [f64],
        count: &mut [u8],
        pending: &mut [u8],
        image: &[f32],
        flags: &mut [u32],
        current: &mut [f32],
        pflags: &mut [u8],
    ) -> StepSummary {
        let pixels = amps
            .chunks_exact_mut(self.n.max(1))
            .zip(count.iter_mut())
            .zip(pending.iter_mut())
            .zip(image.iter())
            .zip(flags.iter_mut())
            .zip(current.iter_mut())
            .zip(pflags.iter_mut());
        for ((((((a, c), p), &m), f), cur), pf) in pixels {
            self.pixel(a, &self.w[..], &self.decay[..], c, p, m, f, cur, pf);
        }
        Counts::of_row(pflags, &self.bits).summary(image.len())
    }

    /// One pixel: predict, flag, early release, decay, respond (module docs). Always
    /// inlined, so that a fixed-size `a` unrolls the term loops.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn pixel<A: AsMut<[f64]> + AsRef<[f64]> + ?Sized>(
        &self,
        a: &mut A,
        w: &A,
        decay: &A,
        count: &mut u8,
        pending: &mut u8,
        m: f32,
        flags: &mut u32,
        current: &mut f32,
        pflags: &mut u8,
    ) {
        let v = self.predict_flag_release(a.as_mut(), w.as_ref(), count, *pending, m);
        // 4 + 5. decay to this exposure's reset and add its response
        let (ak, max_used) = self.response_of(m, *flags);
        for (aj, dj) in a.as_mut().iter_mut().zip(decay.as_ref()) {
            *aj = *aj * dj + ak;
        }
        self.write_pixel(&v, max_used, pending, current, pflags, flags);
    }

    /// Steps 1-3 of one pixel (module docs), shared by the fused kernel and the effect
    /// path ([`crate::model::effect_step`]): predict from the amplitudes `a` (in the
    /// order of `weighted_sum`, the same in every implementation), flag, and early
    /// release (which may zero `a` and updates the release `count`).
    #[inline(always)]
    pub(crate) fn predict_flag_release(
        &self,
        a: &mut [f64],
        w: &[f64],
        count: &mut u8,
        pending: u8,
        m: f32,
    ) -> PixelVerdict {
        // 1. predict
        let pred = super::decay::weighted_sum(a, w);
        // 2. flag
        let max_prev = pending & PENDING_MAX_AMPLITUDE != 0;
        let mut high = pred > self.high || max_prev;
        let mut low = pred > self.low || high;
        // 3. early release
        let mut released = false;
        if self.er_enabled && high {
            if self.release_step(count, m, pred) {
                self.release_amplitudes(a, pred);
                *count = 0;
                high = false;
                low = false;
                released = true;
            }
        } else {
            *count = 0;
        }
        PixelVerdict {
            pred,
            max_prev,
            high,
            low,
            released,
        }
    }

    /// What early release leaves of a released pixel's amplitudes `a`, predicted `pred`
    /// ([`ReleaseKeep`]): zero, or scaled so that the prediction is the high threshold
    /// (unchanged when it is not above it).
    #[inline(always)]
    pub(crate) fn release_amplitudes(&self, a: &mut [f64], pred: f64) {
        match self.er_keep {
            ReleaseKeep::Zero => a.fill(0.0),
            ReleaseKeep::Threshold if pred > self.high => {
                let scale = self.high / pred;
                for v in a.iter_mut() {
                    *v *= scale;
                }
            }
            ReleaseKeep::Threshold => {}
        }
    }

    /// One exposure of early release for a pixel flagged high, measured `m` (raw, e-/s),
    /// predicted `pred`: updates its release `count` ([`crate::model::EarlyRelease`]) and
    /// tells whether it is released. A non-finite measurement resets the count.
    /// - `consecutive`: one more when `m`, less the background, is below the threshold,
    ///   else 0;
    /// - `evidence`: the count is the evidence in quarter noise sigmas, `max(0, count +
    ///   4 (min(threshold, pred) - (m - background)) / noise)`, rounded, at most 255.
    #[inline(always)]
    pub(crate) fn release_step(&self, count: &mut u8, m: f32, pred: f64) -> bool {
        if !m.is_finite() {
            *count = 0;
            return false;
        }
        let m = f64::from(m);
        *count = match self.er_rule {
            ReleaseRule::Consecutive if m < self.er_threshold => count.saturating_add(1),
            ReleaseRule::Consecutive => 0,
            ReleaseRule::Evidence => {
                // `er_threshold` holds the background; so does the reference
                let reference = self.er_threshold.min(pred + self.er_background);
                let quarters = f64::from(*count) + 4.0 * (reference - m) / self.er_noise;
                // finite operands; an infinite quotient (noise 0) clamps to 0 or 255
                quarters.round().clamp(0.0, 255.0) as u8
            }
        };
        *count >= self.er_release_at
    }

    /// The outputs of one pixel after steps 4-5: whether this exposure's response was
    /// the maximum amplitude (`max_used`, pending for the next exposure), the predicted
    /// current, the persistence flags, and the product's persistence bit.
    #[inline(always)]
    pub(crate) fn write_pixel(
        &self,
        v: &PixelVerdict,
        max_used: bool,
        pending: &mut u8,
        current: &mut f32,
        pflags: &mut u8,
        flags: &mut u32,
    ) {
        *pending = if max_used { PENDING_MAX_AMPLITUDE } else { 0 };
        *current = v.pred as f32;
        let b = &self.bits;
        *pflags = (v.high as u8 * b.high)
            | (v.low as u8 * b.low)
            | (v.max_prev as u8 * b.max_amplitude)
            | (v.released as u8 * b.released)
            | self.history;
        *flags = (*flags & !self.bits.persist) | if v.high { self.bits.persist } else { 0 };
    }
}

/// One pixel's prediction and flag state after steps 1-3.
#[derive(Debug, Clone, Copy)]
pub(crate) struct PixelVerdict {
    pub pred: f64,
    /// The previous exposure used the maximum amplitude (unknown fluence).
    pub max_prev: bool,
    pub high: bool,
    pub low: bool,
    pub released: bool,
}

/// How far ahead of the pixel being computed its amplitudes are prefetched. The
/// per-pixel work is long enough that the out-of-order window holds few loads of the
/// amplitude stream and the hardware prefetcher alone leaves the step waiting on them
/// (measured at 2040^2, `persist bench --case step`, medians of 3 x 15: 42.7 ms with
/// no prefetch, 39.6 ms at 8 pixels, 35.8 ms at 32, 34.6-35.6 ms at 128, 36.0 ms at
/// 256, 36.8 ms at 512, one thread; 22.2 -> 18.5-18.9 ms with two).
const PREFETCH_PIXELS: usize = 128;

/// A hint to fetch the cache line holding `p` (never dereferenced; any address is fine).
#[inline(always)]
fn prefetch<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch is a hint; it does not access memory and cannot fault.
    unsafe {
        core::arch::x86_64::_mm_prefetch::<{ core::arch::x86_64::_MM_HINT_T0 }>(p.cast::<i8>());
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Per-row counters (a row has at most [`crate::h5io::MAX_AXIS`] pixels), taken after
/// the row is written from its persistence flags (still in cache), in loops that
/// vectorise, rather than in the per-pixel code.
#[derive(Default)]
struct Counts {
    high: u32,
    low: u32,
    released: u32,
    max_amplitude: u32,
}

impl Counts {
    fn of_row(pflags: &[u8], bits: &FlagBits) -> Counts {
        let bit = |b: u8| pflags.iter().map(|&f| u32::from(f & b != 0)).sum::<u32>();
        Counts {
            high: bit(bits.high),
            low: bit(bits.low),
            released: bit(bits.released),
            max_amplitude: bit(bits.max_amplitude),
        }
    }

    fn summary(&self, pixels: usize) -> StepSummary {
        StepSummary {
            pixels: pixels as u64,
            above_high: u64::from(self.high),
            above_low: u64::from(self.low),
            released: u64::from(self.released),
            max_amplitude: u64::from(self.max_amplitude),
            t_meas_s: None,
            previous_index: None,
        }
    }
}
