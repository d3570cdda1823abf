//! Writing a simulation: Level-1 products through [`crate::product::write`], and the
//! truth beside them, never inside them.
//!
//! Layout of `DIR`:
//! - `DIR/d{detector}_e{index:06}.h5`: the Level-1 products (ICD "Input");
//! - `DIR/truth/d{detector}_e{index:06}.truth.hdf5` (HDF5; deliberately not `*.h5`, so
//!   a stage watching `DIR` recursively never takes the truth for a product): per exposure, `/true_persistence`
//!   (float32 [ny, nx], e-/s: the mean current over the integration emitted by charge
//!   trapped before it began, [`super::engine`]) and `/true_flux` (float32 [ny, nx],
//!   e-/s: the photon flux while illuminated — sky or lamp — as integrated, after
//!   illumination effects), with attributes `detector`, `exposure_index`, `kind`,
//!   `t_start_utc`;
//! - `DIR/truth/truth.json`: the scenario, seed, configuration, trap and detector
//!   parameters, the effects and their parameters, the software version and the list of
//!   exposures.
//!
//! Every file is published atomically (temporary name, rename), and files are
//! byte-identical for the same seed (object times off).

use super::SimExposure;
use crate::error::{Error, Result};
use crate::h5io;
use std::path::{Path, PathBuf};

/// Where the truth of (detector, exposure) of a simulation in `dir` is written.
pub fn truth_path(dir: &Path, det: u8, index: u64) -> PathBuf {
    dir.join("truth")
        .join(format!("d{det}_e{index:06}.truth.hdf5"))
}

/// Writes products and truth as they are simulated.
#[derive(Debug)]
pub struct Writer {
    dir: PathBuf,
    index: Vec<serde_json::Value>,
}

impl Writer {
    pub fn new(dir: &Path) -> Result<Writer> {
        std::fs::create_dir_all(dir.join("truth")).map_err(|e| Error::io(dir, e))?;
        Ok(Writer {
            dir: dir.to_path_buf(),
            index: Vec::new(),
        })
    }

    pub fn product_path(&self, det: u8, index: u64) -> PathBuf {
        self.dir.join(format!("d{det}_e{index:06}.h5"))
    }

    pub fn truth_path(&self, det: u8, index: u64) -> PathBuf {
        truth_path(&self.dir, det, index)
    }

    pub fn write(&mut self, s: &SimExposure) -> Result<()> {
        let m = &s.exposure.meta;
        let det = m.detector.0;
        let p = self.product_path(det, m.exposure_index);
        crate::product::write::write_exposure(&p, &s.exposure)?;
        let t = self.truth_path(det, m.exposure_index);
        h5io::publish(
            &t,
            |tmp| {
                let f = h5io::create(tmp)?;
                h5io::write_plain(&f, "true_persistence", s.true_persistence.view())?;
                h5io::write_plain(&f, "true_flux", s.true_flux.view())?;
                h5io::attr_i64(&f, "detector", i64::from(det))?;
                h5io::attr_i64(&f, "exposure_index", m.exposure_index as i64)?;
                h5io::attr_str(&f, "kind", &s.kind)?;
                h5io::attr_str(&f, "t_start_utc", &m.t_start_utc)?;
                h5io::attr_str(
                    &f,
                    "true_persistence_definition",
                    "mean over the integration of the current emitted by charge trapped before it began, e-/s",
                )?;
                f.close()?;
                Ok(())
            },
            |_| Ok(()),
        )?;
        self.index.push(serde_json::json!({
            "detector": det,
            "exposure_index": m.exposure_index,
            "kind": s.kind,
            "product": p.file_name().map(|n| n.to_string_lossy().to_string()),
            "truth": format!("truth/{}", t.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default()),
            "mean_true_persistence_e_per_s": mean(&s.true_persistence),
        }));
        Ok(())
    }

    /// Write `truth/truth.json` (call once, after the last exposure).
    pub fn finish(self, mut description: serde_json::Value) -> Result<usize> {
        let n = self.index.len();
        if let Some(o) = description.as_object_mut() {
            o.insert("software_version".into(), crate::VERSION.into());
            o.insert("exposures".into(), serde_json::Value::Array(self.index));
        }
        let path = self.dir.join("truth").join("truth.json");
        let text = serde_json::to_string_pretty(&description)
            .map_err(|e| Error::new(crate::ErrorKind::Io, e.to_string()))?;
        let tmp = h5io::temp_path(&path);
        std::fs::write(&tmp, text + "\n").map_err(|e| Error::io(&path, e))?;
        std::fs::rename(&tmp, &path).map_err(|e| Error::io(&path, e))?;
        Ok(n)
    }
}

fn mean(a: &ndarray::Array2<f32>) -> f64 {
    let n = a.len().max(1) as f64;
    a.iter().map(|v| f64::from(*v)).sum::<f64>() / n
}
