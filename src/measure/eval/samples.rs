//! The samples the residual statistics use: which (pixel, exposure) pairs, their
//! measurements and covariates, and how they are grouped into cells ([`Cells`]).
//!
//! # Samples
//! A sample is one (pixel, exposure) with the exposure after an illumination and not
//! itself illuminated. Pixels: every `stride`-th pixel in both directions (a fixed,
//! documented subsample; `stride` 2 by default, i.e. a quarter of the array), with a
//! usable fluence above [`BACKGROUND_FLUENCE_E`] in the last illumination.
//! The model is always run on the whole array (effects such as blooming read
//! neighbours); only the statistics use the subsample.
//!
//! # Neighbour contrast
//! A pixel next to one far brighter than itself (a star, a one-pixel pinhole) has a
//! history of its own: whatever couples neighbours (inter-pixel capacitance, charge
//! spilling) acts on it much more than on a pixel of the same fluence in a smooth
//! image. Within a cell of fluence and time such pixels are few, and a cell's 95th
//! percentile does not see them when the model predicts them too high. `--cells
//! neighbours` ([`Cells::Neighbours`]) keys the per-illumination cells by one more
//! covariate, `neighbour_contrast`: 1 where the mean over the four nearest neighbours of
//! the fluence above saturation (2e5 e-, `neighbour_excess_fluence`) exceeds the pixel's
//! own fluence, else 0. On the smooth laboratory spot no pixel qualifies but those at
//! its saturated centre's edge, so the cells are nearly the per-illumination ones.
//!
//! # Why per illumination
//! The model predicts the 95th percentile of the pixels of one history. A pooled cell of
//! a campaign mixes illuminations whose pixels of the same fluence have different
//! histories (a ring lit at 6e4 e- after saturating in the illumination before holds
//! old charge the same fluence lit first does not), and the 95th percentile of a
//! mixture is not the mixture of the 95th percentiles: the measured side takes the top
//! 5 % of the pooled population spread, the predicted side (no population spread) the
//! level of the brightest illumination, so a pooled cell compares different quantiles
//! and its `z` depends on the mixing fractions. Measured (64 x 64 campaign, seed 1,
//! hidden `temperature` at 0.25 eV; measured with examples/diagnose_matrix): the model
//! fitted on the same campaign without the hidden effect, with the model's
//! `temperature` at the truth's 0.25 eV, scores 12.85 on pooled cells against 4.58 for
//! the baseline campaign, but 2.48 against 2.44 per illumination. On one illumination
//! the two are the same cells.

use super::group::CellStatistic;
use crate::measure::data::{fluence, Sequence, BACKGROUND_FLUENCE_E, SATURATION_FLUENCE_E};
use crate::model::effects::blooming::neighbour_excess;
use ndarray::Array2;
use serde::Serialize;

/// How samples are grouped into the residual's cells (module docs). The default,
/// [`Cells::Illumination`], is that of `persist fit`, `compare` and `diagnose`
/// (`--cells`, whose default is this one).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Cells {
    /// Fluence x time since illumination, all illuminations together.
    Pooled,
    /// Illumination x fluence x time since illumination.
    #[default]
    Illumination,
    /// Illumination x neighbour contrast x fluence x time: the per-illumination cells
    /// with the pixels next to a much brighter one (module docs, "Neighbour
    /// contrast") in cells of their own.
    Neighbours,
}

choices!(Cells, "--cells", Pooled => "pooled", Illumination => "illumination", Neighbours => "neighbours");

impl Cells {
    /// What keys a cell, in words.
    pub fn describe(self) -> &'static str {
        match self {
            Cells::Pooled => "fluence x time",
            Cells::Illumination => "illumination x fluence x time",
            Cells::Neighbours => "illumination x neighbour contrast x fluence x time",
        }
    }

    /// The covariates of [`super::groups`] that key a cell.
    pub fn keys(self) -> &'static [&'static str] {
        match self {
            Cells::Pooled => &["fluence", "time"],
            Cells::Illumination => &["event", "fluence", "time"],
            Cells::Neighbours => &["event", "neighbour_contrast", "fluence", "time"],
        }
    }
}

/// Scales of the two parts of a sample's noise variance (read noise, shot noise): what
/// the residuals show over what the sequence's noise model says.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct NoiseScale {
    pub read_var: f64,
    pub shot_var: f64,
}

impl Default for NoiseScale {
    fn default() -> NoiseScale {
        NoiseScale {
            read_var: 1.0,
            shot_var: 1.0,
        }
    }
}

/// Samples and their covariates.
#[derive(Debug, Clone)]
pub struct Samples {
    /// How [`super::cell_z`] and [`super::CellIndex`] group these samples.
    pub cells: Cells,
    /// What their cells compare.
    pub statistic: CellStatistic,
    pub stride: usize,
    pub pixels: Vec<(usize, usize)>,
    /// Exposure indices (into the sequence) of the samples' rows.
    pub exposures: Vec<usize>,
    /// `[exposures.len() * pixels.len()]`, e-/s, NaN unusable.
    pub measured: Vec<f64>,
    /// Per exposure row: the exposure noise `sigma_k` (background pixels), e-/s.
    pub noise: Vec<f64>,
    /// Per exposure row: the variance of a measured current per e-/s of the pixel's own
    /// current, its shot noise in an unweighted line fit of many evenly spaced reads,
    /// `6 / (5 t_exposure_s)` ((e-/s)^2 per e-/s; [`super::group`] docs, "Population
    /// statistic").
    pub shot_var_per_e_per_s: Vec<f64>,
    /// The scales of the read-noise and shot-noise variances that the pixel reference
    /// weighs and judges these samples with, measured on its residuals once per
    /// diagnosis (`crate::diag::base::measure_noise_scale`); 1 and 1 until then.
    pub noise_scale: NoiseScale,
    /// Per sample: the population's relative spread at its fluence
    /// ([`crate::measure::data::PopulationSpread`], measured once per sequence).
    pub spread_rel: Vec<f64>,
    /// Per sample covariates (same layout as `measured`).
    pub fluence_e: Vec<f64>,
    pub neighbour_excess_e: Vec<f64>,
    /// Per exposure row.
    pub t_since_s: Vec<f64>,
    /// Per exposure row: the illumination event it follows (index into the
    /// sequence's exposures), the key of `diagnose`'s held-out split.
    pub event: Vec<usize>,
    pub illumination_time_s: Vec<f64>,
    pub temperature_k: Vec<f64>,
    pub earlier_illuminations: Vec<f64>,
    /// Per pixel: distance from the array centre in units of the half size.
    pub radius: Vec<f64>,
}

impl Samples {
    pub fn new(seq: &Sequence, stride: usize) -> Samples {
        let stride = stride.max(1);
        let pixels: Vec<(usize, usize)> = (0..seq.ny)
            .step_by(stride)
            .flat_map(|y| (0..seq.nx).step_by(stride).map(move |x| (y, x)))
            .collect();
        Samples::with_pixels(seq, pixels, stride)
    }

    /// Samples at `n` pixels drawn at random (ChaCha8, `seed`) without replacement from
    /// the pixels above [`BACKGROUND_FLUENCE_E`] in at least one illumination (all of
    /// them when fewer), in raster order. `stride` is reported as 0.
    pub fn random(seq: &Sequence, n: usize, seed: u64) -> Samples {
        use rand::seq::SliceRandom;
        use rand::SeedableRng;
        let mut lit = vec![false; seq.ny * seq.nx];
        for &a in &seq.illuminations {
            for ((y, x), v) in fluence(&seq.exposures[a]).indexed_iter() {
                if v.is_finite() && *v > BACKGROUND_FLUENCE_E {
                    lit[y * seq.nx + x] = true;
                }
            }
        }
        let mut cand: Vec<usize> = (0..lit.len()).filter(|&i| lit[i]).collect();
        if cand.len() > n {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            cand.shuffle(&mut rng);
            cand.truncate(n);
            cand.sort_unstable();
        }
        let pixels = cand.iter().map(|&i| (i / seq.nx, i % seq.nx)).collect();
        Samples::with_pixels(seq, pixels, 0)
    }

    /// The same samples grouped by `cells`.
    pub fn with_cells(self, cells: Cells) -> Samples {
        Samples { cells, ..self }
    }

    /// The same samples compared by `statistic`.
    pub fn with_statistic(self, statistic: CellStatistic) -> Samples {
        Samples { statistic, ..self }
    }

    /// The rows (exposures) for which `keep(event)` is true.
    pub fn rows_where(&self, keep: impl Fn(usize) -> bool) -> Samples {
        self.rows(&self.row_indices(keep))
    }

    /// The given rows (indices into `exposures`), in their order.
    pub fn rows(&self, rows: &[usize]) -> Samples {
        let per_row = |v: &Vec<f64>| rows.iter().map(|&r| v[r]).collect::<Vec<f64>>();
        Samples {
            cells: self.cells,
            statistic: self.statistic,
            stride: self.stride,
            pixels: self.pixels.clone(),
            exposures: rows.iter().map(|&r| self.exposures[r]).collect(),
            measured: self.rows_of(&self.measured, rows),
            noise: per_row(&self.noise),
            shot_var_per_e_per_s: per_row(&self.shot_var_per_e_per_s),
            noise_scale: self.noise_scale,
            spread_rel: self.rows_of(&self.spread_rel, rows),
            fluence_e: self.rows_of(&self.fluence_e, rows),
            neighbour_excess_e: self.rows_of(&self.neighbour_excess_e, rows),
            t_since_s: per_row(&self.t_since_s),
            event: rows.iter().map(|&r| self.event[r]).collect(),
            illumination_time_s: per_row(&self.illumination_time_s),
            temperature_k: per_row(&self.temperature_k),
            earlier_illuminations: per_row(&self.earlier_illuminations),
            radius: self.radius.clone(),
        }
    }

    /// Indices of the rows (exposures) for which `keep(event)` is true.
    pub fn row_indices(&self, keep: impl Fn(usize) -> bool) -> Vec<usize> {
        (0..self.exposures.len())
            .filter(|&r| keep(self.event[r]))
            .collect()
    }

    /// Per-sample values `v` (the layout of `measured`, e.g. a prediction) of the
    /// given rows, in their order: what [`Samples::rows_where`] keeps of them.
    pub fn rows_of(&self, v: &[f64], rows: &[usize]) -> Vec<f64> {
        let np = self.npix();
        rows.iter()
            .flat_map(|&r| v[r * np..(r + 1) * np].iter().copied())
            .collect()
    }

    /// The same rows at the pixels `cols` (indices into `pixels`), in their order.
    pub fn columns(&self, cols: &[usize]) -> Samples {
        Samples {
            pixels: cols.iter().map(|&c| self.pixels[c]).collect(),
            measured: self.columns_of(&self.measured, cols),
            spread_rel: self.columns_of(&self.spread_rel, cols),
            fluence_e: self.columns_of(&self.fluence_e, cols),
            neighbour_excess_e: self.columns_of(&self.neighbour_excess_e, cols),
            radius: cols.iter().map(|&c| self.radius[c]).collect(),
            // the per-row columns as they are (not a clone of the whole, whose
            // per-sample vectors would be copied only to be dropped)
            cells: self.cells,
            statistic: self.statistic,
            stride: self.stride,
            exposures: self.exposures.clone(),
            noise: self.noise.clone(),
            shot_var_per_e_per_s: self.shot_var_per_e_per_s.clone(),
            noise_scale: self.noise_scale,
            t_since_s: self.t_since_s.clone(),
            event: self.event.clone(),
            illumination_time_s: self.illumination_time_s.clone(),
            temperature_k: self.temperature_k.clone(),
            earlier_illuminations: self.earlier_illuminations.clone(),
        }
    }

    /// Per-sample values `v` (the layout of `measured`) at the pixels `cols`: what
    /// [`Samples::columns`] keeps of them.
    pub fn columns_of(&self, v: &[f64], cols: &[usize]) -> Vec<f64> {
        let np = self.npix();
        (0..self.exposures.len())
            .flat_map(|r| cols.iter().map(move |&c| v[r * np + c]))
            .collect()
    }

    /// Samples at the given pixels (every row).
    pub fn with_pixels(seq: &Sequence, pixels: Vec<(usize, usize)>, stride: usize) -> Samples {
        Samples::with_pixels_where(seq, pixels, stride, |_| true)
    }

    /// Samples at the given pixels, in the rows of the exposures `k` (indices into the
    /// sequence) for which `keep(k)` is true.
    pub fn with_pixels_where(
        seq: &Sequence,
        pixels: Vec<(usize, usize)>,
        stride: usize,
        keep: impl Fn(usize) -> bool,
    ) -> Samples {
        let mut s = Samples {
            cells: Cells::default(),
            statistic: CellStatistic::default(),
            stride,
            pixels: pixels.clone(),
            exposures: Vec::new(),
            measured: Vec::new(),
            noise: Vec::new(),
            shot_var_per_e_per_s: Vec::new(),
            noise_scale: NoiseScale::default(),
            spread_rel: Vec::new(),
            fluence_e: Vec::new(),
            neighbour_excess_e: Vec::new(),
            t_since_s: Vec::new(),
            event: Vec::new(),
            illumination_time_s: Vec::new(),
            temperature_k: Vec::new(),
            earlier_illuminations: Vec::new(),
            radius: pixels
                .iter()
                .map(|&(y, x)| {
                    let c =
                        |v: usize, n: usize| (v as f64 - (n as f64 - 1.0) / 2.0) / (n as f64 / 2.0);
                    (c(y, seq.ny).powi(2) + c(x, seq.nx).powi(2)).sqrt()
                })
                .collect(),
        };
        let spread = seq.population_spread();
        let mut cache: Option<(usize, Array2<f64>, Array2<f64>)> = None;
        for k in 0..seq.exposures.len() {
            let Some(a) = seq.last_illumination[k] else {
                continue;
            };
            if seq.illuminations.contains(&k) || !keep(k) {
                continue;
            }
            if cache.as_ref().map(|c| c.0) != Some(a) {
                let f = fluence(&seq.exposures[a]);
                let nb = neighbour_excess(&f, SATURATION_FLUENCE_E);
                cache = Some((a, f, nb));
            }
            let (_, f, nb) = cache.as_ref().expect("set above");
            let m = seq.measured(k);
            s.exposures.push(k);
            s.noise.push(seq.noise_e_per_s[k]);
            s.shot_var_per_e_per_s.push(seq.shot_var_per_e_per_s(k));
            s.t_since_s.push(seq.t_mid_after_s(a, k));
            s.event.push(a);
            s.illumination_time_s
                .push(seq.exposures[a].meta.t_illuminated_s());
            s.temperature_k
                .push(seq.exposures[k].meta.focal_plane_temp_k.unwrap_or(f64::NAN));
            s.earlier_illuminations
                .push(seq.illuminations_before(k) as f64 - 1.0);
            for &p in &pixels {
                let fl = f[p];
                let ok = fl.is_finite() && fl > BACKGROUND_FLUENCE_E;
                s.measured.push(if ok { m[p] } else { f64::NAN });
                s.fluence_e.push(fl);
                s.spread_rel.push(spread.at(fl));
                s.neighbour_excess_e.push(nb[p]);
            }
        }
        s
    }

    pub fn len(&self) -> usize {
        self.measured.len()
    }
    pub fn is_empty(&self) -> bool {
        self.measured.is_empty()
    }
    pub fn npix(&self) -> usize {
        self.pixels.len()
    }

    /// The illumination events the samples follow ([`Samples::event`]), sorted, once
    /// each.
    pub fn events(&self) -> Vec<usize> {
        let mut e = self.event.clone();
        e.sort_unstable();
        e.dedup();
        e
    }

    /// What `measured - predicted` of sample `i` is under the model when its prediction
    /// is `pred` (e-/s): `(mean, standard deviation, measurement noise)` of a Gaussian.
    /// With [`CellStatistic::Population`] ([`super::group`] docs, "Population
    /// statistic"): the pixels' spread `s = r max(pred, 0)` below the predicted 95th percentile and the
    /// noise with the sample's own shot noise, `sigma^2 = sigma_k^2 + g_k max(pred, 0)`:
    /// `(-1.645 s, sqrt(s^2 + sigma^2), sigma)`. Otherwise `(0, sigma_k, sigma_k)`.
    pub fn null_of(&self, i: usize, pred: f64) -> (f64, f64, f64) {
        let row = i / self.npix();
        let sigma_k = self.noise[row];
        if self.statistic != CellStatistic::Population {
            return (0.0, sigma_k, sigma_k);
        }
        let c = if pred.is_finite() { pred.max(0.0) } else { 0.0 };
        let sigma = (sigma_k * sigma_k + self.shot_var_per_e_per_s[row] * c).sqrt();
        let spread = self.spread_rel[i] * c;
        (
            -1.645 * spread,
            (spread * spread + sigma * sigma).sqrt(),
            sigma,
        )
    }
}
