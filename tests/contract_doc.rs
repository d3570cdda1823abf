//! docs/contract.md names every dataset, group and attribute that the JSON schemas in
//! schemas/ define (required or optional), and every key of the model file: the product
//! contract and the schemas that encode it stay in step.

use serde_json::Value;
use std::collections::BTreeSet;
use std::path::Path;

/// Keys of the manifest format itself (how a schema describes one attribute or
/// dataset), not names in the product.
const MANIFEST_KEYS: [&str; 8] = [
    "attributes",
    "datasets",
    "groups",
    "links",
    "value",
    "dtype",
    "shape",
    "type",
];

/// Every property name a schema defines, outside `$defs` (the manifest's templates).
fn property_names(schema: &Value, out: &mut BTreeSet<String>) {
    match schema {
        Value::Object(map) => {
            for (key, value) in map {
                if key == "$defs" {
                    continue;
                }
                if key == "properties" {
                    if let Value::Object(props) = value {
                        for (name, sub) in props {
                            if !MANIFEST_KEYS.contains(&name.as_str()) {
                                out.insert(name.clone());
                            }
                            property_names(sub, out);
                        }
                    }
                } else {
                    property_names(value, out);
                }
            }
        }
        Value::Array(items) => items.iter().for_each(|v| property_names(v, out)),
        _ => {}
    }
}

#[test]
fn contract_names_everything_the_schemas_define() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let doc = std::fs::read_to_string(root.join("docs/contract.md")).expect("docs/contract.md");
    let mut schemas: Vec<_> = std::fs::read_dir(root.join("schemas"))
        .expect("schemas/")
        .map(|e| e.expect("dir entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    schemas.sort();
    assert!(
        schemas.len() >= 4,
        "expected the four schemas, found {schemas:?}"
    );

    let mut missing = Vec::new();
    let mut all = BTreeSet::new();
    for path in &schemas {
        let text = std::fs::read_to_string(path).expect("read schema");
        let schema: Value = serde_json::from_str(&text).expect("schema is JSON");
        let mut names = BTreeSet::new();
        property_names(&schema, &mut names);
        for name in &names {
            // Named as code: `name` (the page's tables and text use backticks).
            if !doc.contains(&format!("`{name}`")) {
                missing.push(format!(
                    "{}: `{name}`",
                    path.file_name().unwrap().to_string_lossy()
                ));
            }
        }
        all.extend(names);
    }
    // The walk itself must see the contract (a walker that found nothing would pass).
    for known in [
        "/image",
        "/flags",
        "/persistence",
        "/persistence/current",
        "model_id",
        "t_meas_s",
        "/amplitudes_e",
        "amplitude_knots",
        "threshold_high_e_per_s",
    ] {
        assert!(all.contains(known), "the schema walk missed `{known}`");
    }
    assert!(
        missing.is_empty(),
        "docs/contract.md does not name these (schema: name); describe them there:\n  {}",
        missing.join("\n  ")
    );
}
