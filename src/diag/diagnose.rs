//! `persist diagnose`: which library effect is missing from a fitted model.
//!
//! 1. Residuals `r` = the normalised cell residuals `z` of the model
//!    ([`super::eval`]; `m` cells fluence x time).
//! 2. Score (Lagrange-multiplier) test per library effect not in the model: the
//!    effect is added at the null value of its switch parameter `theta_0`
//!    ([`crate::model::effect::ParamSpec::null`]); `j = dr/dtheta` by a forward
//!    difference; `LM = (j^T r)^2 / (s^2 j^T j)`, `s^2 = r^T r / m` (= `m R^2` of the
//!    regression of `r` on `j`). Ranked by `LM`.
//! 3. Threshold: `LM` is compared with the 95 % point of the largest `LM` over the
//!    library under the null, by parametric bootstrap of the cell residuals: replicas
//!    `r* ~ N(0, s^2)` independently per cell (the fitted model's residual scale with no
//!    structure), `B` replicas (`--bootstrap`, default 19), same `j`. (Not yet: full
//!    re-simulation of the products from the fitted model.)
//! 4. The two leading candidates above threshold are refitted in full
//!    ([`crate::calib::effects::fit`]); `delta_BIC = m ln(RSS_1 / RSS_0) + k ln m`.
//!    An effect is declared significant when its score passes the threshold, its
//!    `delta_BIC < -10` and the refit lowers the RMS by at least 20 %.
//!
//! The pixel sample uses stride 4 (a sixteenth of the array) to keep the run short.

use super::data::Sequence;
use super::eval::{self, Samples};
use crate::error::{Error, ErrorKind, Result};
use crate::model::effects::REGISTRY;
use crate::model::params::{EffectSpec, ModelParams};
use rand::{Rng, SeedableRng};
use rand_distr::StandardNormal;
use serde::Serialize;
use std::path::Path;

#[derive(Debug, Clone, Serialize)]
pub struct Candidate {
    pub effect: String,
    pub score: f64,
    pub threshold: f64,
    pub passes_score: bool,
    pub delta_bic: Option<f64>,
    pub rms_after: Option<f64>,
    pub significant: bool,
    pub covariate: String,
    pub command: String,
}

#[derive(Debug, Clone, Serialize)]
pub struct Diagnosis {
    pub cells: usize,
    pub residual_rms_normalised: f64,
    pub bootstrap_replicas: usize,
    pub ranking: Vec<Candidate>,
    pub verdict: String,
}

fn z_of(p: &ModelParams, seq: &Sequence, s: &Samples) -> Result<Vec<f64>> {
    let pr = eval::predict(p, seq, s, false)?;
    Ok(eval::cell_z(s, &pr.current)
        .iter()
        .map(|(_, g)| g.z)
        .collect())
}

pub fn diagnose(
    params: &ModelParams,
    seq: &Sequence,
    bootstrap: usize,
    seed: u64,
    input: &Path,
    model_path: &Path,
) -> Result<Diagnosis> {
    let samples = Samples::new(seq, 4);
    let r = z_of(params, seq, &samples)?;
    let m = r.len();
    if m < 3 {
        return Err(Error::new(
            ErrorKind::Usage,
            "fewer than 3 residual cells: nothing to test",
        )
        .path(input));
    }
    let rss0: f64 = r.iter().map(|v| v * v).sum();
    let s2 = rss0 / m as f64;
    let mut cols: Vec<(&'static str, Vec<f64>)> = Vec::new();
    for def in REGISTRY.iter() {
        if params.effects.iter().any(|e| e.name == def.name) {
            continue;
        }
        let Some((p, null)) = def.switch() else {
            continue;
        };
        let h = if null == 0.0 {
            1e-2 * p.default.abs().max(1e-12)
        } else {
            1e-2 * null.abs()
        };
        let mut q = params.clone();
        let mut map = serde_json::Map::new();
        map.insert(p.name.into(), serde_json::json!(null + h));
        q.effects.push(EffectSpec {
            name: def.name.into(),
            params: map,
        });
        let z = z_of(&q, seq, &samples)?;
        if z.len() != m {
            continue;
        }
        cols.push((
            def.name,
            z.iter().zip(&r).map(|(a, b)| (a - b) / h).collect(),
        ));
    }
    let score = |res: &[f64], j: &[f64], s2: f64| {
        let jr: f64 = j.iter().zip(res).map(|(a, b)| a * b).sum();
        let jj: f64 = j.iter().map(|a| a * a).sum();
        if jj > 0.0 && s2 > 0.0 {
            jr * jr / (s2 * jj)
        } else {
            0.0
        }
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let mut maxes: Vec<f64> = (0..bootstrap.max(1))
        .map(|_| {
            let rs: Vec<f64> = (0..m)
                .map(|_| s2.sqrt() * rng.sample::<f64, _>(StandardNormal))
                .collect();
            let s2b = rs.iter().map(|v| v * v).sum::<f64>() / m as f64;
            cols.iter()
                .map(|(_, j)| score(&rs, j, s2b))
                .fold(0.0, f64::max)
        })
        .collect();
    maxes.sort_by(|a, b| a.total_cmp(b));
    let threshold = super::data::quantile(&maxes, 0.95);
    let mut ranking: Vec<Candidate> = cols
        .iter()
        .map(|(name, j)| {
            let sc = score(&r, j, s2);
            let def = crate::model::effects::lookup(name).expect("registered");
            Candidate {
                effect: name.to_string(),
                score: sc,
                threshold,
                passes_score: sc > threshold,
                delta_bic: None,
                rms_after: None,
                significant: false,
                covariate: def.covariate.into(),
                command: format!(
                    "persist fit --input {} --out {} --with {name}",
                    input.display(),
                    model_path.with_extension("").display().to_string() + &format!("+{name}.json")
                ),
            }
        })
        .collect();
    ranking.sort_by(|a, b| b.score.total_cmp(&a.score));
    for c in ranking.iter_mut().take(2).filter(|c| c.passes_score) {
        let (_, f) =
            crate::calib::effects::fit(params, std::slice::from_ref(&c.effect), seq, &samples)?;
        let k = f.params.len() as f64;
        let rss1 = f.residual_rms_normalised_after.powi(2) * f.cells as f64;
        let dbic = m as f64 * (rss1 / rss0).ln() + k * (m as f64).ln();
        c.delta_bic = Some(dbic);
        c.rms_after = Some(f.residual_rms_normalised_after);
        c.significant = dbic < -10.0 && f.residual_rms_normalised_after <= 0.8 * (s2.sqrt());
    }
    let verdict = match ranking.iter().find(|c| c.significant) {
        Some(c) => format!(
            "missing effect: {} (evidence in {}); add it with: {}",
            c.effect, c.covariate, c.command
        ),
        None => "no library effect is significant".into(),
    };
    Ok(Diagnosis {
        cells: m,
        residual_rms_normalised: s2.sqrt(),
        bootstrap_replicas: bootstrap.max(1),
        ranking,
        verdict,
    })
}

/// `persist diagnose`.
pub fn run(
    input: &Path,
    model: &Path,
    json: Option<&Path>,
    bootstrap: usize,
    seed: u64,
) -> Result<String> {
    let seq = Sequence::load(input)?;
    let params = crate::model_file::load(model)?;
    let d = diagnose(&params, &seq, bootstrap, seed, input, model)?;
    if let Some(p) = json {
        let text = serde_json::to_string_pretty(&d)
            .map_err(|e| Error::new(ErrorKind::Io, e.to_string()))?;
        crate::calib::write_text(p, &(text + "\n"))?;
    }
    let mut s = format!(
        "persist diagnose: {} cells, residual RMS {:.2}, threshold (bootstrap, {} replicas) {:.2}\n\
         {:<16} {:>10} {:>6} {:>10} {:>9}  covariate\n",
        d.cells, d.residual_rms_normalised, d.bootstrap_replicas, d.ranking.first().map_or(f64::NAN, |c| c.threshold),
        "effect", "score", "pass", "dBIC", "RMS after"
    );
    for c in &d.ranking {
        s += &format!(
            "{:<16} {:>10.2} {:>6} {:>10} {:>9}  {}{}\n",
            c.effect,
            c.score,
            c.passes_score,
            c.delta_bic.map_or("-".into(), |v| format!("{v:.1}")),
            c.rms_after.map_or("-".into(), |v| format!("{v:.2}")),
            c.covariate,
            if c.significant { "  SIGNIFICANT" } else { "" }
        );
    }
    s += &d.verdict;
    Ok(s)
}
