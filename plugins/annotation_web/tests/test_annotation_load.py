"""Load and crash test against the real server on loopback (127.0.0.1, random port; bounded loops).

Phase 1: 20 concurrent annotators x 50 submissions: every acknowledged label is in the database exactly once.
Phase 2: the same load on a second campaign, the server is killed with SIGKILL mid-run, restarted, and every
label acknowledged before the kill is found; the annotators then finish and the totals are exact again.
Figures are printed (run with ``-s``) and written to ``$TRAFFICRLHF_LOAD_REPORT`` when set.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time

import httpx
import pytest

from trafficrlhf_sdk.feedback import FeedbackStore
from trafficrlhf_sdk.testing.feedback import make_tiny_campaign

from trafficrlhf_annotation_web.testing import Server

ANNOTATORS = 20
ITEMS = 50
MAX_ROUNDS = ITEMS + 10  # bound on each client's loop


class Client(threading.Thread):
    """One annotator: GET next, POST a label, until done or the server goes away."""

    def __init__(self, url: str, token: str, name: str, campaign: str, acks: list[tuple[str, int, int]],
                 lock: threading.Lock, deadline: float) -> None:
        super().__init__(daemon=True)
        self.url, self.token, self.name, self.campaign = url, token, name, campaign
        self.acks, self.lock, self.deadline = acks, lock, deadline
        self.requests = 0
        self.interrupted = False
        self.errors: list[str] = []

    def run(self) -> None:
        headers = {"Authorization": f"Bearer {self.token}"}
        base = f"{self.url}/api/campaigns/{self.campaign}"
        with httpx.Client(timeout=30.0, headers=headers) as http:
            for _ in range(MAX_ROUNDS):
                if time.monotonic() > self.deadline:
                    self.errors.append("deadline")
                    return
                try:
                    item = http.get(f"{base}/next")
                    self.requests += 1
                    if item.status_code != 200:
                        self.errors.append(f"next {item.status_code} {item.text[:200]}")
                        return
                    data = item.json()
                    if data.get("done"):
                        return
                    slot = 1 + data["item"] % 5
                    response = http.post(f"{base}/items/{data['item']}/label", json={"choice": slot})
                    self.requests += 1
                except httpx.TransportError:
                    self.interrupted = True  # the server went away: stop; unacknowledged work is not counted
                    return
                if response.status_code == 201:
                    with self.lock:
                        self.acks.append((self.name, data["item"], slot))
                else:
                    self.errors.append(f"label {response.status_code} {response.text[:200]}")
                    return


def run_clients(url: str, tokens: dict[str, str], campaign: str, acks: list[tuple[str, int, int]],
                lock: threading.Lock, timeout_s: float = 40.0) -> list[Client]:
    deadline = time.monotonic() + timeout_s
    clients = [Client(url, token, name, campaign, acks, lock, deadline) for name, token in tokens.items()]
    for c in clients:
        c.start()
    return clients


def stored(db: str, campaign: str) -> list[tuple[str, int, int]]:
    conn = sqlite3.connect(db)
    try:
        return conn.execute(
            "SELECT a.name, l.context_id, l.slot FROM labels l JOIN annotators a ON a.id = l.annotator_id JOIN "
            "campaigns c ON c.id = l.campaign_id WHERE c.name = ?", (campaign,)).fetchall()
    finally:
        conn.close()


def check(db: str, campaign: str, acks: list[tuple[str, int, int]]) -> dict[str, int]:
    rows = stored(db, campaign)
    keys = [(name, item) for name, item, _ in rows]
    present = set(rows)
    return {"rows": len(rows), "duplicated": len(keys) - len(set(keys)),
            "lost": sum(ack not in present for ack in acks), "acknowledged": len(acks)}


@pytest.mark.slow
def test_concurrent_annotators_then_kill9(tmp_path) -> None:  # type: ignore[no-untyped-def]
    db = str(tmp_path / "load.db")
    store = FeedbackStore(db)
    make_tiny_campaign(store, "load", num_contexts=ITEMS)
    make_tiny_campaign(store, "crash", num_contexts=ITEMS, seed=1)
    tokens = {f"annotator{i:02d}": store.add_annotator(f"annotator{i:02d}")[1] for i in range(ANNOTATORS)}
    store.close()
    report: dict[str, object] = {"annotators": ANNOTATORS, "submissions_each": ITEMS}

    # ---- phase 1: full load
    server = Server(db).start()
    try:
        acks: list[tuple[str, int, int]] = []
        lock = threading.Lock()
        began = time.perf_counter()
        clients = run_clients(server.url, tokens, "load", acks, lock)
        for c in clients:
            c.join(timeout=60)
        elapsed = time.perf_counter() - began
        assert not any(c.errors for c in clients), [c.errors for c in clients if c.errors]
        result = check(db, "load", acks)
        report["phase1"] = {**result, "seconds": round(elapsed, 2),
                            "submissions_per_s": round(len(acks) / elapsed, 1),
                            "requests_per_s": round(sum(c.requests for c in clients) / elapsed, 1)}
        assert len(acks) == ANNOTATORS * ITEMS
        assert result == {"rows": 1000, "duplicated": 0, "lost": 0, "acknowledged": 1000}

        # ---- phase 2: kill -9 mid-run
        acks2: list[tuple[str, int, int]] = []
        clients = run_clients(server.url, tokens, "crash", acks2, lock)
        deadline = time.monotonic() + 30
        while len(acks2) < 300 and time.monotonic() < deadline:
            time.sleep(0.005)
        server.kill9()
        killed_at = len(acks2)
        for c in clients:
            c.join(timeout=60)
        acked_before_kill = list(acks2)
    finally:
        server.stop()
    assert 300 <= killed_at < ANNOTATORS * ITEMS, killed_at
    restarted = Server(db).start()  # same file: SQLite recovers the WAL on open
    try:
        after_restart = check(db, "crash", acked_before_kill)
        report["phase2_after_kill"] = {**after_restart, "acks_when_killed": killed_at,
                                       "interrupted_clients": sum(c.interrupted for c in clients)}
        assert after_restart["lost"] == 0 and after_restart["duplicated"] == 0
        clients = run_clients(restarted.url, tokens, "crash", acks2, lock)  # everyone finishes
        for c in clients:
            c.join(timeout=60)
        assert not any(c.errors for c in clients), [c.errors for c in clients if c.errors]
    finally:
        restarted.stop()
    final = check(db, "crash", acks2)
    report["phase2_final"] = final
    assert final["rows"] == 1000 and final["duplicated"] == 0 and final["lost"] == 0
    integrity = sqlite3.connect(db).execute("PRAGMA integrity_check").fetchone()[0]
    assert integrity == "ok"
    print("\nload test:", json.dumps(report))
    if os.environ.get("TRAFFICRLHF_LOAD_REPORT"):
        with open(os.environ["TRAFFICRLHF_LOAD_REPORT"], "w", encoding="utf-8") as handle:
            json.dump(report, handle, indent=2)
