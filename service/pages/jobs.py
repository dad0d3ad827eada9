"""The jobs pages: the front page, the jobs list, a job with its progress, cancel and delete.

    GET  /                      jobs (newest first) and datasets
    GET  /jobs                  every job, 50 a page (?state=running&offset=50)
    GET  /jobs/{id}             state, progress (overall and per medium), error, result, spec
    GET  /jobs/{id}/live        the page's progress section alone (the page's script polls it)
    POST /jobs/{id}/cancel      signed-in users (form with the CSRF token), then back to the job
    POST /jobs/{id}/delete      signed-in users, then to /jobs

A running job's page replaces its progress section every two seconds with ``/live``
(``static/job.js``); without script a ``<noscript>`` meta refresh reloads it every five seconds.
"""

from __future__ import annotations

import re
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import RedirectResponse, Response
from starlette.concurrency import run_in_threadpool

from schema import parse_spec
from service.api.deps import JOB_ID_PATTERN, SettingsDep, StorageDep, StoreDep
from service.pages.auth import PageError, can_read, can_write, check_post, read_form
from service.pages.render import bar_segments, page
from service.store import JobNotActive, JobNotFound, JobProgress, JobPublished, JobRecord, JobState, JobStore
from service.store.states import TERMINAL_JOB_STATES

__all__ = ["router", "require_read", "media_rows", "MEDIA_PER_PAGE"]

router = APIRouter(include_in_schema=False)

JOBS_PER_PAGE = 50
MEDIA_PER_PAGE = 100


def require_read(request: Request, settings) -> None:
    """401 (the sign-in form) unless this request may read (the API's rule)."""
    if not can_read(request, settings):
        raise PageError(401, "this server's pages need a token to read (BSSRDF_READ_OPEN=false): sign in with "
                                 "one of its API tokens")


def _job(store: JobStore, job_id: str) -> tuple[JobRecord, JobProgress]:
    """The job and its progress, or 404 (an id that is no UUID is not looked up)."""
    try:
        if re.fullmatch(JOB_ID_PATTERN, job_id) is None:
            raise JobNotFound(job_id[:40])
        return store.job_progress(job_id)
    except JobNotFound:
        raise PageError(404, "no job with this id (deleted, or never submitted); the jobs are listed on /jobs") \
            from None


def media_rows(store: JobStore, job: JobRecord, offset: int = 0) -> tuple[list[dict[str, Any]], int]:
    """One page of the job's media with their progress, and the number of media."""
    spec = parse_spec(job.spec_dict)
    media = spec.media()
    page_media = media[offset: offset + MEDIA_PER_PAGE]
    per_medium = spec.photons * len(spec.incidence_deg)
    rows = {m.medium: m for m in store.medium_progress(job.id, spec.shards, offset=offset, limit=MEDIA_PER_PAGE)}
    out = []
    for medium in page_media:
        p = rows.get(medium.index)
        total = spec.shards if p is None else p.shards_total
        done, running = (0, 0) if p is None else (p.shards_done + p.shards_skipped, p.shards_running)
        folded = 0 if p is None else p.folded
        out.append({"index": medium.index, "albedo": medium.albedo, "g": medium.g, "eta": medium.eta,
                    "total": total, "done": 0 if p is None else p.shards_done, "running": running,
                    "skipped": 0 if p is None else p.shards_skipped, "folded": folded,
                    "merged": False if p is None else p.merged,
                    "photons": 0 if p is None else p.photons_done,
                    "photons_total": per_medium * len(medium.albedo),
                    "bar": bar_segments(total, folded, done, running)})
    return out, len(media)


def _status(job: JobRecord, p: JobProgress) -> str:
    """One sentence saying what the job is doing now."""
    if p.state == JobState.QUEUED and not p.shards_running:
        return "waiting for a worker to claim its first shard"
    if p.phase and not p.photons_done:
        return p.phase
    if p.state == JobState.MERGING:
        return "every shard is done: merging the tables and publishing the version"
    return {JobState.SUCCEEDED: "done: the dataset version is published",
            JobState.FAILED: "failed (the error is below)", JobState.CANCELLED: "cancelled"}.get(
        JobState(p.state), "walking photons")


def _live_context(store: JobStore, job: JobRecord, p: JobProgress, offset: int) -> dict[str, Any]:
    media, media_total = media_rows(store, job, offset)
    return {"job": job, "p": p, "status_text": _status(job, p), "media": media, "media_total": media_total,
            "media_offset": offset, "media_per_page": MEDIA_PER_PAGE,
            "live": JobState(p.state) not in TERMINAL_JOB_STATES,
            "overall": bar_segments(p.shards_total, p.tasks_folded, p.shards_done + p.shards_skipped, p.shards_running)}


def _offset(value: str | None, limit: int = 2**31 - 1) -> int:
    return int(value) if value and value.isascii() and value.isdigit() and len(value) < 10 and int(value) <= limit else 0


@router.get("/")
def index(request: Request, settings: SettingsDep, store: StoreDep) -> Response:
    require_read(request, settings)
    jobs = store.list_jobs(limit=20)
    progress = {j.id: store.progress(j.id) for j in jobs if j.state not in TERMINAL_JOB_STATES}
    return page(request, settings, "index.html", jobs=jobs, progress=progress, datasets=store.list_datasets(),
                more_jobs=len(jobs) == 20)


@router.get("/jobs")
def jobs_list(request: Request, settings: SettingsDep, store: StoreDep, state: str | None = None,
              offset: str | None = None) -> Response:
    require_read(request, settings)
    states = [s.value for s in JobState]
    if state is not None and state not in states:
        raise PageError(400, f"state must be one of {', '.join(states)}; received {state[:40]!r}")
    start = _offset(offset)
    jobs = store.list_jobs(state=JobState(state) if state else None, limit=JOBS_PER_PAGE + 1, offset=start)
    progress = {j.id: store.progress(j.id) for j in jobs[:JOBS_PER_PAGE] if j.state not in TERMINAL_JOB_STATES}
    return page(request, settings, "jobs.html", jobs=jobs[:JOBS_PER_PAGE], progress=progress, state=state,
                states=states, offset=start, per_page=JOBS_PER_PAGE, more=len(jobs) > JOBS_PER_PAGE)


@router.get("/jobs/{job_id}")
def job_page(request: Request, job_id: str, settings: SettingsDep, store: StoreDep,
             media_offset: str | None = None) -> Response:
    require_read(request, settings)
    job, p = _job(store, job_id)
    return page(request, settings, "job.html", **_live_context(store, job, p, _offset(media_offset)))


@router.get("/jobs/{job_id}/live")
def job_live(request: Request, job_id: str, settings: SettingsDep, store: StoreDep,
             media_offset: str | None = None) -> Response:
    require_read(request, settings)
    job, p = _job(store, job_id)
    response = page(request, settings, "job_live.html", **_live_context(store, job, p, _offset(media_offset)))
    response.headers["X-Job-State"] = str(p.state)
    return response


async def _write_form(request: Request, settings) -> None:
    form = await read_form(request)
    check_post(request, form)
    if not can_write(request, settings):
        raise PageError(401, "cancelling or deleting a job needs a token: sign in with one of this server's "
                                 "API tokens")


@router.post("/jobs/{job_id}/cancel")
async def job_cancel(request: Request, job_id: str, settings: SettingsDep, store: StoreDep) -> Response:
    await _write_form(request, settings)
    job, _ = await run_in_threadpool(_job, store, job_id)
    try:
        await run_in_threadpool(store.cancel, job.id)
    except JobNotActive as exc:
        raise PageError(409, f"{exc}") from None
    return RedirectResponse(f"/jobs/{job.id}", status_code=303)


@router.post("/jobs/{job_id}/delete")
async def job_delete(request: Request, job_id: str, settings: SettingsDep, store: StoreDep,
                     storage: StorageDep) -> Response:
    await _write_form(request, settings)
    job, _ = await run_in_threadpool(_job, store, job_id)
    try:
        await run_in_threadpool(store.delete_job, job.id)
    except JobPublished as exc:
        raise PageError(409, f"{exc}") from None
    await run_in_threadpool(storage.discard_job, job.id)
    return RedirectResponse("/jobs", status_code=303)
