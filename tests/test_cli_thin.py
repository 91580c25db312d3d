"""Every command of ``trafficrlhf`` is thin: it parses, calls one library function and prints.

The measure is the callback's own length (its ``def`` line to its end, decorators left out: the click options
are declarations, one per line). A command that grows past :data:`MAX_LINES` holds logic that belongs in its
stage, where Python users can call it too.
"""

from __future__ import annotations

import inspect

import click
import pytest

MAX_LINES = 40


def _commands(group: click.Group, prefix: str = "") -> list[tuple[str, click.Command]]:
    found = []
    for name, command in sorted(group.commands.items()):
        found.append((prefix + name, command))
        if isinstance(command, click.Group):
            found += _commands(command, f"{prefix}{name} ")
    return found


def _length(callback: object) -> int:
    lines, _ = inspect.getsourcelines(callback)  # type: ignore[arg-type]
    first = next(i for i, line in enumerate(lines) if line.lstrip().startswith(("def ", "async def ")))
    return len(lines) - first


def test_the_measure_counts_the_function_and_not_its_options() -> None:
    @click.command()
    @click.option("--a")
    @click.option("--b")
    def tiny(a: str, b: str) -> None:
        """Doc."""
        click.echo(a + b)

    assert _length(tiny.callback) == 3


@pytest.mark.parametrize(("name", "command"), _commands(__import__("trafficrlhf_sdk.cli", fromlist=["get_cli"])
                                                        .get_cli()))
def test_command_is_at_most_40_lines(name: str, command: click.Command) -> None:
    if command.callback is None:
        pytest.skip(f"{name} has no callback")
    length = _length(command.callback)
    where = f"{inspect.getsourcefile(command.callback)}:{inspect.getsourcelines(command.callback)[1]}"
    assert length <= MAX_LINES, (f"`trafficrlhf {name}` is {length} lines ({where}); move its logic into the "
                                 f"library and keep the command to parsing, one call and printing.")
