"""API of the annotation app (in-process TestClient): auth, items, labels, skips, revisions, bad input."""

from __future__ import annotations

import sqlite3

import pytest

from trafficrlhf_sdk.plugins import registry


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def label_rows(db: str) -> list[tuple]:  # type: ignore[type-arg]
    return sqlite3.connect(db).execute("SELECT context_id, slot, candidate, permutation FROM labels").fetchall()


def test_tokens_are_required(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    for headers in ({}, auth("wrong-token"), {"Authorization": "Basic abc"}, auth("")):
        response = client.get("/api/campaigns/tiny/next", headers=headers)
        assert response.status_code == 401 and "token" in response.json()["error"]
        assert response.headers["WWW-Authenticate"] == "Bearer"
    response = client.post("/api/campaigns/tiny/items/1/label", json={"choice": 1}, headers=auth("nope"))
    assert response.status_code == 401 and label_rows(campaign_db[0]) == []
    assert client.get("/healthz").status_code == 200  # the only open route besides the static pages


def test_next_item_payload_and_resume(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    token = campaign_db[1]["alice"]
    me = client.get("/api/me", headers=auth(token)).json()
    assert me["annotator"] == "alice" and me["campaigns"][0]["progress"]["total"] == 4
    item = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    assert item["num_candidates"] == 5 and [c["slot"] for c in item["candidates"]] == [1, 2, 3, 4, 5]
    assert item["map"].startswith("data:image/png;base64,") and item["status"] == "open"
    assert item["history_steps"] == 11 and item["future_steps"] == 30
    assert len(item["agents"]) == 3 and len(item["candidates"][0]["x"][0]) == 30
    assert "logged" not in str(item.keys()) and "permutation" not in item  # the log and the order stay hidden
    again = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    assert again["item"] == item["item"] and again["candidates"] == item["candidates"]  # resume after reload
    other = client.get(f"/api/campaigns/tiny/items/{item['item']}", headers=auth(campaign_db[1]["bob"])).json()
    strip = lambda cands: sorted(str({k: v for k, v in c.items() if k != "slot"}) for c in cands)  # noqa: E731
    assert strip(other["candidates"]) == strip(item["candidates"])  # the same futures, in bob's own order


def test_label_is_stored_through_the_permutation(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    token = campaign_db[1]["alice"]
    item = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    response = client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": 3, "time_ms": 4200},
                           headers=auth(token))
    assert response.status_code == 201 and response.json()["progress"]["done"] == 1
    [(context_id, slot, candidate, permutation)] = label_rows(campaign_db[0])
    assert context_id == item["item"] and slot == 3 and candidate == eval(permutation)[2]
    duplicate = client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": 1}, headers=auth(token))
    assert duplicate.status_code == 409 and "already labeled" in duplicate.json()["error"]
    assert len(label_rows(campaign_db[0])) == 1
    revised = client.put(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": 0}, headers=auth(token))
    assert revised.status_code == 200 and revised.json()["revision"] == 1
    assert label_rows(campaign_db[0])[0][1:3] == (0, None)
    history = client.get("/api/campaigns/tiny/history", headers=auth(token)).json()
    assert history["items"] == [{"item": item["item"], "position": 1, "status": "labeled", "answer": 0}]
    review = client.get(f"/api/campaigns/tiny/items/{item['item']}", headers=auth(token)).json()
    assert review["status"] == "labeled" and review["answer"] == 0


@pytest.mark.parametrize(("body", "status", "fragment"), [
    ('{"choice": 1', 400, "not valid JSON"),
    ("[]", 422, "invalid request"),
    ('{"choice": "1"}', 422, "choice"),
    ('{"choice": 1.5}', 422, "choice"),
    ('{"choice": 6}', 422, "from 0 (none realistic) to 5"),
    ('{"choice": -1}', 422, "from 0"),
    ('{"choice": 1, "extra": true}', 422, "extra"),
    ('{"time_ms": 5}', 422, "choice"),
])
def test_bad_bodies_write_nothing(client, campaign_db, body, status, fragment) -> None:  # type: ignore[no-untyped-def]
    token = campaign_db[1]["alice"]
    item = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    response = client.post(f"/api/campaigns/tiny/items/{item['item']}/label", content=body,
                           headers={**auth(token), "Content-Type": "application/json"})
    assert response.status_code == status and fragment in response.json()["error"]
    assert label_rows(campaign_db[0]) == []


def test_unknown_and_unopened_items(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    token = campaign_db[1]["alice"]
    assert client.get("/api/campaigns/tiny/items/999", headers=auth(token)).status_code == 404
    assert client.get("/api/campaigns/nope/next", headers=auth(token)).status_code == 404
    response = client.post("/api/campaigns/tiny/items/999/label", json={"choice": 1}, headers=auth(token))
    assert response.status_code == 404 and "no item 999" in response.json()["error"]
    response = client.post("/api/campaigns/tiny/items/2/label", json={"choice": 1}, headers=auth(token))
    assert response.status_code == 409 and "never opened" in response.json()["error"]
    assert client.get("/api/campaigns/tiny/items/abc", headers=auth(token)).status_code == 422
    assert label_rows(campaign_db[0]) == []


def test_skip_with_reason(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    token = campaign_db[1]["bob"]
    item = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    url = f"/api/campaigns/tiny/items/{item['item']}/skip"
    assert client.post(url, json={"reason": ""}, headers=auth(token)).status_code == 422
    assert client.post(url, json={"reason": "can't tell"}, headers=auth(token)).status_code == 201
    assert client.post(url, json={"reason": "again"}, headers=auth(token)).status_code == 409
    nxt = client.get("/api/campaigns/tiny/next", headers=auth(token)).json()
    assert nxt["item"] != item["item"] and nxt["progress"] == {"labeled": 0, "skipped": 1, "done": 1, "total": 4}
    back = client.get(f"/api/campaigns/tiny/items/{item['item']}", headers=auth(token)).json()
    assert back["status"] == "skipped" and back["skip_reason"] == "can't tell"


def test_agreement_and_done(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    for name in ("alice", "bob"):
        token = campaign_db[1][name]
        while not (item := client.get("/api/campaigns/tiny/next", headers=auth(token)).json()).get("done"):
            client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": 0}, headers=auth(token))
        assert item["progress"]["done"] == 4
    own = client.get("/api/campaigns/tiny/agreement", headers=auth(campaign_db[1]["alice"])).json()
    assert own["annotator"] == {"annotator": "alice", "labels": 4, "shared": 4, "agree_with_majority": 1.0}
    assert "bob" not in str(own) and "pairs" not in own  # annotators see only their own figures
    assert client.get("/api/admin/campaigns/tiny", headers=auth(campaign_db[1]["alice"])).status_code == 401
    report = client.get("/api/admin/campaigns/tiny", headers=auth(campaign_db[1]["admin"])).json()["agreement"]
    assert report["items_multi"] == 4 and report["pairwise_agreement"] == 1.0
    assert report["fleiss_kappa"] is None  # every label in one category: kappa undefined
    assert report["pairs"] == [{"a": "alice", "b": "bob", "shared": 4, "agreement": 1.0}]


def test_pages_and_plugin_registration(client) -> None:  # type: ignore[no-untyped-def]
    page = client.get("/")
    assert page.status_code == 200 and '<script src="/static/app.js">' in page.text
    assert client.get("/static/app.js").status_code == 200 and client.get("/agreement").status_code == 200
    assert "web" in registry("annotation_frontends")
    from trafficrlhf_sdk.cli import get_cli

    assert "serve" in get_cli().commands["feedback"].commands  # type: ignore[attr-defined]
