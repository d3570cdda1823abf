//! The `persist fit` commands a diagnosis prints: the one that adds a candidate to the
//! model as it was calibrated, and, when the model's knots stand at the paper's flagging
//! margin, the `--preset readout` fit that measures the candidate instead.

use super::config::Config;
use super::eval;
use crate::model::params::ModelParams;
use std::path::Path;

/// The `persist fit` command that adds effect `name` to the model at `model_path`: its
/// own effects and the candidate, the calibration options the model records
/// ([`crate::model::params::Calibration`]: `--amplification`, `--t-min-s`,
/// `--decay-offset-s`, `--rates-per-s`, `--fit-cn`, `--fit-amplification`) and what its
/// early release keeps (`--release-keep`) where they are not `fit`'s defaults, and the residual cells of this diagnosis when they are not
/// the defaults. A model without that record (written by hand, or by `fit` before
/// 2026-11-24) gets `fit`'s defaults.
pub(super) fn fit_command(
    input: &Path,
    model_path: &Path,
    params: &ModelParams,
    names: &[&str],
    cfg: &Config,
) -> String {
    let mut s = format!(
        "persist fit --input {} --out {}{}.json",
        input.display(),
        model_path.with_extension("").display(),
        names
            .iter()
            .map(|n| format!("+{}", n.split(':').next().unwrap_or(n)))
            .collect::<String>()
    );
    let preset = params.calibration.as_ref().and_then(preset_of);
    if let Some(p) = preset {
        s += &format!(" --preset {p}");
    }
    // the effects `fit` adds by itself: the preset's (the default one's without)
    let from_preset = preset.unwrap_or_default().effects();
    for e in params
        .effects
        .iter()
        .map(crate::calib::effects::with_arg)
        .filter(|e| !from_preset.contains(&e.as_str()))
        .chain(names.iter().map(|n| n.to_string()))
    {
        s += &format!(" --with {e}");
    }
    s += &calibration_args(params.calibration.as_ref());
    let keep = params.early_release.keep;
    if keep != preset.unwrap_or_default().release_keep() {
        s += match keep {
            crate::model::ReleaseKeep::Zero => " --release-keep zero",
            crate::model::ReleaseKeep::Threshold => " --release-keep threshold",
        };
    }
    // `fit`'s defaults are the library's (src/cli/analysis.rs takes them from there)
    if cfg.cells != eval::Cells::default() {
        s += &format!(" --cells {}", cfg.cells);
    }
    if cfg.cell_statistic != eval::CellStatistic::default() {
        s += &format!(" --cell-statistic {}", cfg.cell_statistic);
    }
    if cfg.background != super::data::Background::default() {
        s += &format!(" --background {}", cfg.background);
    }
    s
}

/// When the model's knots stand away from the measured level with nothing free to
/// carry it ([`crate::calib::knots_held_off_level`]; a model without a calibration
/// record has `fit`'s defaults, the paper's 1.2), [`fit_command`] would fit the
/// candidates against that margin, and their parameters would take it in (`persist
/// fit` warns; measured: `temperature` fitted 1.20 eV for the truth's
/// 0.25 under the paper's preset, 0.250 under `--preset readout`). Then: the same
/// effects and cells calibrated with `--preset readout`, which measures them, written
/// beside the model as `MODEL.readout+NAMES.json`. `None` otherwise.
pub(super) fn measure_command(
    input: &Path,
    model_path: &Path,
    params: &ModelParams,
    names: &[&str],
    cfg: &Config,
) -> Option<String> {
    use crate::calib::Preset;
    let c = calibration_or_fit_default(params);
    if !crate::calib::knots_held_off_level(c.amplification, c.fit_cn, c.fit_amplification) {
        return None;
    }
    let mut readout = params.clone();
    readout.calibration = Some(Preset::Readout.config().record());
    let out = model_path.with_extension("readout.json");
    Some(fit_command(input, &out, &readout, names, cfg))
}

/// The calibration the model records, or `fit`'s defaults (the paper's) for a model
/// without the record.
pub(super) fn calibration_or_fit_default(
    params: &ModelParams,
) -> crate::model::params::Calibration {
    params
        .calibration
        .clone()
        .unwrap_or_else(|| crate::calib::CalibConfig::default().record())
}

/// The verdict's sentence on [`measure_command`], empty without one.
pub(super) fn margin_note(measure: Option<&str>, params: &ModelParams) -> String {
    let Some(m) = measure else {
        return String::new();
    };
    let a = calibration_or_fit_default(params).amplification;
    format!(
        ". That fit holds the knots at {a} times the measured level (the paper's flagging \
         margin), which the effect's parameters would take in (fit warns); to measure \
         them: {m}"
    )
}

/// The `persist fit --preset` other than the default whose options calibration `c`
/// has ([`crate::calib::Preset::matches`]).
fn preset_of(c: &crate::model::params::Calibration) -> Option<crate::calib::Preset> {
    use crate::calib::Preset;
    Preset::ALL
        .into_iter()
        .find(|p| *p != Preset::default() && p.matches(c))
}

/// `persist fit`'s options that repeat calibration `c`, those at the defaults of `fit`
/// (of its `--preset`, when [`preset_of`] finds one) left out; each begins with a
/// space.
fn calibration_args(c: Option<&crate::model::params::Calibration>) -> String {
    let Some(c) = c else {
        return String::new();
    };
    let d = preset_of(c).unwrap_or_default().config();
    let mut s = String::new();
    if c.coverage != d.coverage {
        s += &c
            .coverage
            .map_or(" --no-coverage".to_string(), |v| format!(" --coverage {v}"));
    }
    if c.amplification != d.amplification {
        s += &format!(" --amplification {}", c.amplification);
    }
    if c.t_min_s != d.t_min_s {
        s += &format!(" --t-min-s {}", c.t_min_s);
    }
    if c.decay_offset_s != d.decay_offset_s {
        s += &format!(" --decay-offset-s {}", c.decay_offset_s);
    }
    if c.rates_per_s != d.rates_per_s {
        let r: Vec<String> = c.rates_per_s.iter().map(f64::to_string).collect();
        s += &format!(" --rates-per-s {}", r.join(","));
    }
    if c.fit_cn {
        s += " --fit-cn";
    }
    if c.fit_amplification {
        s += " --fit-amplification";
    }
    if c.decay_exponent.is_some() {
        s += " --fit-decay-exponent";
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::params::EffectSpec;

    /// The command that adds a candidate keeps the model's own effects and the
    /// diagnosis's cells (it named the candidate alone, so following it dropped them),
    /// naming the cells only where they differ from `fit`'s defaults, which are the
    /// library's: per illumination, paired. `refill`, which `fit` fits by itself (its
    /// default preset's), is not repeated.
    #[test]
    fn the_suggested_fit_keeps_the_model_s_effects_and_cells() {
        let mut p = ModelParams::default();
        p.effects.push(EffectSpec::named("refill"));
        p.effects.push(EffectSpec::named("chord"));
        // released pixels reset to zero (the paper's): not `fit`'s default, said
        assert!(fit_command(
            Path::new("lab"),
            Path::new("m.json"),
            &p,
            &[],
            &Config::default()
        )
        .ends_with(" --with chord --release-keep zero"));
        p.early_release.keep = crate::model::ReleaseKeep::Threshold;
        let cmd =
            |cfg: &Config| fit_command(Path::new("lab"), Path::new("m.json"), &p, &["soak"], cfg);
        let base = "persist fit --input lab --out m+soak.json --with chord --with soak";
        assert_eq!(
            (Config::default().cells, Config::default().cell_statistic),
            (eval::Cells::Illumination, eval::CellStatistic::Paired)
        );
        assert_eq!(cmd(&Config::default()), base);
        let cfg = Config {
            cells: eval::Cells::Pooled,
            cell_statistic: eval::CellStatistic::Levels,
            ..Config::default()
        };
        assert_eq!(
            cmd(&cfg),
            format!("{base} --cells pooled --cell-statistic levels")
        );
        let cfg = Config {
            cell_statistic: eval::CellStatistic::Levels,
            ..Config::default()
        };
        assert_eq!(cmd(&cfg), format!("{base} --cell-statistic levels"));
        // the joint check's pair: both effects, after the model's own
        assert_eq!(
            fit_command(
                Path::new("lab"),
                Path::new("m.json"),
                &p,
                &["temperature", "soak"],
                &Config::default()
            ),
            "persist fit --input lab --out m+temperature+soak.json --with chord \
             --with temperature --with soak"
        );
    }

    /// The suggested command repeats the calibration the model records, where it is not
    /// `fit`'s default, and nothing for a model without the record.
    #[test]
    fn the_suggested_fit_repeats_the_model_s_calibration() {
        let mut c = crate::calib::CalibConfig::default().record();
        assert_eq!(calibration_args(None), "");
        assert_eq!(calibration_args(Some(&c)), "");
        c.amplification = 1.0;
        c.decay_offset_s = 0.2;
        c.rates_per_s = vec![1.0, 1.58489e-5];
        c.fit_cn = true;
        assert_eq!(
            calibration_args(Some(&c)),
            " --amplification 1 --decay-offset-s 0.2 --rates-per-s 1,0.0000158489 --fit-cn"
        );
    }

    /// Against knots held at the paper's margin (a model of the paper's preset, or one
    /// without a calibration record) the suggested fit would take the margin into the
    /// candidate's parameters: the diagnosis also names the `--preset readout` fit of
    /// the same effects and cells. Not for a readout model, nor where `--fit-cn` or
    /// `--fit-amplification` carries the level.
    #[test]
    fn a_candidate_against_the_paper_margin_also_gets_the_readout_fit() {
        use crate::calib::{CalibConfig, Preset};
        let mut p = ModelParams::default();
        p.effects.push(EffectSpec::named("soak"));
        let cfg = Config {
            cell_statistic: eval::CellStatistic::Population,
            ..Config::default()
        };
        let cmd = |p: &ModelParams| {
            measure_command(
                Path::new("lab"),
                Path::new("m.json"),
                p,
                &["temperature"],
                &cfg,
            )
        };
        let readout = "persist fit --input lab --out m.readout+temperature.json --preset readout \
                       --with soak --with temperature --cell-statistic population";
        for c in [None, Some(CalibConfig::default().record())] {
            p.calibration = c;
            assert_eq!(cmd(&p).as_deref(), Some(readout));
            assert!(margin_note(cmd(&p).as_deref(), &p).contains("1.2 times the measured level"));
        }
        let mut c = CalibConfig::default().record();
        c.fit_amplification = true;
        p.calibration = Some(c.clone());
        assert_eq!(cmd(&p), None);
        c.fit_amplification = false;
        c.fit_cn = true;
        p.calibration = Some(c);
        assert_eq!(cmd(&p), None);
        p.calibration = Some(Preset::Readout.config().record());
        assert_eq!(cmd(&p), None);
        assert_eq!(margin_note(None, &p), "");
    }

    /// A model calibrated with `fit --preset readout` gets `--preset readout` back, its
    /// preset's effects not repeated, and only what differs from the preset spelt out.
    #[test]
    fn the_suggested_fit_names_the_readout_preset() {
        use crate::calib::Preset;
        let mut p = ModelParams::default();
        let mut c = Preset::Readout.config().record();
        p.calibration = Some(c.clone());
        let with: Vec<String> = Preset::Readout.with(&[]);
        p.effects = with
            .iter()
            .map(|w| {
                let (name, pins) = crate::calib::effects::parse_with(w).unwrap();
                let mut e = crate::model::params::EffectSpec::named(name);
                for (k, v) in pins {
                    e.params.insert(k.clone(), v.into());
                    e.fixed.push(k);
                }
                e
            })
            .collect();
        let cmd = |p: &ModelParams| {
            fit_command(
                Path::new("lab"),
                Path::new("m.json"),
                p,
                &["soak"],
                &Config::default(),
            )
        };
        assert_eq!(
            cmd(&p),
            "persist fit --input lab --out m+soak.json --preset readout --with soak"
        );
        // freed after the preset: said; another chord strength: its own --with
        c.fit_cn = true;
        p.calibration = Some(c.clone());
        p.effects[1].params.insert("strength".into(), 0.9.into());
        assert_eq!(
            cmd(&p),
            "persist fit --input lab --out m+soak.json --preset readout \
             --with chord:strength=0.9,first_read_s=1.5 --with soak --fit-cn"
        );
        // one option off the preset: no preset named, every option spelt out
        c.t_min_s = 2.0;
        assert_eq!(preset_of(&c), None);
        assert!(calibration_args(Some(&c)).contains(" --amplification 1 --t-min-s 2"));
    }
}
