//! The per-detector model state carried from exposure to exposure.
//!
//! Invariants: every amplitude is finite and >= 0 (inputs are sanitised before they
//! reach it, see [`crate::model::step`]); `release_count` below the count that releases
//! (`consecutive`, or `evidence_sigma` in quarter sigmas); `pending` holds
//! only [`PENDING_MAX_AMPLITUDE`]; `t_reset` is `None` exactly when no exposure has been
//! absorbed yet, and then every amplitude is zero.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// `pending` bit: this pixel's last response used the maximum amplitude or the transient
/// rule's (its fluence was unknown), so the next exposure marks it and flags it.
pub const PENDING_MAX_AMPLITUDE: u8 = 1;

#[derive(Debug, Clone, PartialEq)]
pub struct State {
    /// `A_n` in electrons, shape `[ny, nx, n_terms]` (term index fastest, so one pixel's
    /// amplitudes are contiguous and a row of pixels is one contiguous block).
    pub amplitudes_e: Array3<f64>,
    /// Early release's count (`Kernel::release_step` in [`crate::model::step`]): the
    /// evidence so far in quarter noise sigmas (`rule: evidence`), or the consecutive
    /// exposures flagged high with a measured current below the early-release threshold
    /// (`rule: consecutive`). `[ny, nx]`
    pub release_count: Array2<u8>,
    /// Per-pixel bits carried to the next exposure. `[ny, nx]`
    pub pending: Array2<u8>,
    /// The reset that ended the last absorbed exposure, seconds since the Unix epoch.
    pub t_reset_unix_s: Option<f64>,
    /// The index of the last absorbed exposure.
    pub last_index: Option<u64>,
}

impl State {
    pub fn zeros(ny: usize, nx: usize, n_terms: usize) -> Self {
        State {
            amplitudes_e: Array3::zeros((ny, nx, n_terms)),
            release_count: Array2::zeros((ny, nx)),
            pending: Array2::zeros((ny, nx)),
            t_reset_unix_s: None,
            last_index: None,
        }
    }

    /// `(ny, nx)`.
    pub fn shape(&self) -> (usize, usize) {
        let s = self.amplitudes_e.shape();
        (s[0], s[1])
    }

    pub fn n_terms(&self) -> usize {
        self.amplitudes_e.shape()[2]
    }

    /// Bytes held by the state's arrays.
    pub fn nbytes(&self) -> usize {
        self.amplitudes_e.len() * 8 + self.release_count.len() + self.pending.len()
    }

    /// Every amplitude finite and >= 0: one branch-free pass (vectorised), in parallel.
    fn amplitudes_valid(&self) -> bool {
        match self.amplitudes_e.as_slice_memory_order() {
            Some(a) => a.par_chunks(1 << 16).all(amplitudes_ok),
            None => self.amplitudes_e.iter().all(|a| a.is_finite() && *a >= 0.0),
        }
    }

    /// Check the invariants (used on loading checkpoints).
    pub fn check(&self) -> Result<(), String> {
        self.check_with(false)
    }

    /// [`State::check`], leaving out the pass over the amplitudes when the caller checks
    /// them itself (`amplitudes_checked_elsewhere`: the checkpoint writer checks each
    /// block with [`amplitudes_ok`] just before writing it, while it is in cache).
    pub fn check_with(&self, amplitudes_checked_elsewhere: bool) -> Result<(), String> {
        let (ny, nx) = self.shape();
        if self.release_count.dim() != (ny, nx) || self.pending.dim() != (ny, nx) {
            return Err("release_count/pending: shape differs from the amplitudes".into());
        }
        if !amplitudes_checked_elsewhere && !self.amplitudes_valid() {
            if let Some(bad) = self
                .amplitudes_e
                .iter()
                .find(|a| !(a.is_finite() && **a >= 0.0))
            {
                return Err(format!(
                    "amplitudes_e: holds {bad}, must be finite and >= 0"
                ));
            }
        }
        let pending_bits = match self.pending.as_slice_memory_order() {
            Some(p) => p.iter().fold(0u8, |acc, p| acc | p),
            None => self.pending.iter().fold(0u8, |acc, p| acc | p),
        };
        if pending_bits & !PENDING_MAX_AMPLITUDE != 0 {
            return Err("pending: unknown bits set".into());
        }
        if self.t_reset_unix_s.is_none() && self.amplitudes_e.iter().any(|a| *a != 0.0) {
            return Err("t_reset: missing although amplitudes are non-zero".into());
        }
        if let Some(t) = self.t_reset_unix_s {
            if !t.is_finite() {
                return Err("t_reset: not finite".into());
            }
        }
        Ok(())
    }
}

/// Whether every amplitude of `a` is finite and `>= 0` (`-0.0` included, as
/// `a >= 0.0`), in one pass with independent lanes so that it vectorises: NaN and
/// infinities reach the lane sums, negatives the lane minima. A sum that overflows
/// reports valid amplitudes as invalid only when they exceed ~1e307 / len, far above
/// any amplitude the model makes (the knot maximum is ~1e3 e-).
pub fn amplitudes_ok(a: &[f64]) -> bool {
    const L: usize = 8;
    let mut sum = [0.0f64; L];
    let mut min = [0.0f64; L];
    let chunks = a.chunks_exact(L);
    let tail = chunks.remainder();
    for c in chunks {
        for l in 0..L {
            sum[l] += c[l];
            min[l] = if c[l] < min[l] { c[l] } else { min[l] };
        }
    }
    let mut total: f64 = sum.iter().sum();
    let mut lowest = min.iter().fold(0.0f64, |m, &v| if v < m { v } else { m });
    for &v in tail {
        total += v;
        lowest = if v < lowest { v } else { lowest };
    }
    total.is_finite() && lowest >= 0.0
}
