"""A pgbouncer process of one's own in front of a PostgreSQL server, configured from
``deploy/pgbouncer/pgbouncer.ini`` (for ``bench.fleet`` and its test).

    with Pgbouncer("postgresql+psycopg://postgres@127.0.0.1:5432/test", "bench_db") as pool:
        pool.url        # postgresql+psycopg://postgres@127.0.0.1:PORT/bssrdf, through the pooler
        pool.pools()    # SHOW POOLS of the admin console: client and server connections now

Every setting of the deploy file is kept (``pool_mode = transaction``, ``max_client_conn``,
``default_pool_size``, ``reserve_pool_size``, ``server_idle_timeout``) except what must differ
for a private process: it listens on a free loopback port, takes ``trust`` authentication (the
server it fronts trusts loopback), its one ``[databases]`` entry (``bssrdf``) points at the
given server and database, and its files live in a temporary directory. A setting this
pgbouncer does not know (``max_prepared_statements`` is new in 1.21; Debian 12 ships 1.18) is
dropped and listed in ``dropped``: the store prepares no server-side statements
(``service.store.engine.PG_CONNECT_ARGS``), so it needs none. pgbouncer refuses to run as root;
as root the process runs as the ``postgres`` user.
"""

from __future__ import annotations

import configparser
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import sqlalchemy as sa
from sqlalchemy.engine import make_url

__all__ = ["Pgbouncer", "pgbouncer_binary", "pgbouncer_unavailable", "fresh_database", "drop_database", "database_url",
           "DEPLOY_INI"]

DEPLOY_INI = Path(__file__).resolve().parents[1] / "deploy" / "pgbouncer" / "pgbouncer.ini"
_NEWER_SETTINGS = {"max_prepared_statements": (1, 21)}
"""Settings of the deploy file and the pgbouncer version that introduced each."""


def pgbouncer_binary() -> str | None:
    """Path of the pgbouncer executable (Debian puts it in /usr/sbin), or None."""
    return shutil.which("pgbouncer") or next((p for p in ("/usr/sbin/pgbouncer",) if os.access(p, os.X_OK)), None)


def pgbouncer_unavailable() -> str | None:
    """None if a pgbouncer can be started here, else why not."""
    if pgbouncer_binary() is None:
        return "pgbouncer is not installed (Debian: apt-get install -y pgbouncer)"
    if os.geteuid() == 0 and subprocess.run(["id", "postgres"], capture_output=True).returncode != 0:
        return "pgbouncer refuses to run as root and there is no 'postgres' user to run it as"
    return None


def _version(binary: str) -> tuple[int, int]:
    out = subprocess.run([binary, "--version"], capture_output=True, text=True, timeout=10).stdout
    major, minor = out.split()[1].split(".")[:2]  # "PgBouncer 1.18.0"
    return int(major), int(minor)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Pgbouncer:
    """A private pgbouncer for ``database`` on the server of ``server_url`` (module docstring)."""

    def __init__(self, server_url: str, database: str, *, ini: Path = DEPLOY_INI, **overrides: object) -> None:
        reason = pgbouncer_unavailable()
        if reason:
            raise RuntimeError(reason)
        self.binary = pgbouncer_binary()
        self.version = _version(self.binary)
        server = make_url(server_url)
        self.user = server.username or "postgres"
        self.port = _free_port()
        self.root = Path(tempfile.mkdtemp(prefix="bssrdf-pgbouncer-"))
        conf = configparser.ConfigParser()
        conf.read(ini)
        settings = dict(conf["pgbouncer"])
        self.dropped = [k for k, since in _NEWER_SETTINGS.items() if k in settings and self.version < since]
        for k in self.dropped:
            del settings[k]
        settings.update(
            listen_addr="127.0.0.1", listen_port=str(self.port), auth_type="trust",
            auth_file=str(self.root / "userlist.txt"), unix_socket_dir="", admin_users=self.user,
            logfile=str(self.root / "pgbouncer.log"), pidfile=str(self.root / "pgbouncer.pid"),
        )
        settings.update({k: str(v) for k, v in overrides.items()})
        self.settings = settings
        (self.root / "userlist.txt").write_text(f'"{self.user}" ""\n')
        host, port = server.host or "127.0.0.1", server.port or 5432
        lines = ["[databases]", f"bssrdf = host={host} port={port} dbname={database} user={self.user}", "",
                 "[pgbouncer]", *(f"{k} = {v}" for k, v in settings.items())]
        (self.root / "pgbouncer.ini").write_text("\n".join(lines) + "\n")
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        """SQLAlchemy URL of the pooled database."""
        return f"postgresql+psycopg://{self.user}@127.0.0.1:{self.port}/bssrdf"

    def start(self, timeout: float = 30.0) -> "Pgbouncer":
        # One descriptor per client and server connection: raise the soft limit (1024 under a
        # login shell's PAM defaults) to what max_client_conn needs, or to the hard limit.
        nofile = int(self.settings.get("max_client_conn", 100)) + 200
        argv = ["sh", "-c", 'ulimit -n "$1" 2>/dev/null || ulimit -n "$(ulimit -Hn)"; shift; exec "$@"', "sh",
                str(nofile), self.binary, str(self.root / "pgbouncer.ini")]
        if os.geteuid() == 0:
            shutil.chown(self.root, self.user)
            for f in self.root.iterdir():
                shutil.chown(f, self.user)
            argv = ["runuser", "-u", self.user, "--", *argv]
        self.process = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"pgbouncer did not start: {self.log()[-2000:]}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=1).close()
                return self
            except OSError:
                time.sleep(0.05)

    @property
    def pid(self) -> int:
        """The pgbouncer process (from its pidfile; ``process`` may be runuser's)."""
        return int((self.root / "pgbouncer.pid").read_text().split()[0])

    def log(self) -> str:
        path = self.root / "pgbouncer.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def pools(self) -> dict[str, int]:
        """The ``bssrdf`` pool from ``SHOW POOLS``: cl_active, cl_waiting, sv_active, sv_idle, ...,
        maxwait_us (the longest a client has waited for a server connection, now)."""
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user=self.user, dbname="pgbouncer", connect_timeout=10,
                             autocommit=True, cursor_factory=psycopg.ClientCursor) as conn:
            cur = conn.execute("SHOW POOLS")
            cols = [c.name for c in cur.description]
            for row in cur.fetchall():
                r = dict(zip(cols, row))
                if r["database"] == "bssrdf":
                    out = {k: int(v) for k, v in r.items() if isinstance(v, int)}
                    out["maxwait_us"] = 1_000_000 * out.get("maxwait", 0) + out.get("maxwait_us", 0)
                    return out
        return {}

    def stop(self) -> None:
        """SIGTERM (immediate shutdown), then remove the files."""
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> "Pgbouncer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def fresh_database(server_url: str, prefix: str = "bench") -> str:
    """CREATE DATABASE with a new name on the server; its name (drop with :func:`drop_database`)."""
    import uuid

    name = f"{prefix}_{uuid.uuid4().hex[:10]}"
    engine = sa.create_engine(server_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.exec_driver_sql(f'CREATE DATABASE "{name}"')
    engine.dispose()
    return name


def drop_database(server_url: str, name: str) -> None:
    """DROP DATABASE ... WITH (FORCE): sessions still open (a pooler's) are ended."""
    engine = sa.create_engine(server_url, isolation_level="AUTOCOMMIT")
    with engine.connect() as conn:
        conn.exec_driver_sql(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')
    engine.dispose()


def database_url(server_url: str, name: str) -> str:
    """``server_url`` with another database name."""
    return make_url(server_url).set(database=name).render_as_string(hide_password=False)
