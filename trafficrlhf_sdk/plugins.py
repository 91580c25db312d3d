"""The plugin manager: core defaults registered in code, third-party plugins from entry points.

Environment variables:
    TRAFFICRLHF_BLOCK_PLUGINS: comma-separated plugin names (entry-point names or default-plugin module
        names) that are not loaded.
    TRAFFICRLHF_TRACE_PLUGINS: when set, every hook call and its result are printed to stderr.
"""

from __future__ import annotations

import importlib
import inspect
import os
import sys
from typing import Any

import pluggy

import trafficrlhf_sdk.hookspecs as hookspecs
from trafficrlhf_sdk.errors import TrafficRLHFError, UnknownComponentError
from trafficrlhf_sdk.registry import Registry

__all__ = ["DEFAULT_PLUGINS", "build_policy", "build_traffic_model", "checkpoint_model", "checkpoint_options",
           "get_plugin_manager", "list_plugins", "registry", "resolve_checkpoint"]

ENTRY_POINT_GROUP = hookspecs.PROJECT_NAME
DEFAULT_PLUGINS = (
    "trafficrlhf_sdk.default_plugins.policies",
    "trafficrlhf_sdk.default_plugins.metrics",
    "trafficrlhf_sdk.default_plugins.reward_models",
    "trafficrlhf_sdk.default_plugins.rewards",
)
KINDS = {
    "traffic_models": ("register_traffic_models", "traffic model"),
    "reward_model_architectures": ("register_reward_model_architectures", "reward-model architecture"),
    "scenario_sources": ("register_scenario_sources", "scenario source"),
    "metrics": ("register_metrics", "metric"),
    "annotation_frontends": ("register_annotation_frontends", "annotation frontend"),
    "rewards": ("register_rewards", "built-in reward"),
    "pretrained": ("register_pretrained", "bundled checkpoint"),
}

pm = pluggy.PluginManager(hookspecs.PROJECT_NAME)
pm.add_hookspecs(hookspecs)
_loaded = False


def blocked_plugins() -> list[str]:
    """Plugin names listed in ``TRAFFICRLHF_BLOCK_PLUGINS``."""
    return [name.strip() for name in os.environ.get("TRAFFICRLHF_BLOCK_PLUGINS", "").split(",") if name.strip()]


def get_plugin_manager() -> pluggy.PluginManager:
    """The process-wide plugin manager with defaults and entry points loaded (once)."""
    global _loaded
    if not _loaded:
        _loaded = True
        for name in blocked_plugins():
            pm.set_blocked(name)
        for module_name in DEFAULT_PLUGINS:
            if not pm.is_blocked(module_name):
                pm.register(importlib.import_module(module_name), name=module_name)
        pm.load_setuptools_entrypoints(ENTRY_POINT_GROUP)
        pm.check_pending()
        if os.environ.get("TRAFFICRLHF_TRACE_PLUGINS"):
            pm.add_hookcall_monitoring(
                lambda name, impls, kwargs: print(f"[trace] {name} -> {[i.plugin_name for i in impls]}",
                                                  file=sys.stderr),
                lambda outcome, name, impls, kwargs: None,
            )
    return pm


def registry(kind: str) -> Registry[Any]:
    """Build the registry of ``kind`` (one of :data:`KINDS`) by calling every plugin's hook.

    Built afresh on each call so plugins registered at run time (tests, notebooks) are seen.
    """
    if kind not in KINDS:
        raise UnknownComponentError(f"Unknown registry kind: {kind!r}. Known kinds: {sorted(KINDS)}.")
    hook_name, label = KINDS[kind]
    manager = get_plugin_manager()
    result: Registry[Any] = Registry(label)
    # get_hookimpls() lists implementations in registration order (pluggy calls them in reverse).
    for impl in getattr(manager.hook, hook_name).get_hookimpls():
        arguments = {"register": result.bind(impl.plugin_name)}
        impl.function(**{name: arguments[name] for name in impl.argnames})  # opt-in arguments, as pluggy does
    return result


def get_scenario_source(name: str, **options: Any) -> Any:
    """Instantiate the registered scenario source ``name`` with its config ``options`` (e.g. ``root=...``)."""
    source_cls = registry("scenario_sources").get(name)
    return source_cls(**options)


def get_traffic_model(name: str, **options: Any) -> Any:
    """Instantiate the registered traffic model (or built-in policy) ``name``."""
    factory = registry("traffic_models").get(name)
    return factory(**options)


def get_metric(name: str) -> Any:
    """The registered metric ``name``."""
    return registry("metrics").get(name)


def build_traffic_model(name: str, options: dict[str, Any], optional: tuple[str, ...] = ()) -> Any:
    """Instantiate registered traffic model ``name`` with ``options`` (None values dropped).

    A ``guidance`` the factory does not take is an error (dropping it would mislabel the results); the keys in
    ``optional`` (e.g. ``checkpoint``, ``seed``) go only to factories that take them; any other option the
    factory does not take is an error that lists the ones it does.
    """
    factory = registry("traffic_models").get(name)
    try:
        params = inspect.signature(factory).parameters
    except (TypeError, ValueError):
        params = {}  # type: ignore[assignment]
    takes_any = any(p.kind == inspect.Parameter.VAR_KEYWORD for p in params.values())
    kwargs = {k: v for k, v in options.items() if v is not None}
    if kwargs.get("guidance") and not takes_any and "guidance" not in params:
        raise TrafficRLHFError(f"traffic model {name!r} does not accept guidance (got {kwargs['guidance']!r}); drop "
                               "the guidance or pick a model that supports it.")
    kwargs = {k: v for k, v in kwargs.items() if takes_any or k in params or k not in optional}
    unknown = sorted(k for k in kwargs if not takes_any and k not in params)
    if unknown:
        raise TrafficRLHFError(f"traffic model {name!r} takes no option {', '.join(map(repr, unknown))} (got "
                               f"{', '.join(f'{k}={kwargs[k]!r}' for k in unknown)}); it accepts: "
                               f"{', '.join(sorted(params)) or 'none'}.")
    return factory(**kwargs)


def resolve_checkpoint(checkpoint: str) -> str:
    """The folder of ``checkpoint``: an existing folder as given, else a bundled checkpoint registered under that
    name (``trafficrlhf plugins`` lists them)."""
    if os.path.isdir(checkpoint):
        return checkpoint
    bundled = registry("pretrained")
    if checkpoint in bundled.names():
        return str(bundled.get(checkpoint))
    raise TrafficRLHFError(f"--checkpoint {checkpoint!r} is neither a folder nor a bundled checkpoint; give a folder "
                           f"holding config.json + model.safetensors, or one of: {', '.join(bundled.names())}.")


def checkpoint_model(folder: str) -> str | None:
    """The traffic model a checkpoint folder was saved by (``adapter`` in its ``config.json``), or None."""
    import json

    path = os.path.join(folder, "config.json")
    if not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as handle:
            config = json.load(handle)
    except (OSError, ValueError) as exc:
        raise TrafficRLHFError(f"{path}: not a readable JSON config ({exc}); re-save the checkpoint.") from None
    adapter = config.get("adapter") if isinstance(config, dict) else None
    return adapter if isinstance(adapter, str) else None


def checkpoint_options(folder: str) -> dict[str, Any]:
    """The adapter options a checkpoint's card was measured with (``options`` in its ``config.json``; empty when
    it records none), e.g. ``{"guidance": "no_collision"}``."""
    import json

    path = os.path.join(folder, "config.json")
    if not os.path.isfile(path):
        return {}
    try:
        with open(path, encoding="utf-8") as handle:
            config = json.load(handle)
    except (OSError, ValueError) as exc:
        raise TrafficRLHFError(f"{path}: not a readable JSON config ({exc}); re-save the checkpoint.") from None
    options = config.get("options", {}) if isinstance(config, dict) else {}
    if not isinstance(options, dict):
        raise TrafficRLHFError(f"{path}: `options` is {options!r}; it must map option names to values, e.g. "
                               '{"guidance": "no_collision"}.')
    return options


def _apply_card_options(checkpoint: str, folder: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` with the checkpoint's card options filled in where the caller gave none (said in a note)."""
    from trafficrlhf_sdk.console import note

    applied = {key: value for key, value in checkpoint_options(folder).items() if options.get(key) is None}
    if applied:
        shown = ", ".join(f"{key}={value!r}" for key, value in applied.items())
        note(f"checkpoint {checkpoint!r} runs with the options its card was measured with: {shown} (pass the "
             "option to change it; guidance 'none' for no guidance).")
    return {**options, **applied}


def build_policy(model: str | None, options: dict[str, Any]) -> Any:
    """Instantiate a traffic model for closed-loop use: ``model`` (registered name) and/or ``options["checkpoint"]``
    (a folder or a bundled checkpoint's name). Without ``model`` the checkpoint's ``config.json`` names it; a
    checkpoint saved by another model is an error. ``seed`` goes to factories that accept it; ``checkpoint``,
    ``guidance`` and any other option must be accepted, or the error names it.

    A checkpoint whose ``config.json`` records the options its card was measured with (``options``, e.g. the
    bundled ``ctg-aligned``'s guidance) runs with those the caller leaves None, and a note on stderr says so;
    ``guidance="none"`` turns a recorded guidance off."""
    options = dict(options)
    checkpoint = options.get("checkpoint")
    if checkpoint is not None:
        options["checkpoint"] = folder = resolve_checkpoint(str(checkpoint))
        options = _apply_card_options(str(checkpoint), folder, options)
        checkpoint = folder
        saved_by = checkpoint_model(checkpoint)
        if model is None:
            model = saved_by
            if model is None:
                raise TrafficRLHFError(f"--checkpoint {checkpoint!r} has no config.json naming its traffic model; "
                                       "add --model NAME.")
        elif saved_by is not None and saved_by != model:
            raise TrafficRLHFError(f"--checkpoint {checkpoint!r} was saved by traffic model {saved_by!r}, not "
                                   f"--model {model!r}; drop --model or pass --model {saved_by}.")
    if model is None:
        raise TrafficRLHFError("no traffic model given: pass --model NAME (`trafficrlhf plugins` lists them) or "
                               "--checkpoint FOLDER.")
    if isinstance(options.get("guidance"), str) and options["guidance"].strip().lower() == "none":
        options["guidance"] = ""  # no guidance, also over a checkpoint's recorded one
    # a --checkpoint given to a model that loads none (a built-in policy) is an error, never silently dropped
    return build_traffic_model(model, options, optional=("seed",))


def list_plugins() -> list[dict[str, Any]]:
    """One dict per loaded plugin: name, version (for entry-point plugins), hooks it implements."""
    manager = get_plugin_manager()
    versions = {plugin_name: dist.version for plugin_name, dist in
                ((manager.get_name(p), d) for p, d in manager.list_plugin_distinfo())}
    rows = []
    for plugin in manager.get_plugins():
        name = manager.get_name(plugin)
        if name is None:
            continue
        hooks = sorted(caller.name for caller in manager.get_hookcallers(plugin) or [])
        rows.append({"name": name, "version": versions.get(name), "hooks": hooks,
                     "default": name in DEFAULT_PLUGINS})
    return sorted(rows, key=lambda row: (not row["default"], row["name"]))
