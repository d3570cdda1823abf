//! Model files on disk: read, validate against `schemas/model.schema.json`, parse.
//!
//! Kept out of [`crate::model`], which does no I/O. Every error has kind
//! [`ErrorKind::Model`], names the file, and names the field by its JSON pointer
//! (`/terms/2/rate_per_s`; `/` for the whole document).

use crate::error::{Error, ErrorKind, Result};
use crate::model::ModelParams;
use crate::product::schema::{self, Schema};
use std::path::Path;

/// Load a model file: schema first (every error), then [`ModelParams::from_json`].
pub fn load(path: &Path) -> Result<ModelParams> {
    check(path).map_err(schema::combine)
}

/// [`load`], with every error found.
pub fn check(path: &Path) -> std::result::Result<ModelParams, Vec<Error>> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        vec![Error::new(ErrorKind::Model, e.to_string())
            .field("/")
            .path(path)]
    })?;
    let value: serde_json::Value = serde_json::from_str(&text).map_err(|e| {
        vec![Error::new(ErrorKind::Model, format!("not JSON: {e}"))
            .field("/")
            .path(path)]
    })?;
    let errors = schema::validate(Schema::Model, &value, path);
    if !errors.is_empty() {
        return Err(errors);
    }
    ModelParams::from_json(&text).map_err(|m| vec![model_error(&m).path(path)])
}

/// `terms[2].rate_per_s: must be ...` -> field `/terms/2/rate_per_s`, reason after `: `.
fn model_error(message: &str) -> Error {
    match message.split_once(": ") {
        Some((field, reason))
            if !field.is_empty()
                && field
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_.[]".contains(c)) =>
        {
            let pointer = format!(
                "/{}",
                field
                    .replace('[', "/")
                    .replace("].", "/")
                    .replace(']', "")
                    .replace('.', "/")
            );
            Error::new(ErrorKind::Model, reason).field(pointer)
        }
        _ => Error::new(ErrorKind::Model, message).field("/"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn default_model_loads_and_keeps_identity() {
        let dir = tempfile::tempdir().unwrap();
        let p = ModelParams::default();
        let path = write(dir.path(), "m.json", &p.to_json_pretty());
        let q = load(&path).unwrap();
        assert_eq!(q.identity(), p.identity());
    }

    #[test]
    fn schema_errors_carry_json_pointers() {
        let dir = tempfile::tempdir().unwrap();
        let mut v = serde_json::to_value(ModelParams::default()).unwrap();
        v["terms"][2]["rate_per_s"] = serde_json::json!(-1.0);
        v["colour"] = serde_json::json!("red");
        v.as_object_mut().unwrap().remove("name");
        let path = write(dir.path(), "bad.json", &v.to_string());
        let errors = check(&path).unwrap_err();
        let fields: Vec<_> = errors
            .iter()
            .map(|e| e.context.field.clone().unwrap())
            .collect();
        assert!(
            fields.contains(&"/terms/2/rate_per_s".to_string()),
            "{fields:?}"
        );
        assert!(fields.contains(&"/colour".to_string()), "{fields:?}");
        assert!(fields.contains(&"/name".to_string()), "{fields:?}");
        assert!(errors.iter().all(|e| e.kind == ErrorKind::Model));
        let text = load(&path).unwrap_err().to_string();
        assert!(text.starts_with(&path.display().to_string()), "{text}");
    }

    #[test]
    fn semantic_errors_come_from_the_model() {
        let dir = tempfile::tempdir().unwrap();
        let mut p = ModelParams::default();
        p.amplitude_knots[1].fluence_e = 50.0;
        let path = write(dir.path(), "m.json", &p.to_json_pretty());
        let e = load(&path).unwrap_err();
        assert_eq!(e.kind, ErrorKind::Model);
        assert_eq!(
            e.context.field.as_deref(),
            Some("/amplitude_knots/1/fluence_e")
        );
        let path = write(dir.path(), "n.json", "{ not json");
        let e = load(&path).unwrap_err();
        assert!(e.message.contains("not JSON"), "{e}");
    }
}
