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

/// The effects by which the measurements' description reads the on-board slope
/// ([`crate::calib::readout`]), held at the readout's values.
const READOUT_EFFECTS: [&str; 2] = ["chord", "linefit_bias"];

/// The model an addition measured against the description `described` goes into, when
/// the user's model `params` is calibrated with the paper's (flagging) preset and the
/// data hold two illumination events or more (`events`): `params` with the
/// description's on-board slope ([`READOUT_EFFECTS`], held at its values) and its decay
/// terms (rates, first time, offset), the flagging margin kept. `None` otherwise: the
/// addition goes into the model as it is.
///
/// On campaigns the flagging calibration takes in an addition that acts on the decay's
/// clock only with them (docs/diagnostics.md, "The flagging model after an addition"):
/// in the README's walk (hidden `temperature`) the flagging model's pixel reference
/// goes 2.26 -> 4.64 with the effect alone and 2.26 -> 1.10 with them. On a single
/// illumination they do not help: the second generator's, hidden `shape:fill_depth`,
/// seed 2, with the offered `smooth_shape`, `compare`'s residual 4.11 -> 3.97 without
/// them and 4.11 -> 6.43 with, over-flagging at the first model's coverage 205 -> 204
/// and 205 -> 212 samples.
pub(super) fn flagging_base(
    params: &ModelParams,
    described: &ModelParams,
    events: usize,
) -> Option<ModelParams> {
    let c = calibration_or_fit_default(params);
    let d = described.calibration.as_ref()?;
    if events < 2 || !crate::calib::Preset::Paper.matches(&c) {
        return None;
    }
    let mut base = params.clone();
    base.effects.extend(
        readout_effects(described)
            .filter(|e| !params.effects.iter().any(|p| p.name == e.name))
            .cloned(),
    );
    base.calibration = Some(crate::model::params::Calibration {
        t_min_s: d.t_min_s,
        decay_offset_s: d.decay_offset_s,
        rates_per_s: d.rates_per_s.clone(),
        ..c
    });
    Some(base)
}

/// The description's effects that read the on-board slope ([`READOUT_EFFECTS`]).
fn readout_effects(
    described: &ModelParams,
) -> impl Iterator<Item = &crate::model::params::EffectSpec> {
    described
        .effects
        .iter()
        .filter(|e| READOUT_EFFECTS.contains(&e.name.as_str()))
}

/// The verdict's sentence on a command built on [`flagging_base`].
pub(super) fn flagging_base_note(described: &ModelParams) -> String {
    let slope: Vec<&str> = readout_effects(described)
        .map(|e| e.name.as_str())
        .collect();
    let terms = described
        .calibration
        .as_ref()
        .map_or(0, |c| c.rates_per_s.len());
    format!(
        ". The flagging model's command also carries the description's on-board slope \
         ({}) and its {terms} decay terms: the paper's calibration takes in an addition \
         that acts on the decay's clock only with them",
        if slope.is_empty() {
            "none measured".to_string()
        } else {
            slope.join(", ")
        }
    )
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

    /// On two illumination events or more, an addition to a model at the paper's preset
    /// goes in with the description's on-board slope, held, and its decay terms; the
    /// flagging margin stays. On one event, or for a model calibrated otherwise: as it is.
    #[test]
    fn a_flagging_model_takes_the_description_s_slope_and_terms_on_campaigns() {
        use crate::calib::Preset;
        let user = ModelParams {
            calibration: Some(Preset::Paper.config().record()),
            effects: vec![EffectSpec::named("refill")],
            ..ModelParams::default()
        };
        let mut described = user.clone();
        described.calibration = Some(Preset::Readout.config().record());
        for name in ["chord", "linefit_bias"] {
            let mut e = EffectSpec::named(name);
            e.params.insert("strength".into(), 1.0.into());
            e.params.insert("first_read_s".into(), 1.5.into());
            e.fixed = vec!["strength".into(), "first_read_s".into()];
            described.effects.push(e);
        }
        assert!(flagging_base(&user, &described, 1).is_none());
        let base = flagging_base(&user, &described, 2).unwrap();
        let c = base.calibration.as_ref().unwrap();
        assert_eq!(c.rates_per_s.len(), 13);
        assert_eq!((c.t_min_s, c.decay_offset_s), (1.0, 0.2));
        assert_eq!(c.amplification, Preset::Paper.config().amplification);
        assert_eq!(c.coverage, Preset::Paper.config().record().coverage);
        let cmd = fit_command(
            Path::new("lab"),
            Path::new("m.json"),
            &base,
            &["temperature:activation_ev=0.25"],
            &Config::default(),
        );
        assert!(
            cmd.starts_with(
                "persist fit --input lab --out m+temperature.json \
                 --with chord:strength=1,first_read_s=1.5 \
                 --with linefit_bias:strength=1,first_read_s=1.5 \
                 --with temperature:activation_ev=0.25 --t-min-s 1 --decay-offset-s 0.2 \
                 --rates-per-s 1,0.398"
            ),
            "{cmd}"
        );
        assert!(
            !cmd.contains("--preset") && !cmd.contains("--amplification"),
            "{cmd}"
        );
        // a model at the measured level goes in as it is
        let mut measured = user.clone();
        measured.calibration = Some(Preset::Readout.config().record());
        assert!(flagging_base(&measured, &described, 2).is_none());
        assert!(flagging_base_note(&described).contains("(chord, linefit_bias) and its 13"));
    }
}
