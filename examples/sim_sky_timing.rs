//! Time one full-frame (2040 x 2040) sky exposure of one detector, in memory:
//! sky map (zodi + stars), slew, trap integration, fit, noise. Run in release:
//! `cargo run --release --example sim_sky_timing [-- REPEATS]`. Prints the median.

use persist::sim::effect::EffectSet;
use persist::sim::engine::{ExposureSpec, SimDetector};
use persist::sim::sky::{plan, sky_flux, SkyConfig};
use std::sync::Arc;
use std::time::Instant;

/// Process CPU time (user + system), seconds, from /proc (Linux); 0 elsewhere.
fn cpu_s() -> f64 {
    let Ok(s) = std::fs::read_to_string("/proc/self/stat") else {
        return 0.0;
    };
    let rest = s.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn main() {
    let repeats: usize = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(7);
    let cfg = SkyConfig {
        exposures: repeats as u64 + 1,
        ..SkyConfig::default()
    };
    let pl = plan(&cfg);
    let t = Instant::now();
    let mut sim = SimDetector::new(
        cfg.traps.clone(),
        cfg.detector.clone(),
        Arc::new(EffectSet::default()),
        cfg.size,
        cfg.size,
        cfg.seed,
        1,
    )
    .expect("valid");
    println!(
        "detector set-up (once per detector): {:.2} s",
        t.elapsed().as_secs_f64()
    );
    let mut times: Vec<f64> = Vec::new();
    let mut cpus: Vec<f64> = Vec::new();
    for (k, p) in pl.iter().enumerate().take(repeats) {
        let t = Instant::now();
        let c = cpu_s();
        sim.gap(p.slew_s, 80.0);
        let flux = sky_flux(&cfg, 1, p);
        let out = sim
            .expose(&ExposureSpec {
                index: k as u64,
                flux: &flux,
                t_exposure_s: cfg.t_exposure_s,
                t_on_s: cfg.t_exposure_s,
                temp_k: 80.0,
                write_ramp: false,
            })
            .expect("valid");
        let dt = t.elapsed().as_secs_f64();
        let dc = cpu_s() - c;
        println!(
            "exposure {k} ({:?}): wall {dt:.3} s, cpu {dc:.2} s, image[0,0] = {}",
            p.kind,
            out.image[[0, 0]]
        );
        times.push(dt);
        cpus.push(dc);
    }
    times.sort_by(|a, b| a.total_cmp(b));
    cpus.sort_by(|a, b| a.total_cmp(b));
    let threads = rayon::current_num_threads();
    println!(
        "median wall {:.3} s; median cpu {:.2} s = {:.3} s per thread ({threads} threads); {} exposures",
        times[times.len() / 2],
        cpus[cpus.len() / 2],
        cpus[cpus.len() / 2] / threads as f64,
        times.len()
    );
}
