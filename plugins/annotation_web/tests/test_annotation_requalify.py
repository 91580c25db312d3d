"""The team lead lets an annotator who missed a gold item take the qualification again; the pages' shared helpers
(``static/shared.js``: the sign-in token from ``?token=`` on both pages, the playback still to watch) run under
node."""

from __future__ import annotations

import json
import os
import shutil
import subprocess

import pytest

from trafficrlhf_sdk.feedback import FeedbackStore

SHARED_JS = os.path.join(os.path.dirname(__file__), "..", "trafficrlhf_annotation_web", "static", "shared.js")


def auth(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_a_failed_annotator_retakes_the_qualification(client, campaign_db) -> None:  # type: ignore[no-untyped-def]
    admin, bob = auth(campaign_db[1]["admin"]), auth(campaign_db[1]["bob"])
    client.post("/api/admin/campaigns/tiny/gold", json={"count": 1}, headers=admin)
    client.put("/api/admin/campaigns/tiny/settings", json={"qualification_gold": 1, "qualification_accuracy": 1.0},
               headers=admin)
    item = client.get("/api/campaigns/tiny/next", headers=bob).json()
    client.post(f"/api/campaigns/tiny/items/{item['item']}/label", json={"choice": "tie"}, headers=bob)  # wrong
    assert client.get("/api/campaigns/tiny/next", headers=bob).json().get("done")  # locked out
    stats = {a["annotator"]: a for a in client.get("/api/admin/campaigns/tiny", headers=admin).json()["annotators"]}
    assert stats["bob"]["status"] == "failed"

    reset = client.post("/api/admin/campaigns/tiny/annotators/bob/requalify", headers=admin)
    assert reset.status_code == 200, reset.text
    assert reset.json()["removed"]["labels"] == 1 and reset.json()["quality"]["status"] == "pending"
    again = client.get("/api/campaigns/tiny/next", headers=bob).json()
    assert again["item"] == item["item"]  # the gold item is served again
    assert client.post("/api/admin/campaigns/tiny/annotators/bob/requalify", headers=auth(campaign_db[1]["bob"])
                       ).status_code == 401
    assert client.post("/api/admin/campaigns/tiny/annotators/nobody/requalify", headers=admin).status_code == 404


def test_reset_keeps_regular_labels(campaign_db) -> None:  # type: ignore[no-untyped-def]
    store = FeedbackStore(campaign_db[0])
    campaign = store.campaign("tiny")
    alice = store.annotator("alice")
    assignment = store.next_item(alice, campaign)
    store.submit_label(alice, campaign, assignment.context_id, 1)
    assert store.reset_qualification("alice", campaign) == {"labels": 0, "skips": 0, "assignments": 0}
    assert store.counts(campaign)["labels"] == 1
    store.close()


def _node(script: str) -> object:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    out = subprocess.run([node, "-e", f"const s = require({json.dumps(os.path.abspath(SHARED_JS))});\n{script}"],
                         capture_output=True, text=True, check=True, timeout=30)
    return json.loads(out.stdout)


def test_the_note_shows_the_playback_still_needed_also_when_paused() -> None:
    result = _node("""
        const left = s.playbackLeft(1.0, 43, 0.1);  // 42 steps of 0.1 s, 1 s played
        console.log(JSON.stringify({left, done: s.playbackLeft(9, 43, 0.1), playing: s.watchNote(left, true),
                                    paused: s.watchNote(left, false)}));""")
    assert result["left"] == pytest.approx(3.2) and result["done"] == 0  # type: ignore[index]
    assert result["playing"].startswith("Watch 3.2 s more")  # type: ignore[index]
    assert "Paused with 3.2 s still to watch" in result["paused"] and "Space" in result["paused"]  # type: ignore[index]


def test_a_token_in_the_address_signs_in_and_leaves_the_address_bar() -> None:
    result = _node("""
        const store = {}, storage = {setItem: (k, v) => { store[k] = v; }, getItem: (k) => store[k] || null};
        let replaced = null;
        const hist = {replaceState: (a, b, url) => { replaced = url; }};
        const token = s.takeTokenFromUrl({search: "?token=abc&campaign=tiny", pathname: "/admin"}, storage,
                                         "trafficrlhf.admin", hist);
        const later = s.takeTokenFromUrl({search: "", pathname: "/admin"}, storage, "trafficrlhf.admin", hist);
        console.log(JSON.stringify({token, replaced, later, stored: store["trafficrlhf.admin"]}));""")
    assert result == {"token": "abc", "replaced": "/admin?campaign=tiny", "later": "abc", "stored": "abc"}


def test_both_pages_load_the_shared_helpers_before_their_own_script(client) -> None:  # type: ignore[no-untyped-def]
    for path, own in (("/", "/static/app.js"), ("/admin", "/static/admin.js")):
        html = client.get(path).text
        assert html.index("/static/shared.js") < html.index(own), path
    assert client.get("/static/shared.js").status_code == 200
