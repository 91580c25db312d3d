"""``AnnotationFrontend``: what an annotation UI plugin registers through ``register_annotation_frontends``."""

from __future__ import annotations

import abc
from typing import Any, ClassVar

__all__ = ["AnnotationFrontend"]


class AnnotationFrontend(abc.ABC):
    """A way for people to label a feedback database (a web app, a desktop tool, ...).

    Register the class with ``register(name, cls)``; the SDK instantiates it without arguments. Every frontend
    reads and writes only through :class:`~trafficrlhf_sdk.feedback.store.FeedbackStore`, so labels from any
    frontend (and from the synthetic annotator) are interchangeable.
    """

    name: ClassVar[str] = ""

    @abc.abstractmethod
    def serve(self, db_path: str, host: str = "127.0.0.1", port: int = 8000, **options: Any) -> None:
        """Serve the database at ``db_path`` until interrupted; bind to ``host`` (localhost by default)."""
