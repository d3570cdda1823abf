//! Each truth effect switched on changes the data the way its documentation says
//! (direction and rough size); neutral settings leave the bytes unchanged.

use ndarray::Array2;
use persist::sim::detector::DetectorParams;
use persist::sim::effect::{EffectSet, EffectSpec};
use persist::sim::engine::{ExposureSpec, SimDetector};
use persist::sim::lab::{self, LabConfig};
use persist::sim::traps::TrapParams;
use persist::sim::SimExposure;
use persist::stats::median;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

const DARKS: usize = 60;

fn lab_run(effects: &str) -> Arc<Vec<SimExposure>> {
    static CACHE: OnceLock<Mutex<HashMap<String, Arc<Vec<SimExposure>>>>> = OnceLock::new();
    let cache = CACHE.get_or_init(|| Mutex::new(HashMap::new()));
    if let Some(v) = cache.lock().unwrap().get(effects) {
        return v.clone();
    }
    let specs: Vec<EffectSpec> = effects
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let cfg = LabConfig {
        size: 128,
        darks: DARKS,
        seed: 11,
        effects: specs,
        ..LabConfig::default()
    };
    let v = Arc::new(run_lab(&cfg));
    cache.lock().unwrap().insert(effects.to_string(), v.clone());
    v
}

/// Every exposure of the laboratory run `cfg`, in order.
fn run_lab(cfg: &LabConfig) -> Vec<SimExposure> {
    let mut all = Vec::new();
    lab::run(cfg, |e| {
        all.push(e);
        Ok(())
    })
    .unwrap();
    all
}

/// True extrapolated fluence of each pixel (from the baseline's true flux).
fn fluence() -> Vec<f64> {
    lab_run("")[0]
        .true_flux
        .iter()
        .map(|v| f64::from(*v) * 481.0)
        .collect()
}

/// Median of dark integration `k` over pixels with true fluence in [lo, hi).
fn med(run: &[SimExposure], k: usize, lo: f64, hi: f64) -> f64 {
    let f = fluence();
    let img = &run[1 + k].exposure.image;
    let v: Vec<f64> = img
        .iter()
        .zip(&f)
        .filter(|(_, q)| **q >= lo && **q < hi)
        .map(|(v, _)| f64::from(*v) - 0.01)
        .collect();
    median(&v)
}

fn ratio(effect: &str, k: usize, lo: f64, hi: f64) -> f64 {
    let r = med(&lab_run(effect), k, lo, hi) / med(&lab_run(""), k, lo, hi);
    println!("{effect}: dark {k}, fluence [{lo:.0}, {hi:.0}): ratio {r:.3}");
    r
}

fn bytes(run: &[SimExposure]) -> Vec<u32> {
    run.iter()
        .flat_map(|e| {
            e.exposure
                .image
                .iter()
                .map(|v| v.to_bits())
                .chain(e.exposure.flags.iter().copied())
                .chain(e.true_persistence.iter().map(|v| v.to_bits()))
                .collect::<Vec<_>>()
        })
        .collect()
}

#[test]
fn neutral_settings_are_byte_identical_to_baseline() {
    let base = bytes(&lab_run(""));
    for e in [
        "ipc:alpha=0",
        "blooming:fraction=0,trapped_fraction=0",
        "soak:capture_scale=1",
        "temperature:activation_ev=0",
        "short_tau_boost:factor=1",
        "ipc:alpha=0 blooming:fraction=0,trapped_fraction=0 soak:capture_scale=1 temperature:activation_ev=0 short_tau_boost:factor=1",
    ] {
        assert!(bytes(&lab_run(e)) == base, "{e} changed the data");
    }
}

/// A lone 1e5 e-/s pixel among 0.5 e-/s ones (9 x 9, no noise): per neighbour, the
/// true flux after the illumination hook, the measured current of the illuminated
/// exposure and of the first dark.
fn lone_bright_pixel(effects: &str) -> (f32, f32, f32) {
    let specs: Vec<EffectSpec> = effects
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    let det = DetectorParams {
        noise: false,
        nonfunc_fraction: 0.0,
        ..Default::default()
    };
    let mut s = SimDetector::new(
        TrapParams::default(),
        det,
        Arc::new(EffectSet::from_specs(&specs).unwrap()),
        9,
        9,
        1,
        1,
    )
    .unwrap();
    let mut flux = Array2::<f32>::from_elem((9, 9), 0.5);
    flux[[4, 4]] = 1e5;
    let zero = Array2::<f32>::zeros((9, 9));
    let a = s
        .expose(&ExposureSpec::paper_illumination(0, &flux))
        .unwrap();
    let b = s.expose(&ExposureSpec::paper_dark(1, &zero)).unwrap();
    (a.flux[[4, 5]], a.image[[4, 5]], b.image[[4, 5]])
}

/// The collected spill: a lone bright pixel saturates its neighbours, which then show
/// persistence.
#[test]
fn blooming_gives_neighbours_persistence() {
    let (f0, _, p0) = lone_bright_pixel("");
    let (f1, _, p1) = lone_bright_pixel("blooming:trapped_fraction=0");
    println!("neighbour flux {f0} -> {f1}, first-dark current {p0} -> {p1}");
    // 5 % of the (1e5 - 416) e-/s excess, a quarter per neighbour: ~1245 e-/s
    assert!((f1 - f0 - 1245.0).abs() < 20.0);
    assert!(p0 < 0.05 && p1 > 5.0);
}

/// The uncollected spill (`trapped_fraction`): the neighbours' true flux is unchanged,
/// their measured current nearly so, and their traps fill: persistence their measured
/// fluence does not explain (what the model's `blooming` looks for).
#[test]
fn blooming_uncollected_charge_fills_traps_but_is_not_measured() {
    let (f0, m0, p0) = lone_bright_pixel("");
    let (f1, m1, p1) = lone_bright_pixel("blooming:fraction=0,trapped_fraction=0.01");
    println!("neighbour flux {f0} -> {f1}, measured {m0} -> {m1}, first dark {p0} -> {p1}");
    assert_eq!(f0, f1);
    // 0.01 * (1e5 - 416) * 481 / 4 = 1.2e5 e-, over half of full well, in no ramp
    assert!((m1 - m0).abs() < 0.5, "measured {m0} -> {m1}");
    assert!(p0 < 0.05 && p1 > 1.0, "first dark {p0} -> {p1}");
}

#[test]
fn capacity_compresses_the_saturated_response() {
    let hi = ratio("capacity", 0, 3.0e6, 4.5e6);
    let lo = ratio("capacity", 0, 0.8e5, 1.2e5);
    assert!(hi < 0.8 && hi > 0.4, "{hi}");
    assert!(lo > 0.9 && lo < 1.0, "{lo}");
}

#[test]
fn ipc_leaks_one_percent_to_neighbours() {
    let base = &lab_run("")[1].exposure;
    let ipc = &lab_run("ipc")[1].exposure;
    let (ny, nx) = base.image.dim();
    let mut checked = 0;
    for y in 1..ny - 1 {
        for x in 1..nx - 1 {
            let nb = [(y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1)];
            let c = base.image[[y, x]];
            if !c.is_finite() || nb.iter().any(|p| !base.image[*p].is_finite()) {
                continue;
            }
            let lap: f32 = nb.iter().map(|p| base.image[*p]).sum::<f32>() - 4.0 * c;
            let want = c + 0.01 * lap;
            assert!((ipc.image[[y, x]] - want).abs() <= 1e-4 * c.abs().max(1.0));
            checked += 1;
        }
    }
    assert!(checked > 1000);
    // the ramp too
    let (rb, ri) = (base.ramp.as_ref().unwrap(), ipc.ramp.as_ref().unwrap());
    let (y, x) = (64, 40);
    let k = rb.dim().0 - 1;
    let lap = rb[[k, y - 1, x]] + rb[[k, y + 1, x]] + rb[[k, y, x - 1]] + rb[[k, y, x + 1]]
        - 4.0 * rb[[k, y, x]];
    assert!((ri[[k, y, x]] - (rb[[k, y, x]] + 0.01 * lap)).abs() < 1e-2);
}

#[test]
fn linefit_bias_reads_the_first_dark_low() {
    let r = ratio("linefit_bias", 0, 3.5e5, 4.5e5);
    assert!(r < 0.8 && r > 0.5, "{r}");
    // the flatter ramp an hour later is barely biased
    let late = ratio("linefit_bias", 20, 3.5e5, 4.5e5);
    assert!(late > 0.97 && late < 1.01, "{late}");
}

#[test]
fn populations_cluster_spatially() {
    let f = fluence();
    let corr = |effect: &str| -> f64 {
        let img = &lab_run(effect)[1].exposure.image;
        let (ny, nx) = img.dim();
        let mut pairs = Vec::new();
        for y in 0..ny {
            for x in 0..nx - 1 {
                let (q0, q1) = (f[y * nx + x], f[y * nx + x + 1]);
                let (a, b) = (img[[y, x]], img[[y, x + 1]]);
                if q0 > 5e5 && q0 < 5e6 && q1 > 5e5 && q1 < 5e6 && a.is_finite() && b.is_finite() {
                    pairs.push((f64::from(a), f64::from(b)));
                }
            }
        }
        let n = pairs.len() as f64;
        let (ma, mb) = (
            pairs.iter().map(|p| p.0).sum::<f64>() / n,
            pairs.iter().map(|p| p.1).sum::<f64>() / n,
        );
        let cov: f64 = pairs.iter().map(|p| (p.0 - ma) * (p.1 - mb)).sum();
        let va: f64 = pairs.iter().map(|p| (p.0 - ma).powi(2)).sum();
        let vb: f64 = pairs.iter().map(|p| (p.1 - mb).powi(2)).sum();
        cov / (va * vb).sqrt()
    };
    let (c0, c1) = (corr(""), corr("populations"));
    println!("neighbour correlation {c0:.3} -> {c1:.3}");
    assert!(c0.abs() < 0.2 && c1 > 0.5);
    let r = ratio("populations", 0, 3.5e5, 4.5e5);
    assert!(r > 0.7 && r < 1.3, "{r}");
}

#[test]
fn short_tau_boost_raises_the_window_only_and_only_early() {
    let w = ratio("short_tau_boost", 0, 3.5e5, 4.5e5);
    assert!(w > 1.1, "{w}");
    let lo = ratio("short_tau_boost", 0, 0.8e5, 1.2e5);
    let hi = ratio("short_tau_boost", 0, 3.0e6, 4.5e6);
    assert!(
        (lo - 1.0).abs() < 0.01 && (hi - 1.0).abs() < 0.01,
        "{lo} {hi}"
    );
    let late = ratio("short_tau_boost", 20, 3.5e5, 4.5e5);
    assert!((late - 1.0).abs() < 0.03, "{late}");
}

#[test]
fn soak_lowers_late_persistence_more_than_early() {
    let early = ratio("soak", 0, 1e6, 4.5e6);
    let late = ratio("soak", 50, 1e6, 4.5e6);
    assert!(late < 0.8, "{late}");
    assert!(early > late, "{early} {late}");
}

#[test]
fn temperature_warmer_array_decays_faster() {
    // defaults: tabulated at 80 K, the lab runs at 80 K: almost no change
    let same = ratio("temperature", 10, 1e6, 4.5e6);
    assert!((same - 1.0).abs() < 0.05, "{same}");
    // tabulated at 76 K: the 80 K array is 4 K warmer, time constants x0.15; early
    // (1/t regime, scale free) barely changes, the tail hours later drops
    let early = ratio("temperature:t_ref_k=76", 0, 1e6, 4.5e6);
    let late = ratio("temperature:t_ref_k=76", 50, 1e6, 4.5e6);
    assert!((early - 1.0).abs() < 0.1, "{early}");
    assert!(late < 0.85 * early, "{early} {late}");
    // and a colder array (tabulated at 84 K) keeps its tail
    let cold = ratio("temperature:t_ref_k=84", 50, 1e6, 4.5e6);
    assert!(cold > late, "{cold} {late}");
}

/// `capacity` limits accumulation over repeated illuminations (its module docs): the
/// charge a pixel still holds counts against its total, so an illumination repeated 30
/// minutes later adds less than the first did. Two equal illuminations (the campaign's
/// 2 and 3: 240 s, 10 darks of 180 s after each), 64 x 64, seed 11: the median first-dark
/// current of saturated pixels after the second, over that after the first, with and
/// without the effect. Measured when written: 1.003 without, 0.934 with (-7 %).
#[test]
fn capacity_limits_a_repeated_illumination() {
    let run = |effects: &str| {
        run_lab(&LabConfig {
            size: 64,
            seed: 11,
            campaign: Some(lab::Illumination::default_campaign()[1..3].to_vec()),
            effects: effects
                .split_whitespace()
                .map(|s| s.parse().unwrap())
                .collect(),
            ..LabConfig::default()
        })
    };
    let second_over_first = |run: &[SimExposure]| {
        let lit: Vec<bool> = run[0]
            .true_flux
            .iter()
            .map(|v| f64::from(*v) * 240.0 > 1e6)
            .collect();
        let m = |k: usize| {
            let v: Vec<f64> = run[k]
                .exposure
                .image
                .iter()
                .zip(&lit)
                .filter(|(_, l)| **l)
                .map(|(v, _)| f64::from(*v) - 0.01)
                .collect();
            median(&v)
        };
        m(12) / m(1)
    };
    let base = second_over_first(&run(""));
    let cap = second_over_first(&run("capacity"));
    println!("second / first illumination's first dark: {base:.3} without, {cap:.3} with");
    assert!(cap < 0.95 * base && cap > 0.7 * base, "{cap} {base}");
}
