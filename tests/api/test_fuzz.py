"""Fuzzing the HTTP API from its own OpenAPI document (schemathesis, in-process ASGI, no network).

Every operation is called with generated requests, valid and invalid ones (schema-valid and
schema-violating bodies, path and query parameters, headers), with a valid token and without
one, against a real SQLite store holding two published versions and a real storage directory.
Properties checked on every answer:

- never a 5xx (schemathesis ``not_a_server_error``); answers match the documented status codes,
  content types and response schemas (the default checks), and a schema-invalid request is
  refused (``negative_data_rejection``);
- every 4xx is ``{"detail": ...}`` with a reason: a 422 lists problems each naming its field
  and saying what is wrong; any other 4xx is one non-empty sentence;
- a refused request (4xx) stored nothing: the job store's rows and the storage's files are the
  same before and after it.

Not checked: ``positive_data_acceptance`` (a schema-valid request is accepted), because the spec
has cross-field rules JSON Schema cannot state (``shards <= photons``, one of ``medium`` or
``sweep``, total bins, cost limits): those refusals are 422s naming the field, which the second
property checks.

Budget: EXAMPLES generated requests per operation, generation mode and token setting, about 45 s
here with the published fixture; ``BSSRDF_FUZZ_SCALE`` multiplies it (tests/support/fuzzing.py).
"""

from __future__ import annotations

import hashlib
import os

import pytest
import schemathesis
import sqlalchemy as sa
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.core.parameters import ParameterLocation

from service.api import create_app
from service.api.deps import get_storage, get_store
from service.settings import Settings
from service.store import tables
from tests.api.conftest import TOKEN
from tests.support.fuzzing import examples

pytestmark = pytest.mark.slow

EXAMPLES = examples(25)
"""Requests per operation and token setting; each generation mode gets this many."""


def store_snapshot(store, storage) -> tuple:
    """Everything a request could have stored: every row of every table (shard payloads by their
    digest) and every file under the storage root with its size."""
    rows = []
    with store.engine.connect() as conn:
        for table in tables.metadata.sorted_tables:
            order = [c for c in table.primary_key.columns] or list(table.columns)
            for row in conn.execute(sa.select(table).order_by(*order)):
                rows.append((table.name, tuple(hashlib.sha256(v).hexdigest() if isinstance(v, bytes) else v
                                               for v in row)))
    files = []
    for root, _dirs, names in os.walk(storage.uri):
        files += [(os.path.relpath(os.path.join(root, n), storage.uri), os.path.getsize(os.path.join(root, n)))
                  for n in names]
    return tuple(rows), tuple(sorted(files))


def assert_reason(response) -> None:
    """A 4xx says why: ``detail`` is a list of problems naming their fields (422), or a sentence
    (HEAD answers have no body, by definition)."""
    if response.request.method == "HEAD":
        return
    body = response.json()
    assert isinstance(body, dict) and "detail" in body, response.text
    detail = body["detail"]
    if response.status_code == 422:
        assert isinstance(detail, list) and detail, response.text
        for p in detail:
            assert isinstance(p.get("field"), str) and p["field"], response.text
            assert isinstance(p.get("message"), str) and len(p["message"]) > 10, response.text
    else:
        assert isinstance(detail, str) and len(detail) > 10, response.text


@pytest.fixture(scope="module")
def fuzz_target(published):
    """(store, storage, jobs): the ``published`` store, two versions of ``tiny`` and their jobs."""
    return published


def fuzz_schema(fuzz_target, tmp_path_factory, **settings):
    """The schemathesis schema of ``create_app(Settings(api_tokens=[TOKEN], **settings))`` over
    the fuzz target, generating valid and invalid requests."""
    store, storage, jobs = fuzz_target
    app = create_app(Settings(data_dir=str(tmp_path_factory.mktemp("unused")), api_tokens=[TOKEN], **settings))
    app.dependency_overrides[get_store] = lambda: store
    app.dependency_overrides[get_storage] = lambda: storage
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    schema.config.generation.update(modes=[GenerationMode.POSITIVE, GenerationMode.NEGATIVE], max_examples=EXAMPLES)

    known = {"name": ["tiny"], "version": ["1", "2", "latest"], "job_id": [j.id for j in jobs],
             "filename": ["summary.json", "metadata.json", "radial.parquet"], "format": ["npz", "csv"]}
    deletable = {**known, "version": ["1"]}  # version 2 stays, for the downloads

    @schema.hook
    def flatmap_case(context, case):
        # Half the time, aim a case whose path is valid at what exists (a published dataset, a
        # real job id), so the fuzzer reaches the routes' code past the lookups, not only their
        # 404s. Cases generated to have an invalid path keep it.
        if not case.path_parameters or (case.meta is not None and case.meta.is_negative_at(ParameterLocation.PATH)):
            return st.just(case)
        values = deletable if context.operation.method.upper() == "DELETE" else known
        aimed = st.fixed_dictionaries({k: st.sampled_from(values[k]) if k in values else st.just(v)
                                       for k, v in case.path_parameters.items()})

        def aim(parameters):
            case.path_parameters = parameters
            return case

        return st.one_of(st.just(case), aimed.map(aim))

    return schema


@pytest.fixture(scope="module")
def open_reads_schema(fuzz_target, tmp_path_factory):
    """Reads open (the default): a token is needed to write only."""
    return fuzz_schema(fuzz_target, tmp_path_factory, read_open=True)


@pytest.fixture(scope="module")
def closed_reads_schema(fuzz_target, tmp_path_factory):
    """BSSRDF_READ_OPEN=false: every endpoint but the probes and the version needs a token."""
    return fuzz_schema(fuzz_target, tmp_path_factory, read_open=False)


open_reads = schemathesis.pytest.from_fixture("open_reads_schema")
closed_reads = schemathesis.pytest.from_fixture("closed_reads_schema")


def fuzz_one(case, fuzz_target, headers: dict[str, str]) -> None:
    """Call the generated request; check the answer and, when refused, that nothing was stored."""
    store, storage, _jobs = fuzz_target
    before = store_snapshot(store, storage)
    response = case.call_and_validate(
        headers=headers, excluded_checks=[schemathesis.checks.positive_data_acceptance])
    if 400 <= response.status_code < 500:
        assert_reason(response)
        after = store_snapshot(store, storage)
        assert after == before, f"{case.method} {case.formatted_path} -> {response.status_code} changed the store"


@open_reads.parametrize()
@settings(deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_fuzz_api_with_a_token(case, fuzz_target):
    fuzz_one(case, fuzz_target, {"Authorization": f"Bearer {TOKEN}"})


@closed_reads.parametrize()
@settings(deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_fuzz_api_without_a_token(case, fuzz_target):
    if case.headers:
        case.headers.pop("Authorization", None)
    fuzz_one(case, fuzz_target, {})
