//! The model runner: a model run over a whole sequence, its predictions and flags at
//! the samples ([`predict`]).

use super::samples::Samples;
use crate::error::Result;
use crate::measure::data::Sequence;
use crate::model::{Input, Model, ModelParams, Output, StepContext};
use ndarray::Array2;

/// The model's predictions (and flags) at the samples.
#[derive(Debug, Clone)]
pub struct Prediction {
    pub current: Vec<f64>,
    pub flagged: Vec<bool>,
}

/// Run `params` over the whole sequence; predictions at the samples. `early_release`
/// false switches it off (residuals), true keeps the model file's setting (flags).
///
/// On a laboratory sequence ([`Sequence::is_laboratory`]) early release subtracts the
/// sequence's measured dark level `b_k` ([`Sequence::background_e_per_s`], measured
/// from the background pixels or the darks) as the exposure's background, as the stage
/// subtracts a background it is given. The step's own estimate, the median of the
/// pixels it predicts quiet, measures persistence there: a laboratory illumination
/// lights every pixel, so the quiet pixels are the least-lit ones and, after the first
/// release, the released ones (their amplitudes zeroed), whose persistence the
/// median then takes for background (campaign of `tests/coverage_after_effect.rs`:
/// 0.37-0.80 e-/s in the first dark after an illumination, 0.09-0.13 e-/s in the
/// second, where the dark level is 0.014-0.018 e-/s), and the pixels released
/// against it are truly well above the threshold. On sky data the step estimates it,
/// as in the stage.
///
/// A model whose pixels do not see one another ([`Model::is_pixel_local`]) runs on the
/// sampled pixels alone, gathered into an array of their own ([`Layout::Gathered`]);
/// any other on the whole array, advancing the sampled pixels and what they read
/// ([`Layout::Whole`]). Both give the same predictions bit for bit where both apply.
pub fn predict(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    early_release: bool,
) -> Result<Prediction> {
    predict_in(params, seq, samples, early_release, Layout::Gathered)
}

/// Where [`predict`] runs the model.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Layout {
    /// The sampled pixels gathered in rows of [`GATHERED_COLS`] when the model is
    /// pixel-local, else as [`Layout::Whole`].
    Gathered,
    /// The whole array, with the sampled pixels as `StepContext::active_pixels`.
    Whole,
}

/// Columns of [`Layout::Gathered`]'s array (its rows are stepped in parallel).
pub const GATHERED_COLS: usize = 64;

/// [`predict`] in the given [`Layout`] (the tests compare the two).
pub fn predict_in(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    early_release: bool,
    layout: Layout,
) -> Result<Prediction> {
    run(params, seq, samples, early_release, layout, None)
}

/// [`predict`] with each exposure's focal-plane temperature `temps_k[k]` (one per
/// exposure of `seq`) in place of the one it records: the model as it would run had the
/// exposures been taken at those temperatures (a permutation of the covariate, for
/// example).
pub fn predict_at_temperatures(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    early_release: bool,
    temps_k: &[Option<f64>],
) -> Result<Prediction> {
    run(
        params,
        seq,
        samples,
        early_release,
        Layout::Gathered,
        Some(temps_k),
    )
}

fn run(
    params: &ModelParams,
    seq: &Sequence,
    samples: &Samples,
    early_release: bool,
    layout: Layout,
    temps_k: Option<&[Option<f64>]>,
) -> Result<Prediction> {
    let mut p = params.clone();
    if !early_release {
        p.early_release.enabled = false;
    }
    let model = Model::new(p)?;
    let gathered = layout == Layout::Gathered && model.is_pixel_local();
    let np = samples.npix();
    let (ny, nx) = if gathered {
        let nx = GATHERED_COLS.min(np).max(1);
        (np.div_ceil(nx).max(1), nx)
    } else {
        (seq.ny, seq.nx)
    };
    // where each sampled pixel sits in the stepped array
    let at: Vec<(usize, usize)> = if gathered {
        (0..np).map(|j| (j / nx, j % nx)).collect()
    } else {
        samples.pixels.clone()
    };
    let mut st = model.new_state(ny, nx);
    let mut cur = Array2::<f32>::zeros((ny, nx));
    let mut pf = Array2::<u8>::zeros((ny, nx));
    let mut image = Array2::<f32>::zeros((ny, nx));
    let mut flags = Array2::<u32>::zeros((ny, nx));
    let mut out = Prediction {
        current: Vec::with_capacity(samples.len()),
        flagged: Vec::with_capacity(samples.len()),
    };
    // only the sampled pixels are read: the model may skip the others
    let active = (!gathered).then(|| {
        let mut a = vec![false; ny * nx];
        for &(y, x) in &samples.pixels {
            a[y * nx + x] = true;
        }
        a
    });
    let lab = seq.is_laboratory();
    let mut row = 0;
    for (k, e) in seq.exposures.iter().enumerate() {
        let image = if gathered {
            // the padding after the last sampled pixel stays dark and unflagged
            flags.fill(0);
            for (&px, &to) in samples.pixels.iter().zip(&at) {
                image[to] = e.image[px];
                flags[to] = e.flags[px];
            }
            image.view()
        } else {
            flags.assign(&e.flags);
            e.image.view()
        };
        let input = Input {
            image_e_per_s: image,
            exposure_index: e.meta.exposure_index,
            t_start_unix_s: e.meta.t_start.0,
            t_exposure_s: e.meta.t_exposure_s,
            t_illuminated_s: e.meta.t_illuminated_s(),
            history_incomplete: false,
            background_e_per_s: lab.then(|| seq.background_e_per_s[k]),
        };
        model.step_with(
            &mut st,
            &input,
            &StepContext {
                focal_plane_temp_k: temps_k.map_or(e.meta.focal_plane_temp_k, |t| t[k]),
                active_pixels: active.as_deref(),
            },
            &mut Output {
                flags: &mut flags,
                current_e_per_s: &mut cur,
                pflags: &mut pf,
            },
        )?;
        if samples.exposures.get(row) == Some(&k) {
            for &px in &at {
                out.current.push(f64::from(cur[px]));
                out.flagged.push(pf[px] & crate::flags::pbits::HIGH != 0);
            }
            row += 1;
        }
    }
    Ok(out)
}
