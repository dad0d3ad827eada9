"""The pages at / under TestClient, on a real store: what they show, the figures and downloads
(byte for byte the version's files and exports), 404 / 410 pages, escaping of user strings, the
live fragment, and the API's auth rules through the sign-in form, the session cookie and the
CSRF checks."""

from __future__ import annotations

import hashlib
import io
import json
import re
import time
import zipfile

import pytest

from schema import parse_spec
from service.pages.auth import CSRF_COOKIE, SESSION_COOKIE, SESSION_SECONDS, safe_next, session_value
from service.worker import compile_phase
from tests.api.conftest import TINY_SPEC, TOKEN, tiny_spec

EVIL = '<script>window.__xss = 1</script><img src=x onerror="window.__xss = 2">'


def _csrf(client, url="/") -> str:
    """The CSRF token of a rendered form (the page sets the cookie it must equal)."""
    html = client.get(url).text
    match = re.search(r'name="csrf" value="([^"]+)"', html)
    assert match, "no form with a CSRF token on " + url
    assert client.cookies.get(CSRF_COOKIE) == match.group(1)
    return match.group(1)


def _sign_in(client, token=TOKEN, next_url="/"):
    return client.post("/signin", data={"token": token, "csrf": _csrf(client, "/signin"), "next": next_url},
                       follow_redirects=False)


# --- what the pages show ---
def test_front_page_lists_jobs_and_datasets(make_client, published):
    store, storage, jobs = published
    r = make_client(store, storage).get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    for job in jobs:
        assert f'href="/jobs/{job.id}"' in r.text
    assert 'href="/datasets/tiny"' in r.text and 'href="/datasets/tiny/versions/2"' in r.text
    assert "script-src 'self'" in r.headers["content-security-policy"] and r.headers["x-content-type-options"] == "nosniff"


def test_job_page_shows_the_finished_job_and_its_result(make_client, published):
    store, storage, jobs = published
    client = make_client(store, storage)
    r = client.get(f"/jobs/{jobs[0].id}")
    assert r.status_code == 200
    assert "state-succeeded" in r.text and "2 / 2" in r.text
    assert f'href="/datasets/tiny/versions/{jobs[0].dataset_version}"' in r.text
    assert 'data-live="false"' in r.text and "http-equiv=\"refresh\"" not in r.text  # ended: no polling
    live = client.get(f"/jobs/{jobs[0].id}/live")
    assert live.status_code == 200 and live.headers["x-job-state"] == "succeeded" and "<html" not in live.text


@pytest.mark.parametrize("url, status", [
    ("/jobs/00000000-0000-4000-8000-000000000000", 404), ("/jobs/not-a-uuid", 404),
    ("/jobs/00000000-0000-4000-8000-000000000000/live", 404),
    ("/datasets/nope", 404), ("/datasets/tiny/versions/99", 404), ("/datasets/tiny/versions/x1", 404),
    ("/datasets/Bad%20Name!/versions/1", 404), ("/datasets/tiny/versions/1/plots/nope.svg", 404),
    ("/datasets/tiny/versions/1/files/../../jobs.sqlite", 404), ("/datasets/tiny/versions/1/files/secret.txt", 404),
    ("/datasets/tiny/versions/1/exports/zip", 404), ("/jobs?state=bogus", 400),
])
def test_missing_things_are_html_error_pages(make_client, published, url, status):
    store, storage, _ = published
    r = make_client(store, storage).get(url)
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("text/html") and 'class="problem"' in r.text


def test_version_page_has_summary_provenance_figures_and_links(make_client, published):
    store, storage, _ = published
    client = make_client(store, storage)
    record = store.get_version("tiny", 1)
    r = client.get("/datasets/tiny/versions/1")
    assert r.status_code == 200, r.text
    html = r.text
    assert record.meta["spec_hash"] in html and str(record.meta["code_version"]["git_commit"] or "") in html
    for name, info in record.meta["files"].items():
        assert f'href="/datasets/tiny/versions/1/files/{name}"' in html and info["sha256"] in html
    for fmt in ("pbrt", "albedo-map", "exr", "npz", "csv", "plots"):
        assert f'href="/datasets/tiny/versions/1/exports/{fmt}"' in html
    summary = json.loads(storage.fs.open_input_stream(f"{record.uri}/summary.json").read())
    total = next(x for x in summary["results"] if x["component"] == "total")
    assert f"{total['Rd']:.5f}" in html and f"{total['Rd_stderr']:.5f}" in html
    svgs = re.findall(r'<img src="(/datasets/tiny/versions/1/plots/[^"]+\.svg)"', html)
    assert any("/plots/rd-" in s for s in svgs)  # one direction bin: no S figure; one albedo: no map
    (plots,) = [e for e in store.list_exports("tiny", 1) if e.format == "plots"]
    for src in svgs:
        svg = client.get(src)
        assert svg.status_code == 200 and svg.headers["content-type"] == "image/svg+xml"
        assert b"<svg" in svg.content[:2000]
        name = src.rsplit("/", 1)[1]
        assert hashlib.sha256(svg.content).hexdigest() == plots.meta["files"][name]["sha256"]


def test_downloads_are_the_versions_bytes(make_client, published):
    store, storage, _ = published
    client = make_client(store, storage)
    record = store.get_version("tiny", 2)
    for name, info in record.meta["files"].items():
        r = client.get(f"/datasets/tiny/versions/2/files/{name}")
        assert r.status_code == 200 and hashlib.sha256(r.content).hexdigest() == info["sha256"]
        assert r.headers["etag"] == f'"{info["sha256"]}"'
    page_zip = client.get("/datasets/tiny/versions/2/exports/csv")
    api_zip = client.get("/v1/datasets/tiny/versions/2/exports/csv")
    assert page_zip.status_code == 200 and page_zip.content == api_zip.content
    (export,) = [e for e in store.list_exports("tiny", 2) if e.format == "csv"]
    assert hashlib.sha256(page_zip.content).hexdigest() == export.sha256
    with zipfile.ZipFile(io.BytesIO(page_zip.content)) as zf:
        assert json.loads(zf.read("export.json"))["version"] == 2
    assert export.sha256 in client.get("/datasets/tiny/versions/2").text  # the page shows the made export


def test_a_deleted_version_is_410_and_listed_as_a_tombstone(make_client, store, storage):
    job = store.submit(parse_spec(TINY_SPEC))
    from service.worker import Worker

    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    version = store.get_job(job.id).dataset_version
    client = make_client(store, storage)
    assert client.delete(f"/v1/datasets/tiny/versions/{version}", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    assert client.get(f"/datasets/tiny/versions/{version}").status_code == 410
    listing = client.get("/datasets/tiny")
    assert listing.status_code == 200 and "deleted" in listing.text


# --- escaping ---
def test_user_strings_are_shown_as_text(make_client, store, storage):
    from service.store import RetryPolicy

    store.retry_policy = RetryPolicy(base_delay_s=0.0)  # retries claimable at once
    spec = parse_spec(tiny_spec(description=EVIL))
    job = store.submit(spec)
    lease = store.claim("w", 60)
    for _ in range(spec.shards * 3):  # fail the task until the job fails, with markup in the error
        if lease is None:
            break
        store.fail_task(lease, f"RuntimeError: {EVIL}")
        lease = store.claim("w", 60)
    client = make_client(store, storage)
    for url in (f"/jobs/{job.id}", f"/jobs/{job.id}/live", "/", "/jobs"):
        html = client.get(url).text
        assert "<script>window" not in html and "<img src=x" not in html, url
    html = client.get(f"/jobs/{job.id}").text
    assert "&lt;script&gt;window.__xss = 1&lt;/script&gt;" in html  # the description, as text
    assert store.get_job(job.id).state == "failed" and "RuntimeError: &lt;script&gt;" in html  # the error too
    missing = client.get("/datasets/tiny/versions/" + "%3Cscript%3E")
    assert missing.status_code == 404 and "<script>" not in missing.text and "&lt;script&gt;" in missing.text


# --- progress ---
def test_a_compiling_shard_is_named_on_the_page(make_client, store, storage):
    job = store.submit(parse_spec(tiny_spec(batches_per_shard=2)))
    lease = store.claim("w", 60)
    phase = compile_phase("walk_step", 1.3)
    assert store.heartbeat(lease, 60, photons=0, phase=phase)
    client = make_client(store, storage)
    html = client.get(f"/jobs/{job.id}").text
    assert phase in html and 'data-live="true"' in html and 'http-equiv="refresh"' in html
    assert "1 compiling" in html
    assert store.heartbeat(lease, 60, photons=100, phase=None)
    live = client.get(f"/jobs/{job.id}/live").text
    assert "compiling" not in live and "100" in live and live.count("<rect") >= 1
    assert client.get(f"/jobs/{job.id}/live").headers["x-job-state"] == "running"


# --- auth ---
def test_closed_reads_need_a_sign_in(make_client, published):
    store, storage, jobs = published
    client = make_client(store, storage, read_open=False)
    for url in ("/", f"/jobs/{jobs[0].id}", "/datasets/tiny/versions/1", "/datasets/tiny/versions/1/files/summary.json",
                "/datasets/tiny/versions/1/exports/csv"):
        r = client.get(url)
        assert r.status_code == 401 and 'action="/signin"' in r.text, url
    assert client.get("/", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    assert _sign_in(client, "wrong-token").status_code == 401
    r = _sign_in(client, next_url=f"/jobs/{jobs[0].id}")
    assert r.status_code == 303 and r.headers["location"] == f"/jobs/{jobs[0].id}"
    cookie = r.headers["set-cookie"]
    assert "HttpOnly" in cookie and "samesite=strict" in cookie.lower() and TOKEN not in cookie
    assert client.get(f"/jobs/{jobs[0].id}").status_code == 200
    assert client.get("/datasets/tiny/versions/1/files/summary.json").status_code == 200
    # the session cookie is not an API token
    session = client.cookies.get(SESSION_COOKIE)
    assert client.get("/v1/jobs", headers={"Authorization": f"Bearer {session}"}).status_code == 401


def _forged(value: str) -> str:
    """value with the last character of its signature changed (to one it is not)."""
    return value[:-1] + ("1" if value.endswith("0") else "0")


# Fixed ids: the values hold the time, and pytest-xdist's workers must collect the same names.
@pytest.mark.parametrize("value", [
    session_value("another-token"), session_value(TOKEN, now=time.time() - SESSION_SECONDS - 10),
    _forged(session_value(TOKEN)), "garbage", "",
], ids=["other-token", "expired", "forged-signature", "garbage", "empty"])
def test_forged_or_expired_sessions_are_refused(make_client, published, value):
    store, storage, _ = published
    client = make_client(store, storage, read_open=False)
    client.cookies.set(SESSION_COOKIE, value)
    assert client.get("/").status_code == 401


def test_cancel_and_delete_need_a_token_and_the_csrf_token(make_client, store, storage):
    job = store.submit(parse_spec(TINY_SPEC))
    client = make_client(store, storage)
    page = client.get(f"/jobs/{job.id}").text
    assert f'action="/jobs/{job.id}/cancel"' not in page and "Sign in</a> to cancel" in page
    csrf = _csrf(client, "/signin")
    assert client.post(f"/jobs/{job.id}/cancel", data={"csrf": csrf}).status_code == 401
    assert _sign_in(client).status_code == 303
    assert f'action="/jobs/{job.id}/cancel"' in client.get(f"/jobs/{job.id}").text
    assert client.post(f"/jobs/{job.id}/cancel", data={"other": "1"}).status_code == 403  # no CSRF token
    assert client.post(f"/jobs/{job.id}/cancel", data={"csrf": "x" * 43}).status_code == 403
    assert client.post(f"/jobs/{job.id}/cancel", data={"csrf": csrf},
                       headers={"Origin": "http://evil.example"}).status_code == 403
    assert client.post(f"/jobs/{job.id}/cancel", content=json.dumps({"csrf": csrf}),
                       headers={"Content-Type": "application/json"}).status_code == 400
    assert store.get_job(job.id).state == "queued"  # nothing above changed it
    r = client.post(f"/jobs/{job.id}/cancel", data={"csrf": csrf}, headers={"Origin": "http://testserver"},
                    follow_redirects=False)
    assert r.status_code == 303 and store.get_job(job.id).state == "cancelled"
    r = client.post(f"/jobs/{job.id}/delete", data={"csrf": csrf}, follow_redirects=False)
    assert r.status_code == 303 and r.headers["location"] == "/jobs"
    assert client.get(f"/jobs/{job.id}").status_code == 404


def test_a_published_job_cannot_be_deleted_from_its_page(make_client, published):
    store, storage, jobs = published
    client = make_client(store, storage)
    assert _sign_in(client).status_code == 303
    assert f'action="/jobs/{jobs[0].id}/delete"' not in client.get(f"/jobs/{jobs[0].id}").text
    r = client.post(f"/jobs/{jobs[0].id}/delete", data={"csrf": _csrf(client)})
    assert r.status_code == 409 and store.get_job(jobs[0].id).state == "succeeded"


def test_without_tokens_forms_are_open_but_still_need_the_csrf_token(make_client, sqlite_store, storage):
    job = sqlite_store.submit(parse_spec(TINY_SPEC))
    client = make_client(sqlite_store, storage, api_tokens=[])
    assert f'action="/jobs/{job.id}/cancel"' in client.get(f"/jobs/{job.id}").text
    assert client.post(f"/jobs/{job.id}/cancel", data={"csrf": "forged" * 7 + "x"}).status_code == 403
    assert client.post(f"/jobs/{job.id}/cancel", data={"csrf": _csrf(client, f"/jobs/{job.id}")}).status_code == 200
    assert sqlite_store.get_job(job.id).state == "cancelled"


def test_sign_out_ends_the_session(make_client, published):
    store, storage, _ = published
    client = make_client(store, storage, read_open=False)
    assert _sign_in(client).status_code == 303 and client.get("/").status_code == 200
    r = client.post("/signout", data={"csrf": _csrf(client)}, follow_redirects=False)
    assert r.status_code == 303 and client.get("/").status_code == 401


@pytest.mark.parametrize("target, expected", [
    ("/jobs/x", "/jobs/x"), ("//evil.example/", "/"), ("https://evil.example/", "/"), ("/\\evil", "/"),
    (None, "/"), ("", "/"),
])
def test_sign_in_only_returns_to_this_site(target, expected):
    assert safe_next(target) == expected


def test_the_pages_are_not_part_of_the_api_document(make_client, published):
    store, storage, _ = published
    paths = make_client(store, storage).get("/openapi.json").json()["paths"]
    assert all(p.startswith("/v1/") or p in ("/healthz", "/readyz", "/metrics") for p in paths), sorted(paths)


@pytest.mark.parametrize("stem, kind, caption", [
    ("rd-exits-g+0.5000-eta1.3000-inc0", "rd", "exits, g = 0.5, eta = 1.3, theta_i = 0 deg"),
    ("s-hybrid-g-0.3000-eta1.3300-inc45", "s", "hybrid, g = -0.3, eta = 1.33, theta_i = 45 deg"),
    ("albedo-map-exits-g+0.0000-eta1.3300", "albedo-map", "exits, g = 0, eta = 1.33"),
    ("something-new", "other", "something-new"),
])
def test_figure_captions_come_from_the_plot_file_names(stem, kind, caption):
    from service.pages.plots import _caption, _kind

    assert _kind(stem) == kind and _caption(stem, kind) == caption
