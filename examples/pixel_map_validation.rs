//! The per-pixel response map against the global 95th-percentile model, on the
//! simulator's truth (docs/validation/pixel_map.md; `scripts/validate_pixel_map.sh`
//! writes the page with its generated header): one simulated detector's laboratory
//! sequence (`persist::pixmap::eval::lab_campaign`) gives the global model (`persist
//! fit`'s calibration) and the map; a sky run of the same detector is flagged by both,
//! after the first `--skip-h` hours, and compared with the true persistence current.
//!
//! ```sh
//! target/release/examples/pixel_map_validation [--size 128] [--seed 1] [--exposures 1143] [--skip-h 6] [--margins 1,1.2,1.5]
//! ```
//! Prints the page's body (markdown) on stdout.
use persist::pixmap::eval::{Experiment, FlagTally, FlightExperiment, BANDS};

fn pct(x: f64) -> String {
    if x.is_nan() {
        "-".into()
    } else {
        format!("{:.3} %", 100.0 * x)
    }
}

fn row(name: &str, t: &FlagTally, base: &FlagTally) -> String {
    let mut s = format!(
        "| {name} | {} | {} | {:.2} |",
        pct(t.flagged as f64 / t.samples.max(1) as f64),
        pct(t.over_flag_fraction()),
        t.over_flag_fraction() / base.over_flag_fraction()
    );
    for b in 0..BANDS.len() {
        s += &format!(" {} ({}) |", pct(t.missed_fraction(b)), t.missed[b]);
    }
    s += &format!(" {} |", pct(t.missed_fraction_all()));
    s
}

fn table(title: &str, global: &FlagTally, maps: &[(f64, &FlagTally)]) -> String {
    let th = global.threshold_e_per_s;
    let band = |b: usize| match BANDS.get(b + 1) {
        Some(hi) => format!("{:.3}-{:.3}", BANDS[b] * th, hi * th),
        None => format!("> {:.3}", BANDS[b] * th),
    };
    let mut s = format!(
        "### {title}\n\n{} pixel-exposures counted; truly above the threshold per band: {}.\n\n",
        global.samples,
        (0..BANDS.len())
            .map(|b| format!("{} e-/s: {}", band(b), global.above[b]))
            .collect::<Vec<_>>()
            .join(", ")
    );
    s += "| model | flagged | over-flagged | over-flagged / global's |";
    for b in 0..BANDS.len() {
        s += &format!(" missed {} e-/s |", band(b));
    }
    s += " missed, all |\n|---|---|---|---|---|---|---|---|---|\n";
    s += &row("global (95th percentile x 1.2)", global, global);
    s += "\n";
    for (m, t) in maps {
        s += &row(&format!("per-pixel map, margin {m}"), t, global);
        s += "\n";
    }
    s
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let opt = |name: &str| {
        args.iter()
            .position(|a| a == name)
            .and_then(|i| args.get(i + 1).cloned())
    };
    if let Some(days) = opt("--flight-days") {
        flight(FlightExperiment {
            size: opt("--size").map_or(128, |v| v.parse().expect("--size")),
            seed: opt("--seed").map_or(1, |v| v.parse().expect("--seed")),
            learn_days: days
                .split(',')
                .map(|d| d.parse().expect("--flight-days"))
                .collect(),
            eval_days: opt("--eval-days").map_or(1.0, |v| v.parse().expect("--eval-days")),
            t_skip_s: 3600.0 * opt("--skip-h").map_or(6.0, |v| v.parse::<f64>().expect("--skip-h")),
            margin: opt("--margin").map_or(0.8, |v| v.parse().expect("--margin")),
        });
        return;
    }
    let e = Experiment {
        size: opt("--size").map_or(128, |v| v.parse().expect("--size")),
        seed: opt("--seed").map_or(1, |v| v.parse().expect("--seed")),
        sky_exposures: opt("--exposures").map_or(1143, |v| v.parse().expect("--exposures")),
        t_skip_s: 3600.0 * opt("--skip-h").map_or(6.0, |v| v.parse::<f64>().expect("--skip-h")),
        cosmic_rate_per_cm2_s: opt("--cosmic-rate").map(|v| v.parse().expect("--cosmic-rate")),
        margins: opt("--margins").map_or(vec![1.0, 1.2, 1.5], |v| {
            v.split(',')
                .map(|m| m.parse().expect("--margins"))
                .collect()
        }),
    };
    let r = e.run().expect("experiment");
    println!(
        "Detector 1, {0} x {0} pixels, seed {1}: laboratory sequence then {2} sky exposures, \
         tallied from {3} h after the first. Map: {4} of {5} pixels measured below full well, \
         {6} above.\n",
        e.size,
        e.seed,
        e.sky_exposures,
        e.t_skip_s / 3600.0,
        r.observed[0],
        r.pixels,
        r.observed[1]
    );
    println!("Over-flagged: flagged while the true current is below the threshold, per functional pixel-exposure. Missed: truly above, not flagged, per band of true current (count in brackets); non-functional pixels left out.\n");
    let hi: Vec<(f64, &FlagTally)> = r.with_map.iter().map(|(m, h, _)| (*m, h)).collect();
    let lo: Vec<(f64, &FlagTally)> = r.with_map.iter().map(|(m, _, l)| (*m, l)).collect();
    println!(
        "{}",
        table("At 0.1 e-/s (the flag, `HIGH`)", &r.global.0, &hi)
    );
    println!("{}", table("At 0.01 e-/s (`LOW`)", &r.global.1, &lo));
    println!("### The map against the truth\n\nPosterior mean ratio above full well (relative to the fluence bin's 95th percentile, the knots' level before their 1.2), per true population of the simulator:\n");
    println!("| population | pixels | mean ratio |\n|---|---|---|");
    for (name, mean, n) in &r.saturated_ratio_by_population {
        println!("| {name} | {n} | {mean:.3} |");
    }
}

/// The flight maps' table (`--flight-days`).
fn flight(e: FlightExperiment) {
    let t = std::time::Instant::now();
    let rows = e.run().expect("flight experiment");
    println!(
        "Detector 1, {0} x {0} pixels, seed {1}: flight maps learned from the first {2:?} days of sky \
         (global model's flags, `verify`'s tracks), then every model flags the next {3} days, \
         tallied from {4} h after that start; map margin {5}. Computed in {6:.0} s.\n",
        e.size,
        e.seed,
        e.learn_days,
        e.eval_days,
        e.t_skip_s / 3600.0,
        e.margin,
        t.elapsed().as_secs_f64()
    );
    let g = (
        rows[0].high.over_flag_fraction(),
        rows[0].low.over_flag_fraction(),
    );
    let lab = (
        rows[1].high.over_flag_fraction(),
        rows[1].low.over_flag_fraction(),
    );
    let red = |x: f64, g: f64, l: f64| {
        if (g - l).abs() > 0.0 {
            format!("{:.2}", (g - x) / (g - l))
        } else {
            "-".into()
        }
    };
    println!("Reduction relative to the laboratory map's: (global's over-flagged - this one's) / (global's - the laboratory map's); 1 = the laboratory map's reduction.\n");
    println!("| model | pixels measured (saturated) | flight observations | over-flagged at 0.1 | / global's | reduction vs lab map's | missed at 0.1, all | over-flagged at 0.01 | / global's | reduction vs lab map's | missed at 0.01, all |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let (h, l) = (r.high.over_flag_fraction(), r.low.over_flag_fraction());
        println!(
            "| {} | {} | {} | {} | {:.2} | {} | {} | {} | {:.2} | {} | {} |",
            r.name,
            r.observed_pixels,
            r.observations,
            pct(h),
            h / g.0,
            red(h, g.0, lab.0),
            pct(r.high.missed_fraction_all()),
            pct(l),
            l / g.1,
            red(l, g.1, lab.1),
            pct(r.low.missed_fraction_all())
        );
    }
    println!("\nPosterior mean ratio above full well per true population of the simulator, over the pixels each map measured (pixels in brackets):\n");
    let names: Vec<String> = rows[1]
        .ratio_by_population
        .iter()
        .map(|p| p.0.clone())
        .collect();
    println!("| model | {} |", names.join(" | "));
    println!("|---|{}", "---|".repeat(names.len()));
    for r in rows.iter().skip(1) {
        let cells: Vec<String> = r
            .ratio_by_population
            .iter()
            .map(|(_, m, n)| format!("{m:.3} ({n})"))
            .collect();
        println!("| {} | {} |", r.name, cells.join(" | "));
    }
}
