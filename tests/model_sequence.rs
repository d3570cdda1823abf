//! The model step against hand-worked arithmetic, and the fused step against the
//! plain reference implementation.

use ndarray::{array, Array2};
use persist::flags::{bits, pbits};
use persist::model::params::{TransientProvenance, TransientRule};
use persist::model::{
    reference, EarlyRelease, Input, Knot, Model, ModelParams, Output, ReleaseKeep, ReleaseRule,
    State, StepSummary, Term, Thresholds,
};
use proptest::prelude::*;

/// A two-term model small enough to follow by hand:
/// `C = [0.1, 0.01] /s`, rates `[0.1, 0.001] /s` (tau 10 s and 1000 s);
/// knots (1e5 e-, 100 e-), (2e5 e-, 1000 e-): `A_k = F/1000` below 1e5 e-,
/// `100 + 9 (F - 1e5)/1000` up to 2e5 e-, 1000 beyond (the maximum);
/// thresholds 0.1 / 0.01 e-/s; early release below 0.5 e-/s three times running
/// (`rule: consecutive`, whose count these hand-worked cases follow).
fn hand_model() -> Model {
    Model::new(ModelParams {
        name: "hand".into(),
        terms: vec![
            Term {
                c_per_s: 0.1,
                rate_per_s: 0.1,
            },
            Term {
                c_per_s: 0.01,
                rate_per_s: 0.001,
            },
        ],
        amplitude_knots: vec![
            Knot {
                fluence_e: 1e5,
                amplitude_e: 100.0,
            },
            Knot {
                fluence_e: 2e5,
                amplitude_e: 1000.0,
            },
        ],
        thresholds: Thresholds {
            high_e_per_s: 0.1,
            low_e_per_s: 0.01,
        },
        early_release: EarlyRelease {
            enabled: true,
            threshold_e_per_s: 0.5,
            consecutive: 3,
            subtract_background: true,
            rule: ReleaseRule::Consecutive,
            ..EarlyRelease::default()
        },
        ..ModelParams::default()
    })
    .unwrap()
}

struct Run {
    /// Passed as `Input::background_e_per_s` (the hand-worked cases pin it to 0).
    background: Option<f64>,
    model: Model,
    state: State,
    current: Array2<f32>,
    pflags: Array2<u8>,
}

impl Run {
    fn new(model: Model, ny: usize, nx: usize) -> Self {
        let state = model.new_state(ny, nx);
        Run {
            background: Some(0.0),
            model,
            state,
            current: Array2::zeros((ny, nx)),
            pflags: Array2::zeros((ny, nx)),
        }
    }

    fn step(
        &mut self,
        index: u64,
        t_start: f64,
        image: Array2<f32>,
        mut flags: Array2<u32>,
    ) -> (StepSummary, Array2<u32>) {
        let input = Input {
            image_e_per_s: image.view(),
            exposure_index: index,
            t_start_unix_s: t_start,
            t_exposure_s: 100.0,
            t_illuminated_s: 100.0,
            history_incomplete: false,
            background_e_per_s: self.background,
        };
        let mut out = Output {
            flags: &mut flags,
            current_e_per_s: &mut self.current,
            pflags: &mut self.pflags,
        };
        let s = self.model.step(&mut self.state, &input, &mut out).unwrap();
        (s, flags)
    }

    fn amps(&self, x: usize) -> [f64; 2] {
        [
            self.state.amplitudes_e[(0, x, 0)],
            self.state.amplitudes_e[(0, x, 1)],
        ]
    }
}

/// A transient rule of `amplitude_e` (its provenance made up: the step does not read it).
fn rule(amplitude_e: f64) -> TransientRule {
    TransientRule {
        amplitude_e,
        measured: TransientProvenance {
            report: "report.json".into(),
            report_sha256: "0".repeat(64),
            quantile: 0.95,
            ratio: amplitude_e / 1000.0,
            flown_amplitude_e: 1000.0,
            events: 1000,
        },
    }
}

/// With a measured transient rule of 50 e- (the hand model's maximum is 1000 e-): a hit
/// on a dark pixel adds 50 e-, one on a pixel whose slope asks for more adds the slope's
/// amplitude, a hit without a usable slope (NaN, or `SUR_ERROR`) keeps the maximum; the
/// exposure after a hit with a slope follows the prediction (the rule was measured
/// there), the one after a hit without a slope is flagged whatever it (`MAX_AMPLITUDE`).
#[test]
fn a_measured_transient_rule_sets_the_hit_s_amplitude_and_its_next_exposure_s_flag() {
    let mut params = hand_model().params().clone();
    params.transient = Some(rule(50.0));
    let mut r = Run::new(Model::new(params).unwrap(), 1, 4);
    let t = bits::TRANSIENT;
    // x = 1: 1500 e-/s x 100 s = 1.5e5 e- -> A_k = 100 + 9 x 50 = 550 > 50.
    r.step(
        0,
        0.0,
        array![[0.0, 1500.0, f32::NAN, 0.0]],
        array![[t, t, t, t | bits::SUR_ERROR]],
    );
    assert_eq!(r.amps(0), [50.0, 50.0]);
    assert_eq!(r.amps(1), [550.0, 550.0]);
    assert_eq!(r.amps(2), [1000.0, 1000.0]);
    assert_eq!(r.amps(3), [1000.0, 1000.0]);
    // E1 a day later: every prediction is far below 0.01 e-/s; only the hits without a
    // slope are flagged.
    r.step(1, 86_400.0, Array2::zeros((1, 4)), Array2::zeros((1, 4)));
    assert!(r.current.iter().all(|&c| c < 0.01), "{:?}", r.current);
    let forced = pbits::HIGH | pbits::LOW | pbits::MAX_AMPLITUDE;
    assert_eq!(r.pflags.row(0).to_vec(), [0, 0, forced, forced]);
}

/// Without a measured rule every hit takes the maximum and the exposure after it is
/// flagged whatever the prediction (the paper's conservative transient, section
/// "Transients").
#[test]
fn without_a_measured_rule_the_exposure_after_every_hit_stays_flagged() {
    let mut r = Run::new(hand_model(), 1, 2);
    let t = bits::TRANSIENT;
    r.step(0, 0.0, array![[0.0, f32::NAN]], array![[t, t]]);
    assert_eq!(r.amps(0), [1000.0, 1000.0]);
    r.step(1, 86_400.0, Array2::zeros((1, 2)), Array2::zeros((1, 2)));
    assert!(r.current.iter().all(|&c| c < 0.01), "{:?}", r.current);
    let forced = pbits::HIGH | pbits::LOW | pbits::MAX_AMPLITUDE;
    assert_eq!(r.pflags.row(0).to_vec(), [forced, forced]);
}

fn close(got: f64, want: f64) {
    let tol = 1e-6 * want.abs().max(1e-12);
    assert!((got - want).abs() <= tol, "got {got}, want {want}");
}

/// Pixel P (x = 0) is lit three times, then dark, and is released early; pixel Q
/// (x = 1) has a transient, is flagged at the maximum amplitude, then released.
/// Exposures are 100 s; starts 0, 120, 250, 1350 (a 1000 s slew), 1460, 1570.
#[test]
fn hand_worked_sequence() {
    let mut r = Run::new(hand_model(), 1, 2);
    let none = || array![[0u32, 0]];

    // E0 (first exposure, no previous state): prediction 0 everywhere.
    // P: 1000 e-/s x 100 s = 1e5 e- -> A_k = 100 -> A = [100, 100].  Q: dark -> A = 0.
    let (s, _) = r.step(0, 0.0, array![[1000.0, 0.0]], none());
    assert_eq!(s.t_meas_s, None);
    assert_eq!(r.current, array![[0.0f32, 0.0]]);
    assert_eq!(r.amps(0), [100.0, 100.0]);
    assert_eq!(r.amps(1), [0.0, 0.0]);

    // E1: reset(E0) = 100 s; slew = 120 - 100 = 20 s; t_meas = 20 + 50 = 70 s;
    // t_elapsed = 220 - 100 = 120 s.
    // P: pred = 100*0.1*e^-7 + 100*0.01*e^-0.07 = 0.0091188 + 0.9323938 = 0.9415126 -> HIGH.
    //    decay: A = [100 e^-12 + 100, 100 e^-0.12 + 100] = [100.000614421, 188.692043672].
    // Q: TRANSIENT -> A_k = max knot = 1000 -> A = [1000, 1000], pending.
    let (s, flags) = r.step(
        1,
        120.0,
        array![[1000.0, 0.0]],
        array![[0, bits::TRANSIENT]],
    );
    assert_eq!(s.t_meas_s, Some(70.0));
    close(r.current[(0, 0)] as f64, 0.9415126395614934);
    assert_eq!(r.pflags[(0, 0)], pbits::HIGH | pbits::LOW);
    assert_eq!(flags[(0, 0)], bits::PERSIST);
    assert_eq!(
        flags[(0, 1)],
        bits::TRANSIENT,
        "Q not yet flagged: its prediction is 0"
    );
    close(r.amps(0)[0], 100.00061442123533);
    close(r.amps(0)[1], 188.69204367171574);
    assert_eq!(r.amps(1), [1000.0, 1000.0]);

    // E2: reset(E1) = 220 s; slew 30 s; t_meas = 80 s; t_elapsed = 130 s.
    // P: pred = 100.000614*0.1*e^-8 + 188.692044*0.01*e^-0.08 = 0.0033546 + 1.7418471 = 1.7452017.
    //    Third bright exposure: A = [100.000614 e^-13 + 100, 188.692044 e^-0.13 + 100]
    //                             = [100.000226034, 265.689621399].
    // Q: pred = 1000*0.1*e^-8 + 1000*0.01*e^-0.08 = 0.0335463 + 9.2311635 = 9.2647097;
    //    flagged with MAX_AMPLITUDE; measured 0.2 < 0.5 -> count 1;
    //    fluence 0.2*100 = 20 e- -> A_k = 0.02; A = [1000 e^-13 + 0.02, 1000 e^-0.13 + 0.02].
    let (s, flags) = r.step(2, 250.0, array![[1000.0, 0.2]], none());
    assert_eq!(s.t_meas_s, Some(80.0));
    close(r.current[(0, 0)] as f64, 1.745201746355179);
    close(r.current[(0, 1)] as f64, 9.264709726656609);
    assert_eq!(
        r.pflags[(0, 1)],
        pbits::HIGH | pbits::LOW | pbits::MAX_AMPLITUDE
    );
    assert_eq!(flags[(0, 1)], bits::PERSIST);
    assert_eq!(r.state.release_count[(0, 1)], 1);
    close(r.amps(0)[0], 100.00022603432949);
    close(r.amps(0)[1], 265.6896213991966);
    close(r.amps(1)[0], 0.022260329406981055);
    close(r.amps(1)[1], 878.1154309205613);

    // E3: a long slew. reset(E2) = 350 s; start 1350 -> slew 1000 s; t_meas = 1050 s;
    // t_elapsed = 1100 s. P now dark (0.1 e-/s -> 10 e- -> A_k = 0.01).
    // P: pred = 100.000226*0.1*e^-105 + 265.689621*0.01*e^-1.05 = 0 + 0.9297483; count 1.
    //    A = [~0 + 0.01, 265.689621 e^-1.1 + 0.01] = [0.01, 88.450392202].
    // Q: pred = 0.0222603*0.1*e^-105 + 878.115431*0.01*e^-1.05 = 3.0728574; count 2.
    let (s, _) = r.step(3, 1350.0, array![[0.1, 0.2]], none());
    assert_eq!(s.t_meas_s, Some(1050.0));
    close(r.current[(0, 0)] as f64, 0.9297482807462991);
    close(r.current[(0, 1)] as f64, 3.0728573735611344);
    assert_eq!(
        r.pflags[(0, 1)],
        pbits::HIGH | pbits::LOW,
        "MAX_AMPLITUDE only once"
    );
    assert_eq!(r.state.release_count[(0, 0)], 1);
    assert_eq!(r.state.release_count[(0, 1)], 2);
    close(r.amps(0)[1], 88.45039220248304);

    // E4: slew 10 s; t_meas = 60 s; t_elapsed = 110 s.
    // P: pred = 0.01*0.1*e^-6 + 88.450392*0.01*e^-0.06 = 0.8329969; count 2.
    // Q: pred = 0.02*0.1*e^-6 + 292.319235*0.01*e^-0.06 = 2.7529638 but third low
    //    measurement -> RELEASED: not flagged, amplitudes zeroed, then A_k = 0.02 added.
    let (s, flags) = r.step(4, 1460.0, array![[0.1, 0.2]], none());
    close(r.current[(0, 0)] as f64, 0.8329969023313297);
    close(r.current[(0, 1)] as f64, 2.7529638385447694);
    assert_eq!(r.pflags[(0, 1)], pbits::RELEASED);
    assert_eq!(flags[(0, 1)], 0);
    // (0.2 is an f32 in the image: 0.2000000030 e-/s.)
    close(r.amps(1)[0], 0.02);
    close(r.amps(1)[1], 0.02);
    assert_eq!(s.released, 1);

    // E5: P's third low measurement: pred 0.7463215 -> RELEASED, A = [0.01, 0.01].
    // Q: pred = 0.02*0.1*e^-6 + 0.02*0.01*e^-0.06 = 0.0001933 -> not flagged.
    let (s, flags) = r.step(5, 1570.0, array![[0.1, 0.2]], none());
    close(r.current[(0, 0)] as f64, 0.7463214944007951);
    close(r.current[(0, 1)] as f64, 0.00019331041107018245);
    assert_eq!(r.pflags, array![[pbits::RELEASED, 0]]);
    assert_eq!(flags, array![[0, 0]]);
    close(r.amps(0)[0], 0.01);
    close(r.amps(0)[1], 0.01);
    assert_eq!((s.released, s.above_high, s.above_low), (1, 0, 0));
}

#[test]
fn out_of_order_and_early_start_are_refused_without_change() {
    let mut r = Run::new(hand_model(), 1, 2);
    r.step(0, 0.0, array![[1000.0, 0.0]], array![[0, 0]]);
    let before = r.state.clone();
    let image = array![[1.0f32, 1.0]];
    let mut flags = array![[0u32, 0]];
    for (index, start, field) in [(0, 200.0, "exposure_index"), (1, 99.0, "t_start_utc")] {
        let input = Input {
            image_e_per_s: image.view(),
            exposure_index: index,
            t_start_unix_s: start,
            t_exposure_s: 100.0,
            t_illuminated_s: 100.0,
            history_incomplete: false,
            background_e_per_s: Some(0.0),
        };
        let mut out = Output {
            flags: &mut flags,
            current_e_per_s: &mut r.current,
            pflags: &mut r.pflags,
        };
        let e = r.model.step(&mut r.state, &input, &mut out).unwrap_err();
        assert_eq!(e.context.field.as_deref(), Some(field), "{e}");
        assert_eq!(r.state, before);
    }
}

#[test]
fn nan_inf_and_negative_never_enter_the_state() {
    let model = Model::new(ModelParams::default()).unwrap();
    let mut r = Run::new(model, 1, 5);
    let image = array![[f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -50.0, f32::NAN]];
    let flags = array![[0, 0, 0, 0, bits::NONFUNC]];
    r.step(0, 0.0, image, flags);
    let a = |x: usize| r.state.amplitudes_e[(0, x, 0)];
    // NaN / +Inf / -Inf: unknown fluence -> maximum amplitude (878 e-); negative -> 0;
    // NONFUNC -> 0 even with NaN.
    assert_eq!(
        [a(0), a(1), a(2), a(3), a(4)],
        [878.0, 878.0, 878.0, 0.0, 0.0]
    );
    assert!(r.state.check().is_ok());
    // The next exposure flags the unknown-fluence pixels with MAX_AMPLITUDE.
    r.step(
        1,
        130.0,
        array![[1.0, 1.0, 1.0, 1.0, 1.0]],
        array![[0, 0, 0, 0, 0]],
    );
    assert_eq!(
        r.pflags.mapv(|p| p & pbits::MAX_AMPLITUDE != 0),
        array![[true, true, true, false, false]]
    );
}

/// One random exposure for the property test.
#[derive(Debug, Clone)]
struct Exp {
    slew_s: f64,
    t_exposure_s: f64,
    image: Vec<f32>,
    flags: Vec<u32>,
    gap: bool,
}

fn exp_strategy(npix: usize) -> impl Strategy<Value = Exp> {
    let value = prop_oneof![
        8 => 0.0f32..50.0,
        3 => 50.0f32..20_000.0,
        1 => Just(f32::NAN),
        1 => Just(f32::INFINITY),
        1 => -5.0f32..0.0,
    ];
    let flag = prop_oneof![
        10 => Just(0u32),
        1 => Just(bits::TRANSIENT),
        1 => Just(bits::SUR_ERROR),
        1 => Just(bits::NONFUNC),
        1 => Just(bits::OVERFLOW | bits::PERSIST),
    ];
    (
        0.0f64..5000.0,
        1.0f64..700.0,
        prop::collection::vec(value, npix),
        prop::collection::vec(flag, npix),
        prop::bool::weighted(0.1),
    )
        .prop_map(|(slew_s, t_exposure_s, image, flags, gap)| Exp {
            slew_s,
            t_exposure_s,
            image,
            flags,
            gap,
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Random action sequences: the fused step and the reference agree bit for bit on
    /// every output and on the state, and the state stays finite and >= 0.
    #[test]
    fn fused_step_matches_reference(seq in prop::collection::vec(exp_strategy(12), 1..25)) {
        let mut params = ModelParams::default();
        params.early_release.threshold_e_per_s = 5.0; // let releases happen often
        let model = Model::new(params).unwrap();
        fused_matches_reference(&model, &seq)?;
    }

    /// The same with the paper-style count (`rule: consecutive`).
    #[test]
    fn fused_step_matches_reference_counting_consecutive(
        seq in prop::collection::vec(exp_strategy(12), 1..25),
    ) {
        let mut params = ModelParams::default();
        params.early_release.threshold_e_per_s = 5.0;
        params.early_release.rule = ReleaseRule::Consecutive;
        let model = Model::new(params).unwrap();
        fused_matches_reference(&model, &seq)?;
    }

    /// The same with released pixels keeping the threshold (`keep: threshold`).
    #[test]
    fn fused_step_matches_reference_keeping_the_threshold(
        seq in prop::collection::vec(exp_strategy(12), 1..25),
    ) {
        let mut params = ModelParams::default();
        params.early_release.threshold_e_per_s = 5.0;
        params.early_release.keep = ReleaseKeep::Threshold;
        let model = Model::new(params).unwrap();
        fused_matches_reference(&model, &seq)?;
    }

    /// The same with a measured transient rule (below the table's maximum).
    #[test]
    fn fused_step_matches_reference_with_a_transient_rule(
        seq in prop::collection::vec(exp_strategy(12), 1..25),
    ) {
        let mut params = ModelParams::default();
        params.early_release.threshold_e_per_s = 5.0;
        params.transient = Some(rule(30.0));
        let model = Model::new(params).unwrap();
        fused_matches_reference(&model, &seq)?;
    }

    /// The same for other term counts (the specialised 4-term loop and the dynamic one).
    #[test]
    fn fused_step_matches_reference_any_term_count(
        seq in prop::collection::vec(exp_strategy(12), 1..12),
        n in 1usize..9,
    ) {
        let mut params = ModelParams::default();
        params.early_release.threshold_e_per_s = 5.0;
        let base = params.terms.clone();
        params.terms = (0..n)
            .map(|i| Term {
                c_per_s: base[i % base.len()].c_per_s,
                rate_per_s: base[i % base.len()].rate_per_s * (1.0 + i as f64),
            })
            .collect();
        let model = Model::new(params).unwrap();
        prop_assert_eq!(model.n_terms(), n);
        fused_matches_reference(&model, &seq)?;
    }
}

fn fused_matches_reference(model: &Model, seq: &[Exp]) -> Result<(), TestCaseError> {
    let (ny, nx) = (3, 4);
    let mut a = model.new_state(ny, nx);
    let mut b = model.new_state(ny, nx);
    let mut t = 1.0e9;
    for (k, e) in seq.iter().enumerate() {
        t += e.slew_s;
        let image = Array2::from_shape_vec((ny, nx), e.image.clone()).unwrap();
        let flags0 = Array2::from_shape_vec((ny, nx), e.flags.clone()).unwrap();
        let input = Input {
            image_e_per_s: image.view(),
            exposure_index: k as u64 * 2,
            t_start_unix_s: t,
            t_exposure_s: e.t_exposure_s,
            t_illuminated_s: e.t_exposure_s,
            history_incomplete: e.gap,
            background_e_per_s: None,
        };
        let (mut fa, mut ca, mut pa) = (
            flags0.clone(),
            Array2::zeros((ny, nx)),
            Array2::zeros((ny, nx)),
        );
        let (mut fb, mut cb, mut pb) = (
            flags0.clone(),
            Array2::zeros((ny, nx)),
            Array2::zeros((ny, nx)),
        );
        let sa = model
            .step(
                &mut a,
                &input,
                &mut Output {
                    flags: &mut fa,
                    current_e_per_s: &mut ca,
                    pflags: &mut pa,
                },
            )
            .unwrap();
        let sb = reference::step(
            model,
            &mut b,
            &input,
            &mut Output {
                flags: &mut fb,
                current_e_per_s: &mut cb,
                pflags: &mut pb,
            },
        )
        .unwrap();
        prop_assert_eq!(sa, sb);
        prop_assert_eq!(ca.mapv(f32::to_bits), cb.mapv(f32::to_bits));
        prop_assert_eq!(&pa, &pb);
        prop_assert_eq!(&fa, &fb);
        prop_assert_eq!(
            a.amplitudes_e.mapv(f64::to_bits),
            b.amplitudes_e.mapv(f64::to_bits)
        );
        prop_assert_eq!(&a.release_count, &b.release_count);
        prop_assert_eq!(&a.pending, &b.pending);
        prop_assert!(a.check().is_ok());
        // PERSIST exactly where HIGH.
        for (f, p) in fa.iter().zip(pa.iter()) {
            prop_assert_eq!(f & bits::PERSIST != 0, p & pbits::HIGH != 0);
        }
        t += e.t_exposure_s;
    }
    Ok(())
}

/// Early release on a sky: a pixel flagged after a transient, measuring only the
/// 1.0 e-/s sky (+0.05), is released after three exposures (`rule: consecutive`) when
/// the background (the image median) is subtracted, and never without it
/// (1.05 > 0.1 e-/s).
#[test]
fn early_release_subtracts_the_sky_level() {
    for (subtract, released_at) in [(true, Some(3u64)), (false, None)] {
        let mut params = ModelParams::default();
        params.early_release.subtract_background = subtract;
        params.early_release.rule = ReleaseRule::Consecutive;
        let mut r = Run::new(Model::new(params).unwrap(), 4, 4);
        r.background = None; // estimated from the image: 1.0 e-/s
        let sky = Array2::from_elem((4, 4), 1.0f32);
        let mut hit = Array2::zeros((4, 4));
        hit[(0, 0)] = bits::TRANSIENT;
        r.step(0, 0.0, sky.clone(), hit);
        let mut first_release = None;
        for k in 1..8u64 {
            let mut image = sky.clone();
            image[(0, 0)] = 1.05;
            let (s, _) = r.step(k, k as f64 * 130.0, image, Array2::zeros((4, 4)));
            if s.released > 0 && first_release.is_none() {
                first_release = Some(k);
                assert_eq!(r.pflags[(0, 0)], pbits::RELEASED);
            }
        }
        assert_eq!(
            first_release, released_at,
            "subtract_background = {subtract}"
        );
    }
}

/// The evidence rule (the default: 4 noise sigma) on a 4 x 8 sky whose 28 quiet pixels
/// measure 0.75, 1.0 or 1.25 e-/s (13, 2 and 13 of them): background 1.0 e-/s (their
/// median), noise 1.4826 x 0.25 e-/s (their median absolute deviation, 0.25). Four
/// pixels lit at 1e4 e-/s stay flagged high for the 30 exposures that follow (checked),
/// measured, less the background:
/// - 0.1 e-/s - 1 sigma each time: 1 sigma of evidence a time, released at the 4th;
/// - 0.1 e-/s - sigma / 2: released at the 8th (`consecutive` would at the 3rd);
/// - the threshold, to f32 rounding: never released;
/// - 1 sigma below and above the threshold in turn: never released (the count rule
///   needs a run, so it would not either; the evidence rule, because it cancels).
#[test]
fn evidence_releases_pixels_measured_below_and_keeps_those_at_the_threshold() {
    let (ny, nx) = (4, 8);
    let sigma = 1.4826 * 0.25;
    let quiet = |i: usize| match i {
        0..13 => 0.75f32,
        13..15 => 1.0,
        _ => 1.25,
    };
    let sky = |levels: [f32; 4]| {
        Array2::from_shape_fn((ny, nx), |(y, x)| {
            let i = y * nx + x;
            if i < 4 {
                levels[i]
            } else {
                quiet(i - 4)
            }
        })
    };
    for (rule, expected) in [
        (ReleaseRule::Evidence, [Some(4u64), Some(8), None, None]),
        (ReleaseRule::Consecutive, [Some(3u64), Some(3), None, None]),
    ] {
        let mut params = ModelParams::default();
        params.early_release.rule = rule;
        let mut r = Run::new(Model::new(params).unwrap(), ny, nx);
        r.background = None; // estimated by the step
        r.step(0, 0.0, sky([1e4; 4]), Array2::zeros((ny, nx)));
        let mut released = [None; 4];
        for k in 1..=30u64 {
            let at = |below_sigma: f64| (1.1 - below_sigma * sigma) as f32;
            let turn = if k % 2 == 1 { 1.0 } else { -1.0 };
            let image = sky([at(1.0), at(0.5), at(0.0), at(turn)]);
            r.step(k, k as f64 * 130.0, image, Array2::zeros((ny, nx)));
            for (x, first) in released.iter_mut().enumerate() {
                let f = r.pflags[(0, x)];
                if f & pbits::RELEASED != 0 {
                    first.get_or_insert(k);
                } else if first.is_none() {
                    assert_ne!(f & pbits::HIGH, 0, "{rule:?}: pixel {x} flagged at {k}");
                }
            }
        }
        assert_eq!(released, expected, "{rule:?}");
    }
}

/// What a released pixel keeps (`early_release.keep`): the hand model's pixel 0 lit at
/// 1.5e5 e- (A = 550 e- on both terms), then measured at 0 e-/s every 200 s until it is
/// released (the third dark, `rule: consecutive`). Reset to zero, its prediction is 0
/// from then on. Kept at the threshold, it is 0.1 e-/s at the release; the 10 s term
/// long gone, the next prediction is `0.1 exp(-0.001 x 200 s)`, and it keeps decaying by
/// that factor, never flagged high, flagged low while above 0.01 e-/s.
#[test]
fn a_released_pixel_keeps_zero_or_the_threshold() {
    let mut after = Vec::new();
    for keep in [ReleaseKeep::Zero, ReleaseKeep::Threshold] {
        let mut params = hand_model().params().clone();
        params.early_release.keep = keep;
        let mut r = Run::new(Model::new(params).unwrap(), 1, 2);
        r.step(0, 0.0, array![[1500.0f32, 0.0]], Array2::zeros((1, 2)));
        let mut released_at = None;
        let mut predicted = Vec::new();
        for k in 1..=8u64 {
            r.step(
                k,
                200.0 * k as f64,
                array![[0.0f32, 0.0]],
                Array2::zeros((1, 2)),
            );
            if r.pflags[(0, 0)] & pbits::RELEASED != 0 {
                assert!(r.current[(0, 0)] > 0.1, "{keep:?}: flagged high before");
                released_at = Some(k);
            } else if released_at.is_some() {
                let p = f64::from(r.current[(0, 0)]);
                assert_eq!(r.pflags[(0, 0)] & pbits::HIGH, 0, "{keep:?} at {k}");
                assert_eq!(
                    r.pflags[(0, 0)] & pbits::LOW != 0,
                    p > 0.01,
                    "{keep:?} at {k}"
                );
                predicted.push(r.current[(0, 0)]);
            }
        }
        assert_eq!(released_at, Some(3), "{keep:?}");
        after.push(predicted);
    }
    assert!(after[0].iter().all(|p| *p == 0.0), "{:?}", after[0]);
    let factor = (-0.001f64 * 200.0).exp();
    for (i, p) in after[1].iter().enumerate() {
        let want = 0.1 * factor.powi(i as i32 + 1);
        assert!(
            (f64::from(*p) / want - 1.0).abs() < 1e-5,
            "{i}: {p} against {want}"
        );
    }
    assert!(after[1].iter().all(|p| *p > 0.01), "{:?}", after[1]);
}

#[test]
fn noise_is_the_quiet_pixels_robust_deviation() {
    use persist::model::step::noise_e_per_s;
    use persist::model::BackgroundEstimate::ImageMedian;
    // 0.75 / 1.0 / 1.25 e-/s: the median 1.0, every deviation 0.25 but one
    let image = array![
        [0.75f32, 1.0, 1.25],
        [0.75, 1.25, 1.0],
        [f32::NAN, 0.75, 1.25]
    ];
    let none = ndarray::Array3::<f64>::zeros((3, 3, 0));
    let got = noise_e_per_s(ImageMedian, &image.view(), &none, &[], 0.01);
    assert!((got - 1.4826 * 0.25).abs() < 1e-12, "{got}");
    let empty = Array2::from_elem((2, 2), f32::NAN);
    assert_eq!(
        noise_e_per_s(ImageMedian, &empty.view(), &none, &[], 0.01),
        0.0
    );
}

#[test]
fn sky_level_is_the_median_of_finite_pixels() {
    use persist::model::step::sky_level_e_per_s;
    let mut a = Array2::from_shape_fn((10, 10), |(y, x)| (y * 10 + x) as f32);
    a[(0, 0)] = f32::NAN;
    a[(9, 9)] = 1e6; // a star does not move the median
                     // 98 finite values 1..=98 plus 1e6: the median (index 49 of 0..99) is 50.
    assert_eq!(sky_level_e_per_s(&a.view()), 50.0);
    assert_eq!(
        sky_level_e_per_s(&Array2::from_elem((3, 3), f32::NAN).view()),
        0.0
    );
}

/// Regression: where most of the array carries
/// persistence (a laboratory spot), the image median does too, and subtracting it as
/// the background released pixels still above the flag threshold. An 8 x 8 array, 48
/// pixels lit at 1e6 e- (predicted ~2 e-/s over the darks that follow, the default
/// model), then dark exposures in which the lit pixels measure 0.6 e-/s of persistence
/// and the 16 others the 0.02 e-/s dark current. The image median is 0.6: with
/// `image_median` the lit pixels pass `0.6 < 0.1 + 0.6` and are released at the third
/// dark exposure; with `quiet_pixels` the background is the 16 unlit pixels' 0.02 e-/s,
/// `0.6 > 0.12`, and nothing is released (`rule: consecutive`).
#[test]
fn a_lit_median_pixel_does_not_release_persistent_pixels() {
    use persist::model::BackgroundEstimate;
    for (estimate, released_at) in [
        (BackgroundEstimate::ImageMedian, Some(3u64)),
        (BackgroundEstimate::QuietPixels, None),
    ] {
        let mut params = ModelParams::default();
        params.early_release.background = estimate;
        params.early_release.rule = ReleaseRule::Consecutive;
        let mut r = Run::new(Model::new(params).unwrap(), 8, 8);
        r.background = None; // estimated by the step
        let lit = |y: usize, _x: usize| y < 6;
        let spot = Array2::from_shape_fn((8, 8), |(y, x)| if lit(y, x) { 1e4f32 } else { 0.02 });
        r.step(0, 0.0, spot, Array2::zeros((8, 8)));
        let dark = Array2::from_shape_fn((8, 8), |(y, x)| if lit(y, x) { 0.6f32 } else { 0.02 });
        let mut first_release = None;
        for k in 1..8u64 {
            let (s, _) = r.step(k, k as f64 * 130.0, dark.clone(), Array2::zeros((8, 8)));
            if k == 1 {
                assert_eq!(s.above_high, 48, "{estimate:?}: the lit pixels are flagged");
            }
            if s.released > 0 && first_release.is_none() {
                first_release = Some(k);
                assert_eq!(s.released, 48);
            }
        }
        assert_eq!(first_release, released_at, "{estimate:?}");
    }
}

/// With an empty state (the first exposure) every pixel is quiet: `quiet_pixels` is the
/// image median; on a sky whose few persistent pixels the model knows, it is the
/// median of the others.
#[test]
fn quiet_pixel_background_is_the_median_of_the_unpersistent_pixels() {
    use persist::model::step::{background_e_per_s, sky_level_e_per_s};
    use persist::model::BackgroundEstimate::{ImageMedian, QuietPixels};
    let image = Array2::from_shape_fn((10, 10), |(y, x)| (y * 10 + x) as f32);
    let zeros = ndarray::Array3::<f64>::zeros((10, 10, 2));
    let w = [0.5, 0.25];
    let median = sky_level_e_per_s(&image.view());
    assert_eq!(median, 50.0);
    assert_eq!(
        background_e_per_s(QuietPixels, &image.view(), &zeros, &w, 0.01),
        median
    );
    // the model predicts persistence (A = 1 e-: 0.75 e-/s > 0.01) in the 40 pixels of
    // rows 6-9 (values 60..=99): the quiet ones are 0..=59, median (upper) 30
    let mut amps = zeros.clone();
    amps.slice_mut(ndarray::s![6.., .., ..]).fill(1.0);
    assert_eq!(
        background_e_per_s(QuietPixels, &image.view(), &amps, &w, 0.01),
        30.0
    );
    assert_eq!(
        background_e_per_s(ImageMedian, &image.view(), &amps, &w, 0.01),
        median
    );
    // every pixel persistent (rows 0-1 at A = 1, rows 2-9 at A = 2): at least the 16 (of
    // 100) with the lowest prediction, here the 20 that tie at A = 1, 0..=19: median 10
    amps.fill(2.0);
    amps.slice_mut(ndarray::s![..2, .., ..]).fill(1.0);
    assert_eq!(
        background_e_per_s(QuietPixels, &image.view(), &amps, &w, 0.01),
        10.0
    );
}
