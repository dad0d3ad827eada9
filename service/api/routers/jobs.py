"""``/v1/jobs``: submit, list, read, cancel and delete jobs."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Header, Query, Response, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.api.bodies import JSONRoute
from service.api.deps import AuthDep, JobDep, JobIdPath, ReadAuthDep, SettingsDep, StorageDep, StoreDep, lookup_job
from service.api.errors import error_responses
from service.api.limits import spec_limit_problems
from schema import parse_spec
from service.api.models import (
    IDEMPOTENCY_KEY_MAX, IDEMPOTENCY_KEY_PATTERN, JobCreate, JobList, JobPublic, MediumList, MediumProgressPublic,
)
from service.store import JobState

__all__ = ["router"]

# JSONRoute: a body is parsed as UTF-8 JSON and refused after the token (service.api.bodies).
router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=JSONRoute)

OFFSET_MAX = 2**31 - 1
"""Largest list offset (bound so that no database integer overflows)."""


def _idempotency_key(body: JobCreate, header: str | None) -> str | None:
    if header is not None and body.idempotency_key is not None and header != body.idempotency_key:
        raise RequestValidationError([{
            "type": "value_error", "loc": ("header", "Idempotency-Key"), "input": header,
            "msg": f"the Idempotency-Key header and the body's idempotency_key differ "
                   f"({body.idempotency_key!r}); send one of them, or the same value in both",
        }])
    return header if header is not None else body.idempotency_key


@router.post(
    "",
    summary="Submit a job",
    response_model=JobPublic,
    status_code=status.HTTP_201_CREATED,
    responses={200: {"model": JobPublic, "description": "Not a new job: the idempotency key names it, or a "
                     "live job or published version has this spec hash (`existing` says which); nothing is "
                     "recomputed."}, **error_responses(401, 409, 422, 503)},
)
def submit_job(
    _token: AuthDep,
    body: JobCreate,
    store: StoreDep,
    settings: SettingsDep,
    response: Response,
    idempotency_key: Annotated[str | None, Header(
        alias="Idempotency-Key", min_length=1, max_length=IDEMPOTENCY_KEY_MAX, pattern=IDEMPOTENCY_KEY_PATTERN,
        description="Same as the body's idempotency_key.")] = None,
) -> JobPublic:
    """Validate the spec, store the job (its shard tasks and merge task) and return it.

    An invalid spec is answered 422 with every bad field (``spec.medium.g`` ...), its allowed
    range and the value received, and so is a spec beyond a limit (photons per job, estimated
    CPU seconds per shard); nothing is stored. With an idempotency key, a retry with the same
    spec returns the stored job with status 200; another spec under the same key is 409. A spec
    whose hash (seed included) matches a published version or a live job returns that job with
    200 and ``existing`` set, unless ``force``.
    """
    key = _idempotency_key(body, idempotency_key)
    problems = spec_limit_problems(body.spec, settings)
    if problems:
        return JSONResponse({"detail": problems}, status_code=422)
    submitted = store.submit_unique(body.spec, idempotency_key=key, force=body.force)  # IdempotencyConflict -> 409
    job = submitted.job
    if submitted.existing is not None:
        response.status_code = status.HTTP_200_OK
    response.headers["Location"] = f"{router.prefix}/{job.id}"
    return JobPublic.from_record(job, store.progress(job.id), submitted.existing)


@router.get("", summary="List jobs", response_model=JobList, responses=error_responses(401, 422, 503))
def list_jobs(
    _token: ReadAuthDep,
    store: StoreDep,
    state: Annotated[JobState | None, Query(description="Only jobs in this state.")] = None,
    limit: Annotated[int, Query(ge=1, le=1000, description="Jobs per page.")] = 100,
    offset: Annotated[int, Query(ge=0, le=OFFSET_MAX, description="Jobs to skip.")] = 0,
) -> JobList:
    """Jobs, newest first (``progress`` is null here: read one job for it)."""
    jobs = store.list_jobs(state=state, limit=limit + 1, offset=offset)
    more = len(jobs) > limit
    return JobList(items=[JobPublic.from_record(j) for j in jobs[:limit]], limit=limit, offset=offset,
                   next_offset=offset + limit if more else None)


@router.get("/{job_id}", summary="Read a job and its progress", response_model=JobPublic,
            responses=error_responses(401, 404, 503))
def get_job(_token: ReadAuthDep, job_id: JobIdPath, store: StoreDep) -> JobPublic:
    """State, shards queued / running / done / failed, photons done, rate, ETA, error, and the
    dataset name and version once it succeeded."""
    # The job and its progress in one read (the status poll of every client and of bssrdf run).
    return JobPublic.from_record(*lookup_job(job_id, store.job_progress))


@router.get("/{job_id}/media", summary="Progress per medium", response_model=MediumList,
            responses=error_responses(401, 404, 422, 503))
def job_media(
    _token: ReadAuthDep,
    job: JobDep,
    store: StoreDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Media per page.")] = 100,
    offset: Annotated[int, Query(ge=0, le=OFFSET_MAX, description="Media to skip.")] = 0,
) -> MediumList:
    """For each medium of the job (a sweep's grid, in index order): its coordinates (albedo, g,
    eta), shards done / running / skipped, how far the merge has folded it, and its photons."""
    spec = parse_spec(job.spec_dict)
    media = spec.media()
    page = media[offset : offset + limit]
    per_medium = spec.photons * len(spec.incidence_deg)
    # Tasks are walk groups x shards: every medium of a group reports its group's shards.
    group_of = {m: k for k, g in enumerate(spec.walk_groups()) for m in g}
    first = group_of[page[0].index] if page else 0
    count = group_of[page[-1].index] - first + 1 if page else 1
    rows = {m.medium: m for m in store.medium_progress(job.id, spec.shards, offset=first, limit=count)}
    items = []
    for medium in page:
        p = rows.get(group_of[medium.index])  # no row: the job's tasks are gone (it was deleted meanwhile)
        items.append(MediumProgressPublic(
            medium=medium.index, albedo=list(medium.albedo), g=list(medium.g), eta=medium.eta,
            shards_total=spec.shards if p is None else p.shards_total, shards_done=0 if p is None else p.shards_done,
            shards_running=0 if p is None else p.shards_running, shards_skipped=0 if p is None else p.shards_skipped,
            shards_folded=0 if p is None else p.folded, merged=False if p is None else p.merged,
            photons_done=0 if p is None else p.photons_done, photons_total=per_medium * len(medium.albedo),
        ))  # fmt: skip
    more = offset + limit < len(media)
    return MediumList(job_id=job.id, media_total=len(media), items=items, limit=limit, offset=offset,
                      next_offset=offset + limit if more else None)


@router.post("/{job_id}/cancel", summary="Cancel a job", response_model=JobPublic,
             responses=error_responses(401, 404, 409, 503))
def cancel_job(_token: AuthDep, job: JobDep, store: StoreDep) -> JobPublic:
    """Stop new claims and release the job's leases; late commits are refused.

    Cancelling a cancelled job returns it unchanged; a succeeded or failed job is 409.
    """
    cancelled = store.cancel(job.id)  # JobNotActive -> 409
    return JobPublic.from_record(cancelled, store.progress(job.id))


@router.delete("/{job_id}", summary="Delete a job", response_model=JobPublic,
               responses=error_responses(401, 404, 409, 503))
def delete_job(_token: AuthDep, job: JobDep, store: StoreDep, storage: StorageDep) -> JobPublic:
    """Cancel the job if it is live, remove its tasks, stored shard results and job files; the
    answer is the job as it was deleted (then GET is 404). A job whose dataset version exists is
    that version's provenance: 409 until the version is deleted."""
    deleted = store.delete_job(job.id)  # JobPublished -> 409
    storage.discard_job(job.id)
    return JobPublic.from_record(deleted)
