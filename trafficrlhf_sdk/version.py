"""The SDK's version, recorded in every file it writes (reward models, campaigns, results)."""

__version__ = "0.1.0"
