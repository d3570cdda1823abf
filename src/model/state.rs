//! The per-detector model state carried from exposure to exposure.
//!
//! Invariants: every amplitude is finite and >= 0 (inputs are sanitised before they
//! reach it, see [`crate::model::step`]); `release_count < consecutive`; `pending` holds
//! only [`PENDING_MAX_AMPLITUDE`]; `t_reset` is `None` exactly when no exposure has been
//! absorbed yet, and then every amplitude is zero.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

/// `pending` bit: this pixel's last response used the maximum amplitude (its fluence
/// was unknown), so the next exposure marks it and flags it.
pub const PENDING_MAX_AMPLITUDE: u8 = 1;

#[derive(Debug, Clone, PartialEq)]
pub struct State {
    /// `A_n` in electrons, shape `[ny, nx, n_terms]` (term index fastest, so one pixel's
    /// amplitudes are contiguous and a row of pixels is one contiguous block).
    pub amplitudes_e: Array3<f64>,
    /// Consecutive exposures flagged high with a measured current below the early-release
    /// threshold. `[ny, nx]`
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
        fn ok(a: &[f64]) -> bool {
            // NaN fails both comparisons; -0.0 >= 0.0 holds, as in `a >= 0.0`.
            a.iter()
                .fold(true, |ok, v| ok & (0.0..f64::INFINITY).contains(v))
        }
        match self.amplitudes_e.as_slice_memory_order() {
            Some(a) => a.par_chunks(1 << 16).all(ok),
            None => self.amplitudes_e.iter().all(|a| a.is_finite() && *a >= 0.0),
        }
    }

    /// Check the invariants (used on saving and loading checkpoints).
    pub fn check(&self) -> Result<(), String> {
        self.check_with(false)
    }

    /// [`State::check`], skipping the pass over the amplitudes when the caller knows
    /// they are valid (`amplitudes_verified`: every step since the state was checked or
    /// created counted no invalid amplitude, [`crate::model::StepSummary`]).
    pub fn check_with(&self, amplitudes_verified: bool) -> Result<(), String> {
        let (ny, nx) = self.shape();
        if self.release_count.dim() != (ny, nx) || self.pending.dim() != (ny, nx) {
            return Err("release_count/pending: shape differs from the amplitudes".into());
        }
        if !amplitudes_verified && !self.amplitudes_valid() {
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
