//! The generator's integration of one array through a sequence (physics in the module
//! docs of [`crate::trapgen`]).

use super::hidden::Hidden;
use super::readout::{self, LineFit};
use super::scene::{purpose, Nuisance, T_REF_K};
use super::traps::{self, Grid};
use crate::flags::bits;
use crate::sim::rng;
use ndarray::{Array2, Array3};
use rand::Rng;
use rand_distr::{Distribution, Normal, Poisson};
use rayon::prelude::*;

/// Emission times above which `soak:capture` slows capture, s.
pub const SOAK_SLOW_TAU_S: f64 = 1.0e3;
/// `soak:capture`: the slow nodes' capture rate, 1/s.
pub const SOAK_CAPTURE_PER_S: f64 = 1.0 / 400.0;
/// `soak:diffusion`: the deep population's diffusion time, s, its sites relative to
/// the pixel's, and its emission-time density (log-normal centre, width).
pub const DIFFUSION_TAU_S: f64 = 2000.0;
pub const DIFFUSION_SITES: f64 = 0.35;
pub const DIFFUSION_LOG10_TAU_S: f64 = 3.7;
pub const DIFFUSION_SIGMA_DEX: f64 = 0.5;
/// `capacity:ceiling`: the most charge a pixel's traps hold, relative to its sites.
pub const CEILING_SITES: f64 = 0.6;
/// `capacity:langmuir`: the pixel's shared site pool, relative to its sites.
pub const LANGMUIR_SITES: f64 = 0.8;
/// `temperature:arrhenius`: activation energy over Boltzmann's constant, K.
pub const ARRHENIUS_K: f64 = 1500.0;
/// `temperature:weight`: relative change of the power-law population's sites per K.
pub const WEIGHT_PER_K: f64 = 0.12;
/// `blooming:spill`: fraction of a neighbour's charge above full well that spills into
/// each of the four neighbours' wells, and how much more it exposes traps than bulk
/// charge (it travels along the trap-rich surface).
pub const SPILL_FRACTION: f64 = 1.0e-3 / 4.0;
pub const SPILL_TRAP_GAIN: f64 = 4.0;
/// `blooming:field`: exposure added per unit ln(1 + excess / full well) of a cardinal
/// neighbour (a diagonal one: half).
pub const FIELD_LAMBDA: f64 = 0.01;
/// `ipc:cross4`: coupling to each of the four neighbours.
pub const IPC_CROSS: f64 = 0.02;
/// `ipc:aniso8`: coupling along rows (x), columns (y) and to each diagonal.
pub const IPC_ANISO: [f64; 3] = [0.025, 0.01, 0.004];
/// `shape:fill_depth`: slope of the power-law population's weights in ln k per unit
/// ln(1 + fluence / full well).
pub const FILL_DEPTH: f64 = 0.1;
/// `shape:fast_ceiling`: the fast population's largest exposure fraction.
pub const FAST_CEILING: f64 = 0.15;
/// Sub-steps of the trap integration while lit, and after the shutter.
const LIT_STEPS: usize = 60;
const HELD_STEPS: usize = 6;

/// How a population fills.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Fill {
    Capture,
    /// Reaches `target * sqrt(min(1, t / tau))` of the time since the illumination
    /// began, immediately (diffusion into a deep layer), and emits as the others.
    Diffusion,
}

#[derive(Debug, Clone)]
struct Pop {
    weights: Vec<f64>,
    /// Sites per pixel (e-) at exposure fraction 1.
    sites: Vec<f64>,
    fill: Fill,
    power_law: bool,
    fast: bool,
}

/// What one exposure gives.
pub struct Out {
    pub image: Array2<f32>,
    pub flags: Array2<u32>,
    pub ramp: Option<Array3<f32>>,
    pub ramp_times_s: Option<ndarray::Array1<f64>>,
    pub true_persistence: Array2<f32>,
}

/// One array's traps through a sequence.
pub struct Engine {
    pub n: usize,
    seed: u64,
    pub nu: Nuisance,
    grid: Grid,
    pops: Vec<Pop>,
    /// Trapped charge, e-: [pixel][population][node].
    q: Vec<f64>,
    full_well: Vec<f64>,
    hidden: Vec<Hidden>,
}

fn has(h: &[Hidden], x: Hidden) -> bool {
    h.contains(&x)
}

impl Engine {
    pub fn new(nu: Nuisance, size: usize, seed: u64, hidden: &[Hidden]) -> Engine {
        let grid = Grid::default();
        let npix = size * size;
        let mut r = rng::stream(seed, &[purpose::PIXEL_MAPS]);
        let normal = Normal::new(0.0, 1.0).expect("unit normal");
        let full_well: Vec<f64> = (0..npix)
            .map(|_| nu.full_well_e * (1.0 + nu.full_well_scatter * normal.sample(&mut r)))
            .collect();
        let spatial = spatial_map(seed, size, hidden);
        let mut pops = Vec::new();
        for (i, p) in nu.populations.iter().enumerate() {
            let weights = if p.kind == "power_law" {
                grid.power_law(p.beta)
            } else {
                grid.log_normal(p.log10_tau_s, p.sigma_dex)
            };
            let sites = (0..npix)
                .map(|k| {
                    nu.sites_e
                        * p.weight
                        * (nu.site_scatter * normal.sample(&mut r)).exp()
                        * spatial[k]
                })
                .collect();
            pops.push(Pop {
                weights,
                sites,
                fill: Fill::Capture,
                power_law: p.kind == "power_law",
                fast: i == 1,
            });
        }
        if has(hidden, Hidden::SoakDiffusion) {
            let sites = (0..npix)
                .map(|k| nu.sites_e * DIFFUSION_SITES * spatial[k])
                .collect();
            pops.push(Pop {
                weights: grid.log_normal(DIFFUSION_LOG10_TAU_S, DIFFUSION_SIGMA_DEX),
                sites,
                fill: Fill::Diffusion,
                power_law: false,
                fast: false,
            });
        }
        let q = vec![0.0; npix * pops.len() * grid.len()];
        Engine {
            n: size,
            seed,
            nu,
            grid,
            pops,
            q,
            full_well,
            hidden: hidden.to_vec(),
        }
    }

    fn stride(&self) -> usize {
        self.pops.len() * self.grid.len()
    }

    /// Emission rates at `temp_k` (Arrhenius only under `temperature:arrhenius`).
    fn rates(&self, temp_k: f64) -> Vec<f64> {
        let f = if has(&self.hidden, Hidden::TemperatureArrhenius) {
            (ARRHENIUS_K * (1.0 / T_REF_K - 1.0 / temp_k)).exp()
        } else {
            1.0
        };
        self.grid.rates_per_s.iter().map(|k| k * f).collect()
    }

    /// Mean current over `[0, t]` of the charge trapped now, per pixel.
    fn mean_release(&self, rates: &[f64], t_s: f64) -> Vec<f64> {
        let s = self.stride();
        let j = self.grid.len();
        self.q
            .par_chunks(s)
            .map(|qp| {
                qp.chunks(j)
                    .map(|qn| traps::released_between(qn, rates, 0.0, t_s))
                    .sum::<f64>()
                    / t_s
            })
            .collect()
    }

    fn decay(&mut self, rates: &[f64], t_s: f64) {
        let j = self.grid.len();
        let f: Vec<f64> = rates.iter().map(|k| (-k * t_s).exp()).collect();
        self.q.par_chunks_mut(j).for_each(|qn| {
            qn.iter_mut().zip(&f).for_each(|(q, f)| *q *= f);
        });
    }

    /// An illuminated integration: lit `t_ill` s at `flux`, then held to `t_exp`.
    pub fn illuminate(
        &mut self,
        index: u64,
        flux: &Array2<f32>,
        t_ill: f64,
        t_exp: f64,
        temp_k: f64,
    ) -> Out {
        let n = self.n;
        let npix = n * n;
        let rates = self.rates(temp_k);
        let pers = self.mean_release(&rates, t_exp);
        let nu = &self.nu;
        let hidden = self.hidden.clone();
        let fw = &self.full_well;
        let phi: Vec<f64> = flux.iter().map(|v| f64::from(*v)).collect();
        // charge above full well a pixel would have collected by time t (lit part)
        let excess = |p: usize, t: f64| (phi[p] * t.min(t_ill) - fw[p]).max(0.0);
        let neighbours4 = |p: usize| -> Vec<usize> {
            let (y, x) = (p / n, p % n);
            let mut v = Vec::with_capacity(4);
            if y > 0 {
                v.push(p - n);
            }
            if y + 1 < n {
                v.push(p + n);
            }
            if x > 0 {
                v.push(p - 1);
            }
            if x + 1 < n {
                v.push(p + 1);
            }
            v
        };
        let spill = has(&hidden, Hidden::BloomingSpill);
        let field = has(&hidden, Hidden::BloomingField);
        // spilled charge into p by time t
        let spilled = |p: usize, t: f64| -> f64 {
            if !spill {
                return 0.0;
            }
            neighbours4(p)
                .into_iter()
                .map(|o| SPILL_FRACTION * excess(o, t))
                .sum()
        };
        let field_term = |p: usize, t: f64| -> f64 {
            if !field {
                return 0.0;
            }
            let (y, x) = ((p / n) as i64, (p % n) as i64);
            let mut s = 0.0;
            for dy in -1i64..=1 {
                for dx in -1i64..=1 {
                    if dy == 0 && dx == 0 {
                        continue;
                    }
                    let (yy, xx) = (y + dy, x + dx);
                    if yy < 0 || xx < 0 || yy >= n as i64 || xx >= n as i64 {
                        continue;
                    }
                    let o = (yy as usize) * n + xx as usize;
                    let w = if dy == 0 || dx == 0 { 1.0 } else { 0.5 };
                    s += w * (1.0 + excess(o, t) / fw[o]).ln();
                }
            }
            FIELD_LAMBDA * s
        };
        // raw charge (without the well's limit) at t
        let raw = |p: usize, t: f64| -> f64 {
            (phi[p] + nu.dark_e_per_s + pers[p]) * t.min(t_ill)
                + (nu.dark_e_per_s + pers[p]) * (t - t_ill).max(0.0)
                + spilled(p, t)
        };
        let exposure = |p: usize, t: f64| -> f64 {
            let r = raw(p, t);
            let mut f = r.min(fw[p]) / fw[p];
            if r >= fw[p] {
                f +=
                    nu.saturation_jump + nu.saturation_log_slope * (1.0 + (r - fw[p]) / fw[p]).ln();
            }
            f + SPILL_TRAP_GAIN * spilled(p, t) / fw[p] + field_term(p, t)
        };
        let capture =
            |p: usize| nu.capture_per_s * phi[p] / (phi[p] + nu.capture_half_flux_e_per_s);
        let temp_weight = if has(&hidden, Hidden::TemperatureWeight) {
            (1.0 + WEIGHT_PER_K * (temp_k - T_REF_K)).max(0.0)
        } else {
            1.0
        };
        let soak_capture = has(&hidden, Hidden::SoakCapture);
        let ceiling = has(&hidden, Hidden::CapacityCeiling);
        let langmuir = has(&hidden, Hidden::CapacityLangmuir);
        let fill_depth = has(&hidden, Hidden::ShapeFillDepth);
        let fast_ceiling = has(&hidden, Hidden::ShapeFastCeiling);
        // sub-step boundaries
        let mut edges: Vec<f64> = (0..=LIT_STEPS)
            .map(|i| t_ill * i as f64 / LIT_STEPS as f64)
            .collect();
        if t_exp > t_ill {
            edges.extend(
                (1..=HELD_STEPS).map(|i| t_ill + (t_exp - t_ill) * i as f64 / HELD_STEPS as f64),
            );
        }
        let j = self.grid.len();
        let stride = self.stride();
        let pops = &self.pops;
        let grid_rates = &self.grid.rates_per_s;
        let total_sites: Vec<f64> = (0..npix)
            .map(|p| pops.iter().map(|po| po.sites[p]).sum())
            .collect();
        self.q
            .par_chunks_mut(stride)
            .enumerate()
            .for_each(|(p, qp)| {
                let held: f64 = qp.iter().sum();
                let block = if langmuir {
                    (1.0 - held / (LANGMUIR_SITES * total_sites[p])).max(0.0)
                } else {
                    1.0
                };
                let c = capture(p);
                // the power-law population's weights for this fill (fill_depth)
                let depth_weights: Option<Vec<f64>> = fill_depth.then(|| {
                    let u = (1.0 + phi[p] * t_ill / fw[p]).ln();
                    let w: Vec<f64> = pops
                        .iter()
                        .find(|po| po.power_law)
                        .map(|po| {
                            po.weights
                                .iter()
                                .zip(grid_rates)
                                .map(|(w, k)| w * (k / 1e-2).powf(-FILL_DEPTH * u))
                                .collect()
                        })
                        .unwrap_or_default();
                    let s: f64 = w.iter().sum();
                    w.into_iter().map(|v| v / s).collect()
                });
                for win in edges.windows(2) {
                    let (t0, t1) = (win[0], win[1]);
                    let dt = t1 - t0;
                    if dt <= 0.0 {
                        continue;
                    }
                    let tm = 0.5 * (t0 + t1);
                    let f = exposure(p, tm);
                    let mut captured = 0.0;
                    let mut emitted_only = Vec::new();
                    for (pi, po) in pops.iter().enumerate() {
                        let qn = &mut qp[pi * j..(pi + 1) * j];
                        let mut fp = f;
                        if po.fast && fast_ceiling {
                            fp = fp.min(FAST_CEILING);
                        }
                        let mut sites = po.sites[p] * fp * block;
                        if po.power_law {
                            sites *= temp_weight;
                        }
                        let weights = match (&depth_weights, po.power_law) {
                            (Some(w), true) => w,
                            _ => &po.weights,
                        };
                        for (m, q) in qn.iter_mut().enumerate() {
                            let k = rates[m];
                            let target = sites * weights[m];
                            let q_emit = *q * (-k * dt).exp();
                            let q_new = match po.fill {
                                Fill::Capture => {
                                    let cm =
                                        if soak_capture && grid_rates[m] < 1.0 / SOAK_SLOW_TAU_S {
                                            c.min(SOAK_CAPTURE_PER_S)
                                        } else {
                                            c
                                        };
                                    traps::step(*q, target, cm, k, dt)
                                }
                                Fill::Diffusion => {
                                    q_emit.max(target * (tm / DIFFUSION_TAU_S).min(1.0).sqrt())
                                }
                            };
                            if ceiling {
                                captured += (q_new - q_emit).max(0.0);
                                emitted_only.push(q_emit);
                            }
                            *q = q_new;
                        }
                    }
                    if ceiling {
                        let cap = CEILING_SITES * total_sites[p];
                        let after: f64 = qp.iter().sum();
                        if after > cap && captured > 0.0 {
                            let emitted_total: f64 = emitted_only.iter().sum();
                            let room = (cap - emitted_total).max(0.0);
                            let s = (room / captured).min(1.0);
                            for (q, e) in qp.iter_mut().zip(&emitted_only) {
                                *q = e + s * (*q - e).max(0.0);
                            }
                        }
                    }
                }
            });
        // the on-board fit of the lit samples
        let times = readout::sample_times(t_exp);
        let seed = self.seed;
        let read = nu.read_noise_e;
        let results: Vec<(f32, u32)> = (0..npix)
            .into_par_iter()
            .map(|p| {
                let mut r = rng::stream(seed, &[purpose::NOISE, index, p as u64]);
                let rn = Normal::new(0.0, read).expect("read noise");
                let mut prev_mu = 0.0;
                let mut acc = 0.0;
                let (mut ts, mut vs) = (Vec::new(), Vec::new());
                let mut first: Option<(f64, f64)> = None;
                for &t in times.iter().filter(|t| **t <= t_ill + 1e-9) {
                    let mu = raw(p, t);
                    acc += poisson(&mut r, (mu - prev_mu).max(0.0));
                    prev_mu = mu;
                    let v = acc.min(fw[p]) + rn.sample(&mut r);
                    if first.is_none() {
                        first = Some((t, v));
                    }
                    if v >= 0.5 * fw[p] {
                        break;
                    }
                    ts.push(t);
                    vs.push(v);
                }
                let slope = if ts.len() >= 2 {
                    readout::fit_slope(&ts, &vs).unwrap_or(0.0)
                } else {
                    first.map_or(0.0, |(t, v)| v / t)
                };
                let flag = if raw(p, t_exp) >= fw[p] {
                    bits::OVERFLOW
                } else {
                    0
                };
                (slope as f32, flag)
            })
            .collect();
        let mut image =
            Array2::from_shape_vec((n, n), results.iter().map(|r| r.0).collect()).expect("shape");
        let flags =
            Array2::from_shape_vec((n, n), results.iter().map(|r| r.1).collect()).expect("shape");
        let mut truth = Array2::from_shape_vec((n, n), pers.iter().map(|v| *v as f32).collect())
            .expect("shape");
        self.couple(&mut image);
        self.couple(&mut truth);
        Out {
            image,
            flags,
            ramp: None,
            ramp_times_s: None,
            true_persistence: truth,
        }
    }

    /// A dark integration of `t_exp` s; `keep_ramp`: sample and store its ramp.
    pub fn dark(&mut self, index: u64, t_exp: f64, temp_k: f64, keep_ramp: bool) -> Out {
        let n = self.n;
        let npix = n * n;
        let rates = self.rates(temp_k);
        let pers = self.mean_release(&rates, t_exp);
        let fit = LineFit::new(t_exp);
        let seed = self.seed;
        let nu = &self.nu;
        let j = self.grid.len();
        let stride = self.stride();
        let mut ramp = keep_ramp.then(|| Array3::<f32>::zeros((fit.times_s.len(), n, n)));
        let image: Vec<f32> = if keep_ramp {
            let rows: Vec<(f32, Vec<f32>)> = self
                .q
                .par_chunks(stride)
                .enumerate()
                .map(|(p, qp)| {
                    let mut r = rng::stream(seed, &[purpose::NOISE, index, p as u64]);
                    let rn = Normal::new(0.0, nu.read_noise_e).expect("read noise");
                    let released = |t: f64| -> f64 {
                        qp.chunks(j)
                            .map(|qn| traps::released_between(qn, &rates, 0.0, t))
                            .sum::<f64>()
                    };
                    let mut prev = 0.0;
                    let mut acc = 0.0;
                    let mut vals = Vec::with_capacity(fit.times_s.len());
                    for &t in &fit.times_s {
                        let mu = nu.dark_e_per_s * t + released(t);
                        acc += poisson(&mut r, (mu - prev).max(0.0));
                        prev = mu;
                        vals.push((acc.min(self.full_well[p]) + rn.sample(&mut r)) as f32);
                    }
                    let v64: Vec<f64> = vals.iter().map(|v| f64::from(*v)).collect();
                    let slope = readout::fit_slope(&fit.times_s, &v64).unwrap_or(0.0);
                    (slope as f32, vals)
                })
                .collect();
            if let Some(ramp) = ramp.as_mut() {
                for (p, (_, vals)) in rows.iter().enumerate() {
                    for (i, v) in vals.iter().enumerate() {
                        ramp[[i, p / n, p % n]] = *v;
                    }
                }
            }
            rows.into_iter().map(|r| r.0).collect()
        } else {
            let gains = fit.gains(&rates);
            self.q
                .par_chunks(stride)
                .enumerate()
                .map(|(p, qp)| {
                    let mut r = rng::stream(seed, &[purpose::NOISE, index, p as u64]);
                    let det: f64 = nu.dark_e_per_s
                        + qp.chunks(j)
                            .map(|qn| qn.iter().zip(&gains).map(|(q, g)| q * g).sum::<f64>())
                            .sum::<f64>();
                    let sd = fit.slope_sd(nu.read_noise_e, nu.dark_e_per_s + pers[p]);
                    let z: f64 = Normal::new(0.0, 1.0).expect("unit").sample(&mut r);
                    (det + sd * z) as f32
                })
                .collect()
        };
        let _ = npix;
        self.decay(&rates, t_exp);
        let mut image = Array2::from_shape_vec((n, n), image).expect("shape");
        let mut truth = Array2::from_shape_vec((n, n), pers.iter().map(|v| *v as f32).collect())
            .expect("shape");
        self.couple(&mut image);
        self.couple(&mut truth);
        if let Some(ramp) = ramp.as_mut() {
            for mut frame in ramp.outer_iter_mut() {
                let mut f = frame.to_owned();
                self.couple(&mut f);
                frame.assign(&f);
            }
        }
        Out {
            image,
            flags: Array2::zeros((n, n)),
            ramp,
            ramp_times_s: keep_ramp.then(|| ndarray::Array1::from(fit.times_s.clone())),
            true_persistence: truth,
        }
    }

    /// The readout's capacitive coupling (`ipc:*`), in place; identity otherwise.
    fn couple(&self, a: &mut Array2<f32>) {
        let kernel: Vec<(i64, i64, f64)> = if has(&self.hidden, Hidden::IpcCross4) {
            vec![
                (-1, 0, IPC_CROSS),
                (1, 0, IPC_CROSS),
                (0, -1, IPC_CROSS),
                (0, 1, IPC_CROSS),
            ]
        } else if has(&self.hidden, Hidden::IpcAniso8) {
            let [ax, ay, ad] = IPC_ANISO;
            vec![
                (0, -1, ax),
                (0, 1, ax),
                (-1, 0, ay),
                (1, 0, ay),
                (-1, -1, ad),
                (-1, 1, ad),
                (1, -1, ad),
                (1, 1, ad),
            ]
        } else {
            return;
        };
        let centre = 1.0 - kernel.iter().map(|k| k.2).sum::<f64>();
        let src = a.clone();
        let (ny, nx) = src.dim();
        for y in 0..ny {
            for x in 0..nx {
                let mut v = centre * f64::from(src[[y, x]]);
                for &(dy, dx, w) in &kernel {
                    let (yy, xx) = (y as i64 + dy, x as i64 + dx);
                    if yy >= 0 && xx >= 0 && (yy as usize) < ny && (xx as usize) < nx {
                        v += w * f64::from(src[[yy as usize, xx as usize]]);
                    }
                }
                a[[y, x]] = v as f32;
            }
        }
    }

    /// Trap sites per pixel at exposure fraction 1 (every population), e-.
    pub fn sites(&self) -> Vec<f64> {
        (0..self.n * self.n)
            .map(|p| self.pops.iter().map(|po| po.sites[p]).sum())
            .collect()
    }

    /// Total trapped charge per pixel, e- (for tests and diagnostics of the generator).
    pub fn trapped(&self) -> Vec<f64> {
        self.q
            .chunks(self.stride())
            .map(|c| c.iter().sum())
            .collect()
    }
}

/// A Poisson draw (normal above 1000 expected counts).
fn poisson(r: &mut impl Rng, mu: f64) -> f64 {
    if mu <= 0.0 {
        0.0
    } else if mu > 1000.0 {
        (mu + mu.sqrt() * Normal::new(0.0, 1.0).expect("unit").sample(r)).max(0.0)
    } else {
        Poisson::new(mu).map_or(mu, |d| d.sample(r))
    }
}

/// The trap-density map over the array: 1 everywhere, or `populations:smooth` (a
/// tilted quadratic surface) or `populations:patches` (disks of 2.5 times the density).
fn spatial_map(seed: u64, size: usize, hidden: &[Hidden]) -> Vec<f64> {
    let n = size as f64;
    let mut r = rng::stream(seed, &[purpose::PATCHES]);
    if has(hidden, Hidden::PopulationsSmooth) {
        let th: f64 = r.random::<f64>() * std::f64::consts::TAU;
        return (0..size * size)
            .map(|p| {
                let u = 2.0 * ((p % size) as f64 + 0.5) / n - 1.0;
                let v = 2.0 * ((p / size) as f64 + 0.5) / n - 1.0;
                1.0 + 0.4 * (th.cos() * u + th.sin() * v) + 0.25 * (u * u - 1.0 / 3.0)
            })
            .collect();
    }
    if has(hidden, Hidden::PopulationsPatches) {
        let disks: Vec<(f64, f64, f64)> = (0..5)
            .map(|_| {
                (
                    r.random::<f64>() * n,
                    r.random::<f64>() * n,
                    (0.06 + 0.06 * r.random::<f64>()) * n,
                )
            })
            .collect();
        return (0..size * size)
            .map(|p| {
                let (y, x) = ((p / size) as f64 + 0.5, (p % size) as f64 + 0.5);
                if disks
                    .iter()
                    .any(|(cy, cx, rr)| (y - cy).powi(2) + (x - cx).powi(2) < rr * rr)
                {
                    2.5
                } else {
                    1.0
                }
            })
            .collect();
    }
    vec![1.0; size * size]
}
