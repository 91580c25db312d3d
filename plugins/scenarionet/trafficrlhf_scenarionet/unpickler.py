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
        value = RestrictedUnpickler(io.BytesIO(data), source).load()
    except DataFormatError:
        raise
    except _CORRUPT_ERRORS as exc:
        raise DataFormatError(
            f"{source}: not a readable pickle (truncated or corrupt: {type(exc).__name__}: {exc})."
        ) from exc
    expanded_size(value, source)
    return value


MAX_EXPANDED_ITEMS = 20_000_000  # values once shared references are expanded (a real scenario holds about 1 M)


def expanded_size(value: Any, source: str, limit: int = MAX_EXPANDED_ITEMS) -> int:
    """How many values ``value`` holds when every shared reference is counted each time it occurs (what turning
    it into arrays allocates); over ``limit`` raises ``DataFormatError``. Each object is visited once, so a
    small "reference bomb" (lists of lists of the same list) is measured without being expanded."""
    sizes: dict[int, int] = {}
    stack: list[tuple[Any, bool]] = [(value, False)]
    while stack:
        obj, children_done = stack.pop()
        key = id(obj)
        if key in sizes:
            continue
        if isinstance(obj, np.ndarray) and obj.dtype != object:
            sizes[key] = max(1, obj.size)
            continue
        if isinstance(obj, dict):
            children = [*obj.keys(), *obj.values()]
        elif isinstance(obj, (list, tuple, set, frozenset, np.ndarray)):
            children = list(obj.flat) if isinstance(obj, np.ndarray) else list(obj)
        else:
            sizes[key] = 1
            continue
        if not children_done:
            stack.append((obj, True))
            stack.extend((child, False) for child in children if id(child) not in sizes)
            continue
        sizes[key] = 1 + sum(sizes.get(id(child), 1) for child in children)
        if sizes[key] > limit:
            raise DataFormatError(f"{source}: the pickle expands to more than {limit:,} values through shared "
                                  "references (a reference bomb, or not a ScenarioNet scenario); refusing it.")
    return sizes[id(value)]


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
