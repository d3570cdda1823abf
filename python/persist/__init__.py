"""persist: predict and flag image persistence in HAWAII-2RG arrays (SPHEREx), from Python.

The same Rust code as the ``persist`` command line and pipeline stage, through PyO3:

- :class:`Model` (a model file or the paper's defaults) and :class:`State` (one
  detector's state); :meth:`Model.step` runs one exposure through the stage's own fused
  step on numpy arrays and returns a :class:`StepResult`;
- :func:`read_product` / :func:`write_product`: Level-1 exposure and persistence output
  products (HDF5, the ICD's layout) as dicts of attributes and numpy arrays;
- :func:`load_checkpoint`: a stage checkpoint with the state as numpy arrays;
- :func:`run`: the stage over a directory of products (as ``persist run``);
- :func:`compare`, :func:`diagnose`: the diagnostics, their JSON as Python objects;
- :func:`simulate_lab`, :func:`simulate_sky`: the simulator (as ``persist simulate``).

Errors in the input raise :class:`PersistError` naming the file, the field and the reason.
See docs/python.md.
"""

from ._native import (
    Model,
    PersistError,
    State,
    StepResult,
    __version__,
    _bench_rust_step,
    _synthetic_frame,
    compare,
    diagnose,
    load_checkpoint,
    read_product,
    run,
    simulate_lab,
    simulate_sky,
    write_product,
)

# Flag bits (ICD; the crate's own constants): on-board flags (uint32) and the
# persistence flags (uint8) a step returns.
from ._native import (  # noqa: E402
    FLAG_NONFUNC,
    FLAG_OVERFLOW,
    FLAG_PERSIST,
    FLAG_SUR_ERROR,
    FLAG_TRANSIENT,
    PFLAG_HIGH,
    PFLAG_HISTORY_INCOMPLETE,
    PFLAG_LOW,
    PFLAG_MAX_AMPLITUDE,
    PFLAG_RELEASED,
)

__all__ = [
    "Model",
    "PersistError",
    "State",
    "StepResult",
    "compare",
    "diagnose",
    "load_checkpoint",
    "read_product",
    "run",
    "simulate_lab",
    "simulate_sky",
    "write_product",
    "__version__",
]
