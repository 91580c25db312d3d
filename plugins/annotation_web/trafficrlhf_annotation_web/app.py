"""The annotation app: a FastAPI application over one feedback database.

Every ``/api`` route needs ``Authorization: Bearer <token>`` (a token from ``trafficrlhf feedback annotator
add``). Errors are JSON ``{"error": message}`` with these statuses:

- 401: missing, unknown or revoked token;
- 404: unknown campaign or item;
- 409: the annotator already labeled (or skipped) the item, or labels an item never opened;
- 400: a body that is not valid JSON; 422: valid JSON of the wrong shape, or a choice outside 0..N.

A request that fails writes nothing: each write is one SQLite transaction in :class:`FeedbackStore`.
Routes are plain ``def`` functions, so FastAPI runs them in its thread pool; the store keeps one SQLite
connection per thread.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from threading import Lock
from typing import Any

from fastapi import Depends, FastAPI, Header, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, StrictInt

from trafficrlhf_sdk import __version__ as sdk_version
from trafficrlhf_sdk.feedback.agreement import campaign_agreement
from trafficrlhf_sdk.feedback.errors import FeedbackError
from trafficrlhf_sdk.feedback.store import Annotator, FeedbackStore

from trafficrlhf_annotation_web.payload import item_base, item_payload

__all__ = ["LabelIn", "SkipIn", "create_app"]

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")


class LabelIn(BaseModel):
    """Body of a label: ``choice`` 1..N is the slot shown, 0 means "none realistic"."""

    model_config = ConfigDict(extra="forbid")

    choice: StrictInt = Field(..., description="Slot 1..N as shown, or 0 for 'none realistic'.")
    time_ms: StrictInt | None = Field(None, ge=0, description="Milliseconds the item was on screen.")


class SkipIn(BaseModel):
    """Body of a skip."""

    model_config = ConfigDict(extra="forbid")

    reason: str = Field(..., min_length=1, max_length=500, description="Why the item was skipped.")


class _ItemCache:
    """The permutation-free payload of recently served items (map image, tracks), keyed by item id."""

    def __init__(self, size: int = 256) -> None:
        self.size = size
        self._items: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._lock = Lock()

    def get(self, store: FeedbackStore, campaign: Any, item_id: int) -> dict[str, Any]:
        with self._lock:
            if item_id in self._items:
                self._items.move_to_end(item_id)
                return self._items[item_id]
        base = item_base(store.load_context(item_id, campaign))
        with self._lock:
            self._items[item_id] = base
            while len(self._items) > self.size:
                self._items.popitem(last=False)
        return base


def create_app(db_path: str, default_campaign: str | None = None, synchronous: str = "FULL") -> FastAPI:
    """The app serving ``db_path`` (which must exist); ``default_campaign`` is preselected in the page."""
    if not os.path.isfile(db_path):
        raise FileNotFoundError(f"feedback database {db_path!r} does not exist; create a campaign first.")
    store = FeedbackStore(db_path, synchronous=synchronous)  # type: ignore[arg-type]
    cache = _ItemCache()
    app = FastAPI(title="TrafficRLHF annotation", version=sdk_version, docs_url=None, redoc_url=None)
    app.state.store = store

    @app.exception_handler(FeedbackError)
    def _feedback_error(request: Request, exc: FeedbackError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.http_status == 401 else None
        return JSONResponse({"error": str(exc)}, status_code=exc.http_status, headers=headers)

    @app.exception_handler(RequestValidationError)
    def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            return JSONResponse({"error": "the request body is not valid JSON; send e.g. {\"choice\": 1}."},
                                status_code=400)
        problems = "; ".join(f"{'.'.join(str(p) for p in e.get('loc', ()) if p != 'body') or 'body'}: "
                             f"{e.get('msg')}" for e in errors)
        return JSONResponse({"error": f"invalid request: {problems}."}, status_code=422)

    def annotator(authorization: str | None = Header(None)) -> Annotator:
        token = None
        if authorization and authorization.lower().startswith("bearer "):
            token = authorization[7:].strip()
        return store.authenticate(token)

    def progress(who: Annotator, campaign: Any) -> dict[str, int]:
        return store.progress(who, campaign)

    # ------------------------------------------------------------------------------------------- pages
    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(os.path.join(STATIC, "index.html"), headers={"Cache-Control": "no-store"})

    @app.get("/agreement", include_in_schema=False)
    def agreement_page() -> FileResponse:
        return FileResponse(os.path.join(STATIC, "agreement.html"), headers={"Cache-Control": "no-store"})

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return {"ok": True, "version": sdk_version}

    # --------------------------------------------------------------------------------------------- api
    @app.get("/api/me")
    def me(who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaigns = [{"name": c.name, "model": c.model, "guidance": c.guidance, "num_candidates": c.num_candidates,
                      "progress": progress(who, c)} for c in store.campaigns()]
        return {"annotator": who.name, "campaigns": campaigns, "default_campaign": default_campaign}

    @app.get("/api/campaigns/{name}/next")
    def next_item(name: str, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        assignment = store.next_item(who, campaign)
        if assignment is None:
            return {"done": True, "progress": progress(who, campaign)}
        return item_payload(cache.get(store, campaign, assignment.context_id), assignment, progress(who, campaign))

    @app.get("/api/campaigns/{name}/items/{item_id}")
    def get_item(name: str, item_id: int, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        assignment = store.open_item(who, campaign, item_id)
        return item_payload(cache.get(store, campaign, item_id), assignment, progress(who, campaign))

    @app.post("/api/campaigns/{name}/items/{item_id}/label", status_code=201)
    def post_label(name: str, item_id: int, body: LabelIn, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        label = store.submit_label(who, campaign, item_id, body.choice, body.time_ms)
        return {"label": label.id, "item": item_id, "choice": label.slot, "progress": progress(who, campaign)}

    @app.put("/api/campaigns/{name}/items/{item_id}/label")
    def put_label(name: str, item_id: int, body: LabelIn, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        label = store.submit_label(who, campaign, item_id, body.choice, body.time_ms, revise=True)
        return {"label": label.id, "item": item_id, "choice": label.slot, "revision": label.revision,
                "progress": progress(who, campaign)}

    @app.post("/api/campaigns/{name}/items/{item_id}/skip", status_code=201)
    def post_skip(name: str, item_id: int, body: SkipIn, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        store.skip(who, campaign, item_id, body.reason)
        return {"item": item_id, "skipped": True, "progress": progress(who, campaign)}

    @app.get("/api/campaigns/{name}/history")
    def history(name: str, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        rows = [{"item": a.context_id, "position": a.position, "status": a.status, "answer": a.slot}
                for a in store.history(who, campaign)]
        return {"items": rows, "progress": progress(who, campaign)}

    @app.get("/api/campaigns/{name}/agreement")
    def agreement(name: str, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        return {"campaign": campaign.name, **store.counts(campaign), **campaign_agreement(store, campaign)}

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app
