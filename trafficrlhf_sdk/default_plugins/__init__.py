"""The core's own plugins, registered like third-party ones."""
