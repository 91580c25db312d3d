"""What the SDK writes for the person running it: progress, notes and warnings, all on stderr.

- :func:`progress` draws a tqdm bar when both stdout and stderr are terminals. When either goes to a file or a
  pipe (``> run.log 2>&1``, CI logs, notebooks capturing output), a bar's carriage returns would interleave with
  the tables printed on stdout, so it writes one plain line instead when the loop ends
  (``simulating: 8/8 batches in 12.3 s``).
- :func:`note` writes ``note: ...`` (something the user should know, e.g. options a checkpoint applies);
  :func:`warn` writes ``warning: ...`` (a figure outside its typical range).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator
from typing import Any

__all__ = ["PlainProgress", "interactive", "note", "progress", "warn"]


def interactive() -> bool:
    """Whether stdout and stderr are both terminals (then progress bars cannot mix into logged output)."""
    return all(getattr(stream, "isatty", lambda: False)() for stream in (sys.stdout, sys.stderr))


def note(message: str) -> None:
    """Write ``note: message`` on stderr."""
    print(f"note: {message}", file=sys.stderr, flush=True)


def warn(message: str) -> None:
    """Write ``warning: message`` on stderr."""
    print(f"warning: {message}", file=sys.stderr, flush=True)


class PlainProgress:
    """The stand-in for a tqdm bar off a terminal: counts, and writes one line on stderr when closed.

    It offers the part of tqdm's interface the SDK uses: iteration, ``update``, ``set_postfix``, ``write`` and
    ``close`` (also as a context manager)."""

    def __init__(self, iterable: Iterable[Any] | None = None, total: int | None = None, desc: str = "",
                 unit: str = "it", initial: int = 0) -> None:
        self.iterable = iterable
        self.total = total if total is not None else _length(iterable)
        self.desc, self.unit = desc, unit
        self.n = self.initial = initial
        self.postfix: dict[str, Any] = {}
        self.began = time.perf_counter()
        self.closed = False

    def __iter__(self) -> Iterator[Any]:
        if self.iterable is None:
            raise TypeError("PlainProgress made without an iterable cannot be iterated; pass one.")
        try:
            for item in self.iterable:
                yield item
                self.n += 1
        finally:
            self.close()

    def __enter__(self) -> PlainProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units."""
        self.n += n

    def set_postfix(self, **values: Any) -> None:
        """Values shown after the count in the closing line (the last ones set)."""
        self.postfix = values

    @staticmethod
    def write(line: str) -> None:
        """Write ``line`` on stderr."""
        print(line, file=sys.stderr, flush=True)

    def close(self) -> None:
        """Write the closing line once: ``desc: n/total units in S s (postfix)``."""
        if self.closed:
            return
        self.closed = True
        done = self.n - self.initial
        if not done:
            return
        count = f"{self.n}/{self.total}" if self.total else str(self.n)
        extra = ", ".join(f"{key} {value}" for key, value in self.postfix.items())
        plural = "" if self.n == 1 else ("es" if self.unit.endswith(("s", "x", "sh", "tch")) else "s")
        self.write(f"{self.desc}: {count} {self.unit}{plural} in "
                   f"{time.perf_counter() - self.began:.1f} s" + (f" ({extra})" if extra else ""))


def _length(iterable: Iterable[Any] | None) -> int | None:
    try:
        return len(iterable)  # type: ignore[arg-type]
    except TypeError:
        return None


def progress(iterable: Iterable[Any] | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
             leave: bool = True, initial: int = 0) -> Any:
    """A tqdm bar over ``iterable`` (or a manual one with ``total``) on a terminal; :class:`PlainProgress`
    otherwise, which writes one line when the loop ends. Both go to stderr."""
    if not interactive():
        return PlainProgress(iterable, total=total, desc=desc, unit=unit, initial=initial)
    from tqdm.auto import tqdm

    return tqdm(iterable, total=total, desc=desc, unit=unit, leave=leave, initial=initial)
