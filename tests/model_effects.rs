//! Model effects through `Model::step`: a null effect changes nothing bit for bit, an
//! active one changes the prediction as its equation says, and bad entries are refused.

use ndarray::Array2;
use persist::model::params::{BackgroundEstimate, EffectSpec};
use persist::model::{Input, Model, ModelParams, Output, State, StepContext};

fn spec(name: &str, params: serde_json::Value) -> EffectSpec {
    EffectSpec {
        params: params.as_object().cloned().unwrap_or_default(),
        ..EffectSpec::named(name)
    }
}

/// The input of exposure `k`: `img` (e-/s), starting at `1e9 + t_start_s`, lit for
/// `t_illuminated_s` of its `t_exposure_s`.
fn input(
    img: &Array2<f32>,
    k: u64,
    t_start_s: f64,
    t_exposure_s: f64,
    t_illuminated_s: f64,
) -> Input<'_> {
    Input {
        image_e_per_s: img.view(),
        exposure_index: k,
        t_start_unix_s: 1e9 + t_start_s,
        t_exposure_s,
        t_illuminated_s,
        history_incomplete: false,
        background_e_per_s: None,
    }
}

/// One `Model::step_with` with the input flags `flags` (the step adds its own): the
/// predicted current and the persistence flags.
fn step(
    m: &Model,
    st: &mut State,
    input: &Input,
    ctx: &StepContext,
    flags: &mut Array2<u32>,
) -> Result<(Array2<f32>, Array2<u8>), persist::Error> {
    let dim = flags.dim();
    let mut cur = Array2::<f32>::zeros(dim);
    let mut pf = Array2::<u8>::zeros(dim);
    m.step_with(
        st,
        input,
        ctx,
        &mut Output {
            flags,
            current_e_per_s: &mut cur,
            pflags: &mut pf,
        },
    )?;
    Ok((cur, pf))
}

/// Run a 4x4 lab-like sequence (one bright exposure, then darks); predictions per step.
fn run(model: &Model, temps: &[f64]) -> Vec<Array2<f32>> {
    run_masked(model, temps, None, &[0]).unwrap()
}

/// [`run`] with bright exposures at the indices `lit`, advancing only the `active`
/// pixels (and a non-finite pixel at (0, 1) in the bright exposures when `active` is
/// given: an unknown-fluence pixel).
fn run_masked(
    model: &Model,
    temps: &[f64],
    active: Option<&[bool]>,
    lit: &[usize],
) -> Result<Vec<Array2<f32>>, persist::Error> {
    let mut st = model.new_state(4, 4);
    let mut out = Vec::new();
    let mut t = 0.0;
    for (k, temp) in temps.iter().enumerate() {
        let img = if lit.contains(&k) {
            Array2::from_shape_fn((4, 4), |(y, x)| {
                if active.is_some() && (y, x) == (0, 1) {
                    f32::NAN
                } else {
                    (200.0 * (1 + y * 4 + x) as f32).powf(1.3)
                }
            })
        } else {
            Array2::from_elem((4, 4), 0.01f32)
        };
        let t_exp = if lit.contains(&k) { 613.0 } else { 180.0 };
        let t_ill = if lit.contains(&k) { 481.0 } else { t_exp };
        let ctx = StepContext {
            focal_plane_temp_k: Some(*temp),
            active_pixels: active,
        };
        let mut flags = Array2::<u32>::zeros((4, 4));
        let (cur, _) = step(
            model,
            &mut st,
            &input(&img, k as u64, t, t_exp, t_ill),
            &ctx,
            &mut flags,
        )?;
        out.push(cur);
        t += t_exp;
    }
    Ok(out)
}

/// The diagnostics advance only their sampled pixels (`StepContext::active_pixels`):
/// what those pixels predict must not depend on whether the others are advanced, for
/// every effect, the spatial ones (blooming, ipc with and without its diagonals) and
/// the position-dependent one (populations) included.
#[test]
fn active_pixels_predict_bit_identically_to_the_whole_array() {
    let temps: Vec<f64> = (0..8).map(|k| 79.0 + 0.5 * k as f64).collect();
    let keep: Vec<bool> = (0..16).map(|i| i % 3 != 0).collect();
    let all = vec![true; 16];
    for (name, p) in [
        ("capacity", serde_json::json!({"inv_q_max_per_e": 1e-4})),
        ("soak", serde_json::json!({"capture_ratio": 0.5})),
        ("temperature", serde_json::json!({})),
        ("linefit_bias", serde_json::json!({})),
        ("blooming", serde_json::json!({"fraction": 0.1})),
        ("short_tau_boost", serde_json::json!({"factor": 2.0})),
        ("ipc", serde_json::json!({"alpha": 0.02})),
        // the diagonal neighbours are two 4-neighbour steps away (its reach)
        (
            "ipc",
            serde_json::json!({"alpha": 0.02, "alpha_split": 0.005, "alpha_diag": 0.003}),
        ),
        ("populations", serde_json::json!({"gx": 0.3, "gyy": -0.2})),
    ] {
        // with an accumulator beside (capacity), so that path runs too
        let mut effects = vec![spec(name, p)];
        if name != "capacity" {
            effects.push(spec("capacity", serde_json::json!({})));
        }
        // the quiet-pixel background reads every row of so small an array, so every
        // pixel is advanced there; the image median reads no state
        for background in [
            BackgroundEstimate::QuietPixels,
            BackgroundEstimate::ImageMedian,
        ] {
            let mut params = ModelParams {
                effects: effects.clone(),
                ..ModelParams::default()
            };
            params.early_release.background = background;
            let m = Model::new(params).unwrap();
            let whole = run_masked(&m, &temps, Some(&all), &[0]).unwrap();
            let part = run_masked(&m, &temps, Some(&keep), &[0]).unwrap();
            for (k, (w, q)) in whole.iter().zip(&part).enumerate() {
                for (i, (a, b)) in w.iter().zip(q.iter()).enumerate() {
                    if keep[i] {
                        assert_eq!(a.to_bits(), b.to_bits(), "{name}: exposure {k} pixel {i}");
                    }
                }
            }
            // one pixel in the middle: the response planes are built for it and the
            // neighbours a spatial hook reads, and nowhere else
            let one: Vec<bool> = (0..16).map(|i| i == 5).collect();
            let alone = run_masked(&m, &temps, Some(&one), &[0]).unwrap();
            for (k, (w, q)) in whole.iter().zip(&alone).enumerate() {
                assert_eq!(
                    w[[1, 1]].to_bits(),
                    q[[1, 1]].to_bits(),
                    "{name}: exposure {k}"
                );
            }
            assert!(whole[1].iter().all(|v| *v > 0.0), "{name}");
            if background == BackgroundEstimate::ImageMedian {
                // the masked-out pixels were really skipped (their current stays 0)
                assert!(part[1].iter().zip(&keep).any(|(v, k)| !k && *v == 0.0));
            }
        }
    }
    // a mask of the wrong size is refused, naming the field
    let m = with(vec![spec("capacity", serde_json::json!({}))]);
    let e = run_masked(&m, &temps, Some(&[true; 3]), &[0]).unwrap_err();
    assert!(e.to_string().contains("active_pixels"), "{e}");
}

/// Regression: with `[capacity, refill]` in the model file the step handed the new
/// response to capacity (the first accumulator) and refill got nothing to combine, so
/// `fit --with refill` on a model holding capacity fitted a parameter with no effect.
/// Accumulators now run by role (limit, then combine): both orders are one model,
/// and refill really acts on the second illumination.
#[test]
fn accumulators_run_by_role_not_by_model_file_order() {
    let temps = vec![80.0; 8];
    let lit = [0, 3];
    let refill = || spec("refill", serde_json::json!({"beta": 1.0}));
    let cap = || spec("capacity", serde_json::json!({"inv_q_max_per_e": 1e-5}));
    let a = run_masked(&with(vec![cap(), refill()]), &temps, None, &lit).unwrap();
    let b = run_masked(&with(vec![refill(), cap()]), &temps, None, &lit).unwrap();
    for (x, y) in a.iter().zip(&b) {
        for (p, q) in x.iter().zip(y) {
            assert_eq!(p.to_bits(), q.to_bits());
        }
    }
    let c = run_masked(&with(vec![cap()]), &temps, None, &lit).unwrap();
    // before the second illumination the darks' tiny responses are all refill changes
    // (the larger, not the sum: < 1e-4 relative); after it, the bright pixel's current
    // is below (the larger of old and new charge instead of their sum; 9.30 vs 9.84 e-/s
    // when written: the short terms, which dominate 180 s after the lit exposure, had
    // decayed before it, so the sum and the larger differ mostly in the long terms)
    for (p, q) in a[2].iter().zip(&c[2]) {
        assert!((p - q).abs() < 1e-4 * q, "{p} {q}");
    }
    let (p, q) = (a[4][[3, 3]], c[4][[3, 3]]);
    assert!(p < 0.97 * q, "{p} {q}");
}

fn with(effects: Vec<EffectSpec>) -> Model {
    Model::new(ModelParams { effects, ..paper() }).unwrap()
}

/// The default model with early release counting three exposures in a row
/// (`rule: consecutive`): the darks of [`run_masked`] have no noise, so the evidence rule
/// (the default) would release every lit pixel at the first dark, zeroing what these
/// tests compare after it.
fn paper() -> ModelParams {
    let mut p = ModelParams::default();
    p.early_release.rule = persist::model::ReleaseRule::Consecutive;
    p
}

#[test]
fn null_effects_are_bit_identical_to_the_paper_model() {
    let temps = vec![80.0; 8];
    let base = run(&Model::new(paper()).unwrap(), &temps);
    for (name, p) in [
        ("capacity", serde_json::json!({"inv_q_max_per_e": 0.0})),
        ("refill", serde_json::json!({"beta": 0.0})),
        ("chord", serde_json::json!({"strength": 0.0})),
        ("soak", serde_json::json!({"capture_ratio": 0.0})),
        ("temperature", serde_json::json!({})), // 80 K = t_ref
        ("linefit_bias", serde_json::json!({"strength": 0.0})),
        ("blooming", serde_json::json!({"fraction": 0.0})),
        ("short_tau_boost", serde_json::json!({"factor": 1.0})),
    ] {
        let got = run(&with(vec![spec(name, p)]), &temps);
        assert_eq!(got, base, "{name}");
    }
}

#[test]
fn active_effects_change_the_prediction_as_documented() {
    let temps = vec![80.0; 8];
    let base = run(&Model::new(paper()).unwrap(), &temps);
    // capacity: a first illumination gives the knots (the calibrated response of empty
    // traps); charge still held when a pixel is lit again takes capacity from the new
    // fill, the more the more it holds (the brightest pixel most)
    let cap_model = with(vec![spec(
        "capacity",
        serde_json::json!({"inv_q_max_per_e": 1e-4}),
    )]);
    let cap = run(&cap_model, &temps);
    assert_eq!(cap[1], base[1]);
    let paper = Model::new(paper()).unwrap();
    let base2 = run_masked(&paper, &temps, None, &[0, 3]).unwrap();
    let cap2 = run_masked(&cap_model, &temps, None, &[0, 3]).unwrap();
    let cut = |p: (usize, usize)| 1.0 - cap2[4][p] / base2[4][p];
    assert!(
        cut((3, 3)) > cut((0, 0)) && cut((0, 0)) >= 0.0,
        "{cap2:?} {base2:?}"
    );
    // warmer array: faster decay -> higher early current? later lower
    let warm = run(
        &with(vec![spec("temperature", serde_json::json!({}))]),
        &[82.0; 8],
    );
    assert!(warm[7][[3, 3]] != base[7][[3, 3]]);
    // the least-squares slope of a convex decay weights the middle of the ramp: it reads
    // above the mid-exposure current (and below the mean current)
    let lf = run(
        &with(vec![spec("linefit_bias", serde_json::json!({}))]),
        &temps,
    );
    assert!(lf[1][[3, 3]] > base[1][[3, 3]]);
}

#[test]
fn bad_effect_entries_are_refused_with_their_field() {
    let e = ModelParams {
        effects: vec![spec("nope", serde_json::json!({}))],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(
        e.starts_with("effects[0].name") && e.contains("nope"),
        "{e}"
    );
    let e = ModelParams {
        effects: vec![spec("soak", serde_json::json!({"capture_ratio": -1.0}))],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.starts_with("effects[0].params.capture_ratio"), "{e}");
    let e = ModelParams {
        effects: vec![
            spec("soak", serde_json::json!({})),
            spec("soak", serde_json::json!({})),
        ],
        ..ModelParams::default()
    }
    .validate()
    .unwrap_err();
    assert!(e.contains("twice"), "{e}");
}

/// Regression: the early-release background (`quiet_pixels`) was taken over every
/// pixel of the sample, and the pixels a caller does not read
/// (`StepContext::active_pixels`) are not advanced: their amplitudes stay 0, so they all
/// counted as quiet whatever their image. Where most of the array is lit (the
/// laboratory spot), that put lit pixels' persistence into the background and released
/// read pixels whose persistence was still above the threshold: `compare` (which reads
/// every second pixel) missed flags that the stage, advancing every pixel, would not.
#[test]
fn unread_pixels_do_not_enter_the_early_release_background() {
    let (ny, nx) = (16, 16);
    // three quarters of the array lit far above saturation, the rest dark
    let lit = |x: usize| x < 12;
    let m = with(vec![spec("refill", serde_json::json!({"beta": 0.5}))]);
    assert!(m.params().early_release.enabled);
    // read: two lit pixels and two dark ones
    let mut read = vec![false; ny * nx];
    for (y, x) in [(2, 2), (8, 6), (4, 14), (12, 13)] {
        read[y * nx + x] = true;
    }
    let run = |active: Option<&[bool]>| {
        let mut st = m.new_state(ny, nx);
        let mut t = 0.0;
        let mut out = Vec::new();
        for k in 0..6u64 {
            let bright = k == 0;
            // after the illumination the lit pixels show 0.15 e-/s of persistence: above
            // the 0.1 e-/s threshold over a 0.01 e-/s dark level, below the prediction
            let img = Array2::from_shape_fn((ny, nx), |(_, x)| match (bright, lit(x)) {
                (true, true) => 5000.0f32,
                (false, true) => 0.16,
                _ => 0.01,
            });
            let t_exp = if bright { 613.0 } else { 180.0 };
            let t_ill = if bright { 481.0 } else { t_exp };
            let ctx = StepContext {
                focal_plane_temp_k: None,
                active_pixels: active,
            };
            let mut flags = Array2::<u32>::zeros((ny, nx));
            out.push(
                step(
                    &m,
                    &mut st,
                    &input(&img, k, t, t_exp, t_ill),
                    &ctx,
                    &mut flags,
                )
                .unwrap(),
            );
            t += t_exp + 10.0;
        }
        out
    };
    let whole = run(None);
    let part = run(Some(&read));
    for (k, ((cw, fw), (cp, fp))) in whole.iter().zip(&part).enumerate() {
        for (i, _) in read.iter().enumerate().filter(|(_, r)| **r) {
            let (y, x) = (i / nx, i % nx);
            assert_eq!(
                (cw[[y, x]].to_bits(), fw[[y, x]]),
                (cp[[y, x]].to_bits(), fp[[y, x]]),
                "exposure {k}, pixel ({y}, {x})"
            );
        }
    }
    // and the lit pixels are still flagged at the end (not released)
    assert!(whole[5].1[[2, 2]] != 0, "{:?}", whole[5].0[[2, 2]]);
}

/// `soak` with `refill` (beta 1): a second illumination relaxes each term's occupancy
/// toward what the exposed traps can hold by the fraction soak fills,
/// `D + f (Cap - D)` (src/model/effects/refill.rs), not `max(D, f Cap)`. `Cap` from
/// the model without soak, `f Cap` from the first illumination with it, `D` (the decayed
/// first illumination) from soak alone, which adds.
#[test]
fn soak_with_refill_relaxes_toward_capacity() {
    let amplitudes = |effects: Vec<EffectSpec>| {
        let mut p = ModelParams {
            effects,
            ..ModelParams::default()
        };
        p.early_release.enabled = false;
        let m = Model::new(p).unwrap();
        let mut st = m.new_state(1, 1);
        let mut after = Vec::new();
        for k in 0..2u64 {
            let img = Array2::from_elem((1, 1), 400.0f32);
            step(
                &m,
                &mut st,
                &input(&img, k, 700.0 * k as f64, 613.0, 481.0),
                &StepContext::default(),
                &mut Array2::<u32>::zeros((1, 1)),
            )
            .unwrap();
            after.push(st.amplitudes_e.iter().copied().collect::<Vec<f64>>());
        }
        after
    };
    let soak = || spec("soak", serde_json::json!({"capture_ratio": 0.05}));
    let refill = || spec("refill", serde_json::json!({"beta": 1.0}));
    let cap = &amplitudes(vec![refill()])[0];
    let s = amplitudes(vec![soak()]);
    let rs = amplitudes(vec![soak(), refill()]);
    let mut partly = 0;
    for n in 0..cap.len() {
        let fcap = s[0][n];
        let d = s[1][n] - fcap;
        let f = fcap / cap[n];
        let want = d + f * (cap[n] - d);
        assert!((rs[0][n] - fcap).abs() <= 1e-12 * fcap, "term {n}");
        assert!(
            (rs[1][n] - want).abs() <= 1e-9 * want,
            "term {n}: {} vs {want}",
            rs[1][n]
        );
        if f < 0.9 && d > 0.1 * cap[n] {
            // where it matters: above max(D, f Cap)
            assert!(rs[1][n] > d.max(fcap) * 1.01, "term {n}");
            partly += 1;
        }
    }
    assert!(partly > 0, "no term fills partly: {cap:?} {s:?}");
}

/// `blooming` counts a neighbour too bright for a slope (`SUR_ERROR`, no fluence) at
/// `no_slope_flux_e_per_s * t_illuminated` (22,222 e-/s * 481 s = 1.07e7 e-), and a
/// transient (also no fluence) at 0: the centre of a 5x5 array of 10 e-/s pixels has no
/// fluence in the lit exposure; its edge neighbours' first-dark current rises with the
/// first flag only. (Counting neither, the neighbours of the brightest pinholes of a x4
/// illumination would be predicted without blooming.)
#[test]
fn blooming_counts_a_neighbour_with_no_slope_not_a_transient() {
    use persist::flags::bits;
    let dark_after = |effects: Vec<EffectSpec>, centre_flag: u32| -> f32 {
        let m = with(effects);
        let mut st = m.new_state(5, 5);
        let mut cur = Array2::<f32>::zeros((5, 5));
        for k in 0..2u64 {
            let lit = k == 0;
            let img = Array2::from_shape_fn((5, 5), |p| {
                if lit && p == (2, 2) {
                    f32::NAN
                } else if lit {
                    10.0
                } else {
                    0.01
                }
            });
            let mut flags = Array2::<u32>::zeros((5, 5));
            if lit {
                flags[[2, 2]] = centre_flag;
            }
            let t_exp = if lit { 613.0 } else { 180.0 };
            let t_ill = if lit { 481.0 } else { t_exp };
            (cur, _) = step(
                &m,
                &mut st,
                &input(&img, k, 613.0 * k as f64, t_exp, t_ill),
                &StepContext::default(),
                &mut flags,
            )
            .unwrap();
        }
        cur[[2, 3]]
    };
    let blooming = || vec![spec("blooming", serde_json::json!({"fraction": 0.01}))];
    for flag in [bits::SUR_ERROR, bits::TRANSIENT] {
        let base = dark_after(Vec::new(), flag);
        let with_blooming = dark_after(blooming(), flag);
        println!("flag {flag}: neighbour {base} -> {with_blooming} e-/s");
        if flag == bits::SUR_ERROR {
            // own 4,810 e- plus 0.01 * (1.07e7 - 2e5) / 4 = 26,200 e-: about 6x
            assert!(with_blooming > 4.0 * base, "{base} -> {with_blooming}");
        } else {
            assert_eq!(with_blooming.to_bits(), base.to_bits());
        }
    }
}

/// `soak` follows capture against emission at the exposure's temperature
/// (src/model/effects/soak.rs, "Emission while held"): at the reference temperature a
/// model with `temperature` as well is `soak` alone, bit for bit; at 82 K every term
/// fills by `(50 + 1) / (50 + 1/0.41) = 0.9726` of what it fills at 80 K (capture
/// ratio 0.02, 0.25 eV: emission 2.44x faster), at 78 K by 1.012.
#[test]
fn soak_fills_less_when_the_exposure_is_warmer() {
    let soak = || spec("soak", serde_json::json!({"capture_ratio": 0.02}));
    let temp = || spec("temperature", serde_json::json!({"activation_ev": 0.25}));
    let first_dark = |effects: Vec<EffectSpec>, t: f64| run(&with(effects), &[t; 3])[1].clone();
    let soak80 = first_dark(vec![soak()], 80.0);
    let both80 = first_dark(vec![soak(), temp()], 80.0);
    assert!(soak80
        .iter()
        .zip(&both80)
        .all(|(a, b)| a.to_bits() == b.to_bits()));
    for (t, lo, hi) in [(82.0, 0.965, 0.98), (78.0, 1.005, 1.02)] {
        let both = first_dark(vec![soak(), temp()], t);
        let alone = first_dark(vec![temp()], t);
        let with_soak = first_dark(vec![soak()], 80.0);
        let without = first_dark(vec![], 80.0);
        // soak's effect at `t` over its effect at 80 K, brightest pixel
        let p = (3, 3);
        let r = (both[p] / alone[p]) / (with_soak[p] / without[p]);
        println!("{t} K: soak's ratio at {t} K / at 80 K = {r:.4}");
        assert!(r > lo && r < hi, "{t} K: {r}");
    }
}

/// A pixel with no slope (`SUR_ERROR`) is brighter than any measured one: `soak` fills
/// its slow terms level-blind (src/model/effects/soak.rs) rather than keeping the full
/// amplitude; a transient still keeps the maximum whatever the hooks do. Regression:
/// kept at the full amplitude, the brightest pixels of the campaign's x4 illumination
/// carried unsoaked slow terms into the next illumination.
#[test]
fn soak_fills_a_pixel_with_no_slope_but_not_a_transient() {
    use persist::flags::bits;
    // the current 3 h after a lit exposure whose pixel (1, 1) had `flag`
    let late = |effects: Vec<EffectSpec>, flag: u32| -> f32 {
        let m = with(effects);
        let mut st = m.new_state(3, 3);
        let mut cur = Array2::<f32>::zeros((3, 3));
        for k in 0..2u64 {
            let lit = k == 0;
            let img = Array2::from_shape_fn((3, 3), |p| match (lit, p == (1, 1)) {
                (true, true) => f32::NAN,
                (true, false) => 2000.0,
                (false, _) => 0.01,
            });
            let mut flags = Array2::<u32>::zeros((3, 3));
            if lit {
                flags[[1, 1]] = flag;
            }
            let (t_start, t_exp, t_ill) = if lit {
                (0.0, 613.0, 481.0)
            } else {
                (613.0 + 10_800.0, 180.0, 180.0)
            };
            (cur, _) = step(
                &m,
                &mut st,
                &input(&img, k, t_start, t_exp, t_ill),
                &StepContext::default(),
                &mut flags,
            )
            .unwrap();
        }
        cur[[1, 1]]
    };
    let soak = || vec![spec("soak", serde_json::json!({"capture_ratio": 0.02}))];
    let (sur, sur_soak) = (
        late(Vec::new(), bits::SUR_ERROR),
        late(soak(), bits::SUR_ERROR),
    );
    let (tr, tr_soak) = (
        late(Vec::new(), bits::TRANSIENT),
        late(soak(), bits::TRANSIENT),
    );
    println!("no slope {sur} -> {sur_soak}; transient {tr} -> {tr_soak} e-/s");
    assert!(sur > 0.0 && sur_soak < 0.9 * sur, "{sur} -> {sur_soak}");
    assert_eq!(tr_soak.to_bits(), tr.to_bits());
}

/// The effect path sets the next exposure's forced flag as the fused kernel does: with a
/// transient rule measured in flight, a hit with a slope follows the prediction and a
/// hit without one (NaN, `SUR_ERROR`) is flagged whatever it (`MAX_AMPLITUDE`); without
/// a rule every hit is flagged. A null effect gives the paper model's currents and flags
/// bit for bit in both cases.
#[test]
fn the_effect_path_forces_the_flag_after_a_hit_as_the_fused_kernel_does() {
    use persist::flags::{bits, pbits};
    use persist::model::params::{TransientProvenance, TransientRule};
    let rule = TransientRule {
        amplitude_e: 20.0,
        measured: TransientProvenance {
            report: "report.json".into(),
            report_sha256: "0".repeat(64),
            quantile: 0.95,
            ratio: 0.01,
            flown_amplitude_e: 2000.0,
            events: 1000,
        },
    };
    let after_hits = |p: ModelParams| -> (Array2<f32>, Array2<u8>) {
        let m = Model::new(p).unwrap();
        let mut st = m.new_state(1, 3);
        let t = bits::TRANSIENT;
        let mut out = Default::default();
        for k in 0..2u64 {
            let hit = k == 0;
            let img = if hit {
                ndarray::array![[0.5f32, f32::NAN, 0.5]]
            } else {
                Array2::zeros((1, 3))
            };
            let mut flags = if hit {
                ndarray::array![[t, t, t | bits::SUR_ERROR]]
            } else {
                Array2::zeros((1, 3))
            };
            let t_start_s = 100_000.0 * k as f64;
            out = step(
                &m,
                &mut st,
                &input(&img, k, t_start_s, 180.0, 180.0),
                &StepContext::default(),
                &mut flags,
            )
            .unwrap();
        }
        out
    };
    let forced = pbits::HIGH | pbits::LOW | pbits::MAX_AMPLITUDE;
    for (measured, want) in [(true, [0, forced, forced]), (false, [forced; 3])] {
        let mut p = paper();
        p.transient = measured.then(|| rule.clone());
        let (base_cur, base_flags) = after_hits(p.clone());
        assert_eq!(
            base_flags.row(0).to_vec(),
            want,
            "rule measured: {measured}"
        );
        let null = vec![spec("refill", serde_json::json!({"beta": 0.0}))];
        let (cur, flags) = after_hits(ModelParams { effects: null, ..p });
        assert_eq!(flags, base_flags, "rule measured: {measured}");
        let bits_of = |a: &Array2<f32>| a.mapv(f32::to_bits);
        assert_eq!(
            bits_of(&cur),
            bits_of(&base_cur),
            "rule measured: {measured}"
        );
    }
}
