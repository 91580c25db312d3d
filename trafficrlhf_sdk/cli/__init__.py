"""The ``trafficrlhf`` command line: the click group of :mod:`trafficrlhf_sdk.cli.app` with the core's commands.

Each command module attaches its commands to the group when imported; plugins add theirs through the
``register_commands(cli)`` hook (see :func:`get_cli`).
"""

from trafficrlhf_sdk.cli import (  # noqa: F401  (importing a command module attaches its commands)
    align_commands,
    compare,
    data_commands,
    evaluate,
    experiment_commands,
    feedback_commands,
    rlhf_commands,
    rm_commands,
)
from trafficrlhf_sdk.cli.app import (
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_USER_ERROR,
    cli,
    format_error,
    get_cli,
    main,
    parse_key_values,
)

__all__ = ["EXIT_INTERNAL", "EXIT_INTERRUPTED", "EXIT_USER_ERROR", "cli", "format_error", "get_cli", "main",
           "parse_key_values"]
