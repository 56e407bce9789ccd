"""A trial as a row of the results store: its key (canonical JSON of its parameters), its result split into scalar
metrics and arrays (validated), the columns besides them, and the store's timestamps."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from datetime import datetime, timezone

import numpy as np

# Columns of the results table besides the parameters and metrics; neither may use these names.
RESERVED = ("study", "status", "error", "traceback", "wall_time", "started", "finished", "ocpkit_version", "code_hash")


def canonical_key(params: Mapping) -> str:
    """The trial's identity: compact JSON with sorted keys and shortest round-trip floats.

    numpy scalars and arrays become plain numbers and lists, tuples become lists and -0.0
    becomes 0.0, so equal parameter sets always give the same key.
    """
    if not isinstance(params, Mapping):
        raise TypeError(f"params must be a mapping of parameter names to values, got {params!r}")
    return json.dumps(_plain(params, "params"), sort_keys=True, separators=(",", ":"), allow_nan=False)


def _plain(value, where: str):
    if isinstance(value, Mapping):
        for k in value:
            if not isinstance(k, str):
                raise TypeError(f"{where} keys must be strings, got {k!r}")
        return {k: _plain(v, f"{where}[{k!r}]") for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v, f"{where}[{i}]") for i, v in enumerate(value)]
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"{where} must be finite, got {value!r}")
        return value + 0.0  # turns -0.0 into 0.0
    raise TypeError(f"{where} must be None, a bool, number, string, list or dict, got {type(value).__name__}")


def split_result(params: Mapping, result) -> tuple[dict, dict]:
    """Split a trial's returned dict into JSON scalar metrics and numpy arrays, validating names and types."""
    if not isinstance(result, Mapping):
        raise TypeError(f"a trial must return a dict of metrics, got {type(result).__name__}")
    metrics, arrays = {}, {}
    for name, value in result.items():
        if not isinstance(name, str) or not name:
            raise TypeError(f"metric names must be non-empty strings, got {name!r}")
        if name in RESERVED or name in params:
            raise ValueError(f"metric {name!r} clashes with a {'reserved column' if name in RESERVED else 'parameter'}")
        if isinstance(value, (list, tuple)) or (isinstance(value, np.ndarray) and value.ndim > 0):
            a = np.asarray(value)
            if a.dtype.hasobject:
                raise TypeError(f"array metric {name!r} must hold numbers or strings, got dtype object")
            arrays[name] = a
            continue
        if isinstance(value, (np.generic, np.ndarray)):
            value = value.item()
        if value is not None and not isinstance(value, (bool, int, float, str)):
            raise TypeError(
                f"metric {name!r} must be a number, bool, string, None or array, got {type(value).__name__}"
            )
        metrics[name] = value
    return metrics, arrays


def now() -> str:
    """The current UTC time as ISO 8601, the store's timestamp format."""
    return datetime.now(timezone.utc).isoformat()
