"""The API tests' fixtures (a real store on SQLite and PostgreSQL, storage, the app under
TestClient, a published dataset) serve the page tests too."""

from tests.api.conftest import make_client, pg_store, published, sqlite_store, storage, store  # noqa: F401
