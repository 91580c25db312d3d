"""Load, crash and memory tests against the real server on loopback (127.0.0.1, random port; bounded loops).

**Caps under load and a crash** (:func:`test_cap_holds_under_load_and_kill9`): A annotators work concurrently on
a campaign of A x S items with ``labels_per_item`` 1 (S submissions each on average); five "ghost" annotators
open an item each and walk away, so their items come back only when the lease (2 s) expires. Mid-run the server
is killed with SIGKILL and restarted on the same file; the annotators then finish. Checked: every label
acknowledged before the kill is stored, no item has more than one label at any point, every item ends with
exactly one, the ghosts' late labels are refused with 409, and SQLite's integrity check passes.

**Large bodies** (:func:`test_large_unauthenticated_bodies`): five clients at once post B MB bodies without a
token (declared length, and chunked with a valid token): all are answered 401/413 and the server's resident
memory stays within +50 MB.

CI runs a small form (A = 20, S = 10; B = 8). The full form is run by hand::

    TRAFFICRLHF_LOAD_SUBMISSIONS=500 TRAFFICRLHF_BODY_MB=100 \
        pytest -m slow -s plugins/annotation_web/tests/test_annotation_load.py

Figures are printed (``-s``) and written to ``$TRAFFICRLHF_LOAD_REPORT`` when set.
"""

from __future__ import annotations

import json
import os
import select
import socket
import sqlite3
import threading
import time

import httpx
import pytest

from trafficrlhf_sdk.feedback import FeedbackStore
from trafficrlhf_sdk.testing.feedback import tiny_context

from trafficrlhf_annotation_web.testing import Server

ANNOTATORS = int(os.environ.get("TRAFFICRLHF_LOAD_ANNOTATORS", "20"))
SUBMISSIONS = int(os.environ.get("TRAFFICRLHF_LOAD_SUBMISSIONS", "10"))
BODY_MB = int(os.environ.get("TRAFFICRLHF_BODY_MB", "8"))
GHOSTS = 5
LEASE_S = 2.0


def _report(name: str, figures: dict[str, object]) -> None:
    print(f"\n{name}:", json.dumps(figures))
    path = os.environ.get("TRAFFICRLHF_LOAD_REPORT")
    if path:
        existing = json.load(open(path, encoding="utf-8")) if os.path.exists(path) else {}
        existing[name] = figures
        with open(path, "w", encoding="utf-8") as handle:
            json.dump(existing, handle, indent=2)


def build_campaign(db: str, items: int, names: list[str]) -> dict[str, str]:
    """Campaign ``load`` (N = 5, no map, labels_per_item 1, 2 s leases, no playback wait); returns tokens."""
    store = FeedbackStore(db, synchronous="OFF")  # setup only; the server runs with FULL
    config = {"name": "load", "model": "tiny", "source": "tiny", "split": "test", "num_candidates": 5, "seed": 0,
              "labels_per_item": 1, "annotation": {"lease_seconds": LEASE_S, "playback_required": False}}
    campaign = store.create_campaign("load", "tiny", None, 0, 5, config, "test")
    scenario, cands, valid, logged, logged_valid = tiny_context(["faithful", "offroad", "collision", "stall", "weave"])
    scenario = scenario.replace_unchecked(map=None)
    for i in range(items):
        store.add_context(campaign, "tiny", "test", f"load-{i:05d}", i, scenario, cands, valid, logged, logged_valid,
                          "test")
    tokens = {name: store.add_annotator(name)[1] for name in names}
    store.close()
    return tokens


class Annotator(threading.Thread):
    """GET next, POST a label, until done, the deadline, or the server goes away."""

    def __init__(self, url: str, name: str, token: str, acks: list[tuple[str, int]], lock: threading.Lock,
                 deadline: float, max_rounds: int) -> None:
        super().__init__(daemon=True)
        self.url, self.name, self.token, self.acks, self.lock = url, name, token, acks, lock
        self.deadline, self.max_rounds = deadline, max_rounds
        self.interrupted, self.finished = False, False
        self.refused = 0
        self.errors: list[str] = []

    def run(self) -> None:
        base = f"{self.url}/api/campaigns/load"
        with httpx.Client(timeout=60.0, headers={"Authorization": f"Bearer {self.token}"}) as http:
            for _ in range(self.max_rounds):
                if time.monotonic() > self.deadline:
                    self.errors.append("deadline")
                    return
                try:
                    item = http.get(f"{base}/next")
                    if item.status_code != 200:
                        self.errors.append(f"next {item.status_code} {item.text[:200]}")
                        return
                    data = item.json()
                    if data.get("done"):
                        self.finished = True
                        return
                    response = http.post(f"{base}/items/{data['item']}/label", json={"choice": 1 + data["item"] % 5})
                except httpx.TransportError:
                    self.interrupted = True  # the server went away; unacknowledged work is not counted
                    return
                if response.status_code == 201:
                    with self.lock:
                        self.acks.append((self.name, data["item"]))
                elif response.status_code == 409:  # lost a race after a lease expired: take the next item
                    self.refused += 1
                else:
                    self.errors.append(f"label {response.status_code} {response.text[:200]}")
                    return


def run_annotators(url: str, tokens: dict[str, str], acks: list[tuple[str, int]], lock: threading.Lock,
                   rounds: int, timeout_s: float) -> list[Annotator]:
    deadline = time.monotonic() + timeout_s
    clients = [Annotator(url, name, token, acks, lock, deadline, rounds) for name, token in tokens.items()]
    for c in clients:
        c.start()
    return clients


def per_item(db: str) -> dict[int, int]:
    conn = sqlite3.connect(db)
    try:
        return dict(conn.execute("SELECT context_id, COUNT(*) FROM labels GROUP BY context_id").fetchall())
    finally:
        conn.close()


def stored(db: str) -> set[tuple[str, int]]:
    conn = sqlite3.connect(db)
    try:
        return set(conn.execute("SELECT a.name, l.context_id FROM labels l JOIN annotators a ON a.id = "
                                "l.annotator_id").fetchall())
    finally:
        conn.close()


@pytest.mark.slow
def test_cap_holds_under_load_and_kill9(tmp_path) -> None:  # type: ignore[no-untyped-def]
    db = str(tmp_path / "load.db")
    items = ANNOTATORS * SUBMISSIONS
    names = [f"annotator{i:02d}" for i in range(ANNOTATORS)]
    ghosts = [f"ghost{i}" for i in range(GHOSTS)]
    tokens = build_campaign(db, items, names + ghosts)
    workers = {n: tokens[n] for n in names}
    rounds = 3 * items  # bound on each client's loop
    timeout_s = 60.0 + 0.1 * items
    report: dict[str, object] = {"annotators": ANNOTATORS, "items": items, "labels_per_item": 1, "ghosts": GHOSTS,
                                 "lease_s": LEASE_S}
    server = Server(db).start()
    acks: list[tuple[str, int]] = []
    lock = threading.Lock()
    try:
        ghost_items = {}
        for g in ghosts:  # open an item each and walk away
            item = httpx.get(f"{server.url}/api/campaigns/load/next",
                             headers={"Authorization": f"Bearer {tokens[g]}"})
            ghost_items[g] = item.json()["item"]
        began = time.perf_counter()
        clients = run_annotators(server.url, workers, acks, lock, rounds, timeout_s)
        kill_at = int(0.4 * items)
        deadline = time.monotonic() + timeout_s
        while len(acks) < kill_at and time.monotonic() < deadline:
            time.sleep(0.005)
        server.kill9()
        killed_at = len(acks)
        for c in clients:
            c.join(timeout=60)
        before_kill = set(acks)
        first_phase_s = time.perf_counter() - began
    finally:
        server.stop()
    assert kill_at <= killed_at < items, killed_at
    counts = per_item(db)
    report["after_kill"] = {"acknowledged": killed_at, "lost": len(before_kill - stored(db)),
                            "items_over_cap": sum(n > 1 for n in counts.values()),
                            "interrupted_clients": sum(c.interrupted for c in clients),
                            "seconds": round(first_phase_s, 1)}
    assert report["after_kill"]["lost"] == 0 and report["after_kill"]["items_over_cap"] == 0  # type: ignore[index]

    restarted = Server(db).start()  # the same file: SQLite recovers the WAL on open
    try:
        began = time.perf_counter()
        clients = run_annotators(restarted.url, workers, acks, lock, rounds, timeout_s)
        for c in clients:
            c.join(timeout=timeout_s + 30)
        second_phase_s = time.perf_counter() - began
        assert not any(c.errors for c in clients), [c.errors for c in clients if c.errors]
        assert all(c.finished for c in clients)
        late = {}
        for g in ghosts:  # their leases expired long ago and others labeled the items
            response = httpx.post(f"{restarted.url}/api/campaigns/load/items/{ghost_items[g]}/label",
                                  json={"choice": 1}, headers={"Authorization": f"Bearer {tokens[g]}"})
            late[g] = response.status_code
    finally:
        restarted.stop()
    counts = per_item(db)
    rows = stored(db)
    report["final"] = {
        "acknowledged": len(acks), "duplicated_acks": len(acks) - len(set(acks)), "lost": len(set(acks) - rows),
        "labels": sum(counts.values()), "items_labeled": len(counts),
        "stored_but_unacknowledged": len(rows - set(acks)),  # committed, the reply lost in the kill
        "items_over_cap": sum(n > 1 for n in counts.values()),
        "refused_409_after_lease_race": sum(c.refused for c in clients),
        "ghost_late_label_statuses": sorted(late.values()), "seconds_after_restart": round(second_phase_s, 1),
        "labels_per_s_after_restart": round((len(acks) - killed_at) / max(second_phase_s, 1e-9), 1),
    }
    conn = sqlite3.connect(db)
    report["final"]["integrity"] = conn.execute("PRAGMA integrity_check").fetchone()[0]  # type: ignore[index]
    conn.close()
    _report("cap_under_load_and_kill9", report)
    final = report["final"]
    assert final["lost"] == 0 and final["duplicated_acks"] == 0 and final["items_over_cap"] == 0  # type: ignore[index]
    assert final["labels"] == items and final["items_labeled"] == items  # type: ignore[index]
    assert set(late.values()) == {409} and final["integrity"] == "ok"  # type: ignore[index]


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as handle:
        for line in handle:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def _post_big(url: str, path: str, size: int, token: str | None, chunked: bool, out: list[object]) -> None:
    """Post ``size`` bytes raw over a socket, stop sending once the server answers; append the status."""
    host, port = url.removeprefix("http://").split(":")
    chunk = b"z" * 65536
    head = [f"POST {path} HTTP/1.1", f"Host: {host}", "Content-Type: application/json"]
    head.append("Transfer-Encoding: chunked" if chunked else f"Content-Length: {size}")
    if token:
        head.append(f"Authorization: Bearer {token}")
    sock = socket.create_connection((host, int(port)), timeout=30)
    sent = 0
    try:
        sock.sendall(("\r\n".join(head) + "\r\n\r\n").encode())
        readable = select.select([sock], [], [], 0.3)[0]
        while not readable and sent < size:
            piece = (b"%x\r\n" % len(chunk) + chunk + b"\r\n") if chunked else chunk
            try:
                sock.sendall(piece)
            except OSError:
                break
            sent += len(chunk)
            readable = select.select([sock], [], [], 0)[0]
        reply = b""
        while b"\r\n" not in reply:
            more = sock.recv(4096)
            if not more:
                break
            reply += more
        out.append((int(reply.split()[1]) if reply else None, sent))
    except OSError as exc:
        out.append((f"error {exc}", sent))
    finally:
        sock.close()


@pytest.mark.slow
def test_large_unauthenticated_bodies(campaign_db) -> None:  # type: ignore[no-untyped-def]
    db, tokens = campaign_db
    server = Server(db).start()
    try:
        pid = server.proc.pid  # type: ignore[union-attr]
        httpx.get(server.url + "/api/me", headers={"Authorization": f"Bearer {tokens['alice']}"})  # warm up
        before = _rss_kb(pid)
        peak = before
        stop = threading.Event()

        def sample() -> None:
            nonlocal peak
            while not stop.is_set():
                peak = max(peak, _rss_kb(pid))
                time.sleep(0.01)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        size = BODY_MB * 1024 * 1024
        results: dict[str, list[object]] = {"declared_no_token": [], "chunked_no_token": [], "chunked_token": []}
        began = time.perf_counter()
        for kind, (token, chunked) in {"declared_no_token": (None, False), "chunked_no_token": (None, True),
                                       "chunked_token": (tokens["alice"], True)}.items():
            threads = [threading.Thread(target=_post_big, args=(server.url, "/api/campaigns/tiny/items/1/label", size,
                                                                token, chunked, results[kind])) for _ in range(5)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(120)
        elapsed = time.perf_counter() - began
        time.sleep(0.2)
        stop.set()
        sampler.join(5)
        after = _rss_kb(pid)
        healthy = httpx.get(server.url + "/healthz").status_code
    finally:
        server.stop()
    figures = {"body_mb": BODY_MB, "clients_at_once": 5, "rss_before_mb": round(before / 1024, 1),
               "rss_peak_mb": round(peak / 1024, 1), "rss_after_mb": round(after / 1024, 1),
               "peak_growth_mb": round((peak - before) / 1024, 1), "seconds": round(elapsed, 2),
               "statuses": {k: sorted(str(s) for s, _ in v) for k, v in results.items()},
               "max_bytes_sent_mb": round(max(n for v in results.values() for _, n in v) / 2**20, 2)}  # type: ignore[type-var]
    _report("large_bodies", figures)
    assert [s for s, _ in results["declared_no_token"]] == [401] * 5
    assert [s for s, _ in results["chunked_no_token"]] == [401] * 5
    assert [s for s, _ in results["chunked_token"]] == [413] * 5
    assert peak - before < 50 * 1024 and healthy == 200
    assert sqlite3.connect(db).execute("SELECT COUNT(*) FROM labels").fetchone()[0] == 0
