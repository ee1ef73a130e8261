"""Review of finished jobs (POST /v1/registrations/{id}/review) against a real server: typed in the
OpenAPI document, round trip on the job and the list, 409 while a job is unfinished, scoped to the
caller's API key, every review in the audit log, and an existing database gaining the columns."""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
import time
from pathlib import Path

import pytest
import sqlalchemy as sa
from tests.support.service_testkit import Server, needs_engine, submit, wait_for
from tests.support.webdriver import Browser, browser_binaries

from tests.system.service.conftest import ALPHA, BETA
SLOW = {"starts": 2, "max_iterations": 400, "seed": 5}
SHOTS = Path(__file__).resolve().parents[3] / "docs" / "images"


def _clients(srv):
    return (srv.client(headers={"Authorization": f"Bearer {ALPHA}"}),
            srv.client(headers={"Authorization": f"Bearer {BETA}"}))


def _events(srv, job_id: str) -> list[tuple[str, dict | None]]:
    with sqlite3.connect(srv.data_dir / "jobs.sqlite3") as db:
        rows = db.execute("SELECT event, detail FROM job_events WHERE job_id = ? ORDER BY seq", (job_id,)).fetchall()
    return [(event, json.loads(detail) if detail else None) for event, detail in rows]


def test_review_is_typed_in_openapi(keyed_server):
    with keyed_server.client() as c:
        doc = c.get("/openapi.json").json()
        garbled = c.post("/v1/registrations/nosuchjob/review", content=b"{not json",
                         headers={"Content-Type": "application/json"})
    operation = doc["paths"]["/v1/registrations/{job_id}/review"]["post"]
    assert str(garbled.status_code) in operation["responses"], garbled.status_code  # what it answers is declared
    assert operation["operationId"] == "review_job"
    body = operation["requestBody"]["content"]["application/json"]["schema"]["$ref"].rsplit("/", 1)[-1]
    request = doc["components"]["schemas"][body]
    assert request["properties"]["decision"]["enum"] == ["approved", "rejected"]
    assert request["properties"]["comment"]["maxLength"] == 2000
    assert {"400", "401", "404", "408", "409", "422"} <= set(operation["responses"])
    review = doc["components"]["schemas"]["Review"]
    assert set(review["required"]) == {"decision", "comment", "by", "at"}
    for model in ("JobStatus", "JobSummary"):
        assert "Review" in json.dumps(doc["components"]["schemas"][model]["properties"]["review"])
    params = {p["name"]: p for p in doc["paths"]["/v1/registrations"]["get"]["parameters"]}
    assert params["review"]["schema"]["enum"] == ["none", "approved", "rejected"]
    audit = doc["paths"]["/v1/registrations/{job_id}/audit"]["get"]
    assert audit["operationId"] == "get_audit" and {"401", "404"} <= set(audit["responses"])
    assert audit["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith("/AuditLog")
    event = doc["components"]["schemas"]["AuditEvent"]
    assert set(event["required"]) == {"at", "event", "actor"} and "details" in event["properties"]
    export = doc["components"]["schemas"]["ExportState"]
    assert export["properties"]["state"]["enum"] == ["awaiting_review", "pending", "exporting", "done", "failed",
                                                     "skipped"]
    assert "ExportState" in json.dumps(doc["components"]["schemas"]["JobStatus"]["properties"]["export"])


@needs_engine
def test_review_round_trip_scoped_and_audited(keyed_server, example_case):
    alpha, beta = _clients(keyed_server)
    with alpha, beta:
        done = submit(alpha, example_case).json()["id"]
        slow = submit(alpha, example_case, options=SLOW).json()["id"]  # queued behind `done`, then running
        # unfinished: 409 problem+json (queued now, running later)
        r = alpha.post(f"/v1/registrations/{slow}/review", json={"decision": "approved"})
        assert r.status_code == 409 and r.headers["content-type"].startswith("application/problem+json"), r.text
        assert r.json()["job_status"] in ("queued", "running")
        final = wait_for(alpha, done, timeout=180)
        assert final["status"] == "succeeded" and final["review"] is None
        running = wait_for(alpha, slow, statuses=("running", "succeeded"), timeout=120)
        if running["status"] == "running":
            r = alpha.post(f"/v1/registrations/{slow}/review", json={"decision": "rejected"})
            assert r.status_code == 409 and r.json()["job_status"] == "running", r.text
        alpha.post(f"/v1/registrations/{slow}/cancel")
        # bad input names the field
        for bad, field in (({"decision": "maybe"}, "decision"), ({"decision": "approved", "comment": "x" * 2001}, "comment")):
            r = alpha.post(f"/v1/registrations/{done}/review", json=bad)
            assert r.status_code == 422 and field in r.json()["field"], r.text
        # another key: its jobs only
        assert beta.post(f"/v1/registrations/{done}/review", json={"decision": "rejected"}).status_code == 404
        first = alpha.post(f"/v1/registrations/{done}/review", json={"decision": "rejected", "comment": "LAT off"})
        assert first.status_code == 200, first.text
        label = "key:" + hashlib.sha256(ALPHA.encode()).hexdigest()[:8]
        assert first.json()["review"]["decision"] == "rejected" and first.json()["review"]["by"] == label
        second = alpha.post(f"/v1/registrations/{done}/review",
                            json={"decision": "approved", "comment": "re-checked: fine"}).json()["review"]
        shown = alpha.get(f"/v1/registrations/{done}").json()["review"]
        assert shown == second and shown["comment"] == "re-checked: fine" and shown["at"].endswith("Z")
        summary = next(j for j in alpha.get("/v1/registrations").json()["items"] if j["id"] == done)
        assert summary["review"] == second
        ids = {state: [j["id"] for j in alpha.get("/v1/registrations", params={"review": state}).json()["items"]]
               for state in ("none", "approved", "rejected")}
        assert done in ids["approved"] and done not in ids["none"] + ids["rejected"] and slow in ids["none"]
        assert alpha.get("/v1/registrations", params={"review": "later"}).json()["field"] == "review"
        assert beta.get("/v1/registrations", params={"review": "approved"}).json()["items"] == []
        assert beta.get(f"/v1/registrations/{done}").status_code == 404
        # the audit log over HTTP: typed events, who without secrets, the owner's only
        audit = alpha.get(f"/v1/registrations/{done}/audit")
        assert audit.status_code == 200, audit.text
        items = audit.json()["items"]
        assert [i["event"] for i in items][:1] == ["queued"] and items[0]["actor"] == label
        assert [(i["details"], i["actor"]) for i in items if i["event"] == "reviewed"] == [
            ({"decision": "rejected", "comment": "LAT off"}, label),
            ({"decision": "approved", "comment": "re-checked: fine"}, label)]
        assert any(i["event"] == "succeeded" and i["actor"].startswith("worker:") for i in items), items
        assert all(i["at"].endswith("Z") for i in items) and "export" not in alpha.get(f"/v1/registrations/{done}").json()
        assert ALPHA not in audit.text and hashlib.sha256(ALPHA.encode()).hexdigest() not in audit.text
        assert beta.get(f"/v1/registrations/{done}/audit").status_code == 404
        assert alpha.get("/v1/registrations/0123456789abcdef0123456789abcdef/audit").status_code == 404
    reviews = [detail for event, detail in _events(keyed_server, done) if event == "reviewed"]
    assert [(d["decision"], d["comment"], d["by"]) for d in reviews] == [
        ("rejected", "LAT off", label), ("approved", "re-checked: fine", label)]
    assert ALPHA not in keyed_server.logs()


def _old_schema() -> sa.MetaData:
    """The tables as they were before reviews (no review columns, no event detail)."""
    from service.storage.store import metadata

    new = {("jobs", "review"), ("jobs", "review_decision"), ("job_events", "detail"), ("jobs", "case_identity"),
           ("jobs", "case_search")}
    old = sa.MetaData()
    for table in metadata.sorted_tables:
        if table.name == "volume_models":  # revision 0003
            continue
        columns = [c for c in table.columns if (table.name, c.name) not in new]
        sa.Table(table.name, old, *[sa.Column(c.name, c.type, primary_key=c.primary_key, nullable=c.nullable)
                                    for c in columns])
    return old


def test_existing_database_gains_review_columns(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    engine = sa.create_engine(f"sqlite:///{data / 'jobs.sqlite3'}")
    old = _old_schema()
    old.create_all(engine)
    now = time.time()
    with engine.begin() as conn:
        conn.execute(old.tables["jobs"].insert().values(
            id="a" * 32, owner="anonymous", status="failed", created_at=now, updated_at=now, finished_at=now,
            attempts=1, max_attempts=3, cancel_requested=False, options="{}", inputs="[]", artifacts="{}",
            warnings="[]", input_bytes=0))
    engine.dispose()
    srv = Server(data, workers=0).start()
    try:
        with srv.client() as c:
            assert c.get(f"/v1/registrations/{'a' * 32}").json()["review"] is None
            assert c.get(f"/v1/registrations/{'a' * 32}").json()["case"] is None
            r = c.post(f"/v1/registrations/{'a' * 32}/review", json={"decision": "rejected", "comment": "no result"})
            assert r.status_code == 200, r.text
            assert r.json()["review"]["by"] == "anonymous"
            assert [j["id"] for j in c.get("/v1/registrations", params={"review": "rejected"}).json()["items"]] == ["a" * 32]
    finally:
        srv.stop()
    assert [e for e, _ in _events(srv, "a" * 32)] == ["reviewed"]


# ---- the review page in a real browser -------------------------------------------------------------


def test_review_page_is_small_and_offline(keyed_server):
    with keyed_server.client() as c:
        assert c.get("/ui", follow_redirects=False).headers["location"] == "/ui/"
        index = c.get("/ui/")
        assert index.status_code == 200 and "default-src 'self'" in index.headers["content-security-policy"]
        parts = [index] + [c.get(f"/ui/{name}") for name in ("app.js", "views2d.js", "scene3d.js", "app.css")]
        assert all(p.status_code == 200 for p in parts)
        assert c.get("/ui/..%2Fjobs.sqlite3").status_code == 404 and c.get("/ui/secret.txt").status_code == 404
    weight = sum(len(p.content) for p in parts)
    assert weight <= 200_000, weight
    for part in parts:  # nothing from outside the service: no CDN, fonts or analytics
        assert "http://" not in part.text and "https://" not in part.text and "//cdn" not in part.text


@needs_engine
def test_review_page_in_chromium(keyed_server, example_case, tmp_path):
    browser_binaries()
    with keyed_server.client(headers={"Authorization": f"Bearer {ALPHA}"}) as alpha, \
            keyed_server.client(headers={"Authorization": f"Bearer {BETA}"}) as beta:
        job_id = submit(alpha, example_case).json()["id"]
        other = submit(beta, example_case, options={"starts": 1, "max_iterations": 21}).json()["id"]
        assert wait_for(alpha, job_id, timeout=180)["status"] == "succeeded"
    browser = Browser(tmp_path / "profile", height=1100)
    try:
        browser.open(keyed_server.url + "/ui/")
        browser.find("#api-key")
        browser.wait("return document.getElementById('message').textContent.includes('401')", what="401 without key")
        browser.type("#api-key", ALPHA + "\ue007")  # typed once, Enter submits
        link = f'a[href="#/job/{job_id}"]'
        browser.find(link)
        rows = browser.run("return [...document.querySelectorAll('#jobs tbody tr')].map(r => r.innerText)")
        assert not [r for r in rows if other[:12] in r], rows  # the other key's job is invisible
        assert "not reviewed" in next(r for r in rows if job_id[:12] in r)
        browser.run("document.activeElement.blur()")
        browser.screenshot(tmp_path / "list.png")
        browser.click(link)  # click 1: open the job
        browser.wait("const s = document.getElementById('views'); return s && s.dataset.ready === '1' && "
                     "document.querySelectorAll('.views canvas[data-drawn]').length === 2", what="views")
        browser.wait("const p = document.querySelector('.plot img'); return p && p.complete && p.naturalWidth > 0",
                     what="loss plot")
        # the loss plot at a readable scale, scaled smoothly (a chart, not pixels), and whole in the screenshot
        browser.resize(1280, 2200)  # the views, the 3D scene, then the plot
        browser.run("window.scrollTo(0, 0)")
        width, bottom, viewport, rendering = browser.run(
            "const p = document.querySelector('.plot img'); const r = p.getBoundingClientRect(); "
            "return [r.width / p.naturalWidth, r.bottom, window.innerHeight, getComputedStyle(p).imageRendering]")
        assert 0.9 <= width <= 1.1 and rendering != "pixelated", (width, rendering)
        assert bottom <= viewport, (bottom, viewport)
        history = browser.wait("const items = [...document.querySelectorAll('#history li')].map(li => li.innerText); "
                               "return items.length >= 3 && items", what="history")
        assert any("queued" in item and "key:" in item for item in history), history
        assert any("succeeded" in item and "worker:" in item for item in history), history
        assert browser.run("return document.querySelector('.plot img').src").startswith("blob:")
        browser.click("#toggle-mask")
        browser.wait("return document.getElementById('toggle-mask').getAttribute('aria-pressed') === 'true'", what="mask")
        browser.click("#toggle-mask")
        text = browser.run("return document.body.innerText")
        assert "Dice ap" in text and "Pose rotation" in text and "Verdict" in text, text
        browser.type("#comment", "Contours follow the vessels in both views.")
        browser.run("document.activeElement.blur(); window.scrollTo(0, 0)")
        browser.screenshot(tmp_path / "job.png")
        browser.click("#approve")  # click 2: approve
        browser.wait("return document.getElementById('review-state').innerText.includes('approved')", what="approved")
        browser.wait("return document.getElementById('history').innerText.includes('reviewed')", what="history")
        with keyed_server.client(headers={"Authorization": f"Bearer {ALPHA}"}) as alpha:
            review = alpha.get(f"/v1/registrations/{job_id}").json()["review"]
        assert review["decision"] == "approved" and review["comment"].startswith("Contours follow")
        # keyboard only: back to the list, the focus ring is visible on a link
        browser.open(keyed_server.url + "/ui/#/")
        browser.find(link)
        browser.keys("\ue004\ue004")
        outline = browser.run("const a = document.activeElement; return [a.tagName, getComputedStyle(a).outlineStyle]")
        assert outline[1] != "none", outline
    finally:
        browser.close()
    _keep_screenshots(tmp_path)


def _keep_screenshots(tmp_path: Path) -> None:
    """Small copies left in /tmp for a look; with DSAREG_UPDATE_SCREENSHOTS=1 also the docs' (docs/images)."""
    from PIL import Image

    for name in ("list", "job"):
        image = Image.open(tmp_path / f"{name}.png").convert("RGB")
        colours = image.convert("L").getcolors(maxcolors=1 << 16)
        assert colours is None or len(colours) > 20, f"{name}: the screenshot is (nearly) blank"
        small = image.convert("P", palette=Image.Palette.ADAPTIVE, colors=64)
        targets = [Path("/tmp") / f"dsareg-review-{name}.png"]
        if os.environ.get("DSAREG_UPDATE_SCREENSHOTS") == "1":
            targets.append(SHOTS / f"review-{name}.png")
        for target in targets:
            try:
                small.save(target, optimize=True)
            except OSError:
                pass
