"""The admin API, campaign settings as the page sees them, and request hygiene (in-process TestClient)."""

from __future__ import annotations

import io
import json
import sqlite3
import time
import zipfile

import pytest

from trafficrlhf_sdk.feedback import FeedbackStore


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def rows(db: str, sql: str) -> list[tuple]:  # type: ignore[type-arg]
    conn = sqlite3.connect(db)
    try:
        return conn.execute(sql).fetchall()
    finally:
        conn.close()


def label_all(client, token: str, choice: object = 1) -> int:  # type: ignore[no-untyped-def]
    done = 0
    while not (item := client.get("/api/campaigns/tiny/next", headers=auth(token)).json()).get("done"):
        response = client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": choice},
                               headers=auth(token))
        assert response.status_code == 201, response.text
        done += 1
    return done


def test_admin_and_annotator_tokens_do_not_mix(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    tokens = campaign_db[1]
    for path in ("/api/admin/overview", "/api/admin/campaigns/tiny", "/api/admin/annotators"):
        assert client.get(path, headers=auth(tokens["alice"])).status_code == 401
        assert client.get(path).status_code == 401
    assert client.get("/api/me", headers=auth(tokens["admin"])).status_code == 401
    overview = client.get("/api/admin/overview", headers=auth(tokens["admin"])).json()
    assert overview["admin"] == "owner" and [c["name"] for c in overview["campaigns"]] == ["tiny"]
    assert {a["name"] for a in overview["annotators"]} == {"alice", "bob"}


def test_admin_manages_annotators(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    admin = auth(campaign_db[1]["admin"])
    created = client.post("/api/admin/annotators", json={"name": "carol"}, headers=admin)
    assert created.status_code == 201
    assert client.get("/api/me", headers=auth(created.json()["token"])).status_code == 200
    assert client.post("/api/admin/annotators", json={"name": "carol"}, headers=admin).status_code == 409
    assert client.post("/api/admin/annotators", json={"name": ""}, headers=admin).status_code == 422
    rotated = client.post("/api/admin/annotators/carol/token", headers=admin).json()["token"]
    assert client.get("/api/me", headers=auth(created.json()["token"])).status_code == 401
    assert client.get("/api/me", headers=auth(rotated)).status_code == 200
    off = client.put("/api/admin/annotators/carol/active", json={"active": False}, headers=admin)
    assert off.json() == {"name": "carol", "active": False}
    assert client.get("/api/me", headers=auth(rotated)).status_code == 401
    assert client.put("/api/admin/annotators/carol/active", json={"active": True}, headers=admin).status_code == 200
    assert client.get("/api/me", headers=auth(rotated)).status_code == 200
    assert client.post("/api/admin/annotators/nobody/token", headers=admin).status_code == 404


def test_settings_guidelines_and_progress(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    admin, alice = auth(campaign_db[1]["admin"]), auth(campaign_db[1]["alice"])
    me = client.get("/api/me", headers=alice).json()["campaigns"][0]
    assert me["guidelines_version"] is None and me["allow_tie"] is True
    text = "# Judge realism\n\n- blue cars are driven by the model\n"
    response = client.put("/api/admin/campaigns/tiny/settings", json={"guidelines": text, "gold_rate": 0.2},
                          headers=admin)
    assert response.status_code == 200 and response.json()["settings"]["gold_rate"] == 0.2
    me = client.get("/api/me", headers=alice).json()["campaigns"][0]
    guide = client.get("/api/campaigns/tiny/guidelines", headers=alice).json()
    assert guide["markdown"] == text and guide["version"] == me["guidelines_version"] is not None
    bad = client.put("/api/admin/campaigns/tiny/settings", json={"gold_rate": 0.9}, headers=admin)
    assert bad.status_code == 422 and "gold_rate" in bad.json()["error"]
    assert client.put("/api/admin/campaigns/tiny/settings", json={"colour": 1}, headers=admin).status_code == 422
    label_all(client, campaign_db[1]["alice"])
    detail = client.get("/api/admin/campaigns/tiny", headers=admin).json()
    assert detail["counts"]["labels"] == 4 and detail["settings"]["guidelines"] == text
    [alice_row] = [a for a in detail["annotators"] if a["annotator"] == "alice"]
    assert alice_row["labels"] == 4 and alice_row["status"] == "none"


def test_gold_items_and_export_download(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    admin = auth(campaign_db[1]["admin"])
    added = client.post("/api/admin/campaigns/tiny/gold", json={"count": 2}, headers=admin)
    assert added.status_code == 201 and added.json()["counts"]["gold_items"] == 2
    assert client.post("/api/admin/campaigns/tiny/gold", json={"count": 9}, headers=admin).status_code == 422
    client.put("/api/admin/campaigns/tiny/settings", json={"qualification_gold": 2, "qualification_accuracy": 0.0},
               headers=admin)
    assert label_all(client, campaign_db[1]["alice"]) == 6  # 2 gold (qualification) + 4 regular
    item = client.get("/api/campaigns/tiny/next", headers=auth(campaign_db[1]["bob"])).json()
    client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": "tie"},
                headers=auth(campaign_db[1]["bob"]))
    response = client.get("/api/admin/campaigns/tiny/export?val_fraction=0&ties=soft", headers=admin)
    assert response.status_code == 200 and response.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        assert sorted(archive.namelist()) == ["tiny/metadata.json", "tiny/preferences.safetensors"]
        meta = json.loads(archive.read("tiny/metadata.json"))
    # alice: 4 choices x 4 pairs; bob's first item was gold (a tie there is a wrong gold answer, not exported)
    assert meta["num_pairs"] == 16 and meta["annotators"] == ["alice"] and response.headers["X-Choices"] == "4"
    assert meta["unqualified_left_out"] == ["bob"]
    assert client.get("/api/admin/campaigns/tiny/export?ties=maybe", headers=admin).status_code == 422
    assert client.get("/api/admin/campaigns/nope/export", headers=admin).status_code == 404


def test_playback_must_finish_before_a_choice(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    FeedbackStore(campaign_db[0]).update_settings("tiny", playback_required=True)
    alice = auth(campaign_db[1]["alice"])
    item = client.get("/api/campaigns/tiny/next", headers=alice).json()
    assert item["playback_required"] is True and item["playback_s"] == pytest.approx(4.0)
    url = f"/api/campaigns/tiny/items/{item['item']}/label"
    early = client.post(url, json={"choice": 1}, headers=alice)
    assert early.status_code == 409 and "watch the future" in early.json()["error"]
    assert rows(campaign_db[0], "SELECT * FROM labels") == []
    time.sleep(item["playback_s"] / 2)  # the fastest play-through (2x speed)
    assert client.post(url, json={"choice": 1}, headers=alice).status_code == 201
    assert client.put(url, json={"choice": "tie"}, headers=alice).json()["choice"] == "tie"  # revisions need no wait


def test_ties_and_bad_choices(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    alice = auth(campaign_db[1]["alice"])
    item = client.get("/api/campaigns/tiny/next", headers=alice).json()
    url = f"/api/campaigns/tiny/items/{item['item']}/label"
    for body in ({"choice": -1}, {"choice": "equal"}, {"choice": 2**70}):
        response = client.post(url, json=body, headers=alice)
        assert response.status_code == 422, (body, response.text)
    response = client.post(url, json={"choice": "tie", "time_ms": 2**63}, headers=alice)
    assert response.status_code == 422 and "time_ms" in response.json()["error"]
    assert client.post(url, json={"choice": "tie"}, headers=alice).json()["choice"] == "tie"
    assert rows(campaign_db[0], "SELECT slot, candidate FROM labels") == [(-1, None)]
    history = client.get("/api/campaigns/tiny/history", headers=alice).json()["items"]
    assert history[0]["answer"] == "tie"
    FeedbackStore(campaign_db[0]).update_settings("tiny", allow_tie=False)
    nxt = client.get("/api/campaigns/tiny/next", headers=alice).json()
    refused = client.post(f"/api/campaigns/tiny/items/{nxt['item']}/label", json={"choice": "tie"}, headers=alice)
    assert refused.status_code == 422 and nxt["allow_tie"] is False


@pytest.mark.parametrize("item_id", [2**63, 2**63 + 5, 10**30, -1])
def test_out_of_range_ids_are_4xx(client, campaign_db, item_id) -> None:  # type: ignore[no-untyped-def]
    alice = auth(campaign_db[1]["alice"])
    for method, path, body in (("GET", "", None), ("POST", "/label", {"choice": 1}), ("PUT", "/label", {"choice": 1}),
                               ("POST", "/skip", {"reason": "x"})):
        response = client.request(method, f"/api/campaigns/tiny/items/{item_id}{path}", json=body, headers=alice)
        assert response.status_code == 422 and "item_id" in response.json()["error"], (method, path, response.text)
    assert client.get(f"/api/campaigns/tiny/items/{2**63 - 1}", headers=alice).status_code == 404


def test_token_then_size_before_the_body(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    big = b"x" * (200 * 1024)
    url = "/api/campaigns/tiny/items/1/label"
    response = client.post(url, content=big, headers={"Content-Type": "application/json"})
    assert response.status_code == 401 and "token" in response.json()["error"]
    response = client.post(url, content=big, headers={**auth(campaign_db[1]["alice"]),
                                                      "Content-Type": "application/json"})
    assert response.status_code == 413 and "limit" in response.json()["error"]
    response = client.post("/api/admin/annotators", content=big, headers=auth(campaign_db[1]["alice"]))
    assert response.status_code == 401  # an annotator token is no admin token, whatever the body

    def chunks():  # no Content-Length: counted as it arrives
        for _ in range(40):
            yield b"y" * 8192

    response = client.post(url, content=chunks(), headers={**auth(campaign_db[1]["alice"]),
                                                           "Content-Type": "application/json"})
    assert response.status_code == 413
    assert rows(campaign_db[0], "SELECT * FROM labels") == []


def test_full_disk_is_507_and_loses_nothing(campaign_db) -> None:  # type: ignore[no-untyped-def]
    from fastapi.testclient import TestClient

    from trafficrlhf_annotation_web.app import create_app

    db = campaign_db[0]
    store = FeedbackStore(db)
    tokens = [store.add_annotator(f"extra{i}")[1] for i in range(40)]
    store.close()
    conn = sqlite3.connect(db)
    conn.execute("PRAGMA wal_checkpoint(TRUNCATE)")
    conn.execute("VACUUM")
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    conn.close()
    app = create_app(db)
    limit = {"pages": pages}
    opened = app.state.store._conn

    def limited():  # type: ignore[no-untyped-def]  # SQLite's own "database or disk is full" at this size
        connection = opened()
        connection.execute(f"PRAGMA max_page_count = {limit['pages']}")
        return connection

    app.state.store._conn = limited
    acked, failed = [], None
    reason = "r" * 480
    with TestClient(app) as client:
        for token in tokens:
            item = client.get("/api/campaigns/tiny/next", headers=auth(token))
            if item.status_code != 200:
                failed = ("next", token, item)
                break
            response = client.post(f"/api/campaigns/tiny/items/{item.json()['item']}/skip", json={"reason": reason},
                                   headers=auth(token))
            if response.status_code != 201:
                failed = ("skip", token, response)
                break
            acked.append((token, item.json()["item"]))
        assert failed is not None, "the database never filled up"
        assert failed[2].status_code == 507 and "full" in failed[2].json()["error"], failed[2].text
        stored = rows(db, "SELECT COUNT(*) FROM skips")[0][0]
        assert stored == len(acked)  # every acknowledged write is there, the refused one is not
        limit["pages"] = pages * 10  # space again: the same request now goes through
        retry = client.get("/api/campaigns/tiny/next", headers=auth(failed[1])).json()
        assert client.post(f"/api/campaigns/tiny/items/{retry['item']}/skip", json={"reason": reason},
                           headers=auth(failed[1])).status_code == 201
    assert rows(db, "PRAGMA integrity_check") == [("ok",)]
