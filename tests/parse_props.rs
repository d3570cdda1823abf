//! Property tests (proptest) of the parsing code that is ours, on arbitrary and mutated
//! text: the model file (JSON, its schema, `ModelParams::from_json`), the manifest of a
//! product's attributes (schema and the checks beyond it), UTC times and `--fits-gain`.
//! None may panic; what parses must mean the same after a round trip.

use persist::model::ModelParams;
use persist::product::schema::{self, Schema, View};
use proptest::prelude::*;
use serde_json::Value;
use std::path::Path;

/// Arbitrary JSON values, a few levels deep.
fn json() -> impl Strategy<Value = Value> {
    let leaf = prop_oneof![
        Just(Value::Null),
        any::<bool>().prop_map(Value::Bool),
        any::<i64>().prop_map(Value::from),
        any::<f64>()
            .prop_map(|x| serde_json::Number::from_f64(x).map_or(Value::Null, Value::Number)),
        "[a-z_/0-9 .:-]{0,12}".prop_map(Value::String),
    ];
    leaf.prop_recursive(4, 64, 8, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..6).prop_map(Value::Array),
            prop::collection::btree_map(
                prop_oneof![
                    "[a-z_]{1,10}".boxed(),
                    Just("attributes".to_owned()).boxed(),
                    Just("datasets".to_owned()).boxed(),
                    Just("value".to_owned()).boxed(),
                    Just("dtype".to_owned()).boxed(),
                    Just("shape".to_owned()).boxed(),
                ],
                inner,
                0..6
            )
            .prop_map(|m| Value::Object(m.into_iter().collect())),
        ]
    })
}

/// The default model file with `edits` applied: (position, byte) overwrites.
fn mutated_model(edits: &[(usize, u8)], cut: Option<usize>) -> String {
    let mut b = ModelParams::default().to_json_pretty().into_bytes();
    for &(at, v) in edits {
        let i = at % b.len();
        b[i] = v;
    }
    if let Some(c) = cut {
        b.truncate(c % (b.len() + 1));
    }
    String::from_utf8_lossy(&b).into_owned()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn a_mutated_model_file_is_refused_or_round_trips(
        edits in prop::collection::vec((any::<usize>(), any::<u8>()), 0..8),
        cut in prop::option::of(any::<usize>()),
    ) {
        let text = mutated_model(&edits, cut);
        if let Ok(p) = ModelParams::from_json(&text) {
            let again = ModelParams::from_json(&p.canonical_json()).unwrap();
            prop_assert_eq!(again.canonical_json(), p.canonical_json());
        }
        if let Ok(v) = serde_json::from_str::<Value>(&text) {
            let _ = schema::validate(Schema::Model, &v, Path::new("m.json"));
        }
    }

    #[test]
    fn arbitrary_json_never_panics_the_model_parser(v in json()) {
        let text = v.to_string();
        let _ = ModelParams::from_json(&text);
        let _ = schema::validate(Schema::Model, &v, Path::new("m.json"));
    }

    #[test]
    fn arbitrary_manifests_never_panic_the_attribute_checks(v in json(), output in any::<bool>()) {
        let which = if output { Schema::L2Persistence } else { Schema::L1Exposure };
        let _ = schema::validate(which, &v, Path::new("p.h5"));
        let _ = schema::check_exposure_manifest(View(&v), output);
    }

    #[test]
    fn utc_times_parse_or_are_refused_and_round_trip(
        s in "[0-9T:.Z+-]{0,32}",
        secs in 0i64..4_000_000_000,
        micros in 0u32..1_000_000,
    ) {
        let _ = persist::units::UtcSeconds::parse(&s);
        let t = persist::units::UtcSeconds(secs as f64 + f64::from(micros) * 1e-6);
        let back = persist::units::UtcSeconds::parse(&t.to_iso()).unwrap();
        // `to_iso` writes whole microseconds.
        prop_assert!((back.0 - t.0).abs() <= 1.5e-6, "{} -> {}", t.0, back.0);
    }

    #[test]
    fn fits_gains_parse_or_are_refused(s in "[0-9a-z:.eE+-]{0,16}") {
        if let Ok((d, g)) = persist::fits::parse_gain(&s) {
            prop_assert!((1..=6).contains(&d) && g.is_finite() && g > 0.0, "{s} -> {d} {g}");
        }
    }
}
