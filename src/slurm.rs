//! Reprocessing on a Slurm cluster: `persist slurm` writes a [`crate::tile::Plan`] and
//! the batch scripts of a split run, and optionally submits them:
//!
//! - `tiles.sbatch`: a job array with one task per (detector, tile), each running
//!   `persist tile --plan PLAN --task $SLURM_ARRAY_TASK_ID`;
//! - `assemble.sbatch`: one job, submitted with `--dependency=afterok:ARRAY` (it starts
//!   only when every array task succeeded), running `persist assemble --plan PLAN`;
//! - `submit.sh`: the two `sbatch` calls, for submitting by hand later;
//! - `run_local.sh`: the same jobs one after the other on this machine, without Slurm.
//!
//! The scripts name the `persist` executable by its absolute path (the one that wrote
//! them, or `--persist`), which must be reachable from the compute nodes, as must the
//! directories. Logs go to `WORK/logs/`.

use crate::error::{Error, ErrorKind, Result};
use crate::tile::{Grid, Plan};
use std::path::{Path, PathBuf};

/// `sbatch` settings of the generated scripts.
#[derive(Debug, Clone, Default)]
pub struct BatchOptions {
    /// The `persist` executable the jobs run (absolute path).
    pub persist: PathBuf,
    pub partition: Option<String>,
    /// Wall-clock limit per job, in Slurm's syntax (`HH:MM:SS`).
    pub time: Option<String>,
    pub cpus_per_task: usize,
    /// Memory per job, in Slurm's syntax (`4G`).
    pub mem: Option<String>,
    /// Further `#SBATCH` lines, verbatim (`--account=...`, `--qos=...`).
    pub extra: Vec<String>,
}

/// The scripts written for a plan.
#[derive(Debug, Clone)]
pub struct Scripts {
    pub plan: PathBuf,
    pub tiles: PathBuf,
    pub assemble: PathBuf,
    pub submit: PathBuf,
    pub run_local: PathBuf,
}

/// Quote a word for a POSIX shell.
fn sh_quote(s: &str) -> String {
    if !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b"/._-+=:,@".contains(&b))
    {
        s.to_string()
    } else {
        format!("'{}'", s.replace('\'', r"'\''"))
    }
}

fn path_word(p: &Path) -> String {
    sh_quote(&p.to_string_lossy())
}

fn header(name: &str, log: &Path, o: &BatchOptions) -> String {
    let mut h = format!(
        "#!/bin/bash\n#SBATCH --job-name={name}\n#SBATCH --output={}\n#SBATCH --cpus-per-task={}\n",
        log.display(),
        o.cpus_per_task.max(1)
    );
    for (k, v) in [
        ("partition", &o.partition),
        ("time", &o.time),
        ("mem", &o.mem),
    ] {
        if let Some(v) = v {
            h += &format!("#SBATCH --{k}={v}\n");
        }
    }
    for e in &o.extra {
        h += &format!("#SBATCH {e}\n");
    }
    h
}

/// Write the plan and the scripts under the plan's work directory.
pub fn write_scripts(plan: &Plan, o: &BatchOptions) -> Result<Scripts> {
    for (what, p) in [
        ("--input", &plan.input),
        ("--output", &plan.output),
        ("--checkpoints", &plan.checkpoints),
        ("--work", &plan.work),
    ] {
        if p.to_string_lossy().contains(['\n', '%']) {
            return Err(Error::new(
                ErrorKind::Usage,
                "a newline or `%` in a path cannot go into a batch script",
            )
            .field(what)
            .path(p));
        }
    }
    let plan_path = plan.save()?;
    let logs = plan.work.join("logs");
    std::fs::create_dir_all(&logs).map_err(|e| Error::io(&logs, e))?;
    let exe = path_word(&o.persist);
    let planw = path_word(&plan_path);
    let n = plan.tasks();
    let tiles = format!(
        "{}#SBATCH --array=0-{}\n\n# One task per (detector, {}tile): {} detector(s){} x {} tile(s).\nset -euo pipefail\nexec {exe} tile --plan {planw} --task \"$SLURM_ARRAY_TASK_ID\"\n",
        header("persist-tiles", &logs.join("tile_%a.out"), o),
        n - 1,
        if plan.time.is_some() { "time span, " } else { "" },
        plan.detectors.len(),
        plan.time.as_ref().map_or(String::new(), |t| format!(
            " x up to {} time span(s)",
            t.spans_requested
        )),
        plan.grid.count(),
    );
    let assemble = format!(
        "{}\n# Submitted with --dependency=afterok:<the tiles' array job>.\nset -euo pipefail\nexec {exe} assemble --plan {planw}\n",
        header("persist-assemble", &logs.join("assemble.out"), o),
    );
    let w = &plan.work;
    let submit = format!(
        "#!/bin/bash\n# Submit the tile array, then the assembly when every tile succeeded.\nset -euo pipefail\ntiles=$(sbatch --parsable {t})\ntiles=${{tiles%%;*}}\nassemble=$(sbatch --parsable --dependency=afterok:\"$tiles\" {a})\nassemble=${{assemble%%;*}}\necho \"tiles $tiles assemble $assemble\"\n",
        t = path_word(&w.join("tiles.sbatch")),
        a = path_word(&w.join("assemble.sbatch")),
    );
    let run_local = format!(
        "#!/bin/bash\n# The same jobs one after the other on this machine, without Slurm.\nset -euo pipefail\nfor task in $(seq 0 {}); do\n  {exe} tile --plan {planw} --task \"$task\"\ndone\n{exe} assemble --plan {planw}\n",
        n - 1
    );
    let write = |name: &str, text: &str| -> Result<PathBuf> {
        let p = w.join(name);
        crate::textfile::write_text(&p, text)?;
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755))
            .map_err(|e| Error::io(&p, e))?;
        Ok(p)
    };
    Ok(Scripts {
        plan: plan_path,
        tiles: write("tiles.sbatch", &tiles)?,
        assemble: write("assemble.sbatch", &assemble)?,
        submit: write("submit.sh", &submit)?,
        run_local: write("run_local.sh", &run_local)?,
    })
}

/// `sbatch --parsable ARGS SCRIPT`; the job id.
fn sbatch(args: &[String], script: &Path) -> Result<String> {
    let out = std::process::Command::new("sbatch")
        .arg("--parsable")
        .args(args)
        .arg(script)
        .output()
        .map_err(|e| {
            Error::new(
                ErrorKind::Io,
                format!("cannot run sbatch (is Slurm installed?): {e}"),
            )
            .path(script)
        })?;
    if !out.status.success() {
        return Err(Error::new(
            ErrorKind::Io,
            format!(
                "sbatch failed ({}): {}",
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            ),
        )
        .path(script));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let id = text
        .trim()
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_string();
    if id.is_empty() || !id.bytes().all(|b| b.is_ascii_digit()) {
        return Err(Error::new(
            ErrorKind::Io,
            format!("sbatch printed no job id: `{}`", text.trim()),
        )
        .path(script));
    }
    Ok(id)
}

/// Submit the tile array, then the assembly depending on it (`afterok`). Returns
/// (array job id, assembly job id).
pub fn submit(s: &Scripts) -> Result<(String, String)> {
    let tiles = sbatch(&[], &s.tiles)?;
    let assemble = sbatch(&[format!("--dependency=afterok:{tiles}")], &s.assemble)?;
    Ok((tiles, assemble))
}

/// Arguments of `persist slurm`.
#[derive(clap::Args, Debug)]
pub struct SlurmArgs {
    /// Directory of Level-1 exposure products (as `persist run`).
    #[arg(long)]
    pub input: PathBuf,
    /// Directory for the output products.
    #[arg(long)]
    pub output: PathBuf,
    /// Directory of the checkpoints (the jobs start from the newest of each detector;
    /// the assembly writes the final one).
    #[arg(long)]
    pub checkpoints: PathBuf,
    /// Directory for the plan, the scripts, the logs and the tiles' work files (on a
    /// file system the compute nodes share).
    #[arg(long)]
    pub work: PathBuf,
    /// Model file (JSON); the built-in default if absent.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Tiles per detector, ROWSxCOLS (one array task each).
    #[arg(long, default_value = "1x1")]
    pub tiles: Grid,
    /// Cut each detector's history into N time spans of equal exposure counts (one
    /// array task per span and tile). A span starts from the retained checkpoint before
    /// it, else from zero after a warm-up (its outputs record the carry-in bound).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=100000))]
    pub time_spans: u64,
    /// Seconds of data a span that starts from zero steps before its first published
    /// exposure [default: the model's carry-over time, when one exposure's largest
    /// response has decayed to the low threshold].
    #[arg(long)]
    pub warmup_s: Option<f64>,
    /// Start every detector from a zero state at its first product instead of its newest
    /// checkpoint, rewriting published outputs (a reprocessing of the whole input).
    #[arg(long)]
    pub from_start: bool,
    /// Continue from checkpoints made with a different model.
    #[arg(long)]
    pub allow_model_change: bool,
    /// Keep this many newest checkpoints per detector (plus one per hour of data).
    #[arg(long, default_value_t = 20)]
    pub keep_latest: usize,
    /// Do not keep one checkpoint per hour of data beyond the newest ones.
    #[arg(long)]
    pub no_hourly_checkpoints: bool,
    /// Submit with sbatch (the array, then the assembly with afterok) and print the job ids.
    #[arg(long)]
    pub submit: bool,
    /// The persist executable the jobs run [default: this one].
    #[arg(long)]
    pub persist: Option<PathBuf>,
    /// `#SBATCH --partition`.
    #[arg(long)]
    pub partition: Option<String>,
    /// `#SBATCH --time` per job (HH:MM:SS).
    #[arg(long)]
    pub time: Option<String>,
    /// `#SBATCH --cpus-per-task`.
    #[arg(long, default_value_t = 1)]
    pub cpus_per_task: usize,
    /// `#SBATCH --mem` per job (e.g. 4G).
    #[arg(long)]
    pub mem: Option<String>,
    /// A further `#SBATCH` option, verbatim (repeatable), e.g. `--sbatch=--account=sx`.
    #[arg(long = "sbatch", allow_hyphen_values = true)]
    pub sbatch: Vec<String>,
}

/// Arguments of `persist tile`.
#[derive(clap::Args, Debug)]
pub struct TileArgs {
    /// The plan written by `persist slurm` (WORK/plan.json).
    #[arg(long)]
    pub plan: PathBuf,
    /// The task number, 0..detectors x tiles [default: $SLURM_ARRAY_TASK_ID].
    #[arg(long)]
    pub task: Option<usize>,
}

/// Arguments of `persist assemble`.
#[derive(clap::Args, Debug)]
pub struct AssembleArgs {
    /// The plan written by `persist slurm` (WORK/plan.json).
    #[arg(long)]
    pub plan: PathBuf,
    /// Keep the tiles' work files after a successful assembly.
    #[arg(long)]
    pub keep_work: bool,
}

/// `persist slurm`: the plan and scripts (printed), submitted with `--submit`.
pub fn slurm_command(a: &SlurmArgs, model: &crate::model::Model) -> Result<Vec<String>> {
    let mut lines = Vec::new();
    let mut plan = Plan::new(
        &a.input,
        &a.output,
        &a.checkpoints,
        &a.work,
        model,
        a.tiles,
        crate::stage::processing_time(),
        crate::checkpoint::Retention {
            keep_latest: a.keep_latest,
            keep_one_per_hour: !a.no_hourly_checkpoints,
            ..Default::default()
        },
        a.allow_model_change,
    )?;
    if a.time_spans > 1 || a.from_start {
        let warmup_s = a
            .warmup_s
            .unwrap_or_else(|| crate::timesplit::default_warmup_s(model));
        plan.split_time(model, a.time_spans as usize, warmup_s, a.from_start)?;
    }
    let persist = match &a.persist {
        Some(p) => std::path::absolute(p).map_err(|e| Error::io(p, e))?,
        None => std::env::current_exe()
            .map_err(|e| Error::new(ErrorKind::Io, format!("cannot find this executable: {e}")))?,
    };
    let o = BatchOptions {
        persist,
        partition: a.partition.clone(),
        time: a.time.clone(),
        cpus_per_task: a.cpus_per_task,
        mem: a.mem.clone(),
        extra: a.sbatch.clone(),
    };
    let s = write_scripts(&plan, &o)?;
    lines.push(format!(
        "plan {}: {} detector(s){} x {} tile(s) = {} array task(s), halo {} px",
        s.plan.display(),
        plan.detectors.len(),
        plan.time.as_ref().map_or(String::new(), |t| format!(
            " x up to {} time span(s)",
            t.spans_requested
        )),
        plan.grid.count(),
        plan.tasks(),
        crate::tile::halo_px(model).map_or("whole array".to_string(), |h| h.to_string())
    ));
    if let Some(t) = &plan.time {
        for (d, spans) in &t.spans {
            for (k, sp) in spans.iter().enumerate() {
                let how = match &sp.start {
                    crate::timesplit::SpanStart::Run => "as the run starts (exact)".to_string(),
                    crate::timesplit::SpanStart::Checkpoint { index } => {
                        format!("from checkpoint {index} (exact)")
                    }
                    crate::timesplit::SpanStart::Warmup {
                        from,
                        warmup_s,
                        carry_in_bound_e_per_s,
                    } => format!(
                        "from zero at exposure {from}: warm-up {warmup_s:.0} s, carry-in bound {carry_in_bound_e_per_s:.3e} e-/s"
                    ),
                };
                lines.push(format!(
                    "detector {d} span {k}: exposures {}..={} {how}",
                    sp.first, sp.last
                ));
            }
        }
    }
    for p in [&s.tiles, &s.assemble, &s.submit, &s.run_local] {
        lines.push(format!("wrote {}", p.display()));
    }
    if a.submit {
        let (tiles, assemble) = submit(&s)?;
        lines.push(format!("submitted tiles {tiles} assemble {assemble}"));
    }
    Ok(lines)
}

/// `persist tile`.
pub fn tile_command(a: &TileArgs) -> Result<Vec<String>> {
    let mut lines = Vec::new();
    let plan = Plan::load(&a.plan)?;
    let task = match a.task {
        Some(t) => t,
        None => std::env::var("SLURM_ARRAY_TASK_ID")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .ok_or_else(|| {
                Error::new(ErrorKind::Usage, "no --task and no SLURM_ARRAY_TASK_ID").field("task")
            })?,
    };
    let model = plan.model()?;
    let r = crate::tile::run_tile(&plan, &model, task)?;
    lines.push(format!(
        "detector {} tile {} rows {}..{} columns {}..{}: {} exposure(s)",
        r.detector,
        r.tile,
        r.rect.y0,
        r.rect.y1,
        r.rect.x0,
        r.rect.x1,
        r.exposures.len()
    ));
    Ok(lines)
}

/// `persist assemble`.
pub fn assemble_command(a: &AssembleArgs) -> Result<Vec<String>> {
    let mut lines = Vec::new();
    let plan = Plan::load(&a.plan)?;
    let model = plan.model()?;
    for d in crate::tile::assemble(&plan, &model, a.keep_work)? {
        lines.push(format!(
            "detector {}: {} output(s) written, {} already published, checkpoint {}",
            d.detector,
            d.written,
            d.already_published,
            d.checkpoint
                .as_deref()
                .map_or("none (nothing processed)".to_string(), |p| p
                    .display()
                    .to_string())
        ));
    }
    Ok(lines)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_parses_and_quotes() {
        assert_eq!("2x3".parse::<Grid>().unwrap(), Grid { rows: 2, cols: 3 });
        assert!("0x3".parse::<Grid>().is_err());
        assert!("2".parse::<Grid>().is_err());
        assert_eq!(sh_quote("/a/b.json"), "/a/b.json");
        assert_eq!(sh_quote("/a b/it's"), r"'/a b/it'\''s'");
    }
}
