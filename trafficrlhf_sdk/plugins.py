"""The plugin manager: core defaults registered in code, third-party plugins from entry points.

Environment variables:
    TRAFFICRLHF_BLOCK_PLUGINS: comma-separated plugin names (entry-point names or default-plugin module
        names) that are not loaded.
    TRAFFICRLHF_TRACE_PLUGINS: when set, every hook call and its result are printed to stderr.
"""

from __future__ import annotations

import importlib
import os
import sys
from typing import Any

import pluggy

from trafficrlhf_sdk import hookspecs
from trafficrlhf_sdk.errors import UnknownComponentError
from trafficrlhf_sdk.registry import Registry

__all__ = ["DEFAULT_PLUGINS", "get_plugin_manager", "list_plugins", "registry"]

ENTRY_POINT_GROUP = hookspecs.PROJECT_NAME
DEFAULT_PLUGINS = (
    "trafficrlhf_sdk.default_plugins.policies",
    "trafficrlhf_sdk.default_plugins.metrics",
    "trafficrlhf_sdk.default_plugins.reward_models",
)
KINDS = {
    "traffic_models": ("register_traffic_models", "traffic model"),
    "reward_model_architectures": ("register_reward_model_architectures", "reward-model architecture"),
    "scenario_sources": ("register_scenario_sources", "scenario source"),
    "metrics": ("register_metrics", "metric"),
    "annotation_frontends": ("register_annotation_frontends", "annotation frontend"),
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
