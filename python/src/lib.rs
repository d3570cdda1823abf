//! `persist._native`: the Python bindings of the `persist` crate (PyO3 + rust-numpy).
//! The package `persist` (python/persist/__init__.py) re-exports everything here; the
//! type hints and docstrings users read are in python/persist/__init__.pyi.
//!
//! Invariants:
//! - `Model.step` runs [`Model::step_with`], the stage's own fused step, on the caller's
//!   arrays: the image is read in place through a numpy view (no copy; any strides);
//!   the on-board flags are copied once, because the step writes the `PERSIST` bit into
//!   its own flag plane; the outputs are written into planes the state keeps and
//!   handed to numpy as views of them (no copy). Planes are written again only when no
//!   Python object refers to them any more, so a result's arrays never change under
//!   the caller; a loop `r = model.step(...)` allocates nothing after its second step.
//!   The GIL is released while the step runs.
//! - Nothing here computes: every function calls the crate's entry point that the CLI
//!   calls (product read/write, checkpoint load, stage run, compare, diagnose,
//!   simulate), so Python and the command line give the same results.
//! - Bad input raises `persist.PersistError` with the crate's message (file, field,
//!   reason), or `TypeError` / `ValueError` for arguments of the wrong type or value;
//!   nothing panics on input.

use ndarray::{Array1, Array2, Array3};
use numpy::{
    IntoPyArray, PyArray1, PyArray2, PyArray3, PyArrayMethods, PyUntypedArrayMethods, ToPyArray,
};
use persist::model::{Input, Model, ModelParams, Output, State, StepContext};
use persist::product::{self, Exposure, ExposureMeta};
use persist::units::{DetectorId, UtcSeconds};
use pyo3::exceptions::{PyException, PyKeyError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use std::path::PathBuf;

pyo3::create_exception!(
    persist,
    PersistError,
    PyException,
    "An error from persist: bad input (naming the file, the field and the reason), a \
     model that does not validate, or a failed write."
);

fn err(e: persist::Error) -> PyErr {
    PersistError::new_err(e.to_string())
}

/// Python objects from JSON text (the standard `json` module: what users expect).
fn json_to_py<'py>(py: Python<'py>, text: &str) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?.call_method1("loads", (text,))
}

fn value_to_py<'py>(py: Python<'py>, v: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| PyValueError::new_err(e.to_string()))?;
    json_to_py(py, &text)
}

/// A read-only view of a 2-D numpy array of `T`, or a `TypeError` naming the argument,
/// the dtype it must have and the one it has.
fn array2<'py, T: numpy::Element>(
    arg: &Bound<'py, PyAny>,
    name: &str,
    dtype: &str,
) -> PyResult<numpy::PyReadonlyArray2<'py, T>> {
    match arg.cast::<PyArray2<T>>() {
        Ok(a) => Ok(a
            .try_readonly()
            .map_err(|e| PyValueError::new_err(format!("{name}: cannot borrow the array: {e}")))?),
        Err(_) => {
            let got = match (arg.getattr("dtype"), arg.getattr("ndim")) {
                (Ok(d), Ok(n)) => format!("a {n}-D array of {d}"),
                _ => format!("{}", arg.get_type().name()?),
            };
            Err(PyTypeError::new_err(format!(
                "{name}: must be a 2-D numpy array of {dtype}, got {got} \
                 (convert with numpy.asarray(x, dtype=numpy.{dtype}))"
            )))
        }
    }
}

/// A validated persistence model (a model file, or the paper's defaults).
#[pyclass(name = "Model", module = "persist", frozen)]
pub struct PyModel {
    inner: Model,
}

#[pymethods]
impl PyModel {
    #[staticmethod]
    fn from_file(path: PathBuf) -> PyResult<Self> {
        let params = persist::model_file::load(&path).map_err(err)?;
        let inner = Model::new(params).map_err(|e| err(e.path(&path)))?;
        Ok(PyModel { inner })
    }

    #[staticmethod]
    fn default() -> PyResult<Self> {
        Ok(PyModel {
            inner: Model::new(ModelParams::default()).map_err(err)?,
        })
    }

    #[getter]
    fn identity(&self) -> &str {
        self.inner.identity()
    }

    #[getter]
    fn name(&self) -> String {
        self.inner.params().name.clone()
    }

    #[getter]
    fn n_terms(&self) -> usize {
        self.inner.n_terms()
    }

    #[getter]
    fn threshold_high_e_per_s(&self) -> f64 {
        self.inner.params().thresholds.high_e_per_s
    }

    #[getter]
    fn threshold_low_e_per_s(&self) -> f64 {
        self.inner.params().thresholds.low_e_per_s
    }

    fn to_json(&self) -> String {
        self.inner.params().to_json_pretty()
    }

    fn __repr__(&self) -> String {
        format!(
            "persist.Model(name={:?}, identity={:?}, n_terms={})",
            self.inner.params().name,
            self.inner.identity(),
            self.inner.n_terms()
        )
    }

    #[pyo3(signature = (state, image, flags=None, t_exposure_s=None, t_slew_s=None, *,
        t_start_unix_s=None, t_illuminated_s=None, exposure_index=None,
        history_incomplete=false, background_e_per_s=None, focal_plane_temp_k=None))]
    #[allow(clippy::too_many_arguments)]
    fn step<'py>(
        &self,
        py: Python<'py>,
        state: &Bound<'py, PyState>,
        image: &Bound<'py, PyAny>,
        flags: Option<&Bound<'py, PyAny>>,
        t_exposure_s: Option<f64>,
        t_slew_s: Option<f64>,
        t_start_unix_s: Option<f64>,
        t_illuminated_s: Option<f64>,
        exposure_index: Option<u64>,
        history_incomplete: bool,
        background_e_per_s: Option<f64>,
        focal_plane_temp_k: Option<f64>,
    ) -> PyResult<StepResult> {
        let t_exposure_s = t_exposure_s
            .ok_or_else(|| PyValueError::new_err("t_exposure_s: required (seconds, > 0)"))?;
        let image = array2::<f32>(image, "image", "float32")?;
        let image = image.as_array();
        let shape = image.dim();
        let flags = match flags {
            Some(f) if !f.is_none() => Some(array2::<u32>(f, "flags", "uint32")?),
            _ => None,
        };
        if let Some(f) = &flags {
            if f.shape() != [shape.0, shape.1] {
                return Err(PyValueError::new_err(format!(
                    "flags: shape {:?} differs from the image's {shape:?}",
                    f.shape()
                )));
            }
        }
        let mut st = state
            .try_borrow_mut()
            .map_err(|e| PyValueError::new_err(format!("state: in use by another step ({e})")))?;
        if st.inner.shape() != shape {
            return Err(PersistError::new_err(format!(
                "image: shape {shape:?} differs from the detector's state {:?}",
                st.inner.shape()
            )));
        }
        let planes = st.free_planes(py, shape)?;
        let t_start = match (t_start_unix_s, t_slew_s) {
            (Some(t), None) => t,
            (None, Some(slew)) => st.inner.t_reset_unix_s.unwrap_or(0.0) + slew,
            (Some(_), Some(_)) => {
                return Err(PyValueError::new_err(
                    "give t_slew_s or t_start_unix_s, not both",
                ))
            }
            (None, None) => {
                return Err(PyValueError::new_err(
                    "t_slew_s: required (seconds from the reset ending the previous \
                     exposure to this one's start), or t_start_unix_s",
                ))
            }
        };
        let exposure_index =
            exposure_index.unwrap_or_else(|| st.inner.last_index.map_or(0, |i| i + 1));
        let input = Input {
            image_e_per_s: image,
            exposure_index,
            t_start_unix_s: t_start,
            t_exposure_s,
            t_illuminated_s: t_illuminated_s.unwrap_or(t_exposure_s),
            history_incomplete,
            background_e_per_s,
        };
        let ctx = StepContext {
            focal_plane_temp_k,
            active_pixels: None,
        };
        let model = &self.inner;
        let inner: &mut State = &mut st.inner;
        let summary = {
            let mut pl = planes.bind(py).borrow_mut();
            let pl: &mut Planes = &mut pl;
            let flags_in = flags.as_ref().map(|f| f.as_array());
            py.detach(|| {
                match flags_in {
                    Some(f) => pl.flags.assign(&f),
                    None => pl.flags.fill(0),
                }
                model.step_with(
                    inner,
                    &input,
                    &ctx,
                    &mut Output {
                        flags: &mut pl.flags,
                        current_e_per_s: &mut pl.current,
                        pflags: &mut pl.pflags,
                    },
                )
            })
            .map_err(err)?
        };
        drop(st);
        let owner = planes.bind(py);
        let pl = owner.borrow();
        // SAFETY: the arrays keep `owner` alive (their base object), and a `Planes` is
        // written again only when nothing but its state refers to it
        // (`PyState::free_planes`), so never while one of these arrays exists; the
        // step does not reallocate them (they are in standard layout).
        let (current, pflags, flags_out) = unsafe {
            (
                PyArray2::borrow_from_array(&pl.current, owner.clone().into_any()),
                PyArray2::borrow_from_array(&pl.pflags, owner.clone().into_any()),
                PyArray2::borrow_from_array(&pl.flags, owner.clone().into_any()),
            )
        };
        Ok(StepResult {
            current_e_per_s: current.unbind(),
            persistence_flags: pflags.unbind(),
            flags: flags_out.unbind(),
            t_meas_s: summary.t_meas_s,
            summary: value_to_py(py, &summary)?.unbind(),
        })
    }
}

/// What one exposure through the model gives.
#[pyclass(name = "StepResult", module = "persist", frozen, get_all)]
pub struct StepResult {
    current_e_per_s: Py<PyArray2<f32>>,
    persistence_flags: Py<PyArray2<u8>>,
    flags: Py<PyArray2<u32>>,
    t_meas_s: Option<f64>,
    summary: Py<PyAny>,
}

#[pymethods]
impl StepResult {
    fn __repr__(&self, py: Python<'_>) -> String {
        format!(
            "persist.StepResult(shape={:?}, t_meas_s={:?}, summary={})",
            self.current_e_per_s.bind(py).shape(),
            self.t_meas_s,
            self.summary
                .bind(py)
                .repr()
                .map_or_else(|_| "?".into(), |r| r.to_string())
        )
    }
}

/// One detector's model state, carried from exposure to exposure.
#[pyclass(name = "State", module = "persist")]
pub struct PyState {
    inner: State,
    /// Output planes of earlier steps, reused once no Python object refers to them.
    pool: Vec<Py<Planes>>,
}

/// The planes one step writes. The arrays of a [`StepResult`] are views of them.
#[pyclass(module = "persist")]
pub struct Planes {
    current: Array2<f32>,
    pflags: Array2<u8>,
    flags: Array2<u32>,
}

/// Output planes kept per state: two, so that `r = model.step(...)` in a loop (the
/// previous result alive during the call) allocates nothing after its second step.
const POOL: usize = 2;

impl PyState {
    fn with(inner: State) -> Self {
        PyState {
            inner,
            pool: Vec::new(),
        }
    }

    /// Planes of `shape` that nothing outside this state refers to (a result's arrays
    /// hold a reference to their planes): one of the pool, or new ones.
    fn free_planes(&mut self, py: Python<'_>, shape: (usize, usize)) -> PyResult<Py<Planes>> {
        self.pool
            .retain(|p| p.bind(py).borrow().current.dim() == shape);
        // SAFETY: reading the reference count of a live object while holding the GIL.
        let free = self
            .pool
            .iter()
            .find(|p| unsafe { pyo3::ffi::Py_REFCNT(p.as_ptr()) } == 1);
        if let Some(p) = free {
            return Ok(p.clone_ref(py));
        }
        let p = Py::new(
            py,
            Planes {
                current: Array2::zeros(shape),
                pflags: Array2::zeros(shape),
                flags: Array2::zeros(shape),
            },
        )?;
        if self.pool.len() < POOL {
            self.pool.push(p.clone_ref(py));
        }
        Ok(p)
    }
}

#[pymethods]
impl PyState {
    #[new]
    fn new(model: &PyModel, shape: (usize, usize)) -> PyResult<Self> {
        if shape.0 == 0 || shape.1 == 0 {
            return Err(PyValueError::new_err(format!(
                "shape: must be two positive sizes, got {shape:?}"
            )));
        }
        Ok(PyState::with(model.inner.new_state(shape.0, shape.1)))
    }

    /// The state saved in a checkpoint (fully checked), to go on stepping from it.
    #[staticmethod]
    fn from_checkpoint(path: PathBuf) -> PyResult<Self> {
        let (_, inner) = persist::checkpoint::load(&path).map_err(err)?;
        Ok(PyState::with(inner))
    }

    #[getter]
    fn shape(&self) -> (usize, usize) {
        self.inner.shape()
    }

    #[getter]
    fn n_terms(&self) -> usize {
        self.inner.n_terms()
    }

    #[getter]
    fn amplitudes_e<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray3<f64>> {
        self.inner.amplitudes_e.to_pyarray(py)
    }

    #[getter]
    fn release_count<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<u8>> {
        self.inner.release_count.to_pyarray(py)
    }

    #[getter]
    fn pending<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<u8>> {
        self.inner.pending.to_pyarray(py)
    }

    #[getter]
    fn t_reset_unix_s(&self) -> Option<f64> {
        self.inner.t_reset_unix_s
    }

    #[getter]
    fn last_index(&self) -> Option<u64> {
        self.inner.last_index
    }

    fn copy(&self) -> Self {
        PyState::with(self.inner.clone())
    }

    fn __repr__(&self) -> String {
        format!(
            "persist.State(shape={:?}, n_terms={}, last_index={:?}, t_reset_unix_s={:?})",
            self.inner.shape(),
            self.inner.n_terms(),
            self.inner.last_index,
            self.inner.t_reset_unix_s
        )
    }
}

fn meta_into<'py>(d: &Bound<'py, PyDict>, m: &ExposureMeta) -> PyResult<()> {
    d.set_item("detector", m.detector.0)?;
    d.set_item("exposure_index", m.exposure_index)?;
    d.set_item("t_start_utc", &m.t_start_utc)?;
    d.set_item("t_start_unix_s", m.t_start.0)?;
    d.set_item("t_exposure_s", m.t_exposure_s)?;
    d.set_item("focal_plane_temp_k", m.focal_plane_temp_k)?;
    d.set_item("t_illuminated_s", m.t_illuminated_s)?;
    Ok(())
}

fn exposure_into<'py>(py: Python<'py>, d: &Bound<'py, PyDict>, e: Exposure) -> PyResult<()> {
    meta_into(d, &e.meta)?;
    d.set_item("image", e.image.into_pyarray(py))?;
    d.set_item("flags", e.flags.into_pyarray(py))?;
    d.set_item("ramp", e.ramp.map(|r| r.into_pyarray(py)))?;
    d.set_item("ramp_times_s", e.ramp_times_s.map(|r| r.into_pyarray(py)))?;
    Ok(())
}

#[pyfunction]
fn read_product<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let has_persistence = {
        let file = persist::h5io::open(&path).map_err(err)?;
        let m = product::schema::manifest(&file).map_err(|e| err(e.path(&path)))?;
        product::schema::View(&m).has_group("/persistence")
    };
    let d = PyDict::new(py);
    if has_persistence {
        let (e, planes, attrs) = py.detach(|| product::read_output(&path)).map_err(err)?;
        exposure_into(py, &d, e)?;
        let p = PyDict::new(py);
        p.set_item("current_e_per_s", planes.current_e_per_s.into_pyarray(py))?;
        p.set_item("flags", planes.flags.into_pyarray(py))?;
        p.set_item("model_id", attrs.model_id)?;
        p.set_item("model_name", attrs.model_name)?;
        p.set_item("threshold_high_e_per_s", attrs.threshold_high_e_per_s)?;
        p.set_item("threshold_low_e_per_s", attrs.threshold_low_e_per_s)?;
        p.set_item("t_meas_s", attrs.t_meas_s)?;
        p.set_item("previous_exposure_index", attrs.previous_exposure_index)?;
        p.set_item("software_version", attrs.software_version)?;
        p.set_item("processed_utc", attrs.processed_utc)?;
        d.set_item("persistence", p)?;
    } else {
        let e = py.detach(|| product::read_exposure(&path)).map_err(err)?;
        exposure_into(py, &d, e)?;
        d.set_item("persistence", py.None())?;
    }
    d.set_item("path", path)?;
    Ok(d)
}

fn item<'py>(d: &Bound<'py, PyDict>, key: &str) -> PyResult<Bound<'py, PyAny>> {
    d.get_item(key)?
        .ok_or_else(|| PyKeyError::new_err(format!("product: `{key}` is missing")))
}

fn opt_item<'py, T: for<'a> FromPyObject<'a, 'py>>(
    d: &Bound<'py, PyDict>,
    key: &str,
) -> PyResult<Option<T>> {
    match d.get_item(key)? {
        Some(v) if !v.is_none() => Ok(Some(v.extract::<T>().map_err(|e| {
            let e: PyErr = e.into();
            PyTypeError::new_err(format!("product: `{key}`: {e}"))
        })?)),
        _ => Ok(None),
    }
}

fn req_item<'py, T: for<'a> FromPyObject<'a, 'py>>(
    d: &Bound<'py, PyDict>,
    key: &str,
) -> PyResult<T> {
    opt_item(d, key)?.ok_or_else(|| PyKeyError::new_err(format!("product: `{key}` is missing")))
}

#[pyfunction]
fn write_product(py: Python<'_>, path: PathBuf, product: &Bound<'_, PyDict>) -> PyResult<()> {
    let detector: i64 = req_item(product, "detector")?;
    let detector = DetectorId::new(detector).ok_or_else(|| {
        PyValueError::new_err(format!(
            "product: `detector` must be in 1..=6, got {detector}"
        ))
    })?;
    let t_start_utc: String = req_item(product, "t_start_utc")?;
    let t_start = UtcSeconds::parse(&t_start_utc)
        .map_err(|m| PyValueError::new_err(format!("product: `t_start_utc`: {m}")))?;
    let meta = ExposureMeta {
        detector,
        exposure_index: req_item(product, "exposure_index")?,
        t_start_utc,
        t_start,
        t_exposure_s: req_item(product, "t_exposure_s")?,
        focal_plane_temp_k: opt_item(product, "focal_plane_temp_k")?,
        t_illuminated_s: opt_item(product, "t_illuminated_s")?,
    };
    let image = array2::<f32>(&item(product, "image")?, "image", "float32")?
        .as_array()
        .to_owned();
    let flags = match product.get_item("flags")? {
        Some(f) if !f.is_none() => array2::<u32>(&f, "flags", "uint32")?.as_array().to_owned(),
        _ => Array2::zeros(image.dim()),
    };
    let ramp: Option<Array3<f32>> = match product.get_item("ramp")? {
        Some(r) if !r.is_none() => Some(
            r.cast::<PyArray3<f32>>()
                .map_err(|_| PyTypeError::new_err("ramp: must be a 3-D numpy array of float32"))?
                .to_owned_array(),
        ),
        _ => None,
    };
    let ramp_times_s: Option<Array1<f64>> = match product.get_item("ramp_times_s")? {
        Some(r) if !r.is_none() => Some(
            r.cast::<PyArray1<f64>>()
                .map_err(|_| {
                    PyTypeError::new_err("ramp_times_s: must be a 1-D numpy array of float64")
                })?
                .to_owned_array(),
        ),
        _ => None,
    };
    let e = Exposure {
        meta,
        image,
        flags,
        ramp,
        ramp_times_s,
    };
    py.detach(|| product::write_exposure(&path, &e))
        .map_err(err)
}

#[pyfunction]
fn load_checkpoint<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyDict>> {
    let (meta, state) = py
        .detach(|| persist::checkpoint::load(&path))
        .map_err(err)?;
    let d = PyDict::new(py);
    d.set_item("path", &path)?;
    d.set_item("detector", meta.detector.0)?;
    d.set_item("exposure_index", meta.exposure_index)?;
    d.set_item("model_id", meta.model_id)?;
    d.set_item("model_name", meta.model_name)?;
    d.set_item("model_json", meta.model_json)?;
    d.set_item("stage", json_to_py(py, &meta.stage_json)?)?;
    d.set_item("software_version", meta.software_version)?;
    d.set_item("t_reset_unix_s", state.t_reset_unix_s)?;
    d.set_item("last_index", state.last_index)?;
    d.set_item("amplitudes_e", state.amplitudes_e.into_pyarray(py))?;
    d.set_item("release_count", state.release_count.into_pyarray(py))?;
    d.set_item("pending", state.pending.into_pyarray(py))?;
    Ok(d)
}

/// A model argument: a `Model`, a model file path, or `None` (the paper's defaults).
fn model_of(model: Option<&Bound<'_, PyAny>>) -> PyResult<Model> {
    match model {
        None => Ok(Model::new(ModelParams::default()).map_err(err)?),
        Some(m) if m.is_none() => Ok(Model::new(ModelParams::default()).map_err(err)?),
        Some(m) => match m.cast::<PyModel>() {
            Ok(pm) => Ok(pm.get().inner.clone()),
            Err(_) => Ok(PyModel::from_file(m.extract::<PathBuf>().map_err(|_| {
                PyTypeError::new_err("model: must be a persist.Model, a model file path or None")
            })?)?
            .inner),
        },
    }
}

#[pyfunction]
#[pyo3(signature = (input, output, checkpoints, model=None, *, checkpoint_every=1,
    keep_latest=20, hourly_checkpoints=true, quarantine=None, from_checkpoint=None,
    allow_model_change=false))]
#[allow(clippy::too_many_arguments)]
fn run<'py>(
    py: Python<'py>,
    input: PathBuf,
    output: PathBuf,
    checkpoints: PathBuf,
    model: Option<&Bound<'py, PyAny>>,
    checkpoint_every: u64,
    keep_latest: usize,
    hourly_checkpoints: bool,
    quarantine: Option<PathBuf>,
    from_checkpoint: Option<(i64, u64)>,
    allow_model_change: bool,
) -> PyResult<Bound<'py, PyDict>> {
    use persist::stage::{self, startup, Ops, RunConfig};
    if checkpoint_every == 0 {
        return Err(PyValueError::new_err("checkpoint_every: must be >= 1"));
    }
    let from_checkpoint = match from_checkpoint {
        None => None,
        Some((d, i)) => Some((
            DetectorId::new(d).ok_or_else(|| {
                PyValueError::new_err(format!("from_checkpoint: detector {d} not in 1..=6"))
            })?,
            i,
        )),
    };
    let model = model_of(model)?;
    let quarantine = quarantine.unwrap_or_else(|| input.join(".quarantine"));
    let cfg = RunConfig {
        input,
        output,
        checkpoints,
        model,
        from_checkpoint,
        allow_model_change,
        checkpoint_every,
        checkpoint_idle: std::time::Duration::ZERO,
        retention: persist::checkpoint::Retention {
            keep_latest,
            keep_one_per_hour: hourly_checkpoints,
            cadence: checkpoint_every,
            ..persist::checkpoint::Retention::default()
        },
        processed_utc: stage::processing_time(),
    };
    let report = py.detach(|| -> persist::Result<stage::RunReport> {
        // As `persist run`: the lock and the cleaning of temporaries; Python keeps its
        // own signal handlers.
        let _started = startup::start(
            &[&cfg.output, &cfg.checkpoints],
            startup::Startup {
                lock: true,
                signals: false,
            },
        )?;
        let ops = Ops {
            quarantine: Some(quarantine),
            ..Ops::default()
        };
        Ok(stage::run_with(&cfg, &ops, &|_| {}))
    });
    let report = report.map_err(err)?;
    let mut exposures: Vec<&stage::ExposureReport> = report.exposures.iter().collect();
    exposures.sort_by_key(|r| (r.detector, r.exposure_index));
    let d = PyDict::new(py);
    d.set_item("exposures", value_to_py(py, &exposures)?)?;
    let errors: Vec<String> = report.errors.iter().map(|e| e.to_string()).collect();
    d.set_item("errors", errors)?;
    d.set_item("quarantined", &report.quarantined)?;
    d.set_item("ignored_copies", &report.ignored_copies)?;
    d.set_item("processed", report.processed)?;
    d.set_item("stopped", report.stopped)?;
    Ok(d)
}

#[pyfunction]
#[pyo3(signature = (input, models, report))]
fn compare<'py>(
    py: Python<'py>,
    input: PathBuf,
    models: Vec<PathBuf>,
    report: PathBuf,
) -> PyResult<Bound<'py, PyAny>> {
    if models.is_empty() {
        return Err(PyValueError::new_err(
            "models: give at least one model file",
        ));
    }
    let summary = report.join("summary.json");
    let text = py
        .detach(|| -> persist::Result<String> {
            persist::diag::compare_command::run(&input, &models, &report)?;
            std::fs::read_to_string(&summary).map_err(|e| persist::Error::io(&summary, e))
        })
        .map_err(err)?;
    json_to_py(py, &text)
}

#[pyfunction]
#[pyo3(signature = (input, model, *, pixels=None, bootstrap=None, seed=1, statistic=None,
    refit=None, joint=false, json=None))]
#[allow(clippy::too_many_arguments)]
fn diagnose<'py>(
    py: Python<'py>,
    input: PathBuf,
    model: PathBuf,
    pixels: Option<usize>,
    bootstrap: Option<usize>,
    seed: u64,
    statistic: Option<&str>,
    refit: Option<&str>,
    joint: bool,
    json: Option<PathBuf>,
) -> PyResult<Bound<'py, PyAny>> {
    use persist::diag::diagnose::Config;
    let defaults = Config::default();
    let cfg = Config {
        pixels: pixels.unwrap_or(defaults.pixels),
        bootstrap: bootstrap.unwrap_or(defaults.bootstrap),
        seed,
        statistic: match statistic {
            Some(s) => s.parse().map_err(err)?,
            None => defaults.statistic,
        },
        refit: match refit {
            Some(s) => s.parse().map_err(err)?,
            None => defaults.refit,
        },
        joint,
        ..defaults
    };
    let text = py
        .detach(|| -> persist::Result<String> {
            let seq = persist::diag::data::Sequence::load_with(&input, cfg.background)?;
            let params = persist::model_file::load(&model)?;
            let d = persist::diag::reference::diagnose_with(
                &params,
                &seq,
                &cfg,
                persist::diag::reference::Reference::default(),
                &input,
                &model,
            )?;
            let text = serde_json::to_string_pretty(&d)
                .map_err(|e| persist::Error::new(persist::ErrorKind::Io, e.to_string()))?;
            if let Some(p) = &json {
                persist::textfile::write_text(p, &(text.clone() + "\n"))?;
            }
            Ok(text)
        })
        .map_err(err)?;
    json_to_py(py, &text)
}

fn effect_specs(effects: &[String]) -> PyResult<Vec<persist::sim::effect::EffectSpec>> {
    effects.iter().map(|s| s.parse().map_err(err)).collect()
}

#[pyfunction]
#[pyo3(signature = (out, *, size=64, darks=60, seed=1, effects=Vec::new()))]
fn simulate_lab(
    py: Python<'_>,
    out: PathBuf,
    size: usize,
    darks: usize,
    seed: u64,
    effects: Vec<String>,
) -> PyResult<usize> {
    use persist::sim::{lab, output::Writer};
    let cfg = lab::LabConfig {
        size,
        seed,
        darks,
        effects: effect_specs(&effects)?,
        ..lab::LabConfig::default()
    };
    py.detach(|| -> persist::Result<usize> {
        lab::validate(&cfg)?;
        let mut w = Writer::new(&out)?;
        let desc = lab::run(&cfg, |e| w.write(&e))?;
        w.finish(desc)
    })
    .map_err(err)
}

#[pyfunction]
#[pyo3(signature = (out, *, size=256, detectors=1, exposures=20, seed=1, effects=Vec::new()))]
fn simulate_sky(
    py: Python<'_>,
    out: PathBuf,
    size: usize,
    detectors: u8,
    exposures: u64,
    seed: u64,
    effects: Vec<String>,
) -> PyResult<usize> {
    use persist::sim::{output::Writer, sky};
    let cfg = sky::SkyConfig {
        size,
        detectors,
        exposures,
        seed,
        effects: effect_specs(&effects)?,
        ..sky::SkyConfig::default()
    };
    py.detach(|| -> persist::Result<usize> {
        sky::validate(&cfg)?;
        let mut w = Writer::new(&out)?;
        let desc = sky::run(&cfg, |e| w.write(&e))?;
        w.finish(desc)
    })
    .map_err(err)
}

/// The benchmark's synthetic exposure `k` (`persist::bench::synthetic_frame`):
/// `(image float32, flags uint32)`.
#[pyfunction]
fn _synthetic_frame<'py>(
    py: Python<'py>,
    size: usize,
    k: u64,
) -> (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<u32>>) {
    let (image, flags) = py.detach(|| persist::bench::synthetic_frame(size, k));
    (image.into_pyarray(py), flags.into_pyarray(py))
}

/// `persist bench`'s step case run in this process: the fused step on a warm state of
/// `size x size`, alternating two synthetic frames, buffers reused, each of `reps`
/// steps timed in Rust (seconds). `threads`: the rayon pool's size (default: that of
/// the pool `Model.step` runs in).
#[pyfunction]
#[pyo3(signature = (size, reps, threads=None))]
fn _bench_rust_step(
    py: Python<'_>,
    size: usize,
    reps: usize,
    threads: Option<usize>,
) -> PyResult<Vec<f64>> {
    use persist::bench::{run_case, Case, CaseSpec};
    let spec = CaseSpec {
        case: Case::Step,
        size,
        threads: threads.unwrap_or_else(rayon::current_num_threads),
        reps,
        checkpoint_every: 1,
        scratch: std::env::temp_dir(),
    };
    let r = py.detach(|| run_case(&spec)).map_err(err)?;
    Ok(r.samples_s)
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("PersistError", m.py().get_type::<PersistError>())?;
    m.add("__version__", persist::VERSION)?;
    use persist::flags::{bits, pbits};
    for (name, v) in [
        ("FLAG_TRANSIENT", bits::TRANSIENT),
        ("FLAG_OVERFLOW", bits::OVERFLOW),
        ("FLAG_SUR_ERROR", bits::SUR_ERROR),
        ("FLAG_NONFUNC", bits::NONFUNC),
        ("FLAG_PERSIST", bits::PERSIST),
    ] {
        m.add(name, v)?;
    }
    for (name, v) in [
        ("PFLAG_HIGH", pbits::HIGH),
        ("PFLAG_LOW", pbits::LOW),
        ("PFLAG_MAX_AMPLITUDE", pbits::MAX_AMPLITUDE),
        ("PFLAG_RELEASED", pbits::RELEASED),
        ("PFLAG_HISTORY_INCOMPLETE", pbits::HISTORY_INCOMPLETE),
    ] {
        m.add(name, v)?;
    }
    m.add_class::<PyModel>()?;
    m.add_class::<PyState>()?;
    m.add_class::<StepResult>()?;
    m.add_function(wrap_pyfunction!(read_product, m)?)?;
    m.add_function(wrap_pyfunction!(write_product, m)?)?;
    m.add_function(wrap_pyfunction!(load_checkpoint, m)?)?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(compare, m)?)?;
    m.add_function(wrap_pyfunction!(diagnose, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_lab, m)?)?;
    m.add_function(wrap_pyfunction!(simulate_sky, m)?)?;
    m.add_function(wrap_pyfunction!(_synthetic_frame, m)?)?;
    m.add_function(wrap_pyfunction!(_bench_rust_step, m)?)?;
    Ok(())
}
