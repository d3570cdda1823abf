"""Type hints and documentation of the `persist` Python package (docs/python.md)."""

from os import PathLike
from typing import Any, Optional, Sequence, Tuple, TypedDict, Union

import numpy as np
import numpy.typing as npt

_Path = Union[str, "PathLike[str]"]

__version__: str

FLAG_TRANSIENT: int
FLAG_OVERFLOW: int
FLAG_SUR_ERROR: int
FLAG_NONFUNC: int
FLAG_PERSIST: int
PFLAG_HIGH: int
PFLAG_LOW: int
PFLAG_MAX_AMPLITUDE: int
PFLAG_RELEASED: int
PFLAG_HISTORY_INCOMPLETE: int

class PersistError(Exception):
    """Bad input (the message names the file, the field and the reason), a model that
    does not validate, or a failed write."""

class Model:
    """A validated persistence model: the terms, the amplitude knots, the thresholds,
    early release and any effects of a model file (schemas/model.schema.json)."""

    @staticmethod
    def from_file(path: _Path) -> "Model":
        """Load and validate a model file (JSON). Raises PersistError naming the field."""
    @staticmethod
    def default() -> "Model":
        """The built-in default: the paper's constants (`persist model default`)."""
    @property
    def identity(self) -> str:
        """SHA-256 (hex) of the model in canonical form, as recorded in every output."""
    @property
    def name(self) -> str: ...
    @property
    def n_terms(self) -> int:
        """Number of exponential terms (the last axis of State.amplitudes_e)."""
    @property
    def threshold_high_e_per_s(self) -> float: ...
    @property
    def threshold_low_e_per_s(self) -> float: ...
    def to_json(self) -> str:
        """The model file (pretty JSON) that gives this model."""
    def step(
        self,
        state: "State",
        image: npt.NDArray[np.float32],
        flags: Optional[npt.NDArray[np.uint32]] = None,
        t_exposure_s: Optional[float] = None,
        t_slew_s: Optional[float] = None,
        *,
        t_start_unix_s: Optional[float] = None,
        t_illuminated_s: Optional[float] = None,
        exposure_index: Optional[int] = None,
        history_incomplete: bool = False,
        background_e_per_s: Optional[float] = None,
        focal_plane_temp_k: Optional[float] = None,
    ) -> "StepResult":
        """Run one exposure through the model, advancing `state` in place.

        The stage's own fused step (`Model::step_with`): predict the persistence
        current at `t_meas = t_slew + t_exposure / 2` from the state, flag it against
        the thresholds, apply early release, decay the state to this exposure's reset
        and add this exposure's response.

        image: line-fit current, e-/s, float32 [ny, nx] (read in place, not copied).
        flags: on-board flags, uint32 [ny, nx] (None: all zero); copied into the
            step's flag plane, returned with the PERSIST bit set where the prediction
            is HIGH.
        t_exposure_s: integration time, s (> 0).
        t_slew_s: time from the reset ending the previous exposure to this exposure's
            start, s (a new state's clock starts at 0); or give t_start_unix_s instead,
            the start in seconds since the Unix epoch (what products record: use it to
            reproduce the stage bit for bit).
        t_illuminated_s: seconds of illumination for the fluence (default
            t_exposure_s).
        exposure_index: default: the state's last index + 1 (0 for a new state); must
            increase.
        history_incomplete: set PFLAG_HISTORY_INCOMPLETE on every pixel.
        background_e_per_s: the exposure's sky + dark level for early release (None:
            estimated as the stage does).
        focal_plane_temp_k: for models whose effects use the temperature.

        Raises PersistError (nothing changed) on a wrong shape, a time that goes back,
        an index that does not increase, or non-finite times. NaN or Inf pixels never
        enter the state (they add the maximum amplitude and are flagged next time).
        """

class StepResult:
    """What Model.step returns. The arrays are views (no copy) of output planes the
    State keeps; they never change while anything refers to them, and the State writes
    a set of planes again only once no result or array refers to it."""

    current_e_per_s: npt.NDArray[np.float32]
    """Predicted persistence current at t_meas, e-/s [ny, nx] (/persistence/current)."""
    persistence_flags: npt.NDArray[np.uint8]
    """PFLAG_* bits per pixel [ny, nx] (/persistence/flags)."""
    flags: npt.NDArray[np.uint32]
    """The on-board flags with FLAG_PERSIST set exactly where PFLAG_HIGH is."""
    t_meas_s: Optional[float]
    """Time after the previous reset the prediction was made at (None: first exposure)."""
    summary: dict[str, Any]
    """Counts: pixels, above_high, above_low, released, max_amplitude, t_meas_s,
    previous_index."""

class State:
    """One detector's model state: amplitudes per pixel and term, early-release counts,
    pending bits, the last reset time and exposure index."""

    def __init__(self, model: Model, shape: Tuple[int, int]) -> None:
        """A new (empty) state of shape (ny, nx) for `model`."""
    @staticmethod
    def from_checkpoint(path: _Path) -> "State":
        """The state saved in a stage checkpoint, fully checked."""
    @property
    def shape(self) -> Tuple[int, int]: ...
    @property
    def n_terms(self) -> int: ...
    @property
    def amplitudes_e(self) -> npt.NDArray[np.float64]:
        """A copy of the amplitudes A_n, electrons [ny, nx, n_terms]."""
    @property
    def release_count(self) -> npt.NDArray[np.uint8]:
        """A copy of the early-release counts [ny, nx]."""
    @property
    def pending(self) -> npt.NDArray[np.uint8]:
        """A copy of the pending bits [ny, nx]."""
    @property
    def t_reset_unix_s(self) -> Optional[float]: ...
    @property
    def last_index(self) -> Optional[int]: ...
    def copy(self) -> "State": ...

class Persistence(TypedDict):
    current_e_per_s: npt.NDArray[np.float32]
    flags: npt.NDArray[np.uint8]
    model_id: str
    model_name: str
    threshold_high_e_per_s: float
    threshold_low_e_per_s: float
    t_meas_s: float
    previous_exposure_index: int
    software_version: str
    processed_utc: str

class Product(TypedDict):
    path: str
    detector: int
    exposure_index: int
    t_start_utc: str
    t_start_unix_s: float
    t_exposure_s: float
    focal_plane_temp_k: Optional[float]
    t_illuminated_s: Optional[float]
    image: npt.NDArray[np.float32]
    flags: npt.NDArray[np.uint32]
    ramp: Optional[npt.NDArray[np.float32]]
    ramp_times_s: Optional[npt.NDArray[np.float64]]
    persistence: Optional[Persistence]

def read_product(path: _Path) -> Product:
    """Read and validate a Level-1 exposure or a persistence output product (HDF5, the
    ICD's layout): root attributes and numpy arrays; `persistence` is None for an L1
    input. Raises PersistError naming the file and the field."""

def write_product(path: _Path, product: dict[str, Any]) -> None:
    """Write a Level-1 exposure product, atomically and validated. `product` has the
    keys read_product returns (detector, exposure_index, t_start_utc, t_exposure_s,
    image float32, flags uint32 or None; optional focal_plane_temp_k, t_illuminated_s,
    ramp, ramp_times_s); others (t_start_unix_s, persistence, path) are ignored."""

class Checkpoint(TypedDict):
    path: str
    detector: int
    exposure_index: int
    model_id: str
    model_name: str
    model_json: str
    stage: dict[str, Any]
    software_version: str
    t_reset_unix_s: Optional[float]
    last_index: Optional[int]
    amplitudes_e: npt.NDArray[np.float64]
    release_count: npt.NDArray[np.uint8]
    pending: npt.NDArray[np.uint8]

def load_checkpoint(path: _Path) -> Checkpoint:
    """Load and fully check a stage checkpoint: its meta data and the detector's state
    as numpy arrays (amplitudes_e [ny, nx, n_terms] in electrons)."""

def run(
    input: _Path,
    output: _Path,
    checkpoints: _Path,
    model: Union[Model, _Path, None] = None,
    *,
    checkpoint_every: int = 1,
    keep_latest: int = 20,
    hourly_checkpoints: bool = True,
    quarantine: Optional[_Path] = None,
    from_checkpoint: Optional[Tuple[int, int]] = None,
    allow_model_change: bool = False,
) -> dict[str, Any]:
    """Run the stage over every product in `input` once, as `persist run` (the
    directories locked, refused products moved to `quarantine`, default
    INPUT/.quarantine). Returns {exposures: [{detector, exposure_index, path, summary,
    history_incomplete, written}], errors: [str], quarantined, ignored_copies,
    processed, stopped}. Bad products are reported in `errors`, not raised."""

def compare(input: _Path, models: Sequence[_Path], report: _Path) -> dict[str, Any]:
    """`persist compare`: the models side by side on a laboratory sequence; writes
    REPORT/report.html and REPORT/summary.json and returns the summary."""

def diagnose(
    input: _Path,
    model: _Path,
    *,
    pixels: Optional[int] = None,
    bootstrap: Optional[int] = None,
    seed: int = 1,
    statistic: Optional[str] = None,
    refit: Optional[str] = None,
    joint: bool = False,
    json: Optional[_Path] = None,
) -> dict[str, Any]:
    """`persist diagnose`: which library effect the model misses on a laboratory
    sequence; returns the ranking (also written to `json` when given)."""

def simulate_lab(
    out: _Path, *, size: int = 64, darks: int = 60, seed: int = 1, effects: Sequence[str] = ()
) -> int:
    """`persist simulate lab`: the paper's laboratory test (products in OUT, truth in
    OUT/truth); returns the number of products."""

def simulate_sky(
    out: _Path,
    *,
    size: int = 256,
    detectors: int = 1,
    exposures: int = 20,
    seed: int = 1,
    effects: Sequence[str] = (),
) -> int:
    """`persist simulate sky`: a SPHEREx-like survey; returns the number of products."""

def _synthetic_frame(size: int, k: int) -> Tuple[npt.NDArray[np.float32], npt.NDArray[np.uint32]]: ...
def _bench_rust_step(size: int, reps: int, threads: Optional[int] = None) -> list[float]: ...
