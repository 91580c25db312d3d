"""``trafficrlhf-annotation-web``: the browser annotation app of TrafficRLHF.

Registers the annotation frontend ``web`` and the command ``trafficrlhf feedback serve``. The page shows the N
candidate futures of an item side by side over the map with one synchronized clock, and records the most
realistic one (keys 1..N), "none realistic" (0), "equally realistic" (E) or a skip with a reason; campaign
owners run the campaign from ``/admin``. Plain HTML/JS/CSS, no build step.
"""

from __future__ import annotations

from typing import Any

import click

from trafficrlhf_sdk import hookimpl
from trafficrlhf_sdk.feedback.frontend import AnnotationFrontend

__all__ = ["WebAnnotationFrontend", "serve"]


def serve(db_path: str, host: str = "127.0.0.1", port: int = 8000, campaign: str | None = None,
          log_level: str = "warning", synchronous: str = "FULL", max_body_bytes: int | None = None) -> None:
    """Run the app on ``host:port`` with uvicorn (one process; SQLite serializes the writes); request bodies
    over ``max_body_bytes`` (default 64 kB) are refused with 413 before they are read."""
    import uvicorn

    from trafficrlhf_annotation_web.app import create_app
    from trafficrlhf_annotation_web.guard import DEFAULT_MAX_BODY_BYTES

    app = create_app(db_path, default_campaign=campaign, synchronous=synchronous,
                     max_body_bytes=max_body_bytes or DEFAULT_MAX_BODY_BYTES)
    uvicorn.run(app, host=host, port=port, log_level=log_level, access_log=False)


class WebAnnotationFrontend(AnnotationFrontend):
    """The FastAPI + canvas app."""

    name = "web"

    def serve(self, db_path: str, host: str = "127.0.0.1", port: int = 8000, **options: Any) -> None:
        """See :func:`serve`."""
        serve(db_path, host, port, **options)


@hookimpl
def register_annotation_frontends(register):  # type: ignore[no-untyped-def]
    """Register ``web``."""
    register("web", WebAnnotationFrontend)


@hookimpl
def register_commands(cli):  # type: ignore[no-untyped-def]
    """Add ``serve`` to the ``feedback`` group."""
    group = cli.commands.get("feedback")
    if group is None:  # an SDK without the feedback commands: nothing to attach to
        return

    @group.command("serve")
    @click.option("--db", "db_path", required=True, type=click.Path(dir_okay=False, exists=True, path_type=str),
                  help="The feedback database.")
    @click.option("--host", default="127.0.0.1", show_default=True,
                  help="Interface to bind; the default serves this machine only. Use 0.0.0.0 to open it up.")
    @click.option("--port", type=click.IntRange(0, 65535), default=8000, show_default=True, help="TCP port.")
    @click.option("--campaign", default=None, help="Campaign preselected in the page.")
    @click.option("--log-level", default="warning", show_default=True,
                  type=click.Choice(["critical", "error", "warning", "info", "debug"]), help="uvicorn log level.")
    @click.option("--max-body-kb", type=click.IntRange(1, 10_000), default=64, show_default=True,
                  help="Largest request body accepted (kB); checked before the body is read.")
    def serve_command(db_path: str, host: str, port: int, campaign: str | None, log_level: str,
                      max_body_kb: int) -> None:
        """Serve the browser annotation app (tokens: `trafficrlhf feedback annotator add NAME`; the campaign
        owner's page is /admin with a token from `trafficrlhf feedback admin NAME`)."""
        from trafficrlhf_sdk.feedback.store import check_database_file

        check_database_file(db_path)  # a file that is not SQLite is refused before the banner
        shown = "localhost" if host in ("127.0.0.1", "::1", "localhost") else host
        click.echo(f"annotation app on http://{shown}:{port}/  (open http://{shown}:{port}/?token=TOKEN; admin page "
                   f"http://{shown}:{port}/admin; Ctrl-C stops)")
        serve(db_path, host, port, campaign=campaign, log_level=log_level, max_body_bytes=max_body_kb * 1024)
