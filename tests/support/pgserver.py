"""A PostgreSQL server of the test's own (never the shared one): initdb into a temporary directory,
started, restarted and stopped with pg_ctl as the ``postgres`` user, on one host of a
:class:`tests.support.netns.Network` (or on the machine itself).

    server = PgServer(net, "db")      # data directory made; listens on net.address("db"):5432
    server.start(); server.restart(); server.stop()
    server.url                        # postgresql+psycopg://postgres@198.18.0.1:5432/postgres

Durability is off (``fsync=off``, ``synchronous_commit=off``): the restarts tested are clean or
fast shutdowns, not power losses, and the walk should not wait for the disk.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["PgServer", "PG_BIN", "pg_unavailable"]

PG_BIN = Path("/usr/lib/postgresql/15/bin")


def pg_unavailable() -> str | None:
    """None if a private server can be made here, else why not."""
    if not (PG_BIN / "initdb").exists():
        return f"PostgreSQL server binaries not found in {PG_BIN} (apt-get install -y postgresql)"
    if subprocess.run(["id", "postgres"], capture_output=True).returncode != 0:
        return "no 'postgres' system user to run a private PostgreSQL server"
    return None


class PgServer:
    """One private PostgreSQL cluster; :meth:`cleanup` stops it and removes its files."""

    def __init__(self, net, host: str, port: int = 5432) -> None:
        self.net, self.host, self.port = net, host, port
        self.address = net.address(host)
        # Not under pytest's tmp_path: the postgres user must be able to reach the directory.
        self.root = Path(tempfile.mkdtemp(prefix="bssrdf-pg-"))
        self.data = self.root / "data"
        self.log = self.root / "server.log"
        shutil.chown(self.root, "postgres", "postgres")
        self._as_postgres([str(PG_BIN / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust",
                           "--no-sync", "-E", "UTF8"], on_host=False)
        with open(self.data / "postgresql.conf", "a") as conf:
            conf.write(f"listen_addresses = '{self.address}'\nport = {port}\nunix_socket_directories = '{self.root}'\n"
                       "fsync = off\nsynchronous_commit = off\nfull_page_writes = off\nmax_connections = 100\n")
        with open(self.data / "pg_hba.conf", "a") as hba:
            hba.write(f"host all all {self.address.rsplit('.', 1)[0]}.0/24 trust\n")

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@{self.address}:{self.port}/postgres"

    def _as_postgres(self, argv: list[str], on_host: bool = True, timeout: float = 60) -> None:
        cmd = ["runuser", "-u", "postgres", "--", *argv]
        if on_host:
            cmd = self.net.command(self.host, cmd)
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        if done.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(argv[:2])} failed: {done.stderr.strip()} {log}")

    def _ctl(self, *args: str) -> None:
        self._as_postgres([str(PG_BIN / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60",
                           *args])

    def start(self) -> None:
        self._ctl("start")

    def restart(self) -> None:
        """Fast shutdown (every session is disconnected, transactions in flight roll back), then start."""
        self._ctl("restart", "-m", "fast")

    def stop(self) -> None:
        self._ctl("stop", "-m", "immediate")

    def cleanup(self) -> None:
        try:
            if (self.data / "postmaster.pid").exists():
                self.stop()
        except Exception:
            pass
        shutil.rmtree(self.root, ignore_errors=True)
