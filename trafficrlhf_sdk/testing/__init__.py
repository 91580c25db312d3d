"""Test helpers for plugin authors.

``trafficrlhf_sdk.testing.strategies`` holds `Hypothesis <https://hypothesis.readthedocs.io>`_ strategies that
build valid random :class:`~trafficrlhf_sdk.scenario.ScenarioTensor` batches. It needs ``hypothesis`` (install
the ``test`` extra); this package itself imports nothing optional. ``trafficrlhf_sdk.testing.feedback`` builds a
tiny, model-free feedback campaign for tests of annotation frontends and annotators;
``trafficrlhf_sdk.testing.rewards`` an easy-to-learn reward for checking that ``align`` moves a new adapter.
"""

__all__ = ["strategies"]
