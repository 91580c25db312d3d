"""Reading TOML configuration files (recipes, loop and experiment configurations) with one clear error."""

from __future__ import annotations

import os
import tomllib
from typing import Any

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError

__all__ = ["read_toml"]


def read_toml(path: str, option: str = "--config") -> dict[str, Any]:
    """The table of TOML file ``path``; a missing file or invalid TOML raises an error naming ``option`` and the
    path."""
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{option} {path!r}: no such file; give a TOML file.")
    try:
        with open(path, "rb") as handle:
            return tomllib.load(handle)
    except tomllib.TOMLDecodeError as exc:
        raise DataFormatError(f"{option} {path!r}: not valid TOML ({exc}).") from None
