//! The map file (`schemas/pixel_map.schema.json`, docs/contract.md "Per-pixel response
//! maps"): written atomically and byte-identically ([`crate::h5io`]), read with its
//! manifest checked against the schema, and attached to a model ([`attach`]) when the
//! model file names it. Errors name the file and the field.

use super::{MapConfig, PixelMap};
use crate::error::{Error, ErrorKind, Result};
use crate::h5io;
use crate::model::params::{sha256_hex, PixelMapRef};
use crate::model::{Model, ModelParams, PixelResponse};
use crate::product::schema::{self, Schema};
use ndarray::Array3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

pub const PRODUCT: &str = "persist.pixel_map";
pub const FORMAT_VERSION: i64 = 1;

/// Write `map` to `path` (atomically; validated after writing).
pub fn write(path: &Path, map: &PixelMap) -> Result<()> {
    let (_, ny, nx) = map.ratio.dim();
    h5io::check_axes("ratio", &[2, ny, nx])?;
    h5io::publish(
        path,
        |tmp| {
            let f = h5io::create(tmp).map_err(Error::from)?;
            h5io::attr_str(&f, "product", PRODUCT)?;
            h5io::attr_i64(&f, "format_version", FORMAT_VERSION)?;
            h5io::attr_i64(&f, "detector", i64::from(map.detector))?;
            h5io::attr_str(&f, "model_identity", &map.model_identity)?;
            h5io::attr_f64(&f, "linear_below_e", map.config.linear_below_e)?;
            h5io::attr_f64(&f, "saturated_above_e", map.config.saturated_above_e)?;
            h5io::attr_f64(&f, "upper_quantile", map.config.upper_quantile)?;
            h5io::attr_i64(
                &f,
                "range_measured_linear",
                i64::from(map.range_measured[0]),
            )?;
            h5io::attr_i64(
                &f,
                "range_measured_saturated",
                i64::from(map.range_measured[1]),
            )?;
            h5io::attr_str(&f, "software_version", env!("CARGO_PKG_VERSION"))?;
            if !map.source.is_empty() {
                h5io::attr_str(&f, "source", &map.source)?;
            }
            let w = |name: &str, r: hdf5::Result<()>| r.map_err(|e| Error::from(e).field(name));
            w("ratio", h5io::write_plain(&f, "ratio", map.ratio.view()))?;
            w(
                "ratio_sigma",
                h5io::write_plain(&f, "ratio_sigma", map.ratio_sigma.view()),
            )?;
            w(
                "ratio_upper",
                h5io::write_plain(&f, "ratio_upper", map.ratio_upper.view()),
            )?;
            w("n_obs", h5io::write_plain(&f, "n_obs", map.n_obs.view()))?;
            w(
                "prior_grid",
                h5io::write_plain(&f, "prior_grid", map.prior_grid.view()),
            )?;
            w(
                "prior_weight",
                h5io::write_plain(&f, "prior_weight", map.prior_weight.view()),
            )?;
            Ok(())
        },
        |tmp| read_as(tmp, path).map(|_| ()),
    )
}

/// Read and check a map file.
pub fn read(path: &Path) -> Result<PixelMap> {
    read_as(path, path)
}

fn read_as(file_path: &Path, name: &Path) -> Result<PixelMap> {
    let file = h5io::open(file_path).map_err(|e| e.path(name))?;
    let m = schema::manifest(&file).map_err(|e| e.path(name))?;
    let errors = schema::validate(Schema::PixelMap, &m, name);
    if !errors.is_empty() {
        return Err(schema::combine(errors));
    }
    let bad = |field: &str, msg: String| Error::invalid(field, msg).path(name);
    let attr = |k: &str| &m["attributes"][k]["value"];
    let f64_of = |k: &str| attr(k).as_f64().unwrap_or(f64::NAN);
    let read3 = |k: &str| -> Result<Array3<f32>> {
        file.dataset(k)
            .and_then(|d| d.read::<f32, ndarray::Ix3>())
            .map_err(|e| Error::from(e).field(k).path(name))
    };
    let ratio = read3("ratio")?;
    let ratio_sigma = read3("ratio_sigma")?;
    let ratio_upper = read3("ratio_upper")?;
    let n_obs = file
        .dataset("n_obs")
        .and_then(|d| d.read::<u8, ndarray::Ix3>())
        .map_err(|e| Error::from(e).field("n_obs").path(name))?;
    let prior_grid = file
        .dataset("prior_grid")
        .and_then(|d| d.read::<f64, ndarray::Ix2>())
        .map_err(|e| Error::from(e).field("prior_grid").path(name))?;
    let prior_weight = file
        .dataset("prior_weight")
        .and_then(|d| d.read::<f64, ndarray::Ix2>())
        .map_err(|e| Error::from(e).field("prior_weight").path(name))?;
    let dim = ratio.dim();
    if dim.0 != 2 {
        return Err(bad("ratio", format!("{} fluence ranges, need 2", dim.0)));
    }
    h5io::check_axes("ratio", &[dim.0, dim.1, dim.2]).map_err(|e| e.path(name))?;
    for (k, d) in [
        ("ratio_sigma", ratio_sigma.dim()),
        ("ratio_upper", ratio_upper.dim()),
        ("n_obs", n_obs.dim()),
    ] {
        if d != dim {
            return Err(bad(k, format!("shape {d:?} differs from /ratio's {dim:?}")));
        }
    }
    for (k, a) in [
        ("ratio", &ratio),
        ("ratio_sigma", &ratio_sigma),
        ("ratio_upper", &ratio_upper),
    ] {
        if let Some(v) = a.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
            return Err(bad(k, format!("holds {v}, must be finite and >= 0")));
        }
    }
    if prior_weight.dim() != prior_grid.dim() || prior_grid.nrows() != 2 {
        return Err(bad(
            "prior_weight",
            format!(
                "shape {:?}, need [2, G] as /prior_grid {:?}",
                prior_weight.dim(),
                prior_grid.dim()
            ),
        ));
    }
    let config = MapConfig {
        linear_below_e: f64_of("linear_below_e"),
        saturated_above_e: f64_of("saturated_above_e"),
        upper_quantile: f64_of("upper_quantile"),
    };
    if !(config.linear_below_e > 0.0 && config.saturated_above_e >= config.linear_below_e) {
        return Err(bad(
            "saturated_above_e",
            "need 0 < linear_below_e <= saturated_above_e".into(),
        ));
    }
    if !(config.upper_quantile > 0.0 && config.upper_quantile < 1.0) {
        return Err(bad("upper_quantile", "must be in (0, 1)".into()));
    }
    Ok(PixelMap {
        detector: attr("detector").as_u64().unwrap_or(0) as u8,
        model_identity: attr("model_identity").as_str().unwrap_or("").to_string(),
        config,
        ratio,
        ratio_sigma,
        ratio_upper,
        n_obs,
        prior_grid,
        prior_weight,
        range_measured: [
            attr("range_measured_linear").as_i64() == Some(1),
            attr("range_measured_saturated").as_i64() == Some(1),
        ],
        source: attr("source").as_str().unwrap_or("").to_string(),
    })
}

/// The factors the model applies: `margin * ratio_upper` in a measured range, 1 in
/// one that is not (module docs of [`super`]).
pub fn response(map: &PixelMap, margin: f64) -> std::result::Result<PixelResponse, String> {
    let mut scale = map.ratio_upper.mapv(|v| (f64::from(v) * margin) as f32);
    for r in 0..2 {
        if !map.range_measured[r] {
            scale.index_axis_mut(ndarray::Axis(0), r).fill(1.0);
        }
    }
    PixelResponse::new(
        map.config.linear_below_e,
        map.config.saturated_above_e,
        scale,
    )
}

/// Where a model file's map path points: relative to the model file's directory.
pub fn resolve(model_path: &Path, path: &str) -> PathBuf {
    let p = Path::new(path);
    if p.is_absolute() {
        p.to_path_buf()
    } else {
        model_path.parent().unwrap_or(Path::new(".")).join(p)
    }
}

/// The model of `params` (loaded from `model_path`) with the per-pixel maps its file
/// names: each file's SHA-256 checked against the model file's, its layout against the
/// schema, its detector and the identity of the model it was measured against.
pub fn attach(model_path: &Path, params: ModelParams) -> Result<Model> {
    let Some(r) = params.pixel_map.clone() else {
        return Model::new(params);
    };
    let maps = load_maps(model_path, &params, &r)?;
    Ok(Model::new(params)?.with_pixel_maps(maps))
}

fn load_maps(
    model_path: &Path,
    params: &ModelParams,
    r: &PixelMapRef,
) -> Result<BTreeMap<u8, PixelResponse>> {
    let base = super::base_identity(params);
    let mut out = BTreeMap::new();
    for (i, f) in r.files.iter().enumerate() {
        let field = |k: &str| format!("/pixel_map/files/{i}/{k}");
        let path = resolve(model_path, &f.path);
        let bytes = std::fs::read(&path).map_err(|e| {
            Error::new(
                ErrorKind::Model,
                format!("cannot read {}: {e}", path.display()),
            )
            .field(field("path"))
            .path(model_path)
        })?;
        let sum = sha256_hex(&bytes);
        if sum != f.sha256 {
            return Err(Error::new(
                ErrorKind::Model,
                format!(
                    "{} has SHA-256 {sum}, the model file names {}",
                    path.display(),
                    f.sha256
                ),
            )
            .field(field("sha256"))
            .path(model_path));
        }
        let map = read(&path)?;
        if map.detector != f.detector {
            return Err(Error::invalid(
                "detector",
                format!(
                    "the map is detector {}'s, the model file names it for detector {}",
                    map.detector, f.detector
                ),
            )
            .path(&path));
        }
        if map.model_identity != base {
            return Err(Error::invalid(
                "model_identity",
                format!(
                    "measured against model {}, this model (without its pixel_map) is {}",
                    &map.model_identity[..map.model_identity.len().min(12)],
                    &base[..12]
                ),
            )
            .path(&path));
        }
        let resp =
            response(&map, r.margin).map_err(|m| Error::invalid("ratio_upper", m).path(&path))?;
        out.insert(f.detector, resp);
    }
    Ok(out)
}

/// `params` naming the map files `files` ((detector, path as written, file on disk))
/// with `margin`: their SHA-256 computed from the files.
pub fn name_maps(
    mut params: ModelParams,
    files: &[(u8, String, PathBuf)],
    margin: f64,
) -> Result<ModelParams> {
    let mut list = Vec::new();
    for (d, written, on_disk) in files {
        let bytes = std::fs::read(on_disk).map_err(|e| Error::io(on_disk, e))?;
        list.push(crate::model::params::PixelMapFile {
            detector: *d,
            path: written.clone(),
            sha256: sha256_hex(&bytes),
        });
    }
    params.pixel_map = Some(PixelMapRef {
        files: list,
        margin,
    });
    params
        .validate()
        .map_err(|m| Error::new(ErrorKind::Model, m))?;
    Ok(params)
}

/// A map's layout summary for reports: observed pixels per range.
pub fn observed(map: &PixelMap) -> [usize; 2] {
    let c = |r: usize| {
        map.n_obs
            .index_axis(ndarray::Axis(0), r)
            .iter()
            .filter(|n| **n > 0)
            .count()
    };
    [c(0), c(1)]
}
