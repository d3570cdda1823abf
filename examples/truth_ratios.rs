//! What hidden effects change in the simulator's truth, illumination by illumination:
//! for a laboratory campaign simulated in memory without and with each effect (same
//! seed), the array-mean true persistence current of chosen dark integrations after each
//! illumination, as the ratio with the effect to without. Two effects whose ratios move
//! together across the illuminations are hard to tell apart on this campaign; two that
//! move in opposite directions in one illumination cancel there (as `soak` and
//! `temperature` do).
//!
//! ```sh
//! target/release/examples/truth_ratios [--size 64] [--seed 1] [--spots centred] [--temperatures mixed] [--durations mixed] EFFECT[+EFFECT] ...
//! ```
//! Each argument is one hidden set, effects joined by `+` (e.g. `soak temperature
//! soak+temperature`). `--fluence LO,HI` averages only the pixels whose true fluence
//! (flux times illuminated time) in the last illumination lies in `[LO, HI)` e-, as
//! `examples/model_ratios --fluence` does with the measured fluence.
use persist::sim::effect::EffectSpec;
use persist::sim::lab::{self, Durations, Illumination, LabConfig, Spots, Temperatures};

/// Per exposure: (kind, mean true persistence e-/s over the pixels of the fluence band,
/// every pixel without one, focal-plane temperature K). A pixel has no fluence before
/// the first illumination, so it is in no band then.
fn run(
    size: usize,
    seed: u64,
    campaign: &[Illumination],
    effects: &[&str],
    band: Option<(f64, f64)>,
) -> Vec<(String, f64, f64)> {
    let cfg = LabConfig {
        size,
        seed,
        campaign: Some(campaign.to_vec()),
        effects: effects
            .iter()
            .map(|e| e.parse::<EffectSpec>().expect("effect"))
            .collect(),
        ..LabConfig::default()
    };
    let mut out = Vec::new();
    let mut fluence: Vec<f64> = Vec::new();
    lab::run(&cfg, |s| {
        if s.kind == "illuminated" {
            let t_on = s.exposure.meta.t_illuminated_s();
            fluence = s.true_flux.iter().map(|&f| f64::from(f) * t_on).collect();
        }
        let (mut sum, mut n) = (0.0, 0usize);
        for (i, &v) in s.true_persistence.iter().enumerate() {
            let in_band =
                |(lo, hi): (f64, f64)| fluence.get(i).is_some_and(|f| (lo..hi).contains(f));
            if band.is_none_or(in_band) {
                sum += f64::from(v);
                n += 1;
            }
        }
        let mean = sum / n.max(1) as f64;
        let t = s.exposure.meta.focal_plane_temp_k.unwrap_or(f64::NAN);
        out.push((s.kind.clone(), mean, t));
        Ok(())
    })
    .expect("simulation");
    out
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let opt = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    let size = opt("--size").map_or(64, |v| v.parse().expect("--size"));
    let seed = opt("--seed").map_or(1, |v| v.parse().expect("--seed"));
    let spots: Spots = opt("--spots").map_or(Spots::default(), |v| v.parse().expect("--spots"));
    let temperatures: Temperatures = opt("--temperatures").map_or(Temperatures::default(), |v| {
        v.parse().expect("--temperatures")
    });
    let durations: Durations =
        opt("--durations").map_or(Durations::default(), |v| v.parse().expect("--durations"));
    let campaign = durations.apply(temperatures.apply(spots.campaign()));
    let band = opt("--fluence").map(|v| {
        let (lo, hi) = v.split_once(',').expect("--fluence LO,HI");
        (lo.parse().expect("LO"), hi.parse().expect("HI"))
    });
    let mut sets = Vec::new();
    let mut skip = false;
    for a in &args {
        if skip {
            skip = false;
        } else if a.starts_with("--") {
            skip = true;
        } else {
            sets.push(a.clone());
        }
    }
    let base = run(size, seed, &campaign, &[], band);
    let runs: Vec<_> = sets
        .iter()
        .map(|s| {
            run(
                size,
                seed,
                &campaign,
                &s.split('+').collect::<Vec<_>>(),
                band,
            )
        })
        .collect();
    println!(
        "| illumination | dark | T (K) | truth without (e-/s) | {} |",
        sets.join(" | ")
    );
    println!("|---|---|---|---|{}", "---|".repeat(sets.len()));
    let (mut ill, mut k) = (0, 0);
    for (i, (kind, mean, temp)) in base.iter().enumerate() {
        if kind == "illuminated" {
            ill += 1;
            k = 0;
            continue;
        }
        k += 1;
        if [1, 2, 5, 10, 20, 40, 60].contains(&k) {
            let r: Vec<String> = runs
                .iter()
                .map(|r| format!("{:.3}", r[i].1 / mean))
                .collect();
            println!(
                "| {ill} | {k} | {temp:.1} | {mean:.4} | {} |",
                r.join(" | ")
            );
        }
    }
}
