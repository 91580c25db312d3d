"""A restricted unpickler for ScenarioNet scenario files.

ScenarioNet stores each scenario as a Python pickle. Unpickling can run arbitrary code through any global the
stream names, so these files are only ever read through :class:`RestrictedUnpickler`, whose ``find_class``
resolves an explicit allow-list of globals (plain containers and numpy arrays) and refuses everything else with
:class:`~trafficrlhf_sdk.errors.UnsafePickleError`. The standard library's unrestricted loader is never used.
"""

from __future__ import annotations

import collections
import io
import pickle
import struct
from collections.abc import Callable
from typing import Any

import numpy as np

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, UnsafePickleError

__all__ = ["ALLOWED_GLOBALS", "RestrictedUnpickler", "restricted_load", "restricted_loads"]


def _numpy_multiarray(name: str) -> Callable[..., Any]:
    """``numpy._core.multiarray.<name>`` (numpy 2), falling back to ``numpy.core.multiarray`` (numpy 1)."""
    try:
        from numpy._core import multiarray  # type: ignore[attr-defined]
    except ImportError:  # numpy < 2
        from numpy.core import multiarray  # type: ignore[no-redef]
    return getattr(multiarray, name)


# (module, name) -> zero-argument resolver. Resolved lazily so nothing is imported for names never asked for.
ALLOWED_GLOBALS: dict[tuple[str, str], Callable[[], Any]] = {
    ("collections", "defaultdict"): lambda: collections.defaultdict,
    ("builtins", "int"): lambda: int,
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy", "dtype"): lambda: np.dtype,
    # numpy 1 writes these under numpy.core, numpy 2 under numpy._core; both name the same functions.
    ("numpy.core.multiarray", "_reconstruct"): lambda: _numpy_multiarray("_reconstruct"),
    ("numpy._core.multiarray", "_reconstruct"): lambda: _numpy_multiarray("_reconstruct"),
    ("numpy.core.multiarray", "scalar"): lambda: _numpy_multiarray("scalar"),
    ("numpy._core.multiarray", "scalar"): lambda: _numpy_multiarray("scalar"),
}

# Everything a malformed (truncated, corrupt, hand-edited) stream can raise while being decoded.
_CORRUPT_ERRORS = (
    pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError,
    struct.error, OverflowError, MemoryError, UnicodeDecodeError, RecursionError,
)


class RestrictedUnpickler(pickle.Unpickler):
    """``pickle.Unpickler`` that only resolves the globals of :data:`ALLOWED_GLOBALS`.

    ``source`` names the file (or other origin) in error messages.
    """

    def __init__(self, handle: io.BufferedIOBase | io.BytesIO, source: str = "<stream>") -> None:
        super().__init__(handle)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        """Resolve ``module.name`` if allowed; otherwise raise ``UnsafePickleError`` naming it and the file."""
        resolver = ALLOWED_GLOBALS.get((module, name))
        if resolver is None:
            allowed = ", ".join(f"{m}.{n}" for m, n in ALLOWED_GLOBALS)
            raise UnsafePickleError(
                f"{self.source}: refusing to unpickle global {module}.{name} (module {module!r}, global {name!r});"
                f" only plain containers and numpy arrays are accepted ({allowed}). The file is not a plain"
                " ScenarioNet scenario or has been tampered with; do not load it with an unrestricted unpickler."
            )
        return resolver()

    def persistent_load(self, pid: Any) -> Any:
        """Persistent ids never occur in scenario files: refuse them."""
        raise UnsafePickleError(f"{self.source}: refusing a pickle persistent id ({pid!r}); not a ScenarioNet file.")


def restricted_loads(data: bytes, source: str = "<bytes>") -> Any:
    """Decode pickle ``data`` with :class:`RestrictedUnpickler`.

    Raises ``UnsafePickleError`` for a forbidden global and ``DataFormatError`` (naming ``source``) for a
    truncated or corrupt stream.
    """
    try:
        return RestrictedUnpickler(io.BytesIO(data), source).load()
    except DataFormatError:
        raise
    except _CORRUPT_ERRORS as exc:
        raise DataFormatError(
            f"{source}: not a readable pickle (truncated or corrupt: {type(exc).__name__}: {exc})."
        ) from exc


def restricted_load(path: str) -> Any:
    """Read the pickle file at ``path`` with :class:`RestrictedUnpickler` (errors as :func:`restricted_loads`;
    a missing file raises ``DataNotFoundError``)."""
    try:
        with open(path, "rb") as handle:
            data = handle.read()
    except FileNotFoundError as exc:
        raise DataNotFoundError(f"scenario file not found: {path!r}; check the path.") from exc
    except OSError as exc:
        raise DataFormatError(f"{path}: cannot read the file ({exc}).") from exc
    return restricted_loads(data, source=path)
