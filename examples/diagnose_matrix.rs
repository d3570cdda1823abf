//! The proof matrix for `persist diagnose`: hidden effects in simulated
//! laboratory campaigns (`persist simulate lab --campaign`), each diagnosed, refitted
//! and compared. Writes a Markdown table (and JSON lines beside it).
//!
//! ```sh
//! cargo run --release --example diagnose_matrix -- --size 128 --out docs/validation/diagnose_matrix.md
//! ```
//! Options: `--size N` (default 128), `--baseline-seeds K` (10), `--seeds K` (3),
//! `--effects a,b,...` (default: every simulator effect; each `NAME` or
//! `NAME:param=value`, a truth effect with a non-default parameter), `--pair a,b` (two hidden
//! effects, default `short_tau_boost,soak`: found one per round at 3 of 3 seeds at 64 x 64,
//! measured with examples/diagnose_matrix; `soak,temperature` is not), `--pixels N`, `--bootstrap B`,
//! `--statistic within|pooled`, `--preset paper|readout` (`persist fit --preset`: the
//! reference's starting point; `readout` is the readout reference), `--reference a,b` (default none: the
//! paper's model; with `--preset`, added to its effects as `persist fit --with` is),
//! `--reference-fit-cn` (the reference also fits the `C_n`, `persist fit --fit-cn`; then
//! every `fit --with` of the matrix refits them jointly too, from the reference's),
//! `--reference-fit-amplification`, `--amplification A`, `--rates-per-s r1,r2,...`,
//! `--t-min-s T`, `--decay-offset-s T0`, `--cells pooled|illumination|neighbours`, `--cell-statistic levels|paired|population`, `--background median|line` (the
//! reference's `persist fit` options, also used by every fit and diagnosis of the
//! matrix; a reference effect `NAME:param=value,...` pins those parameters, as `persist
//! fit --with` does), `--refit candidate|full` (`persist diagnose --refit`), `--decide contrast|score`,
//! `--spots centred|shifted|pinholes` (the campaign, `persist simulate lab --campaign --spots`),
//! `--dark-lengths uniform|varied` (`persist simulate lab --campaign --dark-lengths`),
//! `--temperatures mixed|apart` (`persist simulate lab --campaign --temperatures`),
//! `--repeats N` (`persist simulate lab --campaign --repeats`),
//! `--durations mixed|apart` (`persist simulate lab --campaign --durations`),
//! `--first-seed S` (default 1: the seeds are S, S+1, ...),
//! `--skip-baseline`, `--skip-single`, `--skip-pair`, `--joint` (`persist diagnose --joint`;
//! the pair table then shows round 1's joint check when nothing is declared alone).
//!
//! Per scenario, as the CLI would do it: the reference model (`fit`, the paper's
//! calibration, or `fit --with a --with b` with `--reference a,b`: the reference effects'
//! parameters fitted on the same data) -> `diagnose` against it -> `fit --with` the
//! reference effects and the hidden one, jointly from the reference (stride-2 sample as
//! `persist fit`) -> residual RMS and flag quality at 0.1 e-/s before and after. Missed-flag fraction: `compare`'s
//! (missed samples / all samples) and relative to the samples the effect touches: those
//! where the true persistence current of the run with the effect differs from the run
//! without it (same seed) by more than 10 % or 0.01 e-/s, whichever is larger (for an
//! effect of the readout alone, `linefit_bias`, whose true current is the same, the
//! measured current). The criterion (< 1 %) is on that fraction. Beside it, after a
//! slash: the missed fraction over every sample of a pixel touched at any sample, as
//! `compare --touched-baseline` counts it ("of the pixels the effect touches"). The two
//! differ most where the 0.01 e-/s floor binds: below 0.1 e-/s a sample is touched only
//! if its current is high enough for the effect's relative change to pass the floor, so
//! the per-sample set leans to the pixels above the predicted 95th percentile
//! (measured with examples/diagnose_matrix).

use persist::calib::{self, effects as ceffects, CalibConfig};
use persist::diag::data::{Background, Sequence};
use persist::diag::diagnose::{self, Config, Statistic};
use persist::diag::eval::{self, Samples};
use persist::model::ModelParams;
use persist::sim::effect::EffectSpec;
use persist::sim::lab::{self, Illumination, LabConfig};
use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

struct Sim {
    seq: Sequence,
    truth: Vec<ndarray::Array2<f32>>,
}

fn simulate(
    size: usize,
    seed: u64,
    effects: &[&str],
    campaign: &[Illumination],
    background: Background,
) -> Sim {
    let cfg = LabConfig {
        size,
        seed,
        campaign: Some(campaign.to_vec()),
        effects: effects
            .iter()
            .map(|e| e.parse::<EffectSpec>().expect("effect name"))
            .collect(),
        ..LabConfig::default()
    };
    let mut ex = Vec::new();
    let mut truth = Vec::new();
    lab::run(&cfg, |s| {
        ex.push(s.exposure);
        truth.push(s.true_persistence);
        Ok(())
    })
    .expect("simulation");
    Sim {
        seq: Sequence::from_exposures_with(ex, background).expect("sequence"),
        truth,
    }
}

struct Quality {
    rms: f64,
    missed: f64,
    missed_touched: Option<f64>,
    /// Over every sample of a pixel touched at any sample (`compare`'s definition).
    missed_touched_pixels: Option<f64>,
}

fn quality(p: &ModelParams, seq: &Sequence, s: &Samples, touched: Option<&[bool]>) -> Quality {
    let pr = eval::predict(p, seq, s, false).expect("predict");
    let fl = eval::predict(p, seq, s, true).expect("predict");
    let q = eval::flag_quality(s, &fl.current, Some(&fl.flagged), 0.1);
    let missed_touched = touched.map(|t| {
        eval::flag_quality_of_samples(s, &fl.current, Some(&fl.flagged), 0.1, t)
            .missed_flag_fraction
    });
    let missed_touched_pixels = touched.map(|t| {
        let px = eval::pixels_of(s, t);
        eval::flag_quality_of(s, &fl.current, Some(&fl.flagged), 0.1, Some(&px))
            .missed_flag_fraction
    });
    Quality {
        rms: eval::rms(&persist::diag::spread::model_cell_z(p, s, &pr.current)),
        missed: q.missed_flag_fraction,
        missed_touched,
        missed_touched_pixels,
    }
}

/// "per-sample / per-pixel" missed fractions of touched (module docs).
fn touched_pair(q: &Quality) -> String {
    let f = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.4}"));
    format!("{} / {}", f(q.missed_touched), f(q.missed_touched_pixels))
}

/// The samples the hidden effect touches ([`eval::touched_samples`]): by the true
/// persistence current; for an effect that changes only the readout (the two runs'
/// truths are equal: `linefit_bias`), by the measured current (the same seed draws the
/// same noise).
fn touched(s: &Samples, with: &Sim, without: &Sim) -> Vec<bool> {
    if with.truth == without.truth {
        let measured = |x: &Sim| -> Vec<ndarray::Array2<f32>> {
            x.seq.exposures.iter().map(|e| e.image.clone()).collect()
        };
        return eval::touched_samples(s, &measured(with), &measured(without));
    }
    eval::touched_samples(s, &with.truth, &without.truth)
}

/// The spatial coherence of a diagnosis (`persist::diag::spatial`): best R^2, and
/// "field" when it is at the threshold or above.
fn spatial_cell(d: &diagnose::Diagnosis) -> String {
    d.spatial.as_ref().map_or("-".into(), |c| {
        format!(
            "{:.2}{}",
            c.best_r2,
            if c.coherent { " (field)" } else { "" }
        )
    })
}

/// The reference model: `--reference a,b` (its effects) and `--reference-fit-cn` (the
/// reference and every `fit --with` also fit the `C_n`).
struct Reference {
    effects: Vec<String>,
    fit_cn: bool,
    /// `--reference-fit-amplification`: the reference and every `fit --with` also fit
    /// the knots' level.
    fit_amplification: bool,
    /// The calibration (`--amplification A`, `--rates-per-s r1,r2,...` as on `persist fit`).
    calib: CalibConfig,
}

impl Reference {
    /// This reference with `effect` added to its effects (a later round's reference).
    fn with(&self, effect: &str) -> Reference {
        let mut effects = self.effects.clone();
        effects.push(effect.to_string());
        Reference {
            effects,
            fit_cn: self.fit_cn,
            fit_amplification: self.fit_amplification,
            calib: self.calib.clone(),
        }
    }

    fn free(&self) -> ceffects::Free {
        ceffects::Free {
            c_n: self.fit_cn,
            knot_scale: self.fit_amplification,
            decay_exponent: false,
        }
    }
}

/// The reference model of `seq`: the paper's calibration, then (when the reference has
/// effects or fits the `C_n`) those fitted on the stride-2 sample, as
/// `persist fit --with a --with b [--fit-cn]`.
fn reference_model(seq: &Sequence, reference: &Reference) -> ModelParams {
    let (m0, _) = calib::calibrate(seq, &reference.calib).expect("calibrate");
    if reference.effects.is_empty() && reference.free() == ceffects::Free::default() {
        return m0;
    }
    let s2 = reference.calib.samples(seq);
    ceffects::fit_with(&m0, &reference.effects, reference.free(), seq, &s2)
        .expect("fit reference")
        .0
}

/// `--reference a,b:p=v,q=w,c`: the effects, each as `persist fit --with` takes it (a
/// `NAME:param=value,...` pins those parameters); a piece with `=` and no `:` continues
/// the previous effect's list.
fn reference_effects(v: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for piece in v.split(',').filter(|s| !s.is_empty()) {
        match out.last_mut() {
            Some(last) if piece.contains('=') && !piece.contains(':') => {
                last.push(',');
                last.push_str(piece);
            }
            _ => out.push(piece.to_string()),
        }
    }
    out
}

/// `fit --with` the reference effects and `extra` (jointly, starting from the reference
/// model's values).
fn fit_with(
    mref: &ModelParams,
    reference: &Reference,
    extra: &str,
    seq: &Sequence,
    s2: &Samples,
) -> ModelParams {
    let mut names = reference.effects.clone();
    if !names.iter().any(|n| n == extra) {
        names.push(extra.to_string());
    }
    ceffects::fit_with(mref, &names, reference.free(), seq, s2)
        .expect("fit")
        .0
}

/// The reference model of `seq`, then `diagnose` of it with `cfg` at `seed`.
fn calibrate_and_diagnose(
    seq: &Sequence,
    seed: u64,
    cfg: &Config,
    reference: &Reference,
) -> (ModelParams, diagnose::Diagnosis) {
    let m0 = reference_model(seq, reference);
    let d = diagnose_with(&m0, seq, seed, cfg);
    (m0, d)
}

fn diagnose_with(m: &ModelParams, seq: &Sequence, seed: u64, cfg: &Config) -> diagnose::Diagnosis {
    let c = Config {
        seed,
        ..cfg.clone()
    };
    // as `persist diagnose` does with its defaults: a flagging model is tested against
    // the measurements' description fitted from the same data
    persist::diag::reference::diagnose_with(
        m,
        seq,
        &c,
        persist::diag::reference::Reference::default(),
        Path::new("lab"),
        Path::new("m0.json"),
    )
    .expect("diagnose")
    .diagnosis
}

/// The effect ranked first, when it is significant.
fn declared_first(d: &diagnose::Diagnosis) -> Option<String> {
    d.ranking
        .first()
        .filter(|c| c.significant)
        .map(|c| c.effect.clone())
}

fn arg(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

/// Options that take a value, and flags (module docs).
const VALUE_OPTIONS: &[&str] = &[
    "--size",
    "--baseline-seeds",
    "--seeds",
    "--first-seed",
    "--spots",
    "--dark-lengths",
    "--temperatures",
    "--repeats",
    "--durations",
    "--out",
    "--effects",
    "--pair",
    "--preset",
    "--reference",
    "--amplification",
    "--rates-per-s",
    "--t-min-s",
    "--decay-offset-s",
    "--cells",
    "--cell-statistic",
    "--background",
    "--pixels",
    "--bootstrap",
    "--statistic",
    "--refit",
    "--decide",
];
const FLAGS: &[&str] = &[
    "--reference-fit-cn",
    "--reference-fit-amplification",
    "--joint",
    "--skip-baseline",
    "--skip-single",
    "--skip-pair",
];

/// `--help` prints the options; an unknown option is refused before anything runs (the
/// matrix takes up to hours and writes `--out`, by default docs/validation/diagnose_matrix.md: a
/// mistyped option, or `--help`, once ran the whole default matrix and overwrote it).
fn check_args(args: &[String]) {
    let mut i = 1;
    while i < args.len() {
        let a = args[i].as_str();
        if a == "--help" || a == "-h" {
            println!(
                "diagnose_matrix: the proof matrix (examples/diagnose_matrix.rs, \
                 module docs)\noptions with a value: {}\nflags: {}",
                VALUE_OPTIONS.join(" "),
                FLAGS.join(" ")
            );
            std::process::exit(0);
        }
        if VALUE_OPTIONS.contains(&a) {
            if i + 1 >= args.len() {
                eprintln!("diagnose_matrix: {a} needs a value");
                std::process::exit(2);
            }
            i += 2;
        } else if FLAGS.contains(&a) {
            i += 1;
        } else {
            eprintln!("diagnose_matrix: unknown argument `{a}` (--help lists the options)");
            std::process::exit(2);
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    check_args(&args);
    let size: usize = arg(&args, "--size").map_or(128, |v| v.parse().unwrap());
    let nbase: u64 = arg(&args, "--baseline-seeds").map_or(10, |v| v.parse().unwrap());
    let nseed: u64 = arg(&args, "--seeds").map_or(3, |v| v.parse().unwrap());
    let first: u64 = arg(&args, "--first-seed").map_or(1, |v| v.parse().unwrap());
    let options = lab::CampaignOptions {
        spots: arg(&args, "--spots").map_or(lab::Spots::default(), |v| v.parse().unwrap()),
        dark_lengths: arg(&args, "--dark-lengths")
            .map_or(lab::DarkLengths::default(), |v| v.parse().unwrap()),
        temperatures: arg(&args, "--temperatures")
            .map_or(lab::Temperatures::default(), |v| v.parse().unwrap()),
        repeats: arg(&args, "--repeats").map_or(0, |v| v.parse().unwrap()),
        durations: arg(&args, "--durations")
            .map_or(lab::Durations::default(), |v| v.parse().unwrap()),
    };
    let campaign = options.illuminations();
    // the campaign's `persist simulate lab` flags beyond `--campaign`
    let campaign_flags = options.flags();
    let out = arg(&args, "--out").unwrap_or_else(|| "docs/validation/diagnose_matrix.md".into());
    let effects_arg = arg(&args, "--effects");
    let all: Vec<&str> = persist::sim::effects::NAMES.to_vec();
    let effects: Vec<String> = effects_arg
        .map_or(all.iter().map(|s| s.to_string()).collect(), |v| {
            v.split(',').map(String::from).collect()
        });
    let pair: Vec<String> = arg(&args, "--pair")
        .unwrap_or_else(|| "short_tau_boost,soak".into())
        .split(',')
        .map(String::from)
        .collect();
    let preset: calib::Preset = arg(&args, "--preset").map_or(Default::default(), |v| {
        v.parse().unwrap_or_else(|e| panic!("{e}"))
    });
    let reference = Reference {
        effects: preset
            .with(&arg(&args, "--reference").map_or(Vec::new(), |v| reference_effects(&v))),
        fit_cn: args.iter().any(|a| a == "--reference-fit-cn"),
        fit_amplification: args.iter().any(|a| a == "--reference-fit-amplification"),
        calib: {
            let mut c = preset.config();
            if let Some(v) = arg(&args, "--amplification") {
                c.amplification = v.parse().unwrap();
            }
            if let Some(v) = arg(&args, "--rates-per-s") {
                c.rates_per_s = v.split(',').map(|r| r.parse().unwrap()).collect();
            }
            if let Some(v) = arg(&args, "--t-min-s") {
                c.t_min_s = v.parse().unwrap();
            }
            if let Some(v) = arg(&args, "--decay-offset-s") {
                c.decay_offset_s = v.parse().unwrap();
            }
            if let Some(v) = arg(&args, "--cells") {
                c.cells = v.parse().unwrap();
            }
            if let Some(v) = arg(&args, "--cell-statistic") {
                c.cell_statistic = v.parse().unwrap();
            }
            if let Some(v) = arg(&args, "--background") {
                c.background = v.parse().unwrap();
            }
            c
        },
    };
    let default_calib = CalibConfig::default();
    let cn_label = if reference.fit_cn {
        " + C_n fitted (`--fit-cn`)".to_string()
    } else {
        String::new()
    } + &if reference.calib.amplification != default_calib.amplification {
        format!(", amplification {}", reference.calib.amplification)
    } else {
        String::new()
    } + &if reference.calib.rates_per_s != default_calib.rates_per_s {
        format!(
            ", {} terms from {} s",
            reference.calib.rates_per_s.len(),
            reference.calib.t_min_s
        )
    } else {
        String::new()
    } + &if reference.calib.decay_offset_s != default_calib.decay_offset_s {
        format!(", C_n to 1/(t + {} s)", reference.calib.decay_offset_s)
    } else {
        String::new()
    } + if reference.fit_amplification {
        " + knots' level fitted (`--fit-amplification`)"
    } else {
        ""
    } + &format!(
        ", {} cells, {} cell statistic, {} background",
        reference.calib.cells.describe(),
        reference.calib.cell_statistic,
        reference.calib.background
    );
    let ref_label = if reference.effects.is_empty() {
        "the paper's model (`persist fit`)".to_string()
    } else {
        format!(
            "the paper's model + {} (`persist fit{}`)",
            reference.effects.join(" + "),
            reference
                .effects
                .iter()
                .map(|r| format!(" --with {r}"))
                .collect::<String>()
        )
    } + &cn_label;
    let mut cfg = Config::default();
    if let Some(v) = arg(&args, "--pixels") {
        cfg.pixels = v.parse().unwrap();
    }
    if let Some(v) = arg(&args, "--bootstrap") {
        cfg.bootstrap = v.parse().unwrap();
    }
    if let Some(v) = arg(&args, "--statistic") {
        cfg.statistic = v.parse::<Statistic>().unwrap();
    }
    cfg.cells = reference.calib.cells;
    cfg.cell_statistic = reference.calib.cell_statistic;
    cfg.background = reference.calib.background;
    let bg = reference.calib.background;
    if let Some(v) = arg(&args, "--refit") {
        cfg.refit = v.parse().unwrap();
    }
    cfg.joint = args.iter().any(|a| a == "--joint");
    if let Some(v) = arg(&args, "--decide") {
        cfg.decide = v.parse().unwrap();
    }
    let skip = |f: &str| args.iter().any(|a| a == f);
    let mut md = String::new();
    let mut jl = String::new();
    let cmdline = args[1..].join(" ");
    writeln!(
        md,
        "Command: `cargo run --release --example diagnose_matrix -- {cmdline}`\n\n\
         Laboratory campaign (`persist simulate lab --campaign{campaign_flags}`), {size} x {size} pixels; \
         **reference model: {ref_label}**; diagnose: \
         statistic {:?}, {} random pixels, {} bootstrap replicas, refit {:?}; refit and flag \
         quality on the stride-2 sample of `persist fit`/`compare`.\n",
        cfg.statistic, cfg.pixels, cfg.bootstrap, cfg.refit
    )
    .unwrap();
    let mut baselines: Vec<Option<Sim>> = Vec::new();
    let t_all = Instant::now();
    // --- baseline
    if !skip("--skip-baseline") {
        writeln!(md, "## No hidden effect (reference: {ref_label})\n\n| seed | residual RMS | threshold | top score (effect) | significant | spatial R^2 | seconds |\n|---|---|---|---|---|---|---|").unwrap();
        let mut clean = 0;
        for seed in first..first + nbase {
            let sim = simulate(size, seed, &[], &campaign, bg);
            let t0 = Instant::now();
            let (_, d) = calibrate_and_diagnose(&sim.seq, seed, &cfg, &reference);
            let secs = t0.elapsed().as_secs_f64();
            let sig: Vec<&str> = d
                .ranking
                .iter()
                .filter(|c| c.significant)
                .map(|c| c.effect.as_str())
                .collect();
            clean += sig.is_empty() as usize;
            let top = d
                .ranking
                .iter()
                .max_by(|a, b| a.score.total_cmp(&b.score))
                .unwrap();
            writeln!(
                md,
                "| {seed} | {:.2} | {:.2} | {:.2} ({}) | {} | {} | {secs:.1} |",
                d.residual_rms_normalised,
                d.threshold,
                top.score,
                top.effect,
                if sig.is_empty() {
                    "none".into()
                } else {
                    sig.join(", ")
                },
                spatial_cell(&d)
            )
            .unwrap();
            writeln!(jl, "{}", serde_json::json!({"case": "baseline", "seed": seed, "diagnosis": d, "seconds": secs})).unwrap();
            eprintln!("baseline seed {seed}: {:?} ({secs:.1} s)", sig);
            baselines.push(if seed <= nseed { Some(sim) } else { None });
        }
        writeln!(
            md,
            "\nNothing significant in **{clean} of {nbase}** seeds (criterion: at least 9 of 10).\n"
        )
        .unwrap();
    }
    // --- single effects
    if !skip("--skip-single") {
        writeln!(md, "## One hidden effect (reference: {ref_label}; `fit --with` = reference effects + the hidden one)\n\n\
            | effect | seed | rank by score | declared first | significant | RMS before -> after `fit --with` | halved | missed@0.1 before -> after (all samples) | missed@0.1 of touched before -> after (samples / pixels) | held-out gain | dBIC | spatial R^2 |\n\
            |---|---|---|---|---|---|---|---|---|---|---|---|").unwrap();
        let mut passed = Vec::new();
        for e in &effects {
            let mut ok_all = true;
            for seed in first..first + nseed {
                let sim = simulate(size, seed, &[e.as_str()], &campaign, bg);
                let base_sim = match baselines.get(seed as usize - 1) {
                    Some(Some(_)) => None,
                    _ => Some(simulate(size, seed, &[], &campaign, bg)),
                };
                let b = base_sim
                    .as_ref()
                    .unwrap_or_else(|| baselines[seed as usize - 1].as_ref().unwrap());
                let (m0, d) = calibrate_and_diagnose(&sim.seq, seed, &cfg, &reference);
                // the model-side name of a truth effect given as `NAME[:param=value]`
                let name = e.split(':').next().unwrap_or(e).to_string();
                let rank = d.ranking.iter().find(|c| c.effect == name);
                let first = declared_first(&d);
                let s2 = reference.calib.samples(&sim.seq);
                let t = touched(&s2, &sim, b);
                let q0 = quality(&m0, &sim.seq, &s2, Some(&t));
                let in_model = persist::model::effects::lookup(&name).is_some();
                let q1 = in_model.then(|| {
                    let m1 = fit_with(&m0, &reference, &name, &sim.seq, &s2);
                    quality(&m1, &sim.seq, &s2, Some(&t))
                });
                let found = first.as_deref() == Some(name.as_str());
                let halved = q1.as_ref().is_some_and(|q| q.rms <= 0.5 * q0.rms);
                let flags_ok = q1
                    .as_ref()
                    .is_some_and(|q| q.missed_touched.unwrap_or(1.0) < 0.01);
                ok_all &= found && halved && flags_ok;
                let f3 = |v: f64| format!("{:.4}", v);
                writeln!(
                    md,
                    "| {e} | {seed} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |",
                    rank.map_or(
                        if reference.effects.contains(&name) {
                            "in the reference".into()
                        } else {
                            "not in library".into()
                        },
                        |c| format!("{} ({:.1} vs {:.1})", c.score_rank, c.score, c.threshold)
                    ),
                    first.clone().unwrap_or_else(|| "nothing".into()),
                    rank.is_some_and(|c| c.significant),
                    q1.as_ref()
                        .map_or(format!("{:.2} -> (no model effect)", q0.rms), |q| format!(
                            "{:.2} -> {:.2}",
                            q0.rms, q.rms
                        )),
                    halved,
                    q1.as_ref().map_or(f3(q0.missed), |q| format!(
                        "{} -> {}",
                        f3(q0.missed),
                        f3(q.missed)
                    )),
                    q1.as_ref().map_or(touched_pair(&q0), |q| format!(
                        "{} -> {}",
                        touched_pair(&q0),
                        touched_pair(q)
                    )),
                    rank.and_then(|c| c.held_out.as_ref())
                        .map_or("-".into(), |h| format!(
                            "{:.2} (moved cells: {:.2} of {})",
                            h.gain, h.gain_moved_cells, h.moved_cells
                        )),
                    rank.and_then(|c| c.delta_bic)
                        .map_or("-".into(), |v| format!("{v:.1}")),
                    spatial_cell(&d),
                )
                .unwrap();
                writeln!(jl, "{}", serde_json::json!({"case": "single", "effect": e, "seed": seed, "diagnosis": d,
                    "rms_before": q0.rms, "rms_after": q1.as_ref().map(|q| q.rms),
                    "missed_before": q0.missed, "missed_after": q1.as_ref().map(|q| q.missed),
                    "missed_touched_before": q0.missed_touched, "missed_touched_after": q1.as_ref().and_then(|q| q.missed_touched),
                    "missed_touched_pixels_before": q0.missed_touched_pixels, "missed_touched_pixels_after": q1.as_ref().and_then(|q| q.missed_touched_pixels)})).unwrap();
                eprintln!(
                    "{e} seed {seed}: first {first:?}, rms {:.2} -> {:?}",
                    q0.rms,
                    q1.as_ref().map(|q| q.rms)
                );
            }
            passed.push((e.clone(), ok_all));
        }
        writeln!(md, "\nAll three criteria (declared first and significant, RMS halved, missed of touched < 1 %) at every seed:\n").unwrap();
        for (e, ok) in &passed {
            writeln!(md, "- {e}: **{}**", if *ok { "yes" } else { "no" }).unwrap();
        }
        writeln!(md).unwrap();
    }
    // --- two effects
    if !skip("--skip-pair") {
        writeln!(md, "## Two hidden effects: {} (reference: {ref_label})\n\n| seed | round 1 declared | round 2 declared | RMS m0 -> m1 -> m2 | error falls each round | both found |\n|---|---|---|---|---|---|", pair.join(" + ")).unwrap();
        for seed in first..first + nseed {
            let names: Vec<&str> = pair.iter().map(String::as_str).collect();
            let sim = simulate(size, seed, &names, &campaign, bg);
            let s2 = reference.calib.samples(&sim.seq);
            let (m0, d1) = calibrate_and_diagnose(&sim.seq, seed, &cfg, &reference);
            let w1 = declared_first(&d1);
            let r0 = quality(&m0, &sim.seq, &s2, None).rms;
            let (mut r1, mut r2, mut w2) = (f64::NAN, f64::NAN, None);
            if let Some(w) = &w1 {
                let m1 = fit_with(&m0, &reference, w, &sim.seq, &s2);
                r1 = quality(&m1, &sim.seq, &s2, None).rms;
                let d2 = diagnose_with(&m1, &sim.seq, seed, &cfg);
                w2 = declared_first(&d2);
                if let Some(v) = &w2 {
                    let m2 = fit_with(&m1, &reference.with(w), v, &sim.seq, &s2);
                    r2 = quality(&m2, &sim.seq, &s2, None).rms;
                }
                writeln!(
                    jl,
                    "{}",
                    serde_json::json!({"case": "pair", "seed": seed, "round2": d2})
                )
                .unwrap();
            }
            // --joint: a significant pair in round 1 is added in one `fit --with` both
            let joint = d1.joint.first().filter(|j| w1.is_none() && j.significant);
            if let Some(j) = joint {
                let ref1 = reference.with(&j.effects[0]);
                let m1 = fit_with(&m0, &ref1, &j.effects[1], &sim.seq, &s2);
                r1 = quality(&m1, &sim.seq, &s2, None).rms;
            }
            writeln!(
                jl,
                "{}",
                serde_json::json!({"case": "pair", "seed": seed, "round1": d1, "rms": [r0, r1, r2]})
            )
            .unwrap();
            let both = match (&w1, &w2, joint) {
                (Some(a), Some(b), _) => {
                    (pair.contains(a) && pair.contains(b) && a != b).to_string()
                }
                (None, _, Some(j)) if j.effects.iter().all(|e| pair.contains(e)) => {
                    "together, in one round".to_string()
                }
                _ => false.to_string(),
            };
            // with --joint and nothing declared alone: round 1's joint check
            let w1_label = match d1.joint.first() {
                Some(j) if w1.is_none() => format!(
                    "nothing; joint: {} + {} (dBIC {:.1}, over the leader {:.1}, held-out gain {}){}",
                    j.effects[0],
                    j.effects[1],
                    j.delta_bic,
                    j.delta_bic_over_leader,
                    j.held_out
                        .as_ref()
                        .map_or("-".into(), |h| format!("{:.2}", h.gain)),
                    if j.significant { ", significant" } else { "" }
                ),
                _ => w1.clone().unwrap_or_else(|| "nothing".into()),
            };
            writeln!(
                md,
                "| {seed} | {} | {} | {r0:.2} -> {r1:.2} -> {r2:.2} | {} | {both} |",
                w1_label,
                w2.clone().unwrap_or_else(|| "nothing".into()),
                if joint.is_some() {
                    format!("{} (one round)", r1 < r0)
                } else {
                    (r1 < r0 && r2 < r1).to_string()
                },
            )
            .unwrap();
            eprintln!("pair seed {seed}: {w1:?} {w2:?} {r0:.2} {r1:.2} {r2:.2}");
        }
    }
    writeln!(md, "\nTotal time {:.0} s.", t_all.elapsed().as_secs_f64()).unwrap();
    std::fs::write(&out, md).expect("write table");
    std::fs::write(Path::new(&out).with_extension("jsonl"), jl).expect("write json lines");
    eprintln!("wrote {out}");
}
