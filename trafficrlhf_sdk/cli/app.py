"""The ``trafficrlhf`` click group, its error policy and the helpers every command module shares.

The click group :data:`cli` holds the core commands (``plugins``, ``sources``, ``inspect``, ``render``, and
``evaluate`` where installed); plugins add their own through the ``register_commands(cli)`` hook, which
:func:`get_cli` / :func:`main` call once.

Error policy of :func:`main` (the console-script entry point):

- an SDK error (:class:`~trafficrlhf_sdk.errors.TrafficRLHFError`), a ``pydantic.ValidationError`` or an
  ``OSError`` (missing file, permission, ...) prints one line ``Error: <message>`` on stderr, exit code 2;
- a click usage error keeps click's message (usage line + error), exit code 2;
- Ctrl-C prints ``Interrupted``, exit code 130;
- anything else is a bug: one line ``Error: internal error: <type>: <message> (...)``, exit code 1, or the
  full traceback when ``TRAFFICRLHF_DEBUG=1``.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn, TypeVar

import click
import pydantic

from trafficrlhf_sdk.version import __version__
from trafficrlhf_sdk.errors import TrafficRLHFError

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["EXIT_INTERNAL", "EXIT_INTERRUPTED", "EXIT_USER_ERROR", "cli", "format_error", "get_cli", "main",
           "parse_key_values", "ray_options"]

PROG_NAME = "trafficrlhf"
EXIT_INTERNAL = 1
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130
DEBUG_ENV = "TRAFFICRLHF_DEBUG"


@click.group(name=PROG_NAME, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, "--version", prog_name=PROG_NAME, message="%(prog)s %(version)s")
def cli() -> None:
    """TrafficRLHF: align traffic-simulation models with human preferences.

    Data sources, traffic models, metrics and reward models come from plugins; `trafficrlhf plugins` lists
    what is installed. Set TRAFFICRLHF_DEBUG=1 to see full tracebacks of internal errors.
    """


_plugin_commands_added = False


def get_cli() -> click.Group:
    """The ``trafficrlhf`` group with the plugins' commands attached (the hook runs once per process)."""
    global _plugin_commands_added
    if not _plugin_commands_added:
        from trafficrlhf_sdk.plugins import get_plugin_manager

        _plugin_commands_added = True
        get_plugin_manager().hook.register_commands(cli=cli)
    return cli


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip())


def _short_repr(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def format_error(exc: BaseException) -> str:
    """The one-line message (without the ``Error:`` prefix) shown for an expected error."""
    if isinstance(exc, pydantic.ValidationError):
        problems = []
        for err in exc.errors():
            loc = ".".join(str(part) for part in err.get("loc", ())) or "<value>"
            detail = f"{loc}: {err.get('msg', 'invalid value')}"
            if "input" in err and err.get("type") != "missing":
                detail += f" (got {_short_repr(err['input'])})"
            problems.append(detail)
        return _one_line(f"invalid {exc.title} options: " + "; ".join(problems))
    message = _one_line(str(exc))
    if isinstance(exc, OSError) and not isinstance(exc, TrafficRLHFError):
        if not message:
            message = type(exc).__name__
        elif exc.filename is not None and str(exc.filename) not in message:
            message += f": {exc.filename!r}"
    return message or type(exc).__name__


def parse_key_values(pairs: Sequence[str], option: str) -> dict[str, object]:
    """``("k=v", ...)`` from a repeated ``option`` into a dict; values are parsed as JSON when they can be."""
    import json

    options: dict[str, object] = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {pair!r}", param_hint=option)
        try:
            options[key] = json.loads(value)
        except json.JSONDecodeError:
            options[key] = value
    return options


def ray_options(what: str, numbers: str = "The numbers are the same either way.") -> Callable[[F], F]:
    """``--workers`` and ``--ray-address`` for a command that can run ``what`` (e.g. "each epoch's samples") on
    Ray; ``numbers`` says how its results compare with the in-process run's."""
    def decorate(command: F) -> F:
        command = click.option("--ray-address", default=None, help=f"Run {what} on an existing Ray cluster at this "
                               "address (e.g. auto or HOST:6379) instead of a local one.")(command)
        return click.option("--workers", type=click.IntRange(min=0), default=0, show_default=True,
                            help=f"Run {what} on N Ray workers started for the run (pip install "
                                 f"'trafficrlhf-sdk[ray]'); 0 runs in-process. {numbers}")(command)
    return decorate


def _fail(message: str, code: int) -> NoReturn:
    click.echo(f"Error: {message}", err=True)
    sys.exit(code)


def main(args: Sequence[str] | None = None) -> None:
    """Console-script entry point: run the CLI and turn exceptions into one-line errors and exit codes."""
    try:
        group = get_cli()
        result = group.main(args=list(args) if args is not None else None, prog_name=PROG_NAME,
                            standalone_mode=False)
    except click.exceptions.Abort as exc:
        # click turns Ctrl-C into Abort(); an Abort raised on purpose (e.g. a declined prompt) also stops here.
        click.echo("Interrupted" if isinstance(exc.__cause__, KeyboardInterrupt) else "Aborted", err=True)
        sys.exit(EXIT_INTERRUPTED if isinstance(exc.__cause__, KeyboardInterrupt) else EXIT_INTERNAL)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except KeyboardInterrupt:
        click.echo("Interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except (TrafficRLHFError, pydantic.ValidationError, OSError) as exc:
        _fail(format_error(exc), EXIT_USER_ERROR)
    except Exception as exc:
        if os.environ.get(DEBUG_ENV, "").strip() not in ("", "0"):
            raise
        _fail(f"internal error: {type(exc).__name__}: {_one_line(str(exc))} (set {DEBUG_ENV}=1 for the traceback)",
              EXIT_INTERNAL)
    sys.exit(result if isinstance(result, int) else 0)
