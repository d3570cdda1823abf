//! The model run over a sequence and the residual statistics shared by `fit --with`,
//! `compare` and `diagnose`.
//!
//! One job a file, importing downwards only (tests/import_graph.rs): [`group`] (the
//! statistic of one group) <- [`samples`] (what is sampled, how it is grouped) <-
//! [`runner`] (the model run at the samples), [`cells`] (the cells and their `z`) <-
//! [`quality`] (flag quality). This file only re-exports them, so that every item keeps
//! its path `measure::eval::NAME`.

pub mod cells;
pub mod group;
pub mod quality;
pub mod runner;
pub mod samples;

pub use super::data::SHOT_VAR_LINE_FIT;
pub use cells::{
    bin_of, bin_value, cell_fluence_time, cell_illumination, cell_next_to_brighter, cell_z, groups,
    groups_by, key_of, rms, rss, CellIndex,
};
pub use group::{
    cell_stat, cell_stat_null, group_stat, group_stat_p95, group_stat_paired, noise_p95,
    p95_sigma_median, paired_z, CellStatistic, GroupStat,
};
pub use quality::{
    flag_quality, flag_quality_by_cell, flag_quality_of, flag_quality_of_samples,
    over_flagged_by_pixel, pixels_of, touched_samples, FlagQuality,
};
pub use runner::{predict, predict_at_temperatures, predict_in, Layout, Prediction, GATHERED_COLS};
pub use samples::{Cells, NoiseScale, Samples};

#[cfg(test)]
mod tests;
