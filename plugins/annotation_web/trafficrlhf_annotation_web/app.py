"""The annotation app: a FastAPI application over one feedback database.

Every ``/api`` route needs ``Authorization: Bearer <token>``: an annotator token (``trafficrlhf feedback
annotator add``) or, under ``/api/admin``, an admin token (``trafficrlhf feedback admin NAME``). Requests with
a body are screened by :class:`~trafficrlhf_annotation_web.guard.RequestGuard` before the body is read (token
first, then size). Errors are JSON ``{"error": message}`` with these statuses:

- 400: a body that is not valid JSON, or a malformed ``Content-Length``;
- 401: missing, unknown or revoked token;
- 404: unknown campaign, item or annotator;
- 405: a body sent to a page outside ``/api`` (pages are read-only; refused before the body is read);
- 409: the item's state forbids the request: already labeled (or skipped), never opened, full
  (``labels_per_item``), released after an expired lease, or a label sent before the future played once;
- 413: a body over the size limit; 422: valid JSON of the wrong shape, a choice outside the range, an item
  id outside 0..2^63-1, a bad query parameter;
- 503: the database is busy or failing (retry; nothing was written); 507: the disk (or database) is full
  (nothing was written; acknowledged labels are safe).

A request that fails writes nothing: each write is one SQLite transaction in :class:`FeedbackStore`.
Routes are plain ``def`` functions, so FastAPI runs them in its thread pool; the store keeps one SQLite
connection per thread.
"""

from __future__ import annotations

import errno
import hashlib
import io
import logging
import os
import sqlite3
import tempfile
import zipfile
from collections import OrderedDict
from threading import Lock
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, Header, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, StrictBool, StrictInt
from starlette.exceptions import HTTPException as StarletteHTTPException

from trafficrlhf_sdk import __version__ as sdk_version
from trafficrlhf_sdk.errors import DataFormatError
from trafficrlhf_sdk.feedback.agreement import annotator_agreement, campaign_agreement
from trafficrlhf_sdk.feedback.errors import FeedbackError, InvalidChoiceError
from trafficrlhf_sdk.feedback.gold import add_gold_items
from trafficrlhf_sdk.feedback.preference import export_preferences
from trafficrlhf_sdk.feedback.records import TIE_SLOT
from trafficrlhf_sdk.feedback.settings import MAX_GUIDELINES_CHARS
from trafficrlhf_sdk.feedback.store import SQLITE_MAX_INT, Annotator, Campaign, FeedbackStore

from trafficrlhf_annotation_web.guard import DEFAULT_MAX_BODY_BYTES, RequestGuard, bearer_token, install_log_filter
from trafficrlhf_annotation_web.payload import item_base, item_payload, playback_seconds

__all__ = ["MAX_PLAYBACK_SPEED", "LabelIn", "SkipIn", "create_app"]

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
MAX_PLAYBACK_SPEED = 2.0  # the page's fastest speed: the least time a played-through future can take
PLAYBACK_TOLERANCE_S = 0.25
log = logging.getLogger(__name__)

ItemId = Annotated[int, Path(ge=0, le=SQLITE_MAX_INT, description="Item (context) id.")]
CampaignName = Annotated[str, Path(min_length=1, max_length=100, description="Campaign name.")]
AnnotatorName = Annotated[str, Path(min_length=1, max_length=100, description="Annotator name.")]


class LabelIn(BaseModel):
    """Body of a label: ``choice`` 1..N is the slot shown, 0 means "none realistic", ``"tie"`` "equally
    realistic" (when the campaign allows ties)."""

    model_config = ConfigDict(extra="forbid")

    choice: StrictInt | Literal["tie"] = Field(..., description="Slot 1..N as shown, 0 for 'none realistic', or "
                                                                 "'tie' for 'equally realistic'.")
    time_ms: StrictInt | None = Field(None, ge=0, le=SQLITE_MAX_INT, description="Milliseconds on the item.")


class SkipIn(BaseModel):
    """Body of a skip."""

    model_config = ConfigDict(extra="forbid")

    reason: str = Field(..., min_length=1, max_length=500, description="Why the item was skipped.")


class SettingsIn(BaseModel):
    """Body of a settings change (admin): only the fields given change."""

    model_config = ConfigDict(extra="forbid")

    playback_required: StrictBool | None = Field(None, description="Require the future to play once.")
    guidelines: str | None = Field(None, max_length=MAX_GUIDELINES_CHARS, description="Markdown guidelines.")
    gold_rate: float | None = Field(None, ge=0, le=0.5, description="Share of gold items after qualification.")
    qualification_gold: StrictInt | None = Field(None, ge=0, le=100, description="Gold items to qualify.")
    qualification_accuracy: float | None = Field(None, ge=0, le=1, description="Accuracy needed to qualify.")
    lease_seconds: float | None = Field(None, gt=0, le=86_400, description="Lease of an opened item (s).")
    allow_tie: StrictBool | None = Field(None, description="Offer 'equally realistic'.")


class AnnotatorIn(BaseModel):
    """Body of a new annotator (admin)."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(..., min_length=1, max_length=100, description="Annotator name, unique.")


class ActiveIn(BaseModel):
    """Body of an (de)activation (admin)."""

    model_config = ConfigDict(extra="forbid")

    active: StrictBool = Field(..., description="False revokes the token and releases the open items.")


class GoldIn(BaseModel):
    """Body of a gold-item request (admin)."""

    model_config = ConfigDict(extra="forbid")

    count: StrictInt = Field(..., ge=1, le=1000, description="Gold items to add, built from regular items.")
    seed: StrictInt = Field(0, ge=0, le=SQLITE_MAX_INT, description="Seed of the broken futures and answers.")


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


def _storage_error(exc: BaseException) -> JSONResponse:
    """507 for a full disk or database, 503 (retry later) for a busy or failing one; nothing was written."""
    text = str(exc).lower()
    if (isinstance(exc, OSError) and exc.errno == errno.ENOSPC) or "full" in text:
        return JSONResponse({"error": "the server's disk (or database) is full; nothing was written and every "
                                      "label saved so far is safe. Tell the campaign owner, then retry."},
                            status_code=507)
    log.warning("storage error: %s", exc)
    return JSONResponse({"error": f"the database is not available right now ({exc}); nothing was written. "
                                  "Retry in a few seconds."}, status_code=503, headers={"Retry-After": "5"})


def create_app(db_path: str, default_campaign: str | None = None, synchronous: str = "FULL",
               max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> FastAPI:
    """The app serving ``db_path`` (which must exist); ``default_campaign`` is preselected in the page;
    ``max_body_bytes`` caps request bodies (checked before they are read)."""
    if not os.path.isfile(db_path):
        raise FileNotFoundError(f"feedback database {db_path!r} does not exist; create a campaign first.")
    store = FeedbackStore(db_path, synchronous=synchronous)  # type: ignore[arg-type]
    cache = _ItemCache()
    app = FastAPI(title="TrafficRLHF annotation", version=sdk_version, docs_url=None, redoc_url=None)
    app.state.store = store
    app.add_middleware(RequestGuard, store=store, max_body_bytes=max_body_bytes)
    install_log_filter()

    @app.exception_handler(FeedbackError)
    def _feedback_error(request: Request, exc: FeedbackError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if exc.http_status == 401 else None
        return JSONResponse({"error": str(exc)}, status_code=exc.http_status, headers=headers)

    @app.exception_handler(sqlite3.Error)
    def _sqlite_error(request: Request, exc: sqlite3.Error) -> JSONResponse:
        return _storage_error(exc)

    @app.exception_handler(OSError)
    def _os_error(request: Request, exc: OSError) -> JSONResponse:
        return _storage_error(exc)

    @app.exception_handler(DataFormatError)
    def _data_error(request: Request, exc: DataFormatError) -> JSONResponse:
        return JSONResponse({"error": str(exc)}, status_code=409)

    @app.exception_handler(StarletteHTTPException)
    def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        return JSONResponse({"error": str(exc.detail)}, status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = exc.errors()
        if any(e.get("type") == "json_invalid" for e in errors):
            return JSONResponse({"error": "the request body is not valid JSON; send e.g. {\"choice\": 1}."},
                                status_code=400)
        problems = "; ".join(f"{'.'.join(str(p) for p in e.get('loc', ()) if p != 'body') or 'body'}: "
                             f"{e.get('msg')} (got {str(e.get('input'))[:60]!r})" for e in errors)
        return JSONResponse({"error": f"invalid request: {problems}."}, status_code=422)

    def annotator(authorization: str | None = Header(None)) -> Annotator:
        return store.authenticate(bearer_token(authorization))

    def admin(authorization: str | None = Header(None)) -> str:
        return store.authenticate_admin(bearer_token(authorization))

    def progress(who: Annotator, campaign: Any) -> dict[str, int]:
        return store.progress(who, campaign)

    def guidelines_version(campaign: Campaign) -> str | None:
        text = campaign.settings.guidelines
        return hashlib.sha256(text.encode()).hexdigest()[:16] if text else None

    def campaign_brief(campaign: Campaign) -> dict[str, Any]:
        s = campaign.settings
        return {"name": campaign.name, "num_candidates": campaign.num_candidates,
                "playback_required": s.playback_required, "allow_tie": s.allow_tie,
                "guidelines_version": guidelines_version(campaign)}

    # ------------------------------------------------------------------------------------------- pages
    def page(name: str) -> FileResponse:
        return FileResponse(os.path.join(STATIC, name), headers={"Cache-Control": "no-store"})

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return page("index.html")

    @app.get("/agreement", include_in_schema=False)
    def agreement_page() -> FileResponse:
        return page("agreement.html")

    @app.get("/admin", include_in_schema=False)
    def admin_page() -> FileResponse:
        return page("admin.html")

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return {"ok": True, "version": sdk_version}

    # --------------------------------------------------------------------------------- annotator api
    @app.get("/api/me")
    def me(who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaigns = [{**campaign_brief(c), "model": c.model, "guidance": c.guidance, "progress": progress(who, c)}
                     for c in store.campaigns()]
        return {"annotator": who.name, "campaigns": campaigns, "default_campaign": default_campaign}

    @app.get("/api/campaigns/{name}/guidelines")
    def guidelines(name: CampaignName, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        return {"campaign": campaign.name, "markdown": campaign.settings.guidelines or "",
                "version": guidelines_version(campaign)}

    def with_settings(payload: dict[str, Any], campaign: Campaign) -> dict[str, Any]:
        s = campaign.settings
        seconds = playback_seconds(payload)
        payload.update({"playback_required": s.playback_required, "allow_tie": s.allow_tie,
                        "playback_s": seconds, "guidelines_version": guidelines_version(campaign)})
        return payload

    @app.get("/api/campaigns/{name}/next")
    def next_item(name: CampaignName, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        assignment = store.next_item(who, campaign)
        if assignment is None:
            quality = store.quality(who, campaign)
            reason = {"failed": "qualification_failed", "pending": "qualification_unavailable"}.get(
                quality["status"], "finished")
            return {"done": True, "reason": reason, "quality": quality, "progress": progress(who, campaign)}
        base = cache.get(store, campaign, assignment.context_id)
        return with_settings(item_payload(base, assignment, progress(who, campaign)), campaign)

    @app.get("/api/campaigns/{name}/items/{item_id}")
    def get_item(name: CampaignName, item_id: ItemId, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        assignment = store.open_item(who, campaign, item_id)
        return with_settings(item_payload(cache.get(store, campaign, item_id), assignment,
                                          progress(who, campaign)), campaign)

    def label(name: str, item_id: int, body: LabelIn, who: Annotator, revise: bool) -> dict[str, Any]:
        campaign = store.campaign(name)
        tie_allowed = campaign.settings.allow_tie
        if (body.choice == "tie" and not tie_allowed) or (
                isinstance(body.choice, int) and not 0 <= body.choice <= campaign.num_candidates):
            # exactly what this campaign accepts over HTTP (the store's -1 for a tie is not one of them)
            tie = ', or "tie" (equally realistic)' if tie_allowed else " (this campaign offers no tie)"
            raise InvalidChoiceError(f"`choice` must be an integer from 0 (none realistic) to "
                                     f"{campaign.num_candidates} (the slot shown){tie}; got {body.choice!r}.")
        slot = TIE_SLOT if body.choice == "tie" else int(body.choice)
        min_view = None
        if campaign.settings.playback_required and not revise:
            seconds = playback_seconds(cache.get(store, campaign, item_id))
            min_view = max(0.0, seconds / MAX_PLAYBACK_SPEED - PLAYBACK_TOLERANCE_S)
        stored = store.submit_label(who, campaign, item_id, slot, body.time_ms, revise=revise, min_view_s=min_view)
        choice: int | str = "tie" if stored.tie else stored.slot
        return {"label": stored.id, "item": item_id, "choice": choice, "revision": stored.revision,
                "progress": progress(who, campaign)}

    @app.post("/api/campaigns/{name}/items/{item_id}/label", status_code=201)
    def post_label(name: CampaignName, item_id: ItemId, body: LabelIn,
                   who: Annotator = Depends(annotator)) -> dict[str, Any]:
        return label(name, item_id, body, who, revise=False)

    @app.put("/api/campaigns/{name}/items/{item_id}/label")
    def put_label(name: CampaignName, item_id: ItemId, body: LabelIn,
                  who: Annotator = Depends(annotator)) -> dict[str, Any]:
        return label(name, item_id, body, who, revise=True)

    @app.post("/api/campaigns/{name}/items/{item_id}/skip", status_code=201)
    def post_skip(name: CampaignName, item_id: ItemId, body: SkipIn,
                  who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        store.skip(who, campaign, item_id, body.reason)
        return {"item": item_id, "skipped": True, "progress": progress(who, campaign)}

    @app.get("/api/campaigns/{name}/history")
    def history(name: CampaignName, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        campaign = store.campaign(name)
        rows = [{"item": a.context_id, "position": a.position, "status": a.status,
                 "answer": "tie" if a.slot == TIE_SLOT else a.slot} for a in store.history(who, campaign)]
        return {"items": rows, "progress": progress(who, campaign)}

    @app.get("/api/campaigns/{name}/agreement")
    def agreement(name: CampaignName, who: Annotator = Depends(annotator)) -> dict[str, Any]:
        """The annotator's own figures only: agreement with the others' majority and gold accuracy."""
        campaign = store.campaign(name)
        return {"campaign": campaign.name, **annotator_agreement(store, campaign, who.name),
                "quality": store.quality(who, campaign), "progress": progress(who, campaign)}

    # ------------------------------------------------------------------------------------- admin api
    def annotator_rows() -> list[dict[str, Any]]:
        return [{"name": a.name, "active": a.active, "created_at": a.created_at} for a in store.annotators()]

    @app.get("/api/admin/overview")
    def admin_overview(owner: str = Depends(admin)) -> dict[str, Any]:
        campaigns = []
        for c in store.campaigns():
            counts = store.counts(c)
            campaigns.append({"name": c.name, "model": c.model, "models": list(c.models), "guidance": c.guidance,
                              "num_candidates": c.num_candidates, "labels_per_item": c.labels_per_item, **counts})
        return {"admin": owner, "campaigns": campaigns, "annotators": annotator_rows(),
                "default_campaign": default_campaign}

    @app.get("/api/admin/campaigns/{name}")
    def admin_campaign(name: CampaignName, owner: str = Depends(admin)) -> dict[str, Any]:
        campaign = store.campaign(name)
        return {"name": campaign.name, "model": campaign.model, "models": list(campaign.models),
                "guidance": campaign.guidance, "num_candidates": campaign.num_candidates,
                "labels_per_item": campaign.labels_per_item, "settings": campaign.settings.model_dump(),
                "counts": store.counts(campaign), "annotators": store.annotator_stats(campaign),
                "agreement": campaign_agreement(store, campaign)}

    @app.put("/api/admin/campaigns/{name}/settings")
    def admin_settings(name: CampaignName, body: SettingsIn, owner: str = Depends(admin)) -> dict[str, Any]:
        changes = body.model_dump(exclude_none=True)
        if "guidelines" in changes and not changes["guidelines"].strip():
            changes["guidelines"] = None
        elif "guidelines" in body.model_fields_set and body.guidelines is None:
            changes["guidelines"] = None
        campaign = store.update_settings(name, **changes)
        return {"name": campaign.name, "settings": campaign.settings.model_dump()}

    @app.post("/api/admin/campaigns/{name}/gold", status_code=201)
    def admin_gold(name: CampaignName, body: GoldIn, owner: str = Depends(admin)) -> dict[str, Any]:
        campaign = store.campaign(name)
        added = add_gold_items(store, campaign, body.count, body.seed)
        return {"added": added, "counts": store.counts(campaign)}

    @app.get("/api/admin/campaigns/{name}/export")
    def admin_export(name: CampaignName, owner: str = Depends(admin),
                     val_fraction: Annotated[float, Query(ge=0, lt=1)] = 0.2,
                     seed: Annotated[int, Query(ge=0, le=SQLITE_MAX_INT)] = 0,
                     ties: Literal["drop", "soft"] = "drop",
                     only: Literal["all", "human", "synthetic"] = "all") -> Response:
        """The campaign's preference dataset as a zip of ``preferences.safetensors`` and ``metadata.json``."""
        campaign = store.campaign(name)
        sources = ("human", "synthetic") if only == "all" else (only,)
        dataset = export_preferences(store, campaign, val_fraction=val_fraction, seed=seed, sources=sources,
                                     ties=ties)
        buffer = io.BytesIO()
        with tempfile.TemporaryDirectory() as tmp:
            dataset.save(tmp)
            with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
                for file in sorted(os.listdir(tmp)):
                    archive.write(os.path.join(tmp, file), f"{campaign.name}/{file}")
        filename = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in campaign.name)
        return Response(buffer.getvalue(), media_type="application/zip", headers={
            "Content-Disposition": f'attachment; filename="{filename}-preferences.zip"',
            "X-Pairs": str(len(dataset)), "X-Choices": str(dataset.num_choices)})

    @app.post("/api/admin/campaigns/{name}/annotators/{annotator_name}/requalify")
    def admin_requalify(name: CampaignName, annotator_name: AnnotatorName,
                        owner: str = Depends(admin)) -> dict[str, Any]:
        """Let an annotator take the campaign's qualification again (their gold answers there are removed)."""
        campaign = store.campaign(name)
        removed = store.reset_qualification(annotator_name, campaign)
        return {"annotator": annotator_name, "removed": removed,
                "quality": store.quality(store.annotator(annotator_name), campaign)}

    @app.get("/api/admin/annotators")
    def admin_annotators(owner: str = Depends(admin)) -> dict[str, Any]:
        return {"annotators": annotator_rows()}

    @app.post("/api/admin/annotators", status_code=201)
    def admin_add_annotator(body: AnnotatorIn, owner: str = Depends(admin)) -> dict[str, Any]:
        who, token = store.add_annotator(body.name.strip())
        return {"name": who.name, "token": token}

    @app.post("/api/admin/annotators/{name}/token")
    def admin_rotate(name: AnnotatorName, owner: str = Depends(admin)) -> dict[str, Any]:
        return {"name": name, "token": store.new_token(name)}

    @app.put("/api/admin/annotators/{name}/active")
    def admin_active(name: AnnotatorName, body: ActiveIn, owner: str = Depends(admin)) -> dict[str, Any]:
        who = store.set_active(name, body.active)
        return {"name": who.name, "active": who.active}

    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    return app
