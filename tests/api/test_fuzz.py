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
- a refused request (4xx) stored nothing: no commit reached the job store and the storage's
  files are the same before and after it (:class:`StoreWatch`).

Not checked: ``positive_data_acceptance`` (a schema-valid request is accepted), because the spec
has cross-field rules JSON Schema cannot state (``shards <= photons``, one of ``medium`` or
``sweep``, total bins, cost limits): those refusals are 422s naming the field, which the second
property checks.

Two more fuzzers, plain hypothesis on the same app and store: integer literals of up to 30,000
digits in place of any value of a submission or under a new key (JSON bounds no number; Python
converts at most 4300 digits), and requests with up to 130 generated header fields of up to 40 KB
each (past the head limits: 431). Same properties: no 5xx, a reason, nothing stored. The server's
own parser gets arbitrary heads in tests/api/test_http_limits.py.

Budget: EXAMPLES generated requests per operation, generation mode and token setting, about 45 s
here with the published fixture, and INT_EXAMPLES / HEADER_EXAMPLES (a few seconds each);
``BSSRDF_FUZZ_SCALE`` multiplies them (tests/support/fuzzing.py).
"""

from __future__ import annotations

import os
import sqlite3

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis import GenerationMode
from schemathesis.core.parameters import ParameterLocation

from service.api import create_app
from service.api.deps import get_storage, get_store
from service.settings import Settings
from tests.api.conftest import TINY_SPEC, TOKEN
from tests.support.fuzzing import examples

pytestmark = pytest.mark.slow

EXAMPLES = examples(25)
"""Requests per operation and token setting; each generation mode gets this many."""


class StoreWatch:
    """Whether anything was stored between two looks: a commit to the job store or a file in storage.

    The job store is SQLite: ``PRAGMA data_version`` on a connection of our own changes exactly when
    another connection (any of the store's) has committed a change to the database file since the
    previous look (https://www.sqlite.org/pragma.html#pragma_data_version). That is O(1) per look
    whatever the store holds; reading every row back was O(rows), and an accepted fuzzed job of
    100,000 shard tasks made every later look take seconds. Files under the storage root are
    listed with their sizes.
    """

    def __init__(self, store, storage):
        self._db = sqlite3.connect(f"file:{store.engine.url.database}?mode=ro", uri=True)
        self._root = storage.uri

    def look(self) -> tuple:
        version = self._db.execute("PRAGMA data_version").fetchone()[0]
        files = []
        for root, _dirs, names in os.walk(self._root):
            files += [(os.path.relpath(os.path.join(root, n), self._root), os.path.getsize(os.path.join(root, n)))
                      for n in names]
        return version, tuple(sorted(files))


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
    """(store, storage, jobs, watch): the ``published`` store, two versions of ``tiny``, their jobs
    and a :class:`StoreWatch` over them."""
    store, storage, jobs = published
    return store, storage, jobs, StoreWatch(store, storage)


def fuzz_schema(fuzz_target, tmp_path_factory, **settings):
    """The schemathesis schema of ``create_app(Settings(api_tokens=[TOKEN], **settings))`` over
    the fuzz target, generating valid and invalid requests."""
    store, storage, jobs, _watch = fuzz_target
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
    _store, _storage, _jobs, watch = fuzz_target
    before = watch.look()
    response = case.call_and_validate(
        headers=headers, excluded_checks=[schemathesis.checks.positive_data_acceptance])
    if 400 <= response.status_code < 500:
        assert_reason(response)
        after = watch.look()
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


# -- integers of any length anywhere in a body, and arbitrary headers (hypothesis, not the schema) ---------

INT_EXAMPLES = examples(60)
"""Bodies with long integer literals per run (a few seconds)."""
HEADER_EXAMPLES = examples(80)
"""Requests with generated headers per run (a few seconds)."""


@pytest.fixture(scope="module")
def fuzz_client(fuzz_target, tmp_path_factory):
    """A TestClient of the fuzz target app (reads open, tokens [TOKEN])."""
    from fastapi.testclient import TestClient

    store, storage, _jobs, _watch = fuzz_target
    app = create_app(Settings(data_dir=str(tmp_path_factory.mktemp("unused")), api_tokens=[TOKEN]))
    app.dependency_overrides[get_store] = lambda: store
    app.dependency_overrides[get_storage] = lambda: storage
    with TestClient(app) as client:
        yield client


def _paths(value, prefix=()) -> list[tuple]:
    """Every key path of a JSON value (its objects' keys and list indices), the root's included."""
    out = [prefix]
    if isinstance(value, dict):
        for k, v in value.items():
            out += _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            out += _paths(v, prefix + (i,))
    return out


def _place(body, path: tuple, value) -> None:
    """Set the value at ``path`` (a new key where there is none); skipped when an earlier placement
    replaced a container on the way."""
    parent = body
    for k in path[:-1]:
        if not isinstance(parent, (dict, list)):
            return
        parent = parent[k]
    if isinstance(parent, (dict, list)):
        parent[path[-1]] = value


BODY = {"spec": {**TINY_SPEC, "incidence_deg": [0.0, 30.0]}, "idempotency_key": "fuzz-int", "force": False}
TARGETS = [p for p in _paths(BODY) if p] + [("unknown",), ("spec", "unknown"), ("spec", "medium", "unknown")]


@given(st.lists(st.tuples(st.sampled_from(TARGETS), st.integers(1, 30_000), st.booleans(), st.integers(1, 9)),
                min_size=1, max_size=3))
@settings(max_examples=INT_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_fuzz_integers_of_any_length_anywhere(fuzz_client, fuzz_target, placements):
    """Long integer literals (up to 30,000 digits: JSON has no bound, Python converts 4300 at most)
    in place of any value of a submission, or under a new key: never a 5xx; a refusal names a
    field and stores nothing."""
    import copy
    import json

    body, literals = copy.deepcopy(BODY), {}
    for i, (path, digits, negative, lead) in enumerate(placements):
        marker = f"INT{i}MARK"
        literals[json.dumps(marker)] = "-" * negative + str(lead) + ("0123456789" * (digits // 10 + 1))[:digits - 1]
        _place(body, path, marker)
    text = json.dumps(body)
    for marker, literal in literals.items():
        text = text.replace(marker, literal)
    _store, _storage, _jobs, watch = fuzz_target
    before = watch.look()
    r = fuzz_client.post("/v1/jobs", content=text.encode(), headers={"Authorization": f"Bearer {TOKEN}",
                                                                     "content-type": "application/json"})
    assert r.status_code < 500, r.text
    assert len(r.content) < 20_000, len(r.content)
    if 400 <= r.status_code < 500:
        assert_reason(r)
        assert watch.look() == before


_TOKEN_CHARS = "!#$%&'*+-.^_`|~0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"
_VALUE_CHARS = st.characters(min_codepoint=0x20, max_codepoint=0xFF, exclude_characters="\x7f")


@given(headers=st.lists(st.tuples(st.text(_TOKEN_CHARS, min_size=1, max_size=30),
                                  st.one_of(st.text(_VALUE_CHARS, max_size=200),
                                            st.integers(0, 40_000).map(lambda n: "v" * n))),
                        max_size=130),
       route=st.sampled_from([("GET", "/healthz"), ("GET", "/v1/jobs"), ("POST", "/v1/jobs"),
                              ("GET", "/v1/datasets/tiny/versions/1/files/summary.json")]))
@settings(max_examples=HEADER_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck), database=None)
def test_fuzz_headers(fuzz_client, fuzz_target, headers, route):
    """Any number of header fields of any size (Authorization, Range, If-Range, Content-Type and
    Idempotency-Key among the names the generator may hit): never a 5xx; past the limits, 431."""
    method, path = route
    sent = [(name.lower().encode(), value.encode("latin-1")) for name, value in headers
            if name.lower() not in ("content-length", "host", "transfer-encoding")]
    _store, _storage, _jobs, watch = fuzz_target
    before = watch.look()
    r = fuzz_client.request(method, path, headers=sent, content=b'{"spec": {}}' if method == "POST" else None)
    assert r.status_code < 500, r.text[:500]
    size = len(path) + sum(len(n) + len(v) + 4 for n, v in sent)
    if size > 16384 + 200 or len(sent) > 100:  # the defaults; the client adds a few small headers of its own
        assert r.status_code == 431, (size, len(sent), r.status_code)
    if 400 <= r.status_code < 500:
        assert_reason(r)
        assert watch.look() == before
