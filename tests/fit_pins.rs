//! `persist fit --with NAME:param=value,...`: parameters known from elsewhere (here the
//! readout: `chord` at strength 1, its first read 1.5 s after the reset) are set and
//! held, recorded in the model file's `fixed`, kept by a refit from that file, and
//! written back into the `fit` command `diagnose` suggests. Bad pins are refused with
//! the argument, the parameter and the reason; a model file that pins a parameter its
//! effect does not have is refused. Also `--decay-offset-s` in the model's description
//! and the report, and the calibration options recorded in the model file and repeated
//! by the suggested command. 32 x 32 laboratory campaign, seed 1.

mod common;

use common::{persist_ok, persist_status, read_json};

/// A temporary directory holding the 32 x 32 campaign (seed 1), and its path.
fn lab_32() -> (tempfile::TempDir, String) {
    let tmp = tempfile::tempdir().unwrap();
    let lab = tmp.path().join("lab").to_str().unwrap().to_string();
    common::lab_campaign(&lab, 32, 1, &[]);
    (tmp, lab)
}

/// The `fit` commands `diagnose` (quick, [`common::diagnose_quick`]) suggests for the
/// model at `model`, at least one.
fn suggested_fits(lab: &str, model: &str, json: &str) -> Vec<String> {
    let (d, _) = common::diagnose_quick(lab, model, json);
    let cmds: Vec<String> = d["ranking"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|c| c["command"].as_str().map(String::from))
        .collect();
    assert!(!cmds.is_empty(), "{d}");
    cmds
}

/// Runs suggested command `cmd` (`persist fit ...`) and asserts that it calibrates as
/// `model` is calibrated: the same record, knots and `C_n`.
fn follow_calibrates_as(cmd: &str, model: &serde_json::Value) {
    let args: Vec<&str> = cmd.split_whitespace().collect();
    assert_eq!(args[0], "persist");
    let mut args = args[1..].to_vec();
    args.extend(["--log-level", "warn"]);
    persist_ok(&args);
    let next = read_json(args[args.iter().position(|a| *a == "--out").unwrap() + 1]);
    for key in ["calibration", "amplitude_knots", "terms"] {
        assert_eq!(next[key], model[key], "{key}");
    }
}

#[test]
fn pinned_parameters_are_held_recorded_and_suggested_again() {
    let (tmp, lab) = lab_32();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let out = path("m.json");
    persist_ok(&[
        "fit",
        "--input",
        &lab,
        "--out",
        &out,
        "--with",
        "refill",
        "--with",
        "chord:strength=0.5,first_read_s=1.5",
        "--decay-offset-s",
        "0.2",
        "--amplification",
        "1",
        "--t-min-s",
        "1",
        "--log-level",
        "warn",
    ]);
    let m = read_json(&out);
    assert_eq!(
        m["calibration"],
        serde_json::json!({
            "amplification": 1.0, "t_min_s": 1.0, "decay_offset_s": 0.2,
            "rates_per_s": [0.1, 0.0158, 0.00251, 0.000398, 6.31e-5, 1e-5],
            "fit_cn": false, "fit_amplification": false,
        })
    );
    let chord = m["effects"]
        .as_array()
        .unwrap()
        .iter()
        .find(|e| e["name"] == "chord")
        .unwrap()
        .clone();
    assert_eq!(chord["params"]["strength"], 0.5, "{chord}");
    assert_eq!(chord["params"]["first_read_s"], 1.5, "{chord}");
    assert_eq!(
        chord["fixed"],
        serde_json::json!(["strength", "first_read_s"])
    );
    let refill = &m["effects"][0];
    assert_eq!(refill["name"], "refill");
    assert!(refill.get("fixed").is_none(), "{refill}");
    assert!(
        m["description"].as_str().unwrap().contains("1/(t + 0.2 s)"),
        "{}",
        m["description"]
    );
    // the report fits refill's beta and nothing of chord's
    let rep = read_json(out.replace(".json", ".fit.json"));
    let names: Vec<&str> = rep["effects"]["params"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["effect"].as_str().unwrap_or(""))
        .collect();
    assert!(names.iter().all(|n| *n != "chord"), "{names:?}");
    assert_eq!(rep["calibration"]["c_n"]["offset_s"], 0.2);

    // without the pin, the strength is fitted (on these data it moves off its default 1)
    let out2 = path("m2.json");
    persist_ok(&[
        "fit",
        "--input",
        &lab,
        "--out",
        &out2,
        "--with",
        "refill",
        "--with",
        "chord",
        "--log-level",
        "warn",
    ]);
    let m2 = read_json(&out2);
    let s2 = m2["effects"][1]["params"]["strength"].as_f64().unwrap();
    assert!(s2 < 0.99, "{s2}");
    assert!(m2["effects"][1].get("fixed").is_none());

    // a refit of the pinned model (as diagnose's `--refit full` does, naming the model's
    // own effects) keeps the pins and fits the rest
    let seq = persist::diag::data::Sequence::load(std::path::Path::new(&lab)).unwrap();
    let pinned = persist::model_file::load(std::path::Path::new(&out)).unwrap();
    let names = vec!["refill".to_string(), "chord".to_string()];
    let s = persist::diag::eval::Samples::new(&seq, 2);
    let (refit, rep) = persist::calib::effects::fit(&pinned, &names, &seq, &s).unwrap();
    let c = refit.effects.iter().find(|e| e.name == "chord").unwrap();
    assert_eq!(c.params["strength"], 0.5);
    assert_eq!(c.fixed, ["strength", "first_read_s"]);
    assert!(rep.params.iter().all(|p| p.effect != "chord"), "{rep:?}");
    assert!(rep.params.iter().any(|p| p.effect == "refill"), "{rep:?}");

    // diagnose's suggested command carries the pins
    let cmds = suggested_fits(&lab, &out, &path("d.json"));
    for c in &cmds {
        assert!(
            c.contains(" --with chord:strength=0.5,first_read_s=1.5 --with "),
            "{c}"
        );
        // `refill` is `fit`'s own (its default preset's)
        assert!(!c.contains("--with refill"), "{c}");
        // and the calibration options (it named none, so following it calibrated with
        // the paper's 1.2 and 1/(t+1) instead)
        assert!(
            c.contains(" --amplification 1 --t-min-s 1 --decay-offset-s 0.2"),
            "{c}"
        );
    }
    // following the first command gives the same calibration: knots, C_n, the record
    follow_calibrates_as(&cmds[0], &m);
}

#[test]
fn bad_pins_are_refused_with_the_argument_and_the_reason() {
    let (tmp, lab) = lab_32();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let out = path("m.json");
    for (with, expect) in [
        ("nope:x=1", "unknown effect `nope`"),
        ("chord:speed=1", "`speed` is not a parameter of `chord`"),
        ("chord:strength", "`strength` is not param=value"),
        ("chord:strength=fast", "`fast` is not a finite number"),
        ("chord:strength=2", "strength"),
    ] {
        let (code, text) = persist_status(&[
            "fit",
            "--input",
            &lab,
            "--out",
            &out,
            "--with",
            with,
            "--log-level",
            "warn",
        ]);
        assert_eq!(code, Some(2), "{with}: {text}");
        assert!(text.contains(expect), "{with}: {text}");
        assert!(!std::path::Path::new(&out).exists(), "{with}");
    }
    // a model file pinning a parameter its effect lacks
    let mut m: serde_json::Value =
        serde_json::from_str(&persist_ok(&["model", "default"])).unwrap();
    m["effects"] = serde_json::json!([{"name": "chord", "params": {}, "fixed": ["speed"]}]);
    let bad = path("bad.json");
    std::fs::write(&bad, m.to_string()).unwrap();
    let (code, text) = persist_status(&["model", "id", &bad]);
    assert_ne!(code, Some(0), "{text}");
    assert!(
        text.contains("`/effects/0/fixed`: `speed` is not a parameter of `chord`"),
        "{text}"
    );
}

/// `persist fit --preset readout` (the reference model for comparisons with
/// measurements: knots at the measured level, thirteen rates from 1/s, `refill` fitted,
/// and on the simulator's data, whose slope is the ramp's chord, `chord` held at the
/// readout's `strength=1,first_read_s=1.5`) is the long form of those options: the same
/// model file, byte for byte.
/// `diagnose` names the preset in the command it suggests, and following that command
/// calibrates the same; options given with the preset override its values; an unknown
/// preset is refused, naming the flag.
#[test]
fn the_readout_preset_is_the_long_form_and_is_suggested_back() {
    let (tmp, lab) = lab_32();
    let path = |name: &str| tmp.path().join(name).to_str().unwrap().to_string();
    let fit = |out: &str, extra: &[&str]| {
        let mut a = vec!["fit", "--input", &lab, "--out", out, "--log-level", "warn"];
        a.extend(extra);
        persist_ok(&a);
        read_json(out)
    };
    let preset = fit(&path("p.json"), &["--preset", "readout"]);
    let rates = common::rates_13_terms();
    let long = fit(
        &path("l.json"),
        &[
            "--with",
            "refill",
            "--with",
            "chord:strength=1,first_read_s=1.5",
            "--amplification",
            "1",
            "--t-min-s",
            "1",
            "--decay-offset-s",
            "0.2",
            "--rates-per-s",
            &rates,
            // the readout preset compares with measurements: no coverage margin, and
            // released pixels reset to zero
            "--no-coverage",
            "--release-keep",
            "zero",
        ],
    );
    assert_eq!(preset, long);
    assert_eq!(
        std::fs::read(path("p.json")).unwrap(),
        std::fs::read(path("l.json")).unwrap()
    );
    assert_eq!(preset["terms"].as_array().unwrap().len(), 13);

    let cmds = suggested_fits(&lab, &path("p.json"), &path("d.json"));
    for c in &cmds {
        assert!(c.contains(" --preset readout --with "), "{c}");
        assert!(
            !c.contains("refill") && !c.contains("--amplification"),
            "{c}"
        );
    }
    follow_calibrates_as(&cmds[0], &preset);

    // an option given with the preset overrides its value; its effects stay
    let over = fit(
        &path("o.json"),
        &["--preset", "readout", "--amplification", "1.2"],
    );
    assert_eq!(over["calibration"]["amplification"], 1.2);
    assert_eq!(over["calibration"]["decay_offset_s"], 0.2);
    let names: Vec<&str> = over["effects"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["refill", "chord"]);

    let (code, text) = persist_status(&[
        "fit",
        "--input",
        &lab,
        "--out",
        &path("x.json"),
        "--preset",
        "fastest",
    ]);
    assert_eq!(code, Some(2), "{text}");
    assert!(
        text.contains("--preset") && text.contains("fastest"),
        "{text}"
    );

    // negative values reach the validator, which names the option (clap read `-1` as
    // a flag and answered "unexpected argument")
    for (opt, val) in [
        ("--amplification", "-1"),
        ("--t-min-s", "-1"),
        ("--decay-offset-s", "-0.2"),
        ("--rates-per-s", "-0.1,1"),
    ] {
        let (code, text) =
            persist_status(&["fit", "--input", &lab, "--out", &path("x.json"), opt, val]);
        assert_eq!(code, Some(2), "{opt} {val}: {text}");
        assert!(
            text.contains(&format!("`{opt}`")) && text.contains("> 0"),
            "{opt} {val}: {text}"
        );
    }
    assert!(!std::path::Path::new(&path("x.json")).exists());
}
