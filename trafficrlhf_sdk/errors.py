"""Exceptions raised by the SDK.

Every message names the offending argument or file, shows the value and says how to fix it. The CLI turns
any :class:`TrafficRLHFError` into one line on stderr and exit code 2, never a traceback.
"""

from __future__ import annotations

__all__ = [
    "DataFormatError",
    "DataNotFoundError",
    "DatabaseFileError",
    "DeviceUnavailableError",
    "DuplicateRegistrationError",
    "FileEncodingError",
    "InputLimitError",
    "InvalidOptionError",
    "MapMismatchError",
    "RewardModelError",
    "SafetensorsFileError",
    "ScenarioValidationError",
    "TrafficRLHFError",
    "UnknownComponentError",
    "UnsafePickleError",
]


class TrafficRLHFError(Exception):
    """Base class of every error the SDK raises on purpose."""


class UnknownComponentError(TrafficRLHFError, KeyError):
    """A name was looked up in a registry (sources, models, metrics, ...) and is not there."""

    def __str__(self) -> str:  # KeyError would wrap the message in quotes
        return str(self.args[0]) if self.args else ""


class DuplicateRegistrationError(TrafficRLHFError, ValueError):
    """Two plugins registered the same name in the same registry."""


class ScenarioValidationError(TrafficRLHFError, ValueError):
    """A ScenarioTensor field has the wrong shape, dtype or non-finite values."""


class DataNotFoundError(TrafficRLHFError, FileNotFoundError):
    """A data directory or file the user pointed at does not exist."""


class DataFormatError(TrafficRLHFError, ValueError):
    """A data file exists but cannot be parsed (malformed row, corrupt safetensors, ...)."""


class FileEncodingError(DataFormatError):
    """A text file (labels, configs, rankings) is not valid in the encoding it must have (UTF-8)."""


class DatabaseFileError(DataFormatError):
    """A file given as a database is not an SQLite database, is damaged, or is missing where it must exist."""


class SafetensorsFileError(DataFormatError):
    """A safetensors file has a bad header, does not match its declared size, or is too large to read here."""


class InvalidOptionError(TrafficRLHFError, ValueError):
    """An option (``--architecture-option``, ``--model-option``, a config field) has a value the component
    cannot use; the message names the option, the value and the accepted range."""


class RewardModelError(TrafficRLHFError, ValueError):
    """A reward model loads but does not behave as one: its probe pass gives outputs that are not finite or not in
    the architecture's range."""


class UnsafePickleError(DataFormatError):
    """A pickle asked for a global outside the allow-list of the restricted unpickler."""


class DeviceUnavailableError(TrafficRLHFError, ValueError):
    """A torch device was asked for that this machine does not have (e.g. ``cuda`` on a CPU-only install)."""


class MapMismatchError(DataFormatError):
    """A scene's map does not line up with its logged agents (wrong origin, scale or orientation of the map)."""


class InputLimitError(DataFormatError):
    """An input is larger than a stated limit (agents, steps, map pixels, shared references); the message names the
    option that raises the limit."""
