"""Reading TOML configuration files (recipes, loop and experiment configurations) with one clear error.

Nested tables (``[align]``, ``[reward]``, ...) are pydantic models with ``extra="forbid"`` too, so a misspelled key
anywhere in a file fails when the file is loaded, before any work starts, and the error names the key's path
(``align.learnig_rate``). A nested section keeps only the fields the file sets (:data:`ONLY_SET_FIELDS`): the
stage that runs it fills the rest (its seed, its guidance) before the section's own defaults apply.
"""

from __future__ import annotations

import os
import tomllib
from typing import Any, TypeVar

from pydantic import BaseModel, PlainSerializer, SerializationInfo, ValidationError

from trafficrlhf_sdk.errors import DataFormatError, DataNotFoundError, FileEncodingError

__all__ = ["ONLY_SET_FIELDS", "encoding_error", "load_config", "read_text", "read_toml", "set_fields",
           "validation_message"]

ModelT = TypeVar("ModelT", bound=BaseModel)


def set_fields(section: BaseModel | None) -> dict[str, Any]:
    """The fields ``section`` was given (not its defaults), as Python values; ``{}`` for None."""
    return {} if section is None else section.model_dump(exclude_unset=True)


def _dump_set_fields(section: BaseModel, info: SerializationInfo) -> dict[str, Any]:
    return section.model_dump(mode=info.mode, exclude_unset=True)


ONLY_SET_FIELDS = PlainSerializer(_dump_set_fields)
"""Annotation of a nested section (``Annotated[AlignConfig, ONLY_SET_FIELDS]``): validated in full, written back
(``model_dump``) with only the fields that were given, as the table in the file reads."""


def validation_message(exc: ValidationError) -> str:
    """Every problem of ``exc`` on one line, each as ``path.to.field: message``."""
    return "; ".join(f"{'.'.join(map(str, e['loc'])) or '<config>'}: {e['msg']}" for e in exc.errors())


def encoding_error(path: str, option: str, exc: UnicodeDecodeError) -> FileEncodingError:
    """The error for text file ``path`` (given as ``option``) that is not UTF-8, naming the first bad byte."""
    bad = exc.object[exc.start:exc.start + 4]
    return FileEncodingError(f"{option} {path!r} is not UTF-8 text (byte {exc.start} is {bytes(bad)!r}); save it as "
                             "UTF-8 (e.g. `iconv -t UTF-8`), or pass the file you meant.")


def read_text(path: str, option: str) -> str:
    """The text of UTF-8 file ``path``, given as ``option``; a missing file or another encoding is one error
    naming the option and the path."""
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{option} {path!r}: no such file; check the path.")
    with open(path, "rb") as handle:
        raw = handle.read()
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise encoding_error(path, option, exc) from None


def read_toml(path: str, option: str = "--config") -> dict[str, Any]:
    """The table of TOML file ``path``; a missing file, another encoding than UTF-8 or invalid TOML raises an
    error naming ``option`` and the path."""
    if not os.path.isfile(path):
        raise DataNotFoundError(f"{option} {path!r}: no such file; give a TOML file.")
    text = read_text(path, option)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DataFormatError(f"{option} {path!r}: not valid TOML ({exc}).") from None


def load_config(model: type[ModelT], path: str, option: str = "--config", **fields: Any) -> ModelT:
    """``model`` validated from TOML file ``path`` with ``fields`` over the file's; any problem, nested keys
    included, raises ``DataFormatError`` naming ``option``, the path and each field's path."""
    data = {**read_toml(path, option), **fields}
    try:
        return model(**data)
    except ValidationError as exc:
        raise DataFormatError(f"{option} {path!r}: {validation_message(exc)}") from None
