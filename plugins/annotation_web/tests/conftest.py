"""Fixtures of the annotation app tests: a tiny campaign database, tokens, an in-process client, and a real
uvicorn server in a subprocess on 127.0.0.1 (loopback only, random free port)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from trafficrlhf_sdk.feedback import FeedbackStore
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

from trafficrlhf_annotation_web.testing import Server


@pytest.fixture()
def campaign_db(tmp_path) -> tuple[str, dict[str, str]]:  # type: ignore[no-untyped-def]
    """A database with campaign ``tiny`` (4 items, N = 5, labels accepted without waiting for the playback),
    annotators alice and bob and the admin owner; returns (path, tokens) with the admin token as "admin"."""
    path = str(tmp_path / "fb.db")
    store = FeedbackStore(path)
    make_tiny_campaign(store, num_contexts=4)
    store.update_settings("tiny", playback_required=False)
    tokens = {name: store.add_annotator(name)[1] for name in ("alice", "bob")}
    tokens["admin"] = store.add_admin("owner")
    store.close()
    return path, tokens


@pytest.fixture()
def client(campaign_db):  # type: ignore[no-untyped-def]
    """A FastAPI TestClient over ``campaign_db``."""
    from fastapi.testclient import TestClient

    from trafficrlhf_annotation_web.app import create_app

    with TestClient(create_app(campaign_db[0])) as test_client:
        yield test_client


@pytest.fixture()
def server(campaign_db) -> Iterator[Server]:  # type: ignore[no-untyped-def]
    """A real server over ``campaign_db`` on a random loopback port."""
    srv = Server(campaign_db[0]).start()
    try:
        yield srv
    finally:
        srv.stop()
