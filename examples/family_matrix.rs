//! The diagnostics' family matrix: sequences from the second truth generator
//! (`persist simulate family`, `persist::trapgen`), each run through the DEFAULT
//! commands a user would type, and a Markdown table of what they found.
//!
//! ```sh
//! cargo build --release --bin persist
//! cargo run --release --example family_matrix -- --size 64 --seeds 5 \
//!     --out docs/validation/diagnostics_family.md
//! # one row, small, for a quick look:
//! cargo run --release --example family_matrix -- --rows soak:capture --size 32 --seeds 1
//! ```
//!
//! Options: `--rows R1,R2,...` (default: the four nothing-hidden rows and every form not
//! held aside), `--size N` (64), `--seeds K` (5), `--first-seed S` (1),
//! `--darks N` (single-illumination darks, 120), `--dark-pixels` (hidden rows with the
//! right-hand quarter unlit), `--held-out` (also the forms held aside for the final
//! proof), `--work DIR` (data, default `target/family_matrix`), `--persist PATH` (the
//! binary; default: `persist` beside this example's directory), `--out FILE`
//! (default `docs/validation/diagnostics_family.md`; JSON lines beside it),
//! `--fit-args "..."` (added to every `fit`, for comparing a non-default calibration;
//! the page's command line records it), `--resume FILE` (below).
//!
//! With `--resume FILE` every finished run is also appended to FILE, keyed by the code
//! that produced it (the git tree ids of `src/`, `Cargo.toml`, `Cargo.lock` and this
//! example) and by the settings (size, darks, fit arguments); a later call with the same
//! FILE takes the runs of the same key from it instead of running them again, so a
//! matrix of hours can be run in parts. Runs are never reused from a tree whose code has
//! uncommitted changes, and the page says how many runs it took from FILE.
//!
//! A row is `none` or `CLASS:FORM`, then optionally `@single` or `@campaign` (default:
//! `single` for `none`, `campaign` otherwise) and `+dark` (with dark pixels). Blooming
//! and ipc rows are simulated with the pinhole grid (`--pinholes on`) and so are their
//! baselines.
//!
//! Per row and seed:
//! 1. `persist simulate family --out D --seed S --size N --sequence Q [--hidden H]`, and
//!    the same without the hidden effect (the baseline B, shared by the rows that use it);
//! 2. `persist fit --input D --out M.json` (fit success);
//! 3. `persist diagnose --input D --model M.json --json diag.json`: the effect declared
//!    first (the first significant candidate of the ranking), and the candidates the
//!    output calls untestable (any candidate or list entry marked so);
//! 4. if something is declared: `persist fit --input D --out M2.json --with EFFECT`;
//! 5. `persist compare --input D --model M.json [--model M2.json]`: each model's pixel
//!    reference's normalised residual RMS (`compare`'s `pixel_reference`, the line
//!    `diagnose` prints as "pixel reference"); the excess is that minus the same of the
//!    baseline's own
//!    fit on the baseline (same seed, nothing hidden; when `diagnose` tested against a
//!    description of the measurements, the same printed `fit` command on the baseline's
//!    data); "halved" when the excess after `fit --with` is at most half the excess
//!    before (not counted, either way, when the excess before is not positive). The
//!    hidden share, `1 - RMS(baseline) / RMS(before)`, is the share of the residual RMS
//!    the hidden effect accounts for: about the most a candidate that captured it
//!    exactly could gain, held out, over all cells; the runs where it reaches
//!    `diagnose`'s held-out gate are counted apart. The same RMS of M.json and M2.json
//!    themselves (the flagging models) is given beside it;
//! 6. `persist run` with each model; the missed-flag fraction at 0.1 e-/s over the
//!    touched pixels: a pixel is touched when its true persistence differs from the
//!    baseline's by more than 0.01 e-/s at any exposure; a sample (touched pixel, any
//!    exposure but the first) with a true persistence current of at least 0.1 e-/s is
//!    missed when the output's `PERSIST` flag bit is not set. Fraction = missed / such
//!    samples.

use persist::diag::refit::HELD_OUT_MIN_GAIN;
use persist::flags::bits;
use persist::trapgen::hidden::{self, Hidden};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Debug, Clone)]
struct Row {
    hidden: Option<Hidden>,
    sequence: String,
    dark: bool,
}

impl Row {
    fn parse(s: &str, dark_default: bool) -> Row {
        let (s, dark) = match s.strip_suffix("+dark") {
            Some(r) => (r, true),
            None => (s, false),
        };
        let (h, seq) = match s.split_once('@') {
            Some((h, q)) => (h, Some(q.to_string())),
            None => (s, None),
        };
        let hidden = if h == "none" {
            None
        } else {
            Some(
                h.parse::<Hidden>()
                    .unwrap_or_else(|e| panic!("row `{s}`: {e}")),
            )
        };
        let sequence = seq.unwrap_or_else(|| {
            if hidden.is_some() {
                "campaign".into()
            } else {
                "single".into()
            }
        });
        assert!(
            sequence == "single" || sequence == "campaign",
            "row `{s}`: sequence must be single or campaign"
        );
        Row {
            dark: dark || (hidden.is_some() && dark_default),
            hidden,
            sequence,
        }
    }

    fn pinholes(&self) -> bool {
        self.hidden
            .is_some_and(|h| h.class() == "blooming" || h.class() == "ipc")
    }

    fn name(&self) -> String {
        format!(
            "{}@{}{}",
            self.hidden.map_or("none".into(), |h| h.to_string()),
            self.sequence,
            if self.dark { "+dark" } else { "" }
        )
    }

    fn baseline(&self) -> Row {
        Row {
            hidden: None,
            ..self.clone()
        }
    }
}

fn arg(args: &[String], name: &str) -> Option<String> {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1).cloned())
}

struct Ctx {
    persist: PathBuf,
    work: PathBuf,
    size: usize,
    darks: usize,
    /// Extra arguments of every `fit` (`--fit-args`; none by default).
    fit_args: Vec<String>,
}

/// Run a `persist` command; Ok(stdout) or Err(the last line of stderr).
fn persist(ctx: &Ctx, args: &[&str]) -> Result<String, String> {
    let extra: &[String] = if args.first() == Some(&"fit") {
        &ctx.fit_args
    } else {
        &[]
    };
    let out = Command::new(&ctx.persist)
        .args(args)
        .args(extra)
        .env("PERSIST_LOG", "error")
        .output()
        .map_err(|e| format!("cannot run {}: {e}", ctx.persist.display()))?;
    if out.status.success() {
        Ok(String::from_utf8_lossy(&out.stdout).into_owned())
    } else {
        let err = String::from_utf8_lossy(&out.stderr);
        Err(err
            .lines()
            .rev()
            .find(|l| !l.trim().is_empty())
            .unwrap_or("failed without a message")
            .to_string())
    }
}

fn simulate(ctx: &Ctx, row: &Row, pinholes: bool, seed: u64) -> Result<PathBuf, String> {
    let dir = ctx.work.join(format!(
        "{}{}_s{seed}",
        row.name().replace([':', '@', '+'], "_"),
        if pinholes { "_pin" } else { "" }
    ));
    if dir.join("truth").join("truth.json").exists() {
        return Ok(dir);
    }
    let _ = std::fs::remove_dir_all(&dir);
    let (size, seed_s, darks) = (
        ctx.size.to_string(),
        seed.to_string(),
        ctx.darks.to_string(),
    );
    let mut a: Vec<String> = [
        "simulate",
        "family",
        "--out",
        dir.to_str().expect("utf-8 path"),
        "--seed",
        &seed_s,
        "--size",
        &size,
        "--sequence",
        &row.sequence,
        "--darks",
        &darks,
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    if row.dark {
        a.push("--dark-pixels".into());
    }
    if pinholes {
        a.extend(["--pinholes".into(), "on".into()]);
    }
    if let Some(h) = row.hidden {
        a.extend(["--hidden".into(), h.to_string()]);
    }
    let refs: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
    persist(ctx, &refs)?;
    Ok(dir)
}

fn read_json(p: &Path) -> Option<serde_json::Value> {
    serde_json::from_str(&std::fs::read_to_string(p).ok()?).ok()
}

/// What `diagnose` printed to run next: the declared effect's `fit` command (for the
/// model as given; with nothing declared, the data-driven term's when it offered one),
/// the one that measures it, and the fit of the measurements'
/// description it tested against (absent when it tested the model itself).
#[derive(Debug, Default)]
struct Suggested {
    /// The effect or term its command adds.
    effect: Option<String>,
    command: Option<String>,
    measure_command: Option<String>,
    reference_fit: Option<String>,
}

fn read_suggested(v: &serde_json::Value) -> Suggested {
    let text = |x: Option<&serde_json::Value>| x.and_then(|c| c.as_str()).map(str::to_string);
    let first = v.get("ranking").and_then(|r| r.as_array()).and_then(|r| {
        r.iter()
            .find(|c| c.get("significant") == Some(&true.into()))
    });
    // no library effect declared: the data-driven term, when `diagnose` offered one
    let term = v
        .get("data_term")
        .filter(|t| t.get("offered") == Some(&true.into()));
    let first = first.or(term);
    Suggested {
        effect: text(first.and_then(|c| c.get("effect"))),
        command: text(first.and_then(|c| c.get("command"))),
        measure_command: text(first.and_then(|c| c.get("measure_command"))),
        reference_fit: text(v.get("reference").and_then(|r| r.get("fit_command"))),
    }
}

/// The contrast class a hidden class's evidence lies in
/// (`persist::diag::contrast::class_of` of the library effect of that name); `None` for
/// a class no library effect stands for (`shape`).
fn kind_of_class(class: &str) -> Option<&'static str> {
    persist::model::effects::lookup(class)
        .map(|def| persist::diag::contrast::class_of(def.name, def.covariate))
}

/// The kind of physics the verdict names: the first significant candidate's contrast
/// class, else the first covariate the base's residual depends on (`dependences[]`
/// with `depends`: the verdict then says the physics is of that kind in another form).
fn read_kind(v: &serde_json::Value) -> Option<String> {
    let declared = v
        .get("ranking")?
        .as_array()?
        .iter()
        .find(|c| c.get("significant") == Some(&true.into()))
        .and_then(|c| {
            let e = c.get("effect")?.as_str()?;
            let cov = c.get("covariate")?.as_str()?;
            Some(persist::diag::contrast::class_of(e, cov).to_string())
        });
    declared.or_else(|| {
        v.get("dependences")?
            .as_array()?
            .iter()
            .find(|d| d.get("depends") == Some(&true.into()))
            .and_then(|d| d.get("class")?.as_str().map(str::to_string))
    })
}

/// Declared first, every declared effect, the candidates called untestable.
fn read_diagnosis(v: &serde_json::Value) -> (Option<String>, Vec<String>, Vec<String>) {
    let name = |c: &serde_json::Value| {
        c.get("effect")
            .or_else(|| c.get("name"))
            .or_else(|| c.get("class"))
            .and_then(|e| e.as_str())
            .map(str::to_string)
    };
    let mut declared = Vec::new();
    let mut untestable = Vec::new();
    for c in v
        .get("ranking")
        .and_then(|r| r.as_array())
        .into_iter()
        .flatten()
    {
        if c.get("significant").and_then(|s| s.as_bool()) == Some(true) {
            declared.extend(name(c));
        }
        let marked = c.get("untestable").and_then(|u| u.as_bool()) == Some(true)
            || c.get("status").and_then(|s| s.as_str()) == Some("untestable");
        if marked {
            untestable.extend(name(c));
        }
    }
    for u in v
        .get("untestable")
        .and_then(|r| r.as_array())
        .into_iter()
        .flatten()
    {
        if let Some(s) = u.as_str() {
            untestable.push(s.to_string());
        } else if let Some(n) = name(u) {
            untestable.push(n);
        }
    }
    untestable.sort();
    untestable.dedup();
    (declared.first().cloned(), declared, untestable)
}

/// The pixel reference's residual RMS of model `k` in `compare`'s summary.
fn rms_of(summary: &serde_json::Value, k: usize) -> Option<f64> {
    summary
        .pointer(&format!(
            "/models/{k}/pixel_reference/residual_rms_normalised"
        ))
        .and_then(|v| v.as_f64())
}

fn compare(ctx: &Ctx, data: &Path, models: &[&Path], report: &Path) -> Result<Vec<f64>, String> {
    let mut a = vec![
        "compare".to_string(),
        "--input".into(),
        data.display().to_string(),
        "--report".into(),
        report.display().to_string(),
    ];
    for m in models {
        a.extend(["--model".into(), m.display().to_string()]);
    }
    let refs: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
    persist(ctx, &refs)?;
    let s = read_json(&report.join("summary.json")).ok_or("no summary.json")?;
    (0..models.len())
        .map(|k| rms_of(&s, k).ok_or_else(|| "no pixel_reference".to_string()))
        .collect()
}

/// True persistence planes of a simulation, in exposure order.
fn truths(dir: &Path) -> Result<Vec<ndarray::Array2<f32>>, String> {
    let mut names: Vec<PathBuf> = std::fs::read_dir(dir.join("truth"))
        .map_err(|e| e.to_string())?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.to_string_lossy().ends_with(".truth.hdf5"))
        .collect();
    names.sort();
    names
        .iter()
        .map(|p| {
            let f = hdf5::File::open(p).map_err(|e| format!("{}: {e}", p.display()))?;
            f.dataset("true_persistence")
                .and_then(|d| d.read_2d::<f32>())
                .map_err(|e| format!("{}: {e}", p.display()))
        })
        .collect()
}

/// `persist run` with `model`; over the touched pixels' samples after the first
/// exposure, the fraction of those truly at or above 0.1 e-/s left unflagged (missed)
/// and of those truly below it flagged (over-flagged).
fn run_missed(
    ctx: &Ctx,
    data: &Path,
    model: &Path,
    tag: &str,
    truth: &[ndarray::Array2<f32>],
    touched: &ndarray::Array2<bool>,
) -> Result<(f64, f64), String> {
    let out = data.with_extension(format!("run_{tag}"));
    let ck = data.with_extension(format!("ck_{tag}"));
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&ck);
    persist(
        ctx,
        &[
            "run",
            "--input",
            data.to_str().unwrap_or_default(),
            "--output",
            out.to_str().unwrap_or_default(),
            "--checkpoints",
            ck.to_str().unwrap_or_default(),
            "--model",
            model.to_str().unwrap_or_default(),
            "--quiet",
        ],
    )?;
    let mut outs: Vec<PathBuf> = walk_h5(&out);
    outs.sort();
    if outs.len() != truth.len() {
        return Err(format!(
            "{} outputs for {} exposures",
            outs.len(),
            truth.len()
        ));
    }
    let (mut missed, mut above, mut over, mut below) = (0usize, 0usize, 0usize, 0usize);
    for (k, p) in outs.iter().enumerate().skip(1) {
        let (e, _, _) = persist::product::read_output(p).map_err(|e| e.to_string())?;
        for ((t, f), &tp) in truth[k].iter().zip(e.flags.iter()).zip(touched.iter()) {
            if !tp {
                continue;
            }
            let flagged = f & bits::PERSIST != 0;
            if *t >= 0.1 {
                above += 1;
                missed += usize::from(!flagged);
            } else {
                below += 1;
                over += usize::from(flagged);
            }
        }
    }
    let _ = std::fs::remove_dir_all(&out);
    let _ = std::fs::remove_dir_all(&ck);
    let frac = |a: usize, n: usize| {
        if n == 0 {
            f64::NAN
        } else {
            a as f64 / n as f64
        }
    };
    Ok((frac(missed, above), frac(over, below)))
}

fn walk_h5(dir: &Path) -> Vec<PathBuf> {
    let mut v = Vec::new();
    if let Ok(rd) = std::fs::read_dir(dir) {
        for e in rd.flatten() {
            let p = e.path();
            if p.is_dir() {
                v.extend(walk_h5(&p));
            } else if p.extension().is_some_and(|x| x == "h5") {
                v.push(p);
            }
        }
    }
    v
}

#[derive(Default, Debug, Clone, serde::Serialize, serde::Deserialize)]
struct Run {
    row: String,
    seed: u64,
    fit_ok: bool,
    fit_error: Option<String>,
    diagnose_error: Option<String>,
    declared_first: Option<String>,
    /// The kind of physics the verdict names: the declared effect's contrast class, or
    /// else the covariate the base's residual depends on ([`read_kind`]).
    kind_named: Option<String>,
    declared: Vec<String>,
    untestable: Vec<String>,
    fit_with_error: Option<String>,
    rms_before: Option<f64>,
    rms_after: Option<f64>,
    rms_baseline: Option<f64>,
    excess_before: Option<f64>,
    excess_after: Option<f64>,
    /// `1 - RMS(baseline) / RMS(before)`: the share of the pixel reference's residual RMS
    /// that the hidden effect accounts for.
    hidden_share: Option<f64>,
    halved: Option<bool>,
    /// The pixel reference's RMS of the flagging models themselves (`fit`'s default
    /// model, and the one the printed command writes), whatever `diagnose` tested
    /// against.
    flagging_before: Option<f64>,
    flagging_after: Option<f64>,
    touched_pixels: Option<usize>,
    missed_before: Option<f64>,
    missed_after: Option<f64>,
    over_before: Option<f64>,
    over_after: Option<f64>,
    /// What the fit that followed added: the declared effect or the data-driven term.
    suggested: Option<String>,
    /// Wall time of `diagnose` alone.
    diagnose_seconds: Option<f64>,
    seconds: f64,
}

/// The baseline's own fit and RMS (cached per fit command): `fit`'s defaults, or with
/// `reference` the very `fit` command `diagnose` printed for the measurements'
/// description of the hidden row (`reference.fit_command`, `persist::diag::reference`)
/// run on the baseline's data instead, so that both RMS come from the same description.
fn baseline_rms(
    ctx: &Ctx,
    b: &Path,
    reference: Option<&str>,
    cache: &mut BTreeMap<Vec<String>, Option<f64>>,
) -> Option<f64> {
    let input = b.to_str()?;
    let words = match reference {
        Some(line) => printed_words(line),
        None => vec!["fit", "--input", input, "--out", ""],
    };
    // the command with its input replaced and its output left out: the cache key
    let key = with_values(&words, input, "");
    if let Some(v) = cache.get(&key) {
        return *v;
    }
    let m = b.with_extension(format!("baseline{}.json", cache.len()));
    let a = with_values(&words, input, m.to_str()?);
    let refs: Vec<&str> = a.iter().map(String::as_str).collect();
    let v = persist(ctx, &refs)
        .ok()
        .and_then(|_| compare(ctx, b, &[&m], &m.with_extension("compare")).ok())
        .map(|v| v[0]);
    cache.insert(key, v);
    v
}

/// The words of a printed `persist ...` command line, without `persist`.
fn printed_words(line: &str) -> Vec<&str> {
    line.split_whitespace()
        .skip_while(|w| *w == "persist")
        .collect()
}

/// Command words with the values of `--input` and `--out` replaced.
fn with_values(words: &[&str], input: &str, out: &str) -> Vec<String> {
    let mut a = Vec::with_capacity(words.len());
    let mut it = words.iter();
    while let Some(w) = it.next() {
        a.push(w.to_string());
        match *w {
            "--input" => a.push(input.to_string()),
            "--out" => a.push(out.to_string()),
            _ => continue,
        }
        it.next();
    }
    a
}

/// Run a `persist ...` command line as `diagnose` prints it; Ok(its `--out` path).
fn run_printed(ctx: &Ctx, line: &str) -> Result<PathBuf, String> {
    let words = printed_words(line);
    let out = words
        .iter()
        .position(|w| *w == "--out")
        .and_then(|i| words.get(i + 1))
        .map(PathBuf::from)
        .ok_or_else(|| format!("no --out in `{line}`"))?;
    persist(ctx, &words).map(|_| out)
}

fn one(ctx: &Ctx, row: &Row, seed: u64, cache: &mut BTreeMap<Vec<String>, Option<f64>>) -> Run {
    let t0 = Instant::now();
    let mut r = Run {
        row: row.name(),
        seed,
        ..Run::default()
    };
    let pin = row.pinholes();
    let d = match simulate(ctx, row, pin, seed) {
        Ok(d) => d,
        Err(e) => {
            r.fit_error = Some(format!("simulate: {e}"));
            return r;
        }
    };
    let m = d.with_extension("model.json");
    if let Err(e) = persist(
        ctx,
        &[
            "fit",
            "--input",
            d.to_str().unwrap_or_default(),
            "--out",
            m.to_str().unwrap_or_default(),
        ],
    ) {
        r.fit_error = Some(e);
        r.seconds = t0.elapsed().as_secs_f64();
        return r;
    }
    r.fit_ok = true;
    let dj = d.with_extension("diag.json");
    let mut suggested: Suggested = Suggested::default();
    let t_diagnose = Instant::now();
    let diagnosed = persist(
        ctx,
        &[
            "diagnose",
            "--input",
            d.to_str().unwrap_or_default(),
            "--model",
            m.to_str().unwrap_or_default(),
            "--json",
            dj.to_str().unwrap_or_default(),
        ],
    );
    r.diagnose_seconds = Some(t_diagnose.elapsed().as_secs_f64());
    match diagnosed {
        Err(e) => r.diagnose_error = Some(e),
        Ok(_) => {
            if let Some(v) = read_json(&dj) {
                let (first, declared, untestable) = read_diagnosis(&v);
                r.declared_first = first;
                r.declared = declared;
                r.untestable = untestable;
                suggested = read_suggested(&v);
                r.suggested = suggested.effect.clone();
                r.kind_named = read_kind(&v);
            }
        }
    }
    // step 4: the commands `diagnose` printed for the declared effect
    let mut m2 = None;
    if let Some(cmd) = &suggested.command {
        match run_printed(ctx, cmd) {
            Ok(p) => m2 = Some(p),
            Err(e) => r.fit_with_error = Some(e),
        }
    }
    let with_ok = m2.is_some();
    // step 5: the error, of the measurements' description when `diagnose` tested
    // against one, else of the model
    let printed = |line: &Option<String>| line.as_ref().and_then(|l| run_printed(ctx, l).ok());
    let described =
        printed(&suggested.reference_fit).map(|a| (a, printed(&suggested.measure_command)));
    let models_as_given: Vec<&Path> = std::iter::once(m.as_path()).chain(m2.as_deref()).collect();
    let models: Vec<&Path> = match &described {
        Some((a, b)) => std::iter::once(a.as_path()).chain(b.as_deref()).collect(),
        None => models_as_given.clone(),
    };
    if let Ok(v) = compare(ctx, &d, &models, &d.with_extension("compare")) {
        r.rms_before = v.first().copied();
        r.rms_after = v.get(1).copied();
    }
    // the flagging models themselves: the models just compared, unless those were
    // the descriptions
    (r.flagging_before, r.flagging_after) = match described {
        None => (r.rms_before, r.rms_after),
        Some(_) => compare(
            ctx,
            &d,
            &models_as_given,
            &d.with_extension("compare_flagging"),
        )
        .map_or((None, None), |v| (v.first().copied(), v.get(1).copied())),
    };
    if row.hidden.is_some() {
        if let Ok(b) = simulate(ctx, &row.baseline(), pin, seed) {
            r.rms_baseline = baseline_rms(ctx, &b, suggested.reference_fit.as_deref(), cache);
            if let (Some(x), Some(b0)) = (r.rms_before, r.rms_baseline) {
                r.excess_before = Some(x - b0);
                r.hidden_share = Some(1.0 - b0 / x);
                if let Some(y) = r.rms_after {
                    r.excess_after = Some(y - b0);
                    // no excess to halve: not counted either way
                    r.halved = (x > b0).then_some(y - b0 <= 0.5 * (x - b0));
                }
            }
            if let (Ok(td), Ok(tb)) = (truths(&d), truths(&b)) {
                let mut touched = ndarray::Array2::from_elem(td[0].dim(), false);
                for (a, b) in td.iter().zip(&tb) {
                    ndarray::Zip::from(&mut touched)
                        .and(a)
                        .and(b)
                        .for_each(|t, a, b| *t |= (a - b).abs() > 0.01);
                }
                r.touched_pixels = Some(touched.iter().filter(|t| **t).count());
                let before = run_missed(ctx, &d, &m, "before", &td, &touched).ok();
                r.missed_before = before.map(|v| v.0);
                r.over_before = before.map(|v| v.1);
                if let Some(m2) = m2.as_deref().filter(|_| with_ok) {
                    let after = run_missed(ctx, &d, m2, "after", &td, &touched).ok();
                    r.missed_after = after.map(|v| v.0);
                    r.over_after = after.map(|v| v.1);
                }
            }
        }
    }
    r.seconds = t0.elapsed().as_secs_f64();
    r
}

fn default_rows(held_out: bool) -> Vec<String> {
    let mut v: Vec<String> = [
        "none@single",
        "none@single+dark",
        "none@campaign",
        "none@campaign+dark",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    for h in hidden::ALL {
        if held_out || !h.held_aside() {
            v.push(h.to_string());
        }
    }
    v
}

fn f3(x: Option<f64>) -> String {
    x.filter(|v| v.is_finite())
        .map_or("-".into(), |v| format!("{v:.3}"))
}

/// The paths whose committed trees identify the code behind a run (`--resume`).
const CODE_PATHS: [&str; 4] = [
    "src",
    "Cargo.toml",
    "Cargo.lock",
    "examples/family_matrix.rs",
];

/// The key of the code that produces a run: the git object ids of [`CODE_PATHS`] at
/// HEAD, or None when the repository cannot say or those paths have uncommitted changes.
fn code_key() -> Option<String> {
    let git = |a: &[&str]| {
        Command::new("git")
            .args(a)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    let mut status = vec!["status", "--porcelain", "--"];
    status.extend(CODE_PATHS);
    if !git(&status)?.is_empty() {
        return None;
    }
    let ids: Option<Vec<String>> = CODE_PATHS
        .iter()
        .map(|p| git(&["rev-parse", &format!("HEAD:{p}")]))
        .collect();
    Some(ids?.join(","))
}

/// One line of the `--resume` file.
#[derive(serde::Serialize, serde::Deserialize)]
struct Stored {
    code: String,
    settings: String,
    run: Run,
}

/// The runs of `file` produced by `code` with `settings`, by (row, seed); a missing file
/// is none, an unreadable line is skipped.
fn stored_runs(file: &Path, code: &str, settings: &str) -> BTreeMap<(String, u64), Run> {
    std::fs::read_to_string(file)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| serde_json::from_str::<Stored>(l).ok())
        .filter(|s| s.code == code && s.settings == settings)
        .map(|s| ((s.run.row.clone(), s.run.seed), s.run))
        .collect()
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let size: usize = arg(&args, "--size").map_or(64, |s| s.parse().expect("--size"));
    let seeds: u64 = arg(&args, "--seeds").map_or(5, |s| s.parse().expect("--seeds"));
    let first: u64 = arg(&args, "--first-seed").map_or(1, |s| s.parse().expect("--first-seed"));
    let darks: usize = arg(&args, "--darks").map_or(persist::trapgen::DEFAULT_DARKS, |s| {
        s.parse().expect("--darks")
    });
    let held_out = args.iter().any(|a| a == "--held-out");
    let dark_default = args.iter().any(|a| a == "--dark-pixels");
    if !held_out && first + seeds > hidden::HELD_ASIDE_FIRST_SEED {
        panic!(
            "seeds from {} on are held aside for the final proof (--held-out)",
            hidden::HELD_ASIDE_FIRST_SEED
        );
    }
    let rows: Vec<Row> = arg(&args, "--rows")
        .map(|s| s.split(',').map(str::to_string).collect())
        .unwrap_or_else(|| default_rows(held_out))
        .iter()
        .map(|s| Row::parse(s, dark_default))
        .collect();
    if !held_out {
        if let Some(r) = rows
            .iter()
            .find(|r| r.hidden.is_some_and(|h| h.held_aside()))
        {
            panic!(
                "{} is held aside for the final proof (--held-out)",
                r.name()
            );
        }
    }
    let out = PathBuf::from(
        arg(&args, "--out").unwrap_or("docs/validation/diagnostics_family.md".into()),
    );
    let exe = std::env::current_exe().expect("current exe");
    let default_bin = exe
        .parent()
        .and_then(|p| p.parent())
        .map(|p| p.join("persist"))
        .unwrap_or_else(|| PathBuf::from("persist"));
    let ctx = Ctx {
        persist: arg(&args, "--persist").map_or(default_bin, PathBuf::from),
        work: PathBuf::from(arg(&args, "--work").unwrap_or("target/family_matrix".into())),
        size,
        darks,
        fit_args: arg(&args, "--fit-args")
            .map(|s| s.split_whitespace().map(String::from).collect())
            .unwrap_or_default(),
    };
    std::fs::create_dir_all(&ctx.work).expect("work directory");
    let mut cache = BTreeMap::new();
    let mut runs: Vec<Run> = Vec::new();
    let jsonl = out.with_extension("jsonl");
    if let Some(p) = out.parent() {
        std::fs::create_dir_all(p).expect("output directory");
    }
    let resume = arg(&args, "--resume").map(PathBuf::from);
    let code = resume.as_ref().and_then(|_| code_key());
    let settings = format!("size {size}, darks {darks}, fit {:?}", ctx.fit_args);
    let mut stored = match (&resume, &code) {
        (Some(f), Some(c)) => stored_runs(f, c, &settings),
        (Some(f), None) => {
            eprintln!(
                "--resume {}: the code ({}) has uncommitted changes or is not a git checkout; nothing is reused or stored",
                f.display(),
                CODE_PATHS.join(", ")
            );
            BTreeMap::new()
        }
        _ => BTreeMap::new(),
    };
    let mut reused = 0;
    let mut lines = String::new();
    for row in &rows {
        for seed in first..first + seeds {
            let r = match stored.remove(&(row.name(), seed)) {
                Some(r) => {
                    reused += 1;
                    r
                }
                None => {
                    let r = one(&ctx, row, seed, &mut cache);
                    if let (Some(f), Some(c)) = (&resume, &code) {
                        append_stored(f, c, &settings, &r);
                    }
                    r
                }
            };
            eprintln!(
                "{} seed {seed}: fit {} | first {:?} | kind {:?} | untestable {:?} | excess {} -> {} | missed {} -> {} | {:.0} s{}",
                r.row,
                if r.fit_ok { "ok" } else { "FAILED" },
                r.declared_first,
                r.kind_named,
                r.untestable,
                f3(r.excess_before),
                f3(r.excess_after),
                f3(r.missed_before),
                f3(r.missed_after),
                r.seconds,
                r.fit_error
                    .as_ref()
                    .or(r.diagnose_error.as_ref())
                    .map_or(String::new(), |e| format!(" | {e}"))
            );
            lines.push_str(&serde_json::to_string(&r).expect("json"));
            lines.push('\n');
            std::fs::write(&jsonl, &lines).expect("write jsonl");
            runs.push(r);
            write_table(
                &args, &rows, &runs, reused, &out, &jsonl, size, first, seeds,
            );
        }
    }
    write_table(
        &args, &rows, &runs, reused, &out, &jsonl, size, first, seeds,
    );
    eprintln!("wrote {}", out.display());
}

/// Append one finished run to the `--resume` file (one line, flushed before the next
/// run starts, so a stopped matrix keeps every run it finished).
fn append_stored(file: &Path, code: &str, settings: &str, run: &Run) {
    use std::io::Write as _;
    let line = serde_json::to_string(&Stored {
        code: code.into(),
        settings: settings.into(),
        run: run.clone(),
    })
    .expect("json");
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(file)
        .unwrap_or_else(|e| panic!("--resume {}: {e}", file.display()));
    writeln!(f, "{line}")
        .and_then(|()| f.sync_all())
        .unwrap_or_else(|e| panic!("--resume {}: {e}", file.display()));
}

/// The Markdown page (rewritten after every run, so a long matrix can be stopped).
#[allow(clippy::too_many_arguments)]
fn write_table(
    args: &[String],
    rows: &[Row],
    runs: &[Run],
    reused: usize,
    out: &Path,
    jsonl: &Path,
    size: usize,
    first: u64,
    seeds: u64,
) {
    let mut md = String::new();
    let now = chrono::Utc::now().format("%Y-%m-%d %H:%M UTC");
    let machine = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    // `git describe --always --dirty`; a bare commit id (no tag) is not written: the
    // repository's text carries no commit ids, so only the tree's state is recorded
    let describe = Command::new("git")
        .args(["describe", "--always", "--dirty"])
        .output()
        .ok()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
        .unwrap_or_default();
    let bare_id = describe
        .trim_end_matches("-dirty")
        .chars()
        .all(|c| c.is_ascii_hexdigit());
    let describe = if bare_id {
        format!(
            "no tag (commit id not recorded), {}",
            if describe.ends_with("-dirty") {
                "dirty"
            } else {
                "clean"
            }
        )
    } else {
        describe
    };
    writeln!(
        md,
        "# Diagnostics on the family of the second truth generator\n"
    )
    .unwrap();
    writeln!(
        md,
        "Generated {now} on {machine} ({cores} cores), `git describe --always --dirty`: `{describe}`.\n\nCommand: `cargo run --release --example family_matrix -- {}`\n",
        args.join(" ")
    )
    .unwrap();
    writeln!(
        md,
        "Data: `persist simulate family` ({size} x {size}, seeds {first}..{}, see `persist::trapgen` for the physics and the forms). Every run uses the default commands only (`examples/family_matrix.rs` docs): `fit`, `diagnose`, then the `fit` commands `diagnose` prints for the effect declared first, or, with nothing declared, for the data-driven term it offers (column \"added\"). Kind named: the declared effect's contrast class, or else the covariate the verdict says the residual depends on (\"of this kind in another form\"). Excess RMS: the pixel reference's normalised residual RMS (`compare`'s \"pixel reference\", the reference `diagnose` judges its offers against) minus the baseline's (same seed, nothing hidden, its own fit), of the measurements' description `diagnose` tested against when it fitted one (the baseline fitted with the same printed command). Hidden share: `1 - RMS(baseline) / RMS(before)`, the share of that RMS the hidden effect accounts for, about the most a candidate capturing it exactly could gain over all cells; \"declared where share >= gate\": the runs where it reaches `diagnose`'s held-out gate ({HELD_OUT_MIN_GAIN}), and in how many of them the class was declared first. Flagging model's pixel reference: the same RMS of `fit`'s default model and of the model the printed command writes (the models that flag), and in how many runs it fell. Missed: the fraction of samples of touched pixels with a true persistence current of at least 0.1 e-/s that `persist run` did not flag; over-flagged: of those truly below it, the fraction flagged. Diagnose s: the wall time of `diagnose` alone, with its defaults (this machine; other work may run beside it).\n",
        first + seeds - 1
    )
    .unwrap();
    writeln!(
        md,
        "| row | runs | fit ok | diagnose ran | class named first | kind named first | kind (each run) | declared first (each run) | untestable answers | added (each run) | excess RMS before -> after (median) | hidden share of RMS (each run) | declared where share >= gate | halved | flagging model's pixel reference before -> after (median; fell in) | missed@0.1 touched before -> after (median) | over-flagged@0.1 touched before -> after (median) | diagnose s (median, max) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
    )
    .unwrap();
    for row in rows {
        let rs: Vec<&Run> = runs.iter().filter(|r| r.row == row.name()).collect();
        let n = rs.len();
        let class = row.hidden.map(|h| h.class());
        let named = rs
            .iter()
            .filter(|r| match class {
                Some(c) => r.declared_first.as_deref() == Some(c),
                None => r.declared_first.is_none() && r.fit_ok && r.diagnose_error.is_none(),
            })
            .count();
        let kind = class.map(kind_of_class);
        let kind_named = rs
            .iter()
            .filter(|r| match kind {
                Some(k) => k.is_some() && r.kind_named.as_deref() == k,
                None => r.kind_named.is_none() && r.fit_ok && r.diagnose_error.is_none(),
            })
            .count();
        let kinds: Vec<String> = rs
            .iter()
            .map(|r| r.kind_named.clone().unwrap_or("nothing".into()))
            .collect();
        let firsts: Vec<String> = rs
            .iter()
            .map(|r| {
                if !r.fit_ok {
                    "fit failed".into()
                } else if r.diagnose_error.is_some() {
                    "diagnose failed".into()
                } else {
                    r.declared_first.clone().unwrap_or("nothing".into())
                }
            })
            .collect();
        let unt: Vec<String> = rs
            .iter()
            .flat_map(|r| r.untestable.iter().cloned())
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        let med = |f: &dyn Fn(&Run) -> Option<f64>| -> Option<f64> {
            let mut v: Vec<f64> = rs
                .iter()
                .filter_map(|r| f(r))
                .filter(|x| x.is_finite())
                .collect();
            v.sort_by(f64::total_cmp);
            (!v.is_empty()).then(|| v[v.len() / 2])
        };
        let halved = rs.iter().filter(|r| r.halved == Some(true)).count();
        let shares = if class.is_none() {
            "-".to_string()
        } else {
            rs.iter()
                .map(|r| r.hidden_share.map_or("-".into(), |x| format!("{x:.2}")))
                .collect::<Vec<_>>()
                .join(", ")
        };
        // the runs where removing the hidden effect lowers the RMS by at least what the
        // held-out gate asks of a candidate over all cells
        let over_gate: Vec<&&Run> = rs
            .iter()
            .filter(|r| r.hidden_share.is_some_and(|x| x >= HELD_OUT_MIN_GAIN))
            .collect();
        let visible = match class {
            Some(c) if !over_gate.is_empty() => format!(
                "{} of {}",
                over_gate
                    .iter()
                    .filter(|r| r.declared_first.as_deref() == Some(c))
                    .count(),
                over_gate.len()
            ),
            _ => "-".into(),
        };
        let halved_of = rs.iter().filter(|r| r.halved.is_some()).count();
        writeln!(
            md,
            "| {} | {n} | {} | {} | {} | {} | {} | {} | {} | {} | {} -> {} | {} | {} | {} | {} -> {} ({}) | {} -> {} | {} -> {} | {} |",
            row.name(),
            rs.iter().filter(|r| r.fit_ok).count(),
            rs.iter()
                .filter(|r| r.fit_ok && r.diagnose_error.is_none())
                .count(),
            match class {
                Some(c) => format!("{c}: {named} of {n}"),
                None => format!("nothing declared: {named} of {n}"),
            },
            match kind {
                Some(Some(k)) => format!("{k}: {kind_named} of {n}"),
                Some(None) => "- (no library class)".into(),
                None => format!("nothing named: {kind_named} of {n}"),
            },
            kinds.join(", "),
            firsts.join(", "),
            if unt.is_empty() {
                "-".into()
            } else {
                unt.join(", ")
            },
            rs.iter()
                .map(|r| r.suggested.clone().unwrap_or("nothing".into()))
                .collect::<Vec<_>>()
                .join(", "),
            f3(med(&|r| r.excess_before)),
            f3(med(&|r| r.excess_after)),
            shares,
            visible,
            if halved_of == 0 {
                "-".into()
            } else {
                format!("{halved} of {halved_of}")
            },
            f3(med(&|r| r.flagging_before)),
            f3(med(&|r| r.flagging_after)),
            {
                let pairs: Vec<(f64, f64)> = rs
                    .iter()
                    .filter_map(|r| r.flagging_before.zip(r.flagging_after))
                    .collect();
                let fell = pairs.iter().filter(|(b, a)| a < b).count();
                format!("{fell} of {}", pairs.len())
            },
            f3(med(&|r| r.missed_before)),
            f3(med(&|r| r.missed_after)),
            f3(med(&|r| r.over_before)),
            f3(med(&|r| r.over_after)),
            match (
                med(&|r| r.diagnose_seconds),
                rs.iter().filter_map(|r| r.diagnose_seconds).reduce(f64::max),
            ) {
                (Some(m), Some(x)) => format!("{m:.1}, {x:.1}"),
                _ => "-".into(),
            },
        )
        .unwrap();
    }
    let errors: BTreeMap<String, usize> = runs
        .iter()
        .filter_map(|r| r.fit_error.clone().or(r.diagnose_error.clone()))
        .fold(BTreeMap::new(), |mut m, e| {
            *m.entry(e).or_insert(0) += 1;
            m
        });
    if !errors.is_empty() {
        writeln!(md, "\nFailures (message, runs):\n").unwrap();
        for (e, k) in errors {
            writeln!(md, "- {k} x `{}`", e.replace('`', "'")).unwrap();
        }
    }
    let secs: f64 = runs.iter().map(|r| r.seconds).sum();
    writeln!(
        md,
        "\n{} runs, {secs:.0} s in all. Per-run JSON lines: `{}`.",
        runs.len(),
        jsonl.display()
    )
    .unwrap();
    if reused > 0 {
        writeln!(
            md,
            "{reused} of these runs were taken from the `--resume` file: produced earlier by the same code ({}) with the same settings.",
            CODE_PATHS.join(", ")
        )
        .unwrap();
    }
    std::fs::write(out, md).expect("write the table");
}
