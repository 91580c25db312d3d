"""Checks on a safetensors file made from its 8-byte length, its JSON header and its size alone, before any
tensor byte is read or hashed.

A safetensors file is ``<u64 little-endian header length N><N bytes of JSON header><tensor data>``; the header
gives every tensor's dtype, shape and byte range. :func:`check_safetensors_file` refuses, with a
:class:`~trafficrlhf_sdk.errors.SafetensorsFileError` naming the file, the numbers and the fix:

- a header that is cut off, not JSON, larger than :data:`MAX_HEADER_BYTES` or with inconsistent byte ranges;
- a file whose size is not what its header declares (truncated, or with bytes appended);
- more tensor data than the caller expects (a reward model of a given architecture has a known size);
- more tensor data than this process can hold: the memory the system has available, and the address space left
  under a limit such as ``ulimit -v`` (reading maps the file and copies the tensors).
"""

from __future__ import annotations

import json
import os
import struct
from typing import Any

from trafficrlhf_sdk.errors import DataNotFoundError, SafetensorsFileError

__all__ = ["MAX_HEADER_BYTES", "SafetensorsHeader", "address_space_left", "available_memory_bytes",
           "check_safetensors_file", "format_bytes", "read_header"]

MAX_HEADER_BYTES = 100 * 1024 * 1024  # the limit the safetensors library itself applies
DTYPE_BYTES = {"BOOL": 1, "U8": 1, "I8": 1, "F8_E5M2": 1, "F8_E4M3": 1, "I16": 2, "U16": 2, "F16": 2, "BF16": 2,
               "I32": 4, "U32": 4, "F32": 4, "I64": 8, "U64": 8, "F64": 8}


class SafetensorsHeader:
    """What the header of a safetensors file declares: ``tensors`` (name -> ``(dtype, shape)``), ``metadata``,
    ``header_bytes`` (the length field and the JSON) and ``data_bytes`` (the tensor data); ``file_bytes`` is the
    size the file has (``header_bytes + data_bytes`` when it is intact)."""

    def __init__(self, tensors: dict[str, tuple[str, tuple[int, ...]]], metadata: dict[str, str], header_bytes: int,
                 data_bytes: int, file_bytes: int) -> None:
        self.tensors = tensors
        self.metadata = metadata
        self.header_bytes = header_bytes
        self.data_bytes = data_bytes
        self.file_bytes = file_bytes


def format_bytes(n: float) -> str:
    """``1536`` -> ``"1.5 KiB"``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


def _proc_kib(path: str, key: str) -> int | None:
    try:
        with open(path, encoding="ascii") as handle:
            for line in handle:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def available_memory_bytes() -> int | None:
    """The memory this machine has available (``MemAvailable``), or None where unknown (not Linux)."""
    return _proc_kib("/proc/meminfo", "MemAvailable")


def address_space_left() -> tuple[int, int] | None:
    """``(bytes left, limit)`` of this process's address space under a limit such as ``ulimit -v``, or None when
    there is no limit."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, ValueError, OSError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    used = _proc_kib("/proc/self/status", "VmSize") or 0
    return max(soft - used, 0), soft


def read_header(path: str) -> SafetensorsHeader:
    """Parse and check the header of the safetensors file ``path`` (reads at most 8 + :data:`MAX_HEADER_BYTES`)."""
    if not os.path.isfile(path):
        raise DataNotFoundError(f"safetensors file not found: {path!r}; check the path.")
    size = os.path.getsize(path)
    fix = "re-save it, or restore the file that was written"
    with open(path, "rb") as handle:
        head = handle.read(8)
        if len(head) < 8:
            raise SafetensorsFileError(f"{path!r} is not a readable safetensors file ({size} bytes, too short: an "
                                       f"8-byte header length comes first); {fix}.")
        (length,) = struct.unpack("<Q", head)
        if length > MAX_HEADER_BYTES or 8 + length > size:
            raise SafetensorsFileError(f"{path!r} is not a readable safetensors file (the header declares {length} "
                                       f"bytes of JSON, the file has {size} bytes, the limit is "
                                       f"{format_bytes(MAX_HEADER_BYTES)}); {fix}.")
        raw = handle.read(length)
    try:
        header: Any = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SafetensorsFileError(f"{path!r} is not a readable safetensors file (the header is not UTF-8 JSON: "
                                   f"{exc}); {fix}.") from None
    if not isinstance(header, dict):
        raise SafetensorsFileError(f"{path!r} is not a readable safetensors file (the header is a JSON "
                                   f"{type(header).__name__}, not an object); {fix}.")
    metadata = header.pop("__metadata__", None) or {}
    tensors: dict[str, tuple[str, tuple[int, ...]]] = {}
    end = 0
    for name, entry in header.items():
        try:
            dtype, shape, (start, stop) = entry["dtype"], tuple(int(d) for d in entry["shape"]), entry["data_offsets"]
            numel = 1
            for d in shape:
                if d < 0:
                    raise ValueError
                numel *= d
            width = DTYPE_BYTES[dtype]
        except (KeyError, TypeError, ValueError):
            raise SafetensorsFileError(f"{path!r} is not a readable safetensors file (tensor {name!r} has a "
                                       f"malformed header entry {json.dumps(entry)[:120]}); {fix}.") from None
        in_order = isinstance(start, int) and isinstance(stop, int) and 0 <= start <= stop
        if not in_order or stop - start != numel * width:
            raise SafetensorsFileError(f"{path!r} is not a readable safetensors file (tensor {name!r}, {dtype} of "
                                       f"shape {list(shape)}, needs {numel * width} bytes but its byte range is "
                                       f"{[start, stop]}); {fix}.")
        tensors[name] = (dtype, shape)
        end = max(end, stop)
    return SafetensorsHeader(tensors, {str(k): str(v) for k, v in metadata.items()}, 8 + length, end, size)


def check_safetensors_file(path: str | os.PathLike[str], what: str = "safetensors file",
                           expected_bytes: int | None = None, exact_size: bool = True) -> SafetensorsHeader:
    """Check ``path`` from its header and size before anything reads it (see the module docstring); returns the
    header.

    Args:
        path: the file.
        what: how the message names the file (e.g. "the weights of reward model 'x'").
        expected_bytes: the tensor data the caller needs; a file holding more than twice that (plus 1 MiB) is
            refused without being hashed or read.
        exact_size: also refuse a file whose size differs from what its header declares (truncated or padded);
            a caller that checks a recorded SHA-256 next may leave that to its own, more specific, message.
    """
    path = os.fspath(path)
    header = read_header(path)
    if expected_bytes is not None and header.data_bytes > 2 * expected_bytes + (1 << 20):
        raise SafetensorsFileError(
            f"{what} {path!r} holds {format_bytes(header.data_bytes)} of tensors but should hold about "
            f"{format_bytes(expected_bytes)}; it is not the file its config describes: restore the saved file.")
    refused = "; nothing was read. Check that this is the file you meant, or run where more memory is available."
    free = available_memory_bytes()
    if free is not None and header.data_bytes > free:
        raise SafetensorsFileError(f"{what} {path!r} holds {format_bytes(header.data_bytes)} of tensors but this "
                                   f"machine has {format_bytes(free)} of memory available{refused}")
    left = address_space_left()
    if left is not None and header.file_bytes + header.data_bytes > left[0]:  # reading maps the file, then copies
        raise SafetensorsFileError(
            f"{what} {path!r} needs {format_bytes(header.file_bytes + header.data_bytes)} of address space to read "
            f"({format_bytes(header.file_bytes)} mapped, {format_bytes(header.data_bytes)} of tensors) but only "
            f"{format_bytes(left[0])} is left under this process's limit of {format_bytes(left[1])} (ulimit -v)"
            f"{refused}")
    if exact_size and header.header_bytes + header.data_bytes != header.file_bytes:
        raise SafetensorsFileError(
            f"{path!r} is not a readable safetensors file (its header declares {format_bytes(header.data_bytes)} of "
            f"tensor data, so the file should be {header.header_bytes + header.data_bytes} bytes, but it is "
            f"{header.file_bytes} bytes: truncated or padded); re-save it, or restore the file that was written.")
    return header
