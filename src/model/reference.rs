//! The plain reference implementation of [`Model::step`]: one whole-array pass per
//! stage of the algorithm, written for reading rather than speed. Tests and benches
//! keep it to check that the fused step agrees with it bit for bit.

use super::state::PENDING_MAX_AMPLITUDE;
use super::step::{Input, Model, Output, StepSummary};
use super::State;
use crate::error::Error;
use crate::flags::pbits;
use ndarray::{s, Array2, Zip};

pub fn step(
    model: &Model,
    state: &mut State,
    input: &Input<'_>,
    out: &mut Output<'_>,
) -> Result<StepSummary, Error> {
    let k = model.prepare(state, input, out)?;
    let (ny, nx) = state.shape();
    let image = &input.image_e_per_s;

    // Pass 1: prediction at t_meas.
    let mut pred = Array2::<f64>::zeros((ny, nx));
    for ((y, x), p) in pred.indexed_iter_mut() {
        // Even-indexed terms, odd-indexed terms, then their sum (the documented order of
        // `decay::weighted_sum`).
        let a = state.amplitudes_e.slice(s![y, x, ..]);
        let (mut even, mut odd) = (0.0f64, 0.0f64);
        for j in 0..k.n {
            if j % 2 == 0 {
                even += a[j] * k.w[j];
            } else {
                odd += a[j] * k.w[j];
            }
        }
        *p = even + odd;
    }

    // Pass 2: thresholds (and the forced flag of an unknown previous fluence).
    let max_prev = state.pending.mapv(|p| p & PENDING_MAX_AMPLITUDE != 0);
    let mut high = Zip::from(&pred)
        .and(&max_prev)
        .map_collect(|&p, &m| p > k.high || m);
    let mut low = Zip::from(&pred)
        .and(&high)
        .map_collect(|&p, &h| p > k.low || h);

    // Pass 3: early release.
    let mut released = Array2::from_elem((ny, nx), false);
    for ((y, x), r) in released.indexed_iter_mut() {
        let count = &mut state.release_count[(y, x)];
        if k.er_enabled && high[(y, x)] {
            let m = image[(y, x)];
            if k.release_step(count, m, pred[(y, x)]) {
                let mut a = state.amplitudes_e.slice_mut(s![y, x, ..]);
                let a = a.as_slice_mut().expect("a pixel's terms are contiguous");
                k.release_amplitudes(a, pred[(y, x)]);
                *count = 0;
                high[(y, x)] = false;
                low[(y, x)] = false;
                *r = true;
            }
        } else {
            *count = 0;
        }
    }

    // Pass 4: this exposure's response A_k.
    let mut ak = Array2::<f64>::zeros((ny, nx));
    for ((y, x), a) in ak.indexed_iter_mut() {
        let (v, used_max) = k.response_of(image[(y, x)], out.flags[(y, x)]);
        *a = v;
        state.pending[(y, x)] = if used_max { PENDING_MAX_AMPLITUDE } else { 0 };
    }

    // Pass 5: decay to the new reset, add the response.
    for ((y, x, j), a) in state.amplitudes_e.indexed_iter_mut() {
        *a = *a * k.decay[j] + ak[(y, x)];
    }

    // Pass 6: outputs.
    let mut summary = StepSummary {
        pixels: (ny * nx) as u64,
        t_meas_s: k.t_meas_s,
        previous_index: state.last_index,
        ..Default::default()
    };
    for y in 0..ny {
        for x in 0..nx {
            let (h, l, r, m) = (
                high[(y, x)],
                low[(y, x)],
                released[(y, x)],
                max_prev[(y, x)],
            );
            out.current_e_per_s[(y, x)] = pred[(y, x)] as f32;
            out.pflags[(y, x)] = (if h { pbits::HIGH } else { 0 })
                | (if l { pbits::LOW } else { 0 })
                | (if m { pbits::MAX_AMPLITUDE } else { 0 })
                | (if r { pbits::RELEASED } else { 0 })
                | k.history;
            let f = out.flags[(y, x)] & !k.bits.persist;
            out.flags[(y, x)] = if h { f | k.bits.persist } else { f };
            summary.above_high += h as u64;
            summary.above_low += l as u64;
            summary.released += r as u64;
            summary.max_amplitude += m as u64;
        }
    }
    state.t_reset_unix_s = Some(input.t_start_unix_s + input.t_exposure_s);
    state.last_index = Some(input.exposure_index);
    Ok(summary)
}
