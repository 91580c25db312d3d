"""The plugin manager and registries: run-time plugins, duplicates, unknown names, blocking."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from contextlib import contextmanager

import pytest

import trafficrlhf_sdk
from trafficrlhf_sdk.errors import DuplicateRegistrationError, UnknownComponentError
from trafficrlhf_sdk.plugins import get_plugin_manager, list_plugins, registry
from trafficrlhf_sdk.registry import Registry
from trafficrlhf_sdk.scenario import ScenarioSource


class UndoTestSource(ScenarioSource):
    """A do-nothing source registered by the in-test plugin."""

    name = "undo_test_source"

    @property
    def root(self) -> str:
        return "/nowhere"

    def splits(self) -> list[str]:
        return []

    def scene_ids(self, split: str) -> list[str]:
        return []

    def load_scene(self, split, scene_id):  # type: ignore[no-untyped-def]
        raise NotImplementedError


@contextmanager
def registered(plugin: object, name: str):
    pm = get_plugin_manager()
    pm.register(plugin, name=name)
    try:
        yield pm
    finally:
        pm.unregister(name=name)


def test_run_time_plugin_appears_in_registry_and_list():
    class Plugin:
        __name__ = "UndoTestPlugin"

        @trafficrlhf_sdk.hookimpl
        def register_scenario_sources(self, register):
            register("undo_test_source", UndoTestSource)

    with registered(Plugin(), "undo-test"):
        sources = registry("scenario_sources")
        assert "undo_test_source" in sources.names()
        assert sources.get("undo_test_source") is UndoTestSource
        assert sources.owner("undo_test_source") == "undo-test"
        row = next(p for p in list_plugins() if p["name"] == "undo-test")
        assert row["hooks"] == ["register_scenario_sources"] and row["default"] is False
        source = trafficrlhf_sdk.get_scenario_source("undo_test_source", dt=0.5)
        assert isinstance(source, UndoTestSource) and source.config.dt == 0.5
    assert "undo_test_source" not in registry("scenario_sources")
    assert all(p["name"] != "undo-test" for p in list_plugins())


def test_registries_are_rebuilt_and_independent_per_kind():
    class Plugin:
        __name__ = "UndoTestPlugin"

        @trafficrlhf_sdk.hookimpl
        def register_metrics(self, register):
            register("undo_test_metric", object())

    with registered(Plugin(), "undo-test"):
        assert "undo_test_metric" in registry("metrics")
        assert "undo_test_metric" not in registry("scenario_sources")


def test_duplicate_name_across_plugins_names_both():
    if "nuscenes_pred" not in registry("scenario_sources"):
        pytest.skip("the nuscenes_pred plugin is not installed")

    class Plugin:
        __name__ = "UndoTestPlugin"

        @trafficrlhf_sdk.hookimpl
        def register_scenario_sources(self, register):
            register("nuscenes_pred", UndoTestSource)

    with registered(Plugin(), "undo-test"):
        with pytest.raises(DuplicateRegistrationError) as info:
            registry("scenario_sources")
    message = str(info.value)
    assert "nuscenes_pred" in message and "'undo-test'" in message and "scenario source" in message
    # the plugin registered first is the owner; the newcomer is the one to block
    assert message.index("'nuscenes_pred'", message.index("by plugin")) < message.index("'undo-test'")
    assert "TRAFFICRLHF_BLOCK_PLUGINS=undo-test" in message
    assert isinstance(info.value, ValueError)
    assert registry("scenario_sources").get("nuscenes_pred") is not UndoTestSource


def test_duplicate_names_follow_registration_order():
    def make(tag: str):
        class Plugin:
            __name__ = f"Plugin{tag}"

            @trafficrlhf_sdk.hookimpl
            def register_metrics(self, register):
                register("undo_test_dup", tag)

        return Plugin()

    with registered(make("first"), "undo-first"), registered(make("second"), "undo-second"):
        with pytest.raises(DuplicateRegistrationError, match="by plugin 'undo-first' and by plugin 'undo-second'"):
            registry("metrics")


def test_hookimpl_may_take_no_arguments():
    class Plugin:
        __name__ = "UndoTestPlugin"

        @trafficrlhf_sdk.hookimpl
        def register_scenario_sources(self):  # pluggy lets an implementation accept a subset of the arguments
            pass

    with registered(Plugin(), "undo-test"):
        assert "undo_test_source" not in registry("scenario_sources")


def test_unknown_name_lists_registered_names():
    class Plugin:
        __name__ = "UndoTestPlugin"

        @trafficrlhf_sdk.hookimpl
        def register_scenario_sources(self, register):
            register("undo_test_source", UndoTestSource)

    with registered(Plugin(), "undo-test"):
        sources = registry("scenario_sources")
        with pytest.raises(UnknownComponentError) as info:
            sources.get("undo_test_sauce")
        with pytest.raises(KeyError):
            trafficrlhf_sdk.get_scenario_source("no-such-source")
    message = str(info.value)
    assert isinstance(info.value, KeyError)
    assert "'undo_test_sauce'" in message and "scenario source" in message
    assert "Registered: " in message and "undo_test_source" in message
    assert "Did you mean ['undo_test_source']" in message
    assert not message.startswith('"')  # not KeyError's quoted repr


def test_unknown_registry_kind():
    with pytest.raises(UnknownComponentError, match="scenario_sources"):
        registry("scenario_source")


def test_registry_direct_use():
    reg: Registry[int] = Registry("widget")
    reg.add("a", 1, plugin="p1")
    assert reg.get("a") == 1 and reg.owner("a") == "p1" and len(reg) == 1 and "a" in reg
    with pytest.raises(DuplicateRegistrationError, match=r"'p1'.*'p2'"):
        reg.add("a", 2, plugin="p2")
    with pytest.raises(ValueError, match="p3"):
        reg.add("", 3, plugin="p3")
    with pytest.raises(UnknownComponentError, match=r"Unknown widget: 'b'\. Registered: \['a'\]"):
        reg.get("b")


def test_block_plugins_env_var():
    if "nuscenes_pred" not in registry("scenario_sources"):
        pytest.skip("the nuscenes_pred plugin is not installed, so blocking it proves nothing")
    code = (
        "import json, trafficrlhf_sdk as t\n"
        "names = [p['name'] for p in t.list_plugins()]\n"
        "print(json.dumps({'sources': t.registry('scenario_sources').names(), 'plugins': names}))\n"
        "assert 'nuscenes_pred' not in t.registry('scenario_sources')\n"
    )
    env = {**os.environ, "TRAFFICRLHF_BLOCK_PLUGINS": "nuscenes_pred, trafficrlhf_sdk.default_plugins.metrics"}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert "nuscenes_pred" not in seen["sources"]
    assert "nuscenes_pred" not in seen["plugins"]
    assert "trafficrlhf_sdk.default_plugins.metrics" not in seen["plugins"]
    assert "trafficrlhf_sdk.default_plugins.policies" in seen["plugins"]
