"""Plugin hooks of ``trafficrlhf_sdk``.

Every hook receives a ``register`` callback (or the CLI group) and returns nothing. A plugin implements any
subset, accepting any subset of the arguments (pluggy's opt-in arguments), so arguments can be added later
without breaking plugins. Registering a name that another plugin already registered is an error naming both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:
    import click

    from trafficrlhf_sdk.registry import Register

__all__ = ["hookimpl", "hookspec"]

PROJECT_NAME = "trafficrlhf_sdk"
hookspec = pluggy.HookspecMarker(PROJECT_NAME)
hookimpl = pluggy.HookimplMarker(PROJECT_NAME)


@hookspec
def register_traffic_models(register: Register) -> None:
    """Register traffic models: ``register(name, factory)`` where ``factory(**options)`` returns a policy."""


@hookspec
def register_reward_model_architectures(register: Register) -> None:
    """Register reward-model classes: ``register(name, cls)``; ``name`` is stored in ``config.json``."""


@hookspec
def register_rewards(register: Register) -> None:
    """Register hand-written rewards: ``register(name, factory)``; ``factory(**options)`` returns an object with
    ``step_rewards`` (and ``agent_scores``), used as ``builtin:NAME`` wherever a reward model is asked for."""


@hookspec
def register_pretrained(register: Register) -> None:
    """Register bundled checkpoints: ``register(name, folder)``; ``folder`` holds ``config.json`` naming its
    traffic model, so ``--checkpoint NAME`` and :func:`trafficrlhf_sdk.from_pretrained` find it by name."""


@hookspec
def register_scenario_sources(register: Register) -> None:
    """Register dataset readers: ``register(name, cls)`` with ``cls`` a ``ScenarioSource`` subclass."""


@hookspec
def register_metrics(register: Register) -> None:
    """Register closed-loop metrics: ``register(name, metric)`` with ``metric`` a ``Metric`` instance."""


@hookspec
def register_annotation_frontends(register: Register) -> None:
    """Register annotation frontends: ``register(name, cls)``."""


@hookspec
def register_commands(cli: click.Group) -> None:
    """Add subcommands to the ``trafficrlhf`` command-line group."""
