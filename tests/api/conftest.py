"""Fixtures of the API tests: the app from ``create_app`` under FastAPI's TestClient, with the
job store and storage dependencies overridden by a real store (SQLite in tmp_path, or a fresh
PostgreSQL schema) and a real local storage directory. No fakes of the store.
"""

from __future__ import annotations

import copy

import pytest
from fastapi.testclient import TestClient

import service.client as client_module
from service.api import create_app
from service.api.deps import get_storage, get_store
from service.client import ApiClient, main
from service.datasets import DatasetStorage
from service.settings import Settings
from service.store import JobStore
from tests.service.conftest import PG_ENV, drop_pg_schema, fresh_pg_schema_url, pg_base_url

TOKEN = "test-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}

# One channel, albedo 0.5, a handful of bins: a job that runs in seconds without torch.compile.
TINY_SPEC = {
    "name": "tiny",
    "medium": {"sigma_a": 1.0, "sigma_s": 1.0, "g": 0.0, "eta": 1.3},
    "photons": 200,
    "shards": 2,
    "batches_per_shard": 1,
    "seed": 7,
    "estimator": "exits",
    "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}},
}


@pytest.fixture
def cli(monkeypatch, make_client):
    """``cli(store, storage, capsys)`` -> run(*argv) -> (exit status, stdout, stderr): the client
    commands (``bssrdf submit``, ``status``, ``datasets``) in-process against the app."""

    def bind(store, storage, capsys):
        app = make_client(store, storage).app

        def fresh(args):  # one HTTP client per command, like the real thing
            return ApiClient("http://testserver", args.token, http=TestClient(app, base_url="http://testserver"))

        monkeypatch.setattr(client_module, "_client", fresh)

        def run(*argv: str) -> tuple[int, str, str]:
            capsys.readouterr()
            status = main(list(argv))
            out, err = capsys.readouterr()
            return status, out, err

        return run

    return bind


def job_count(store) -> int:
    """How many jobs the store holds (a refused submission must leave it unchanged)."""
    return len(store.list_jobs(limit=10_000))


def tiny_spec(**changes) -> dict:
    """A deep copy of TINY_SPEC with top-level keys changed."""
    spec = copy.deepcopy(TINY_SPEC)
    spec.update(changes)
    return spec


@pytest.fixture
def sqlite_store(tmp_path):
    s = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    yield s
    s.dispose()


@pytest.fixture
def pg_store():
    base = pg_base_url()
    if base is None:
        pytest.skip(f"PostgreSQL tests need {PG_ENV} (e.g. postgresql+psycopg://postgres@127.0.0.1:5432/test)")
    url, schema = fresh_pg_schema_url(base)
    s = JobStore(url)
    yield s
    s.dispose()
    drop_pg_schema(base, schema)


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def store(request):
    """A fresh, empty, real job store on each backend."""
    return request.getfixturevalue({"sqlite": "sqlite_store", "postgres": "pg_store"}[request.param])


@pytest.fixture
def storage(tmp_path):
    return DatasetStorage(str(tmp_path / "data"))


@pytest.fixture
def make_client(tmp_path):
    """``make_client(store, storage, **settings)`` -> a TestClient of ``create_app(Settings(...))``
    whose store and storage dependencies are overridden; tokens default to [TOKEN]."""
    clients = []

    def make(store, storage, **settings) -> TestClient:
        settings.setdefault("api_tokens", [TOKEN])
        app = create_app(Settings(data_dir=str(tmp_path / "unused-data-dir"), **settings))
        app.dependency_overrides[get_store] = lambda: store
        app.dependency_overrides[get_storage] = lambda: storage
        client = TestClient(app)
        client.__enter__()
        clients.append(client)
        return client

    yield make
    for c in clients:
        c.__exit__(None, None, None)


@pytest.fixture
def client(make_client, store, storage) -> TestClient:
    """The app with tokens [TOKEN], open reads, on the parametrized store."""
    return make_client(store, storage)


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    """A real SQLite store and storage holding one succeeded job: ``tiny`` versions 1 and 2
    (run in-process by the real worker loop). Read-only for the tests that use it."""
    from schema import parse_spec
    from service.worker import Worker

    root = tmp_path_factory.mktemp("published")
    store = JobStore(f"sqlite:///{root / 'jobs.sqlite'}")
    storage = DatasetStorage(str(root / "data"))
    jobs = [store.submit(parse_spec(TINY_SPEC)), store.submit(parse_spec(tiny_spec(seed=8)))]
    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    for job in jobs:
        assert store.get_job(job.id).state == "succeeded", store.get_job(job.id).error
    yield store, storage, [store.get_job(j.id) for j in jobs]
    store.dispose()
