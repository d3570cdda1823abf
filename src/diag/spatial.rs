//! Spatial coherence of the residuals: is part of the model's misfit a field that
//! neighbouring pixels share and that a pixel carries from one illumination to the next?
//!
//! # Why
//! The residual cells of [`super::eval`] pool the pixels of one fluence and time from the
//! whole array. A trap density that varies across the array in patches (the simulator's
//! `populations`, correlation length 8 pixels by default) moves pixels against each other
//! within a cell and leaves the cell's 95th percentile nearly where it was, so neither the
//! cells nor a library effect of a few numbers (the model's `populations` is a quadratic
//! surface over the whole array) see it. This check looks at the pixels themselves.
//!
//! # Statistic
//! For each illumination event, its first exposure after the illumination: at every pixel
//! predicted above [`MIN_PREDICTED_E_PER_S`] and measured above 0 (background
//! subtracted, [`super::data`]), `r = ln(measured / predicted)` less the median of `r`
//! over the pixels of its fluence bin (20 per decade) in that exposure. What depends on
//! fluence alone is the knots'; the spot's fluence pattern is smooth on the array, so
//! without this the knots' own misfit would look like a spatial field. The map `M` of an
//! event is `r` smoothed over `length_px`: three masked box passes of half-width
//! `round(length_px / 2)` ([`crate::sim::analysis::box_blur`] of the values and of the
//! mask, divided), the simulator's own smoothing of its field. For every ordered pair of
//! events (A, B), the `R^2` of the least-squares line of `r_B` on `M_A` over the pixels
//! where both are defined: the part of B's per-pixel misfit that a smooth map learnt
//! from A predicts. `r2_smoothed` is its mean over the pairs, for each length of
//! [`LENGTHS_PX`]; `r2_raw` is the same with the unsmoothed `r_A` (a pixel's own traps are
//! the same in every event, so that one is high on any campaign: 0.67-0.74 on the
//! baseline campaigns below).
//!
//! # Sharp features
//! Pixels next to a far brighter, saturated neighbour, and every pixel within one step
//! of them, are left out ([`near_sharp_features`], in each event's own illumination).
//! Whatever couples neighbours (inter-pixel capacitance, charge spilled by blooming)
//! moves them by a fixed fraction of the bright source's persistence; a grid of
//! pinholes lit in every event puts that at the same pixels each time, a field shared
//! from event to event that no trap density makes. Measured (examples/family_matrix,
//! 64 x 64 pinhole-grid campaigns of the second generator, hidden `ipc:cross4`, seed
//! 1): with these pixels kept, `r2_smoothed` at 4 px was 0.29 and the hidden coupling
//! was declared as `populations`.
//!
//! # Threshold
//! `coherent` when the largest `r2_smoothed` over the lengths is at least
//! [`COHERENT_R2`]. It is an effect size, not a test: `diagnose`'s bootstrap replicas are
//! the model plus white noise and hold no spatial structure, so they would call any real
//! campaign coherent. Measured (measured with examples/diagnose_matrix): 64 x 64
//! laboratory campaigns, the readout reference fitted to each, length 8 px: no hidden
//! effect 0.035, 0.048, 0.049 (seeds 1-3); hidden `populations` (its defaults) 0.51,
//! 0.69, 0.51.
//!
//! Needs two illumination events or more (`None` otherwise, before the model is run).
//! Cost: one more run of the model over the sequence, with every pixel sampled at one
//! exposure per event (about 40 bytes per pixel and event: 0.8 GB for five events of a
//! 2040 x 2040 array), and four smoothings per event.

use super::data::Sequence;
use super::eval::{self, Samples};
use crate::error::Result;
use crate::model::params::ModelParams;
use ndarray::Array2;
use serde::Serialize;

/// Pixels predicted below this in the first exposure after an illumination are left out
/// (noise dominated), e-/s.
pub const MIN_PREDICTED_E_PER_S: f64 = 1.0;

/// Fluence bins per decade of the demeaning (module docs).
pub const FLUENCE_BINS_PER_DECADE: f64 = 20.0;

/// The smoothing lengths tried, pixels.
pub const LENGTHS_PX: [f64; 4] = [4.0, 8.0, 16.0, 32.0];

/// `coherent` at or above this `r2_smoothed` (module docs, "Threshold").
pub const COHERENT_R2: f64 = 0.2;

/// One event's per-pixel log ratio (module docs).
#[derive(Debug, Clone)]
pub struct EventRatio {
    /// Exposure index of the illumination.
    pub illumination_exposure_index: u64,
    /// `[ny, nx]`, NaN where not defined.
    pub ratio: Array2<f64>,
}

/// The result (module docs).
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Coherence {
    pub events: usize,
    /// Ordered pairs of events compared.
    pub pairs: usize,
    /// Median over the events of the pixels with a ratio.
    pub pixels_per_event: usize,
    /// Mean `R^2` of `r_B` on the unsmoothed `r_A`.
    pub r2_raw: f64,
    /// `(length_px, mean R^2 of r_B on M_A)`, one per [`LENGTHS_PX`].
    pub r2_smoothed: Vec<(f64, f64)>,
    /// The length of the largest `r2_smoothed`, px.
    pub best_length_px: f64,
    /// The largest `r2_smoothed`.
    pub best_r2: f64,
    pub threshold: f64,
    pub coherent: bool,
    /// Where the mean map over the events (smoothed over the best length) is highest:
    /// `(y, x)` and the ratio measured / predicted there (`exp` of the map).
    pub highest: Option<((usize, usize), f64)>,
    /// Where it is lowest.
    pub lowest: Option<((usize, usize), f64)>,
    /// That map, in blocks (`persist compare`'s figure of where the field is).
    pub field: FieldMap,
}

/// A map of the array in square blocks of `block_px` (the last row and column of blocks
/// may be cut by the edge), at most [`FIELD_BLOCKS`] on a side.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct FieldMap {
    pub block_px: usize,
    /// Blocks down and across.
    pub rows: usize,
    pub cols: usize,
    /// Row-major, the mean of the block's finite values; `null` where it has none.
    pub log_ratio: Vec<Option<f64>>,
}

/// Blocks on a side of [`FieldMap`] at most.
pub const FIELD_BLOCKS: usize = 64;

impl FieldMap {
    /// `map` in blocks (type docs).
    pub fn of(map: &Array2<f64>) -> FieldMap {
        let (ny, nx) = map.dim();
        let block_px = ny.max(nx).div_ceil(FIELD_BLOCKS).max(1);
        let (rows, cols) = (ny.div_ceil(block_px), nx.div_ceil(block_px));
        let mut log_ratio = Vec::with_capacity(rows * cols);
        for r in 0..rows {
            for c in 0..cols {
                let block = map.slice(ndarray::s![
                    r * block_px..((r + 1) * block_px).min(ny),
                    c * block_px..((c + 1) * block_px).min(nx)
                ]);
                let v: Vec<f64> = block.iter().copied().filter(|v| v.is_finite()).collect();
                log_ratio.push((!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64));
            }
        }
        FieldMap {
            block_px,
            rows,
            cols,
            log_ratio,
        }
    }
}

/// The first exposure after each illumination (indices into the sequence), with the
/// illumination's index.
fn first_after(seq: &Sequence) -> Vec<(usize, usize)> {
    seq.illuminations
        .iter()
        .filter_map(|&a| {
            (a + 1..seq.exposures.len())
                .take_while(|k| seq.last_illumination[*k] == Some(a))
                .find(|k| !seq.illuminations.contains(k))
                .map(|k| (a, k))
        })
        .collect()
}

/// Each event's demeaned log ratio (module docs, "Statistic"), in the order of the
/// sequence's illuminations (those with an exposure after them).
pub fn log_ratios(seq: &Sequence, params: &ModelParams) -> Result<Vec<EventRatio>> {
    ratios_after(seq, params, &first_after(seq))
}

/// [`log_ratios`] at the given (illumination, first exposure after it) pairs.
fn ratios_after(
    seq: &Sequence,
    params: &ModelParams,
    firsts: &[(usize, usize)],
) -> Result<Vec<EventRatio>> {
    let (ny, nx) = (seq.ny, seq.nx);
    let pixels: Vec<(usize, usize)> = (0..ny).flat_map(|y| (0..nx).map(move |x| (y, x))).collect();
    let s = Samples::with_pixels_where(seq, pixels, 1, |k| firsts.iter().any(|f| f.1 == k));
    let pr = eval::predict(params, seq, &s, false)?;
    let np = s.npix();
    Ok(s.exposures
        .iter()
        .enumerate()
        .map(|(row, &k)| {
            let a = firsts.iter().find(|f| f.1 == k).map_or(0, |f| f.0);
            let at = |p: usize| row * np + p;
            let near = near_sharp_features(&super::data::fluence(&seq.exposures[a]));
            let mut r: Vec<f64> = (0..np)
                .map(|p| {
                    let (m, q) = (s.measured[at(p)], pr.current[at(p)]);
                    if !near[s.pixels[p]] && q > MIN_PREDICTED_E_PER_S && m > 0.0 && m.is_finite() {
                        (m / q).ln()
                    } else {
                        f64::NAN
                    }
                })
                .collect();
            let mut bins: std::collections::BTreeMap<i64, Vec<usize>> = Default::default();
            for p in (0..np).filter(|&p| r[p].is_finite()) {
                let f = s.fluence_e[at(p)].max(1.0);
                let b = (FLUENCE_BINS_PER_DECADE * f.log10()).floor() as i64;
                bins.entry(b).or_default().push(p);
            }
            for members in bins.values() {
                let v: Vec<f64> = members.iter().map(|&p| r[p]).collect();
                let med = crate::stats::median(&v);
                for &p in members {
                    r[p] -= med;
                }
            }
            EventRatio {
                illumination_exposure_index: seq.exposures[a].meta.exposure_index,
                ratio: Array2::from_shape_vec((ny, nx), r).expect("ny * nx values"),
            }
        })
        .collect())
}

/// The pixels next to a far brighter neighbour ([`super::data::neighbour_dominated`])
/// and every pixel within one step of them (diagonals and the bright source itself):
/// what couples neighbours (charge spilled, inter-pixel capacitance) moves them by the
/// same amount in every event of a fixed pattern of sharp sources, a field that is not
/// a trap density (module docs, "Sharp features").
pub fn near_sharp_features(fluence_e: &Array2<f64>) -> Array2<bool> {
    let dominated = super::data::neighbour_dominated(fluence_e);
    let (ny, nx) = dominated.dim();
    let mut near = dominated.clone();
    for ((y, x), _) in dominated.indexed_iter().filter(|(_, d)| **d) {
        for yy in y.saturating_sub(1)..(y + 2).min(ny) {
            for xx in x.saturating_sub(1)..(x + 2).min(nx) {
                near[[yy, xx]] = true;
            }
        }
    }
    near
}

/// `v` smoothed over `length_px` (module docs): NaN is no value; NaN where no value is
/// within reach.
pub fn smooth(v: &Array2<f64>, length_px: f64) -> Array2<f64> {
    let h = (length_px / 2.0).round().max(1.0) as usize;
    let mut val = v.mapv(|x| if x.is_finite() { x } else { 0.0 });
    let mut w = v.mapv(|x| f64::from(u8::from(x.is_finite())));
    for _ in 0..3 {
        val = crate::sim::analysis::box_blur(&val, h);
        w = crate::sim::analysis::box_blur(&w, h);
    }
    ndarray::Zip::from(&val)
        .and(&w)
        .map_collect(|a, b| if *b > 1e-9 { a / b } else { f64::NAN })
}

/// `R^2` of the least-squares line of `y` on `x` over the elements where both are
/// finite; NaN with fewer than 3, 0 when either is constant.
pub fn r2(x: &Array2<f64>, y: &Array2<f64>) -> f64 {
    let pts: Vec<(f64, f64)> = x
        .iter()
        .zip(y)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(a, b)| (*a, *b))
        .collect();
    let n = pts.len() as f64;
    if n < 3.0 {
        return f64::NAN;
    }
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let (mut sxy, mut sxx, mut syy) = (0.0, 0.0, 0.0);
    for (a, b) in &pts {
        sxy += (a - mx) * (b - my);
        sxx += (a - mx).powi(2);
        syy += (b - my).powi(2);
    }
    if sxx == 0.0 || syy == 0.0 {
        return 0.0;
    }
    sxy * sxy / (sxx * syy)
}

/// Mean over the ordered pairs of events of `r2(map(A), r_B)`.
fn mean_transfer(ratios: &[EventRatio], maps: &[&Array2<f64>]) -> f64 {
    let mut v = Vec::new();
    for (i, m) in maps.iter().enumerate() {
        for (j, e) in ratios.iter().enumerate() {
            if i != j {
                v.push(r2(m, &e.ratio));
            }
        }
    }
    let v: Vec<f64> = v.into_iter().filter(|x| x.is_finite()).collect();
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

/// The spatial coherence of `params`' residuals on `seq` (module docs); `None` with
/// fewer than two events.
pub fn coherence(seq: &Sequence, params: &ModelParams) -> Result<Option<Coherence>> {
    let firsts = first_after(seq);
    if firsts.len() < 2 {
        // before running the model
        return Ok(None);
    }
    Ok(coherence_of(&ratios_after(seq, params, &firsts)?))
}

/// The mean of the events' ratios where each is defined (NaN where none is).
pub fn mean_ratio(ratios: &[EventRatio]) -> Array2<f64> {
    let dim = ratios.first().map_or((0, 0), |e| e.ratio.dim());
    let mut sum = Array2::<f64>::zeros(dim);
    let mut cnt = Array2::<f64>::zeros(dim);
    for e in ratios {
        ndarray::Zip::from(&mut sum)
            .and(&mut cnt)
            .and(&e.ratio)
            .for_each(|s, c, v| {
                if v.is_finite() {
                    *s += v;
                    *c += 1.0;
                }
            });
    }
    ndarray::Zip::from(&sum)
        .and(&cnt)
        .map_collect(|s, c| if *c > 0.0 { s / c } else { f64::NAN })
}

/// [`coherence`] of given ratios.
pub fn coherence_of(ratios: &[EventRatio]) -> Option<Coherence> {
    let n = ratios.len();
    if n < 2 {
        return None;
    }
    let raw: Vec<&Array2<f64>> = ratios.iter().map(|e| &e.ratio).collect();
    let r2_smoothed: Vec<(f64, f64)> = LENGTHS_PX
        .iter()
        .map(|&l| {
            let maps: Vec<Array2<f64>> = ratios.iter().map(|e| smooth(&e.ratio, l)).collect();
            (l, mean_transfer(ratios, &maps.iter().collect::<Vec<_>>()))
        })
        .collect();
    let (best_length_px, best_r2) =
        r2_smoothed
            .iter()
            .copied()
            .fold(
                (f64::NAN, f64::NEG_INFINITY),
                |b, c| if c.1 > b.1 { c } else { b },
            );
    // the mean over the events where defined, then smoothed: where the field is
    let map = smooth(&mean_ratio(ratios), best_length_px);
    let finite = || map.indexed_iter().filter(|(_, v)| v.is_finite());
    let at = |(p, v): ((usize, usize), &f64)| (p, v.exp());
    let highest = finite().max_by(|a, b| a.1.total_cmp(b.1)).map(at);
    let lowest = finite().min_by(|a, b| a.1.total_cmp(b.1)).map(at);
    let mut counts: Vec<f64> = ratios
        .iter()
        .map(|e| e.ratio.iter().filter(|v| v.is_finite()).count() as f64)
        .collect();
    counts.sort_by(f64::total_cmp);
    Some(Coherence {
        events: n,
        pairs: n * (n - 1),
        pixels_per_event: counts[n / 2] as usize,
        r2_raw: mean_transfer(ratios, &raw),
        r2_smoothed,
        best_length_px,
        best_r2,
        threshold: COHERENT_R2,
        coherent: best_r2 >= COHERENT_R2,
        highest,
        lowest,
        field: FieldMap::of(&map),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A one-pixel source far above saturation: its four neighbours are dominated by
    /// it, and they, the source and the pixels one step from them are left out; a
    /// smooth image leaves nothing out.
    #[test]
    fn pixels_around_a_sharp_source_are_left_out_and_a_smooth_image_keeps_all() {
        let mut f = Array2::from_elem((9, 9), 1.0e4);
        f[[4, 4]] = 1.0e7;
        let near = near_sharp_features(&f);
        for p in [(4, 4), (3, 4), (4, 5), (3, 3), (2, 4), (6, 4), (4, 2)] {
            assert!(near[p], "{p:?} is next to the source");
        }
        for p in [(2, 2), (6, 6), (0, 0), (4, 7), (1, 4)] {
            assert!(!near[p], "{p:?} is two steps from every dominated pixel");
        }
        let smooth = Array2::from_shape_fn((9, 9), |(y, x)| 1.0e4 * (1.0 + (y + x) as f64));
        assert!(!near_sharp_features(&smooth).iter().any(|b| *b));
    }

    /// A field shared by neighbours is carried by the smoothed map; independent pixel
    /// values are carried raw but not smoothed.
    #[test]
    fn a_shared_field_is_coherent_and_independent_pixels_are_not() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let (ny, nx) = (64, 64);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let mut noise = || -> Array2<f64> {
            Array2::from_shape_fn((ny, nx), |_| StandardNormal.sample(&mut rng))
        };
        // the field: white noise smoothed as the simulator does, unit variance
        let f = crate::sim::effects::populations::field(ny, nx, 8.0, 3, &[1]);
        let own = noise();
        let event = |shared: &Array2<f64>, n: Array2<f64>| EventRatio {
            illumination_exposure_index: 0,
            ratio: shared + &own + &(n * 0.3),
        };
        let zero = Array2::<f64>::zeros((ny, nx));
        let with: Vec<EventRatio> = (0..3).map(|_| event(&f, noise())).collect();
        let without: Vec<EventRatio> = (0..3).map(|_| event(&zero, noise())).collect();
        let (c1, c0) = (
            coherence_of(&with).unwrap(),
            coherence_of(&without).unwrap(),
        );
        assert_eq!((c1.events, c1.pairs), (3, 6));
        assert!(c1.coherent && c1.best_r2 > 0.3, "{c1:?}");
        assert!(!c0.coherent && c0.best_r2 < 0.05, "{c0:?}");
        // the pixel's own part repeats in both: raw R^2 about (1 / (1 + 0.09))^2 = 0.84
        assert!((c0.r2_raw - 0.84).abs() < 0.03, "{c0:?}");
        assert!(coherence_of(&with[..1]).is_none());
        // the field's own extremes, smoothed again: near them
        let ((y, x), hi) = c1.highest.unwrap();
        let ((y0, x0), lo) = c1.lowest.unwrap();
        assert!(hi > 1.0 && lo < 1.0, "{hi} {lo}");
        let fs = smooth(&f, c1.best_length_px);
        let top = fs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let bottom = fs.iter().copied().fold(f64::INFINITY, f64::min);
        assert!(fs[[y, x]] > 0.5 * top, "{} vs {top}", fs[[y, x]]);
        assert!(fs[[y0, x0]] < 0.5 * bottom, "{} vs {bottom}", fs[[y0, x0]]);
    }

    #[test]
    fn field_map_blocks_average_and_cover_the_array() {
        let m = Array2::from_shape_fn((130, 70), |(y, x)| if x < 35 { y as f64 } else { f64::NAN });
        let f = FieldMap::of(&m);
        // 130 / 64 -> blocks of 3 px: 44 x 24
        assert_eq!((f.block_px, f.rows, f.cols), (3, 44, 24));
        assert_eq!(f.log_ratio.len(), 44 * 24);
        assert_eq!(f.log_ratio[0], Some(1.0)); // rows 0-2
        assert_eq!(f.log_ratio[43 * 24], Some(129.0)); // the last block: row 129 only
        assert_eq!(f.log_ratio[23], None); // x 69: no value
        let small = FieldMap::of(&Array2::<f64>::zeros((8, 8)));
        assert_eq!((small.block_px, small.rows, small.cols), (1, 8, 8));
    }

    #[test]
    fn smoothing_keeps_a_constant_and_fills_gaps() {
        let mut v = Array2::<f64>::from_elem((9, 9), 2.0);
        v[[4, 4]] = f64::NAN;
        let s = smooth(&v, 4.0);
        assert!(s.iter().all(|x| (x - 2.0).abs() < 1e-12), "{s:?}");
        let empty = Array2::<f64>::from_elem((5, 5), f64::NAN);
        assert!(smooth(&empty, 4.0).iter().all(|x| x.is_nan()));
    }
}
