"""Named registries filled by plugin hooks, with duplicate detection that names both plugins."""

from __future__ import annotations

import difflib
from typing import Any, Generic, Protocol, TypeVar

from trafficrlhf_sdk.errors import DuplicateRegistrationError, UnknownComponentError

__all__ = ["Lazy", "Register", "Registry", "register_folders"]

T = TypeVar("T")


class Register(Protocol):
    """The callback a ``register_*`` hook receives."""

    def __call__(self, name: str, value: object) -> None:
        """Register ``value`` under ``name``."""


class Lazy:
    """A component named by ``"module:attribute"`` and imported only when first looked up, so listing plugins
    and starting the command line import no model code. With ``args``/``kwargs`` the attribute is called with
    them, or without any when ``call=True`` (e.g. a metric instance built from its class)."""

    def __init__(self, target: str, *args: Any, call: bool = False, **kwargs: Any) -> None:
        module, sep, attribute = target.partition(":")
        if not sep or not module or not attribute:
            raise ValueError(f"lazy target {target!r} must read 'package.module:attribute'.")
        self.target, self.args, self.kwargs, self.call = target, args, kwargs, call or bool(args or kwargs)

    def resolve(self) -> Any:
        """Import the target (and call it when arguments were given)."""
        import importlib

        module, _, attribute = self.target.partition(":")
        value = getattr(importlib.import_module(module), attribute)
        return value(*self.args, **self.kwargs) if self.call else value

    def __repr__(self) -> str:
        return f"Lazy({self.target!r})"


class Registry(Generic[T]):
    """Maps names to components of one kind and remembers which plugin registered each."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._items: dict[str, T] = {}
        self._owners: dict[str, str] = {}

    def add(self, name: str, value: T, plugin: str = "<direct>") -> None:
        """Register ``value`` under ``name`` on behalf of ``plugin``."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"{self.kind} names must be non-empty strings; plugin {plugin!r} passed {name!r}.")
        if name in self._items:
            raise DuplicateRegistrationError(
                f"{self.kind} {name!r} is registered twice: by plugin {self._owners[name]!r} and by plugin "
                f"{plugin!r}. Uninstall one of them or block it with TRAFFICRLHF_BLOCK_PLUGINS={plugin}."
            )
        self._items[name] = value
        self._owners[name] = plugin

    def bind(self, plugin: str) -> Register:
        """A ``register(name, value)`` callback that records ``plugin`` as the owner."""

        def register(name: str, value: object) -> None:
            self.add(name, value, plugin)  # type: ignore[arg-type]

        return register

    def get(self, name: str) -> T:
        """The component called ``name``; unknown names raise :class:`UnknownComponentError` with suggestions."""
        if name not in self._items:
            close = difflib.get_close_matches(name, self._items, n=3)
            hint = f" Did you mean {close}?" if close else ""
            raise UnknownComponentError(
                f"Unknown {self.kind}: {name!r}. Registered: {sorted(self._items)}.{hint} "
                "Install the plugin that provides it (see `trafficrlhf plugins`)."
            )
        value = self._items[name]
        if isinstance(value, Lazy):
            value = self._items[name] = value.resolve()
        return value

    def owner(self, name: str) -> str:
        """The plugin that registered ``name``."""
        return self._owners[name]

    def names(self) -> list[str]:
        """Registered names, sorted."""
        return sorted(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def __len__(self) -> int:
        return len(self._items)


def register_folders(register: Register, package: str, folders: dict[str, str]) -> None:
    """Register bundled checkpoint folders by name for a ``register_pretrained`` hook: each value of ``folders``
    is a path relative to the folder that holds ``package`` (found without importing it); folders that do not
    exist (e.g. an install without the optional aligned models) are skipped."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec(package)
    if spec is None or spec.origin is None:
        return
    root = Path(spec.origin).resolve().parent.parent
    for name, relative in folders.items():
        folder = (root / relative).resolve()
        if folder.is_dir():
            register(name, str(folder))
