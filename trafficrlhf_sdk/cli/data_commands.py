"""Commands about installed components and data: ``plugins``, ``sources``, ``inspect``, ``render`` (``render
scene`` and ``render compare``)."""

from __future__ import annotations

import difflib
import json
import os
from typing import TYPE_CHECKING, Any

import click
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from trafficrlhf_sdk.cli.app import cli, format_error, parse_key_values
from trafficrlhf_sdk.errors import TrafficRLHFError, UnknownComponentError

if TYPE_CHECKING:
    from trafficrlhf_sdk.scenario import ScenarioSource

__all__ = ["compare_command", "inspect_command", "plugins_command", "render", "render_command", "sources_command"]

json_option = click.option("--json", "as_json", is_flag=True, help="Print machine-readable JSON instead of a table.")
split_option = click.option("--split", default="val", show_default=True, help="Which split of the source.")
root_option = click.option(
    "--root", type=click.Path(file_okay=False, path_type=str), default=None,
    help="Data directory of the source (default: the source's own default, see `trafficrlhf sources`).",
)


def _console() -> Console:
    console = Console(highlight=False)
    if not console.is_terminal:  # pipes and captured output: do not squeeze tables into 80 columns
        console = Console(highlight=False, width=max(console.width, 120))
    return console


def _echo_json(data: Any) -> None:
    click.echo(json.dumps(data, indent=2, sort_keys=False))


def _error_text(exc: BaseException) -> str:
    """Message of an exception raised by a plugin: expected errors as is, others with their type."""
    import pydantic

    if isinstance(exc, (TrafficRLHFError, OSError, pydantic.ValidationError)):
        return format_error(exc)
    return f"{type(exc).__name__}: {format_error(exc)}"


def open_source(name: str, root: str | None) -> ScenarioSource:
    """The registered source ``name``, with ``root`` only when the user gave one."""
    from trafficrlhf_sdk.plugins import get_scenario_source

    return get_scenario_source(name, root=root) if root is not None else get_scenario_source(name)


# ------------------------------------------------------------------------------------------------ plugins
@cli.command("plugins")
@json_option
def plugins_command(as_json: bool) -> None:
    """List loaded plugins and the components each registry holds."""
    from trafficrlhf_sdk.plugins import KINDS, blocked_plugins, list_plugins, registry

    plugins = list_plugins()
    registries: dict[str, dict[str, Any]] = {}
    for kind, (_hook, label) in KINDS.items():
        entry: dict[str, Any] = {"label": label, "components": [], "error": None}
        try:
            reg = registry(kind)
            entry["components"] = [{"name": name, "plugin": reg.owner(name)} for name in reg.names()]
        except Exception as exc:  # one broken plugin must not hide the rest of the listing
            entry["error"] = _error_text(exc)
        registries[kind] = entry
    blocked = blocked_plugins()
    if as_json:
        _echo_json({"plugins": plugins, "registries": registries, "blocked": blocked})
        return

    console = _console()
    table = Table(title="Loaded plugins", title_justify="left")
    for column in ("plugin", "version", "default", "hooks"):
        table.add_column(column, overflow="fold")
    for row in plugins:
        table.add_row(escape(row["name"]), escape(row["version"] or "-"), "yes" if row["default"] else "no",
                      escape(", ".join(row["hooks"]) or "-"))
    console.print(table)
    components = Table(title="Registered components", title_justify="left")
    for column in ("kind", "name", "plugin"):
        components.add_column(column, overflow="fold")
    for entry in registries.values():
        if entry["error"]:
            components.add_row(escape(entry["label"]), "[red]error[/red]", escape(entry["error"]))
        elif not entry["components"]:
            components.add_row(escape(entry["label"]), "[dim](none)[/dim]", "")
        for item in entry["components"]:
            components.add_row(escape(entry["label"]), escape(item["name"]), escape(item["plugin"]))
    console.print(components)
    if blocked:
        console.print(f"Blocked by TRAFFICRLHF_BLOCK_PLUGINS: {escape(', '.join(blocked))}")


# ------------------------------------------------------------------------------------------------ sources
@cli.command("sources")
@json_option
def sources_command(as_json: bool) -> None:
    """List scenario sources: owning plugin, default data root and the splits found there."""
    from trafficrlhf_sdk.plugins import registry

    reg = registry("scenario_sources")
    rows = []
    for name in reg.names():
        row: dict[str, Any] = {"name": name, "plugin": reg.owner(name), "root": None, "root_exists": False,
                               "splits": None, "error": None}
        try:
            source = reg.get(name)()
            row["root"] = str(source.root)
            row["root_exists"] = os.path.isdir(row["root"])
            row["splits"] = list(source.splits())
        except Exception as exc:  # report per source; a missing dataset is normal
            row["error"] = _error_text(exc)
        rows.append(row)
    if as_json:
        _echo_json(rows)
        return
    if not rows:
        click.echo("No scenario source is registered; install a source plugin (see `trafficrlhf plugins`).")
        return
    table = Table(title="Scenario sources", title_justify="left")
    for column in ("source", "plugin", "default root", "exists", "splits"):
        table.add_column(column, overflow="fold")
    for row in rows:
        splits = ", ".join(row["splits"]) if row["splits"] is not None else f"missing: {row['error']}"
        table.add_row(escape(row["name"]), escape(row["plugin"]), escape(row["root"] or "-"),
                      "yes" if row["root_exists"] else "[red]no[/red]", escape(splits or "(none)"))
    _console().print(table)


# ------------------------------------------------------------------------------------------------ inspect
def _fmt(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _fmt_summary(summary: dict[str, float | None], unit: str = "s") -> str:
    return f"mean {_fmt(summary['mean'])} {unit} (min {_fmt(summary['min'])}, max {_fmt(summary['max'])})"


@cli.command("inspect")
@click.argument("source_name", metavar="SOURCE")
@split_option
@root_option
@click.option("--scenes", "num_scenes", type=click.IntRange(min=1), default=None,
              help="Load only the first N scenes (sorted by name) that are long enough. Default: all.")
@click.option("--ids", "list_ids", is_flag=True, help="Only list the ids of the scenes that are long enough.")
@json_option
def inspect_command(source_name: str, split: str, root: str | None, num_scenes: int | None, list_ids: bool,
                    as_json: bool) -> None:
    """Load scenes of SOURCE and print statistics (scenes, agents, durations, types, speeds)."""
    from trafficrlhf_sdk.scenario.statistics import inspect_source

    source = open_source(source_name, root)
    if list_ids:
        source.check_split(split)
        ids = source.scene_ids(split)
        click.echo(json.dumps(ids, indent=2) if as_json else "\n".join(ids))
        return
    report = inspect_source(source, split, num_scenes)
    if as_json:
        _echo_json(report)
        return
    table = Table(title=f"{source_name} / {split}", title_justify="left", show_header=False)
    table.add_column("property", style="bold")
    table.add_column("value", overflow="fold")
    for key, value in _inspect_rows(report):
        table.add_row(escape(key), escape(value))
    _console().print(table)


def _inspect_rows(report: dict[str, Any]) -> list[tuple[str, str]]:
    """The lines of ``inspect``'s table, from :func:`~trafficrlhf_sdk.scenario.statistics.inspect_source`."""
    scenes_info = report["scenes"]
    scene_line = f"{scenes_info['loaded']} loaded of {scenes_info['long_enough']} long enough"
    if scenes_info["total"] is not None:
        scene_line += f" ({scenes_info['total']} in the split)"
    a, c = report["agents"], report["controlled_agents"]
    return [
        ("root", report["root"]),
        ("scenes", scene_line),
        ("time step", ", ".join(f"{dt:g} s" for dt in report["dt_s"])),
        ("agents", f"{a['total']} (per scene mean {_fmt(a['per_scene_mean'])}, max {a['per_scene_max']})"),
        ("controlled agents", f"{c['total']} (per scene mean {_fmt(c['per_scene_mean'])})"),
        ("duration", _fmt_summary(report["duration_s"])),
        ("history", _fmt_summary(report["history_s"])),
        ("future", _fmt_summary(report["future_s"])),
        ("agent types", ", ".join(f"{name}: {count}" for name, count in report["agent_types"].items()) or "-"),
        ("mean speed (valid agents)", f"{_fmt(report['mean_speed_mps'], 2)} m/s"),
    ]


# ------------------------------------------------------------------------------------------------- render
class _DefaultCommandGroup(click.Group):
    """A group whose first argument, when it names none of its commands, goes to its default command: ``render
    SOURCE SCENE`` runs ``render scene SOURCE SCENE``."""

    def __init__(self, *args: Any, default: str, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.default = default

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        if args and args[0] not in self.commands and args[0] not in ctx.help_option_names:
            args = [self.default, *args]
        return super().parse_args(ctx, args)


@cli.group("render", cls=_DefaultCommandGroup, default="scene")
def render() -> None:
    """Pictures of scenes: a logged scene as a PNG (`render SOURCE SCENE`, short for `render scene`), or models
    side by side in closed loop from the same start (`render compare`)."""


@render.command("scene")
@click.argument("source_name", metavar="SOURCE")
@click.argument("scene_id", metavar="SCENE")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=str), default=None,
              help="PNG file to write. Default: SCENE.png in the current directory.")
@split_option
@root_option
@click.option("--step", type=click.IntRange(min=0), default=None,
              help="Time step at which agents are drawn. Default: the current step (end of history).")
@click.option("--dpi", type=click.IntRange(min=20, max=600), default=110, show_default=True)
def render_command(source_name: str, scene_id: str, output: str | None, split: str, root: str | None,
                   step: int | None, dpi: int) -> None:
    """Render scene SCENE of SOURCE (map, boxes, trails) to a PNG and print its path.

    `trafficrlhf render SOURCE SCENE` is short for `trafficrlhf render scene SOURCE SCENE`.
    """
    from trafficrlhf_sdk.render import save_scene_png

    source = open_source(source_name, root)
    source.check_split(split)
    try:
        scenario = source.load_scene(split, scene_id)
    except (FileNotFoundError, KeyError) as exc:
        known = source.scene_ids(split)
        if scene_id in known:  # the scene exists: something else is missing (e.g. its map)
            raise
        close = difflib.get_close_matches(scene_id, known, n=3)
        hint = f" Did you mean {close}?" if close else ""
        raise UnknownComponentError(
            f"scene {scene_id!r} not found in split {split!r} of source {source_name!r} "
            f"({format_error(exc).rstrip('.')}).{hint}"
            f" List the scene ids with `trafficrlhf inspect {source_name} --split {split} --ids`."
        ) from exc
    path = save_scene_png(scenario, output or f"{scene_id}.png", step=step, dpi=dpi)
    click.echo(path)


@render.command("compare")
@click.option("--checkpoint", "checkpoints", multiple=True,
              help="A model's weights (a folder or a bundled checkpoint's name), repeatable: one panel each, the base "
                   "first, e.g. --checkpoint ctg-4s --checkpoint ctg-baseline.")
@click.option("--model", "models", multiple=True,
              help="Registered traffic model or built-in policy: once for every --checkpoint, once per --checkpoint, "
                   "or, without --checkpoint, one panel per --model.")
@click.option("--guidance", default=None, help="Guidance for every model that supports it, e.g. no_collision "
              "[default: the one a bundled checkpoint's card was measured with; `none` turns it off].")
@click.option("--model-option", "model_options", multiple=True, metavar="KEY=VALUE",
              help="Traffic-model option (JSON value) for every model, repeatable.")
@click.option("--source", default="nuscenes_pred", show_default=True, help="Registered scenario source.")
@split_option
@root_option
@click.option("--scenes", "num_scenes", type=click.IntRange(min=1), default=100, show_default=True,
              help="Simulate the first N long-enough scenes of the split.")
@click.option("--scene-id", "scene_ids", multiple=True,
              help="Simulate and draw exactly this scene, failing or not (repeatable); overrides --scenes and --worst.")
@click.option("--worst", type=click.IntRange(min=1), default=3, show_default=True,
              help="Draw the N scenes where the base fails with the most agents.")
@click.option("--seed", type=int, default=0, show_default=True, help="The seed of every model's run.")
@click.option("--batch-size", type=click.IntRange(min=1), default=50, show_default=True,
              help="Scenes per simulated batch.")
@click.option("--duration", type=click.FloatRange(min=0.5), default=10.0, show_default=True,
              help="Seconds simulated after the 3 s of history.")
@click.option("--frame-hz", type=click.FloatRange(0.5, 10.0), default=5.0, show_default=True,
              help="Animation frames per simulated second (2-5 keeps a GIF to a few hundred KB).")
@click.option("--speed", type=click.FloatRange(0.1, 10.0), default=1.0, show_default=True,
              help="Playback speed of the animations (1: real time).")
@click.option("--dpi", type=click.IntRange(min=40, max=300), default=100, show_default=True)
@click.option("--out", "out_dir", required=True, type=click.Path(path_type=str),
              help="Folder for <rank>_<scene>.gif / .png per scene and side_by_side.json.")
def compare_command(checkpoints: tuple[str, ...], models: tuple[str, ...], guidance: str | None,
                    model_options: tuple[str, ...], source: str, split: str, root: str | None, num_scenes: int,
                    scene_ids: tuple[str, ...], worst: int, seed: int, batch_size: int, duration: float,
                    frame_hz: float, speed: float, dpi: int, out_dir: str) -> None:
    """Models side by side from the same start, on the scenes where the base fails (GIF + PNG per scene).

    Every model runs in closed loop from the same logged start with the same seed; the scenes where a controlled
    agent of the first model (the base) collides or leaves the road are drawn, the most failing first: an
    animation with one panel per model and a still at the base's first failure.
    """
    from trafficrlhf_sdk.evaluation.side_by_side import SideBySideRequest, panel_specs, render_side_by_side
    from trafficrlhf_sdk.simulation.simulator import SimulationConfig

    request = SideBySideRequest(
        panels=panel_specs(models, checkpoints), guidance=guidance, source=source, split=split, root=root,
        model_options=parse_key_values(model_options, "--model-option"), num_scenes=num_scenes,
        scene_ids=scene_ids, worst=worst, seed=seed, batch_size=batch_size,
        simulation=SimulationConfig(duration_s=duration), frame_hz=frame_hz, speed=speed, dpi=dpi)
    outcome = render_side_by_side(request, out_dir, log=lambda line: click.echo(line, err=True))
    runs = outcome.runs
    for m, (label, rate) in enumerate(zip(runs.labels, runs.failure_rates)):
        click.echo(f"{label}: failure rate {rate:.4f}, fails in {runs.scenes_failing(m)} of {runs.num_scenes} scenes")
    for scene in outcome.scenes:
        counts = ", ".join(f"{label} {n}" for label, n in zip(runs.labels, scene.failing_agents))
        click.echo(f"{scene.rank}. {scene.scene_id} (failing agents: {counts})\n   {scene.animation}\n   {scene.still}")
    click.echo(f"summary: {outcome.summary}")


@cli.command("checkpoint-digest")
@click.argument("folders", nargs=-1, required=True)
def checkpoint_digest_command(folders: tuple[str, ...]) -> None:
    """Record the SHA-256 of each traffic-model checkpoint FOLDER's weights in its config.json.

    Loading refuses a checkpoint without one; use this only on folders you trust (the weights are not changed).
    """
    from trafficrlhf_sdk.models.checkpoint import record_weights_digest

    for folder in folders:
        if not os.path.isdir(folder):
            raise TrafficRLHFError(f"checkpoint folder not found: {folder!r}; pass a folder holding config.json and "
                                   "model.safetensors.")
        click.echo(f"{folder}: sha256 {record_weights_digest(folder)}")
