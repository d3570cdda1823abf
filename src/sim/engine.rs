//! The per-pixel integration engine: trap occupancies through slews and exposures,
//! the ramp, the on-board fit, noise and flags. Shared by the lab and sky scenarios.
//!
//! # One exposure of one pixel
//! Photon flux `phi` (e-/s) falls for `t_on` seconds of a `T`-second integration, dark
//! current throughout. Charge `Q(t) = (phi + dark) t` rises to full well `Q_fw`, then
//! the excess `Q_ex` forward-biases the diode (traps module docs). The integration is
//! cut into segments of constant condition: 4 rising sub-steps (1 if the pixel stays
//! below 1 % of full well), 3 saturated sub-steps, and the time after `t_on`; each bin
//! then follows the closed form of [`super::traps`]. Dim pixels (the vast majority of
//! sky pixels) are one segment whose `exp(-T/tau)` factors are computed once per
//! exposure per bin, not per pixel.
//!
//! # Slope
//! The on-board slope is linear in the samples, so it is the sum of the slope of the
//! linear signal (`phi + dark`, exact: the fit uses only samples while illuminated and
//! below half full well) and, per bin, `(n0 - n_eq) W_j(m)` with
//! `W_j(m) = sum_i w_i (1 - exp(-t_i/tau_j))` precomputed per exposure (least squares
//! with `linefit_bias`, the chord between first and last used sample without). For
//! pixels with several segments the persistence term uses the first segment's
//! condition (an approximation; such pixels are bright, where persistence is < 1 % of
//! the signal). Noise: closed form of [`super::detector`], one normal draw per pixel.
//! Where `/ramp` is written, the samples are built explicitly (same bins, cumulative
//! Poisson (Gaussian) shot noise, read noise per sample) and the slope is fitted from
//! them; a test checks both paths agree without noise.
//!
//! # Truth
//! The true persistence current of an exposure is the mean, over the integration, of
//! the current emitted by the charge trapped *before* it began:
//! `sum_j n_j(start) (1 - exp(-T/tau_e,j)) / T` (e-/s). It excludes capture and
//! re-emission within the exposure itself, which no flagging model predicts.

use super::detector::{DetectorParams, FitTables};
use super::effect::{CapacityCtx, EffectSet};
use super::rng::{purpose, stream};
use super::traps::{draw_pixels, Bins, PixelTraps, TrapParams};
use crate::flags::bits;
use ndarray::{Array1, Array2, Array3};
use rand::Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use std::sync::Arc;

/// One detector's simulated history.
#[derive(Debug)]
pub struct SimDetector {
    pub detector: u8,
    pub seed: u64,
    pub traps: TrapParams,
    pub det: DetectorParams,
    pub pixels: PixelTraps,
    pub bins: Bins,
    pub effects: Arc<EffectSet>,
    occ: Vec<f32>,
    ny: usize,
    nx: usize,
}

/// What to integrate.
#[derive(Debug, Clone)]
pub struct ExposureSpec<'a> {
    pub index: u64,
    /// Photon flux while illuminated, e-/s (without dark current). [ny, nx]
    pub flux: &'a Array2<f32>,
    pub t_exposure_s: f64,
    /// Seconds of illumination from the reset (`<= t_exposure_s`).
    pub t_on_s: f64,
    pub temp_k: f64,
    pub write_ramp: bool,
}

impl<'a> ExposureSpec<'a> {
    /// The paper's laboratory illumination (section "Persistence measurements"): a 613 s
    /// integration lit for its first 481 s, at 80 K, without a ramp.
    pub fn paper_illumination(index: u64, flux: &'a Array2<f32>) -> Self {
        ExposureSpec {
            index,
            flux,
            t_exposure_s: 613.0,
            t_on_s: 481.0,
            temp_k: 80.0,
            write_ramp: false,
        }
    }

    /// One of the paper's 180 s dark integrations after it (lit the whole time by
    /// `flux`, zeros for a true dark), at 80 K, without a ramp.
    pub fn paper_dark(index: u64, flux: &'a Array2<f32>) -> Self {
        ExposureSpec {
            index,
            flux,
            t_exposure_s: 180.0,
            t_on_s: 180.0,
            temp_k: 80.0,
            write_ramp: false,
        }
    }
}

/// What one exposure produced.
#[derive(Debug, Clone)]
pub struct ExposureOut {
    pub image: Array2<f32>,
    pub flags: Array2<u32>,
    pub ramp: Option<Array3<f32>>,
    pub ramp_times_s: Option<Array1<f64>>,
    /// True mean persistence current of the integration, e-/s.
    pub true_persistence: Array2<f32>,
    /// The photon flux actually integrated (after illumination effects), e-/s.
    pub flux: Array2<f32>,
}

struct Plan {
    nb: usize,
    n_s: usize,
    t_exp: f64,
    t_on: f64,
    tau_e: Vec<f64>,
    tau_f: Vec<f64>,
    f_eq: Vec<f32>,
    ed_t: Vec<f32>,
    ef_t: Vec<f32>,
    k_truth: Vec<f32>,
    /// per-sample factors for the explicit ramp
    ed_dt: Vec<f32>,
    ef_dt: Vec<f32>,
    /// [m * nb + j], selected (LS or chord) and LS
    wd: Vec<f32>,
    wf: Vec<f32>,
    wd_ls: Vec<f32>,
    wf_ls: Vec<f32>,
    fit: FitTables,
    share: f64,
    bins_per_decade: f64,
    cr_prob: f64,
}

impl Plan {
    fn new(b: &Bins, t_exp: f64, t_on: f64, det: &DetectorParams, ls: bool) -> Plan {
        let nb = b.len();
        let tau_e = b.tau_e.clone();
        let tau_f: Vec<f64> = (0..nb).map(|j| b.tau_fill(j)).collect();
        let f_eq = (0..nb).map(|j| b.f_eq(j) as f32).collect();
        let ed_t = tau_e.iter().map(|t| (-t_exp / t).exp() as f32).collect();
        let ef_t = tau_f.iter().map(|t| (-t_exp / t).exp() as f32).collect();
        let k_truth = tau_e
            .iter()
            .map(|t| (-(-t_exp / t).exp_m1() / t_exp) as f32)
            .collect();
        let dt = det.frame_time_s;
        let ed_dt = tau_e.iter().map(|t| (-dt / t).exp() as f32).collect();
        let ef_dt = tau_f.iter().map(|t| (-dt / t).exp() as f32).collect();
        let fit = FitTables::new(t_exp, dt);
        let n_s = fit.n_samples();
        // g[i][j] = 1 - exp(-t_i/tau)
        let g = |taus: &[f64]| -> Vec<f64> {
            let mut g = vec![0.0; n_s * nb];
            for i in 0..n_s {
                for j in 0..nb {
                    g[i * nb + j] = -(-fit.times[i] / taus[j]).exp_m1();
                }
            }
            g
        };
        let gd = g(&tau_e);
        let gf = g(&tau_f);
        let mut wd_ls = vec![0f32; (n_s + 1) * nb];
        let mut wf_ls = vec![0f32; (n_s + 1) * nb];
        let mut wd_ch = vec![0f32; (n_s + 1) * nb];
        let mut wf_ch = vec![0f32; (n_s + 1) * nb];
        let mut acc_d = vec![0f64; nb];
        let mut acc_f = vec![0f64; nb];
        for m in 3..=n_s {
            let w = super::detector::ls_weights(&fit.times[..m]);
            acc_d.iter_mut().for_each(|v| *v = 0.0);
            acc_f.iter_mut().for_each(|v| *v = 0.0);
            for (i, wi) in w.iter().enumerate() {
                let (rd, rf) = (&gd[i * nb..(i + 1) * nb], &gf[i * nb..(i + 1) * nb]);
                for j in 0..nb {
                    acc_d[j] += wi * rd[j];
                    acc_f[j] += wi * rf[j];
                }
            }
            let span = fit.times[m - 1] - fit.times[0];
            for j in 0..nb {
                wd_ls[m * nb + j] = acc_d[j] as f32;
                wf_ls[m * nb + j] = acc_f[j] as f32;
                wd_ch[m * nb + j] = ((gd[(m - 1) * nb + j] - gd[j]) / span) as f32;
                wf_ch[m * nb + j] = ((gf[(m - 1) * nb + j] - gf[j]) / span) as f32;
            }
        }
        let (wd, wf) = if ls {
            (wd_ls.clone(), wf_ls.clone())
        } else {
            (wd_ch, wf_ch)
        };
        Plan {
            nb,
            n_s,
            t_exp,
            t_on,
            tau_e,
            tau_f,
            f_eq,
            ed_t,
            ef_t,
            k_truth,
            ed_dt,
            ef_dt,
            wd,
            wf,
            wd_ls,
            wf_ls,
            fit,
            share: b.share,
            bins_per_decade: 1.0 / b.share,
            cr_prob: if det.noise {
                det.cosmic_probability(t_exp)
            } else {
                0.0
            },
        }
    }
}

#[derive(Clone, Copy)]
struct Seg {
    dur: f64,
    e_lin: f64,
    e_sat: f64,
}

struct RowOut {
    image: Vec<f32>,
    flags: Vec<u32>,
    truth: Vec<f32>,
    ramp: Vec<f32>, // [n_s * nx]
}

impl SimDetector {
    pub fn new(
        traps: TrapParams,
        det: DetectorParams,
        effects: Arc<EffectSet>,
        ny: usize,
        nx: usize,
        seed: u64,
        detector: u8,
    ) -> crate::Result<SimDetector> {
        traps.validate()?;
        if ny == 0 || nx == 0 {
            return Err(crate::Error::invalid("--size", "must be >= 1"));
        }
        let mut pixels = draw_pixels(&traps, &det, ny, nx, seed, detector);
        for e in &effects.list {
            e.trap_pixels(&mut pixels, &traps, seed, detector);
        }
        let bins = Bins::new(&traps);
        let nb = bins.len();
        Ok(SimDetector {
            detector,
            seed,
            traps,
            det,
            pixels,
            bins,
            effects,
            occ: vec![0.0; ny * nx * nb],
            ny,
            nx,
        })
    }

    /// With explicit pixels (calibration, tests).
    pub fn with_pixels(mut self, pixels: PixelTraps) -> SimDetector {
        assert_eq!(pixels.d_lin.dim(), (self.ny, self.nx));
        self.pixels = pixels;
        self
    }

    pub fn dim(&self) -> (usize, usize) {
        (self.ny, self.nx)
    }

    fn bins_at(&self, temp_k: f64) -> Bins {
        let mut b = self.bins.clone();
        for e in &self.effects.list {
            e.time_constants(&mut b, temp_k);
        }
        b
    }

    /// Total trapped charge per pixel, electrons.
    pub fn trapped(&self) -> Array2<f32> {
        let nb = self.bins.len();
        Array2::from_shape_fn((self.ny, self.nx), |(y, x)| {
            let o = (y * self.nx + x) * nb;
            self.occ[o..o + nb].iter().sum()
        })
    }

    /// A reset interval of `d_s` seconds with no charge collected (slew with frequent
    /// resets, or the gap between integrations): every bin only emits.
    pub fn gap(&mut self, d_s: f64, temp_k: f64) {
        if d_s <= 0.0 {
            return;
        }
        let b = self.bins_at(temp_k);
        let e: Vec<f32> = b.tau_e.iter().map(|t| (-d_s / t).exp() as f32).collect();
        let nb = e.len();
        self.occ.par_chunks_mut(nb * self.nx).for_each(|row| {
            for px in row.chunks_exact_mut(nb) {
                for (n, f) in px.iter_mut().zip(&e) {
                    *n *= f;
                }
            }
        });
    }

    /// Integrate one exposure.
    pub fn expose(&mut self, spec: &ExposureSpec<'_>) -> crate::Result<ExposureOut> {
        let (ny, nx) = (self.ny, self.nx);
        if spec.flux.dim() != (ny, nx) {
            return Err(crate::Error::invalid(
                "flux",
                "shape differs from the detector",
            ));
        }
        if !(spec.t_exposure_s > 0.0 && spec.t_on_s >= 0.0 && spec.t_on_s <= spec.t_exposure_s) {
            return Err(crate::Error::invalid(
                "t_exposure_s",
                "need t_exposure_s > 0 and 0 <= t_on_s <= t_exposure_s",
            ));
        }
        if spec.t_exposure_s < 3.0 * self.det.frame_time_s {
            return Err(crate::Error::invalid(
                "t_exposure_s",
                "shorter than three frames: no slope possible",
            ));
        }
        let bins = self.bins_at(spec.temp_k);
        let mut flux = spec.flux.clone();
        // charge that fills traps uncollected: only an illumination with effects has any
        let mut uncollected = None;
        if spec.t_on_s > 0.0 && !self.effects.list.is_empty() {
            let u = uncollected.insert(Array2::<f32>::zeros((ny, nx)));
            for e in &self.effects.list {
                e.illumination(&mut flux, u, spec.t_on_s, &self.pixels.full_well);
            }
        }
        let ls = self.effects.least_squares_persistence();
        let plan = Plan::new(&bins, spec.t_exposure_s, spec.t_on_s, &self.det, ls);
        let nb = plan.nb;
        let has_cap = self.effects.has_capacity();
        let effects = &*self.effects;
        let traps = &self.traps;
        let det = &self.det;
        let pixels = &self.pixels;
        let flux_ref = &flux;
        let uncollected_ref = uncollected.as_ref();
        let (seed, detector, index, write_ramp) =
            (self.seed, self.detector, spec.index, spec.write_ramp);
        let plan_ref = &plan;
        let rows: Vec<RowOut> = self
            .occ
            .par_chunks_mut(nb * nx)
            .enumerate()
            .map(|(y, occ_row)| {
                let mut rng = stream(
                    seed,
                    &[purpose::NOISE, u64::from(detector), index, y as u64],
                );
                let mut out = RowOut {
                    image: vec![0.0; nx],
                    flags: vec![0; nx],
                    truth: vec![0.0; nx],
                    ramp: if write_ramp {
                        vec![0.0; plan_ref.n_s * nx]
                    } else {
                        Vec::new()
                    },
                };
                let mut neq = vec![0f32; nb];
                let mut fac = vec![1f64; nb];
                let mut dirs = vec![false; nb];
                let mut p_buf = vec![0f32; nb];
                for x in 0..nx {
                    let n = &mut occ_row[x * nb..(x + 1) * nb];
                    let px = PixelIn {
                        phi: f64::from(flux_ref[[y, x]].max(0.0)),
                        uncollected_e: uncollected_ref
                            .map_or(0.0, |u| f64::from(u[[y, x]].max(0.0))),
                        fw: f64::from(pixels.full_well[[y, x]]),
                        d_lin: f64::from(pixels.d_lin[[y, x]]),
                        d_sat: f64::from(pixels.d_sat[[y, x]]),
                        nonfunc: pixels.nonfunc[[y, x]],
                    };
                    let r = pixel(
                        plan_ref, traps, det, effects, has_cap, &px, n, &mut neq, &mut fac,
                        &mut dirs, &mut p_buf, &mut rng, write_ramp,
                    );
                    out.image[x] = r.image;
                    out.flags[x] = r.flags;
                    out.truth[x] = r.truth;
                    if write_ramp {
                        for i in 0..plan_ref.n_s {
                            out.ramp[i * nx + x] = r.ramp[i];
                        }
                    }
                }
                out
            })
            .collect();
        let mut image = Array2::<f32>::zeros((ny, nx));
        let mut flags = Array2::<u32>::zeros((ny, nx));
        let mut truth = Array2::<f32>::zeros((ny, nx));
        let mut ramp = write_ramp.then(|| Array3::<f32>::zeros((plan.n_s, ny, nx)));
        for (y, r) in rows.into_iter().enumerate() {
            for x in 0..nx {
                image[[y, x]] = r.image[x];
                flags[[y, x]] = r.flags[x];
                truth[[y, x]] = r.truth[x];
            }
            if let Some(a) = ramp.as_mut() {
                for i in 0..plan.n_s {
                    for x in 0..nx {
                        a[[i, y, x]] = r.ramp[i * nx + x];
                    }
                }
            }
        }
        for e in &self.effects.list {
            e.measured(&mut image, ramp.as_mut());
        }
        let ramp_times_s = write_ramp.then(|| Array1::from(plan.fit.times.clone()));
        Ok(ExposureOut {
            image,
            flags,
            ramp,
            ramp_times_s,
            true_persistence: truth,
            flux,
        })
    }
}

struct PixelIn {
    phi: f64,
    /// Charge that raises the trap fill level from the start of the illumination to the
    /// end of the integration but is never collected, e-; 0 without such an effect
    /// ([`crate::sim::effect::Effect::illumination`]).
    uncollected_e: f64,
    fw: f64,
    d_lin: f64,
    d_sat: f64,
    nonfunc: bool,
}

struct PixelOut {
    image: f32,
    flags: u32,
    truth: f32,
    ramp: Vec<f32>,
}

#[allow(clippy::too_many_arguments)]
fn pixel(
    p: &Plan,
    tp: &TrapParams,
    det: &DetectorParams,
    effects: &EffectSet,
    has_cap: bool,
    px: &PixelIn,
    n: &mut [f32],
    neq: &mut [f32],
    fac: &mut [f64],
    dirs: &mut [bool],
    p0: &mut [f32],
    rng: &mut rand_chacha::ChaCha8Rng,
    write_ramp: bool,
) -> PixelOut {
    let nb = p.nb;
    let dark = det.dark_e_per_s;
    let rate = px.phi + dark;
    let fw = px.fw.max(1.0);
    let t_on = p.t_on;
    // ---- segments
    let mut segs: [Seg; 9] = [Seg {
        dur: 0.0,
        e_lin: 0.0,
        e_sat: 0.0,
    }; 9];
    let mut ns = 0usize;
    let saturated = rate * t_on >= fw;
    let t_s = if saturated { fw / rate } else { t_on };
    let q_rise = rate * t_s;
    // fill rate the traps see while rising: collected plus uncollected charge (the
    // latter arrives while the shutter is open; exactly `rate` without it)
    let r_fill = if t_on > 0.0 {
        rate + px.uncollected_e / t_on
    } else {
        rate
    };
    let single = px.uncollected_e == 0.0 && !saturated && t_on >= p.t_exp && q_rise < 0.01 * fw;
    if single {
        segs[0] = Seg {
            dur: p.t_exp,
            e_lin: (0.5 * rate * p.t_exp / fw).min(1.0),
            e_sat: 0.0,
        };
        ns = 1;
    } else {
        let k = if r_fill * t_s > 0.01 * fw { 4 } else { 1 };
        for i in 0..k {
            let d = t_s / k as f64;
            if d > 0.0 {
                segs[ns] = Seg {
                    dur: d,
                    e_lin: (r_fill * d * (i as f64 + 0.5) / fw).min(1.0),
                    e_sat: 0.0,
                };
                ns += 1;
            }
        }
        let mut e_sat_end = 0.0;
        if saturated {
            let tb = t_on - t_s;
            let q_ex_end = rate * tb;
            for i in 0..3 {
                let d = tb / 3.0;
                if d > 0.0 {
                    segs[ns] = Seg {
                        dur: d,
                        e_lin: 1.0,
                        e_sat: tp.e_sat(q_ex_end * (i as f64 + 0.5) / 3.0, fw),
                    };
                    ns += 1;
                }
            }
            e_sat_end = tp.e_sat(q_ex_end, fw);
        }
        let d = p.t_exp - t_on;
        if d > 0.0 {
            let q = (q_rise + px.uncollected_e + dark * 0.5 * d).min(fw);
            segs[ns] = Seg {
                dur: d,
                e_lin: if saturated { 1.0 } else { q / fw },
                e_sat: e_sat_end,
            };
            ns += 1;
        }
        if ns == 0 {
            segs[0] = Seg {
                dur: p.t_exp,
                e_lin: 0.0,
                e_sat: 0.0,
            };
            ns = 1;
        }
    }
    let fluence = px.phi * t_on;
    // charge the traps hold as the exposure begins (what the capacity hook sees)
    let held = if has_cap {
        n.iter().map(|&v| f64::from(v)).sum()
    } else {
        0.0
    };
    // exposed equilibrium occupancy for a segment
    let fill_neq = |s: &Seg, neq: &mut [f32], fac: &mut [f64]| {
        let c = p.share * (px.d_lin * s.e_lin + px.d_sat * s.e_sat);
        if has_cap {
            fac.iter_mut().for_each(|v| *v = 1.0);
            let ctx = CapacityCtx {
                fluence_e: fluence,
                held_e: held,
                e_lin: s.e_lin,
                e_sat: s.e_sat,
                d_lin: px.d_lin,
                d_sat: px.d_sat,
                bins_per_decade: p.bins_per_decade,
                tau_e: &p.tau_e,
            };
            for e in &effects.list {
                if e.has_capacity() {
                    e.capacity(&ctx, fac);
                }
            }
            for j in 0..nb {
                neq[j] = (c * fac[j]) as f32 * p.f_eq[j];
            }
        } else {
            let c = c as f32;
            for (q, f) in neq.iter_mut().zip(&p.f_eq) {
                *q = c * f;
            }
        }
    };
    // ---- fit sample count
    let m = p.fit.samples_used(rate, t_on, fw);
    let mm = if m >= 3 { m } else { 0 };
    let (wd, wf) = (&p.wd[mm * nb..(mm + 1) * nb], &p.wf[mm * nb..(mm + 1) * nb]);
    // ---- truth, slope term, first segment
    fill_neq(&segs[0], neq, fac);
    let mut truth = 0f32;
    let mut pslope = 0f32;
    let mut pslope_ls = 0f32;
    for j in 0..nb {
        let nj = n[j];
        truth += nj * p.k_truth[j];
        let d = nj - neq[j];
        let drain = d >= 0.0;
        dirs[j] = drain;
        p0[j] = d;
        pslope += d * if drain { wd[j] } else { wf[j] };
        if write_ramp {
            pslope_ls += d * if drain {
                p.wd_ls[mm * nb + j]
            } else {
                p.wf_ls[mm * nb + j]
            };
        }
    }
    // ---- evolve
    for (si, s) in segs[..ns].iter().enumerate() {
        if si > 0 {
            fill_neq(s, neq, fac);
        }
        for j in 0..nb {
            let d = n[j] - neq[j];
            let e = if single {
                if d >= 0.0 {
                    p.ed_t[j]
                } else {
                    p.ef_t[j]
                }
            } else {
                let tau = if d >= 0.0 { p.tau_e[j] } else { p.tau_f[j] };
                (-s.dur / tau).exp() as f32
            };
            n[j] = neq[j] + d * e;
        }
    }
    // ---- measurement
    let mut flags = 0u32;
    if saturated {
        flags |= bits::OVERFLOW;
    }
    let mut hit: Option<(usize, f64)> = None;
    if p.cr_prob > 0.0 && rng.random::<f64>() < p.cr_prob {
        let k = rng.random_range(0..p.n_s);
        let e = 300.0 * (20_000f64 / 300.0).powf(rng.random::<f64>());
        hit = Some((k, e));
        flags |= bits::TRANSIENT;
    }
    let mut ramp = Vec::new();
    let mut image;
    if write_ramp {
        ramp = vec![0f32; p.n_s];
        let mut rem: Vec<f32> = p0.to_vec();
        let total: f32 = p0.iter().sum();
        let mut shot = 0f64;
        let mut prev = 0f64;
        for (i, &t) in p.fit.times.iter().enumerate() {
            let mut left = 0f32;
            for j in 0..nb {
                rem[j] *= if dirs[j] { p.ed_dt[j] } else { p.ef_dt[j] };
                left += rem[j];
            }
            let lin = rate * t.min(t_on) + dark * (t - t_on).max(0.0);
            let s = (lin + f64::from(total - left)).min(fw);
            if det.noise {
                let inc = (s - prev).max(0.0);
                let z: f64 = StandardNormal.sample(rng);
                shot += z * inc.sqrt();
            }
            prev = s;
            let mut v = s + shot;
            if det.noise {
                let z: f64 = StandardNormal.sample(rng);
                v += det.read_noise_e * z;
            }
            if let Some((k, e)) = hit {
                if i >= k {
                    v += e;
                }
            }
            ramp[i] = v as f32;
        }
        image = if mm >= 3 {
            // on-board fit with the jump removed
            let y: Vec<f64> = (0..mm)
                .map(|i| {
                    let j = match hit {
                        Some((k, e)) if i >= k => e,
                        _ => 0.0,
                    };
                    f64::from(ramp[i]) - j
                })
                .collect();
            let ls = super::detector::ls_slope(&p.fit.times[..mm], &y);
            (ls - f64::from(pslope_ls) + f64::from(pslope)) as f32
        } else {
            f32::NAN
        };
    } else {
        image = if mm >= 3 {
            let mut v = rate + f64::from(pslope);
            if det.noise {
                let f = rate + f64::from(pslope.max(0.0));
                let var = det.read_noise_e.powi(2) * p.fit.v_read[mm] + f * p.fit.v_shot[mm];
                let z: f64 = StandardNormal.sample(rng);
                v += z * var.sqrt();
            }
            v as f32
        } else {
            f32::NAN
        };
    }
    if mm < 3 {
        flags |= bits::SUR_ERROR;
    }
    if px.nonfunc {
        flags |= bits::NONFUNC;
        image = f32::NAN;
    }
    PixelOut {
        image,
        flags,
        truth,
        ramp,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sim(ny: usize, nx: usize, noise: bool, ls: bool) -> SimDetector {
        let det = DetectorParams {
            noise,
            nonfunc_fraction: 0.0,
            ..Default::default()
        };
        let specs: Vec<super::super::effect::EffectSpec> = if ls {
            vec!["linefit_bias".parse().unwrap()]
        } else {
            vec![]
        };
        let eff = Arc::new(EffectSet::from_specs(&specs).unwrap());
        SimDetector::new(TrapParams::default(), det, eff, ny, nx, 7, 1).unwrap()
    }

    fn illuminate(s: &mut SimDetector) {
        let (ny, nx) = s.dim();
        let flux =
            Array2::from_shape_fn((ny, nx), |(y, x)| 50.0 * 2f32.powi((y * nx + x) as i32 % 9));
        s.expose(&ExposureSpec::paper_illumination(0, &flux))
            .unwrap();
    }

    /// The fast (weights) path and the explicit ramp agree without noise.
    #[test]
    fn fast_slope_equals_fit_of_explicit_ramp() {
        for ls in [false, true] {
            let mut a = sim(4, 6, false, ls);
            illuminate(&mut a);
            let zero = Array2::<f32>::zeros((4, 6));
            let mut spec = ExposureSpec::paper_dark(1, &zero);
            let mut b = sim(4, 6, false, ls);
            illuminate(&mut b);
            let fast = a.expose(&spec).unwrap();
            spec.write_ramp = true;
            let slow = b.expose(&spec).unwrap();
            let ramp = slow.ramp.unwrap();
            let t = slow.ramp_times_s.unwrap().to_vec();
            for y in 0..4 {
                for x in 0..6 {
                    let (f, s) = (fast.image[[y, x]], slow.image[[y, x]]);
                    assert!((f - s).abs() <= 1e-3 * f.abs().max(0.05), "{ls} {f} {s}");
                    if ls {
                        let col: Vec<f64> =
                            (0..t.len()).map(|i| f64::from(ramp[[i, y, x]])).collect();
                        let fit = super::super::detector::ls_slope(&t, &col) as f32;
                        assert!((fit - s).abs() <= 1e-3 * s.abs().max(0.05), "{fit} {s}");
                    }
                }
            }
            assert_eq!(fast.true_persistence, slow.true_persistence);
        }
    }

    #[test]
    fn dark_after_illumination_shows_persistence_and_decays() {
        let mut a = sim(3, 3, false, false);
        illuminate(&mut a);
        let zero = Array2::<f32>::zeros((3, 3));
        let spec = ExposureSpec::paper_dark(1, &zero);
        let first = a.expose(&spec).unwrap();
        a.gap(3600.0, 80.0);
        let later = a.expose(&spec).unwrap();
        for (f, l) in first
            .true_persistence
            .iter()
            .zip(later.true_persistence.iter())
        {
            assert!(*f > 0.0 && l < f);
        }
    }
}
