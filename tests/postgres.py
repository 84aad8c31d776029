"""A real PostgreSQL server for tests: Debian's binaries, a throw-away cluster on a free loopback port,
password (SCRAM) authentication, stopped and removed afterwards. PostgreSQL refuses to run as root,
so under root the cluster belongs to the `postgres` user the Debian package creates."""

from __future__ import annotations

import os
import pwd
import secrets
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import _free_port

HOST, USER = "127.0.0.1", "sim2act"


@dataclass(frozen=True)
class PostgresServer:
    port: int
    password: str
    log: Path
    pg_ctl: tuple[str, ...]  # pg_ctl -D <data>, as the cluster's owner
    options: str  # the server's own: loopback, port, socket folder

    def stop(self) -> None:
        """The database goes away at once (`-m immediate`: no shutdown checkpoint, as a crash)."""
        self._pg_ctl("-m", "immediate", "-w", "stop")

    def start(self) -> None:
        self._pg_ctl("-l", str(self.log), "-w", "-t", "60", "start", "-o", self.options)

    def _pg_ctl(self, *args: str) -> None:
        done = subprocess.run([*self.pg_ctl, *args], capture_output=True, text=True, timeout=90)
        if done.returncode:
            raise RuntimeError(f"pg_ctl {' '.join(args)} failed: {done.stdout[-1500:]}{done.stderr[-1500:]}")

    def url(self, database: str, driver: str = "postgresql") -> str:
        return f"{driver}://{USER}:{self.password}@{HOST}:{self.port}/{database}"

    def query(self, database: str, sql: str) -> list[tuple]:
        import psycopg2

        with psycopg2.connect(host=HOST, port=self.port, user=USER, password=self.password, dbname=database) as con:
            with con.cursor() as cursor:
                cursor.execute(sql)
                return cursor.fetchall()


def _bindir() -> Path:
    versions = sorted(Path("/usr/lib/postgresql").glob("*/bin/initdb"), key=lambda p: int(p.parent.parent.name))
    if not versions:
        pytest.fail("no PostgreSQL: `apt-get install postgresql` (scripts/setup.sh does it as root)")
    return versions[-1].parent


@contextmanager
def postgres_server(databases: tuple[str, ...]) -> Iterator[PostgresServer]:
    """A started server with `databases` created, owned by the user `sim2act`."""
    bindir, port, password = _bindir(), _free_port(), secrets.token_urlsafe(18)
    root = Path(tempfile.mkdtemp(prefix="sim2act-postgres-"))  # not under pytest's root-only tmp: postgres reads it
    as_owner: list[str] = []
    if os.getuid() == 0:
        owner = pwd.getpwnam("postgres")
        os.chown(root, owner.pw_uid, owner.pw_gid)
        as_owner = ["runuser", "-u", "postgres", "--"]
    data, log, password_file = root / "data", root / "server.log", root / "password"

    def run(*command: str) -> None:
        done = subprocess.run([*as_owner, *command], capture_output=True, text=True, timeout=120)
        if done.returncode:
            raise RuntimeError(f"{command[0]} failed: {done.stdout[-1500:]}{done.stderr[-1500:]}")

    try:
        # the password goes through a file only its owner reads, never a command line
        subprocess.run([*as_owner, "sh", "-c", f"umask 077; cat > {password_file}"], input=password, text=True,
                       check=True)
        run(str(bindir / "initdb"), "-D", str(data), "-U", USER, f"--pwfile={password_file}", "--auth=scram-sha-256",
            "-E", "UTF8", "--no-instructions")
        server = PostgresServer(port, password, log, (*as_owner, str(bindir / "pg_ctl"), "-D", str(data)),
                                f"-h {HOST} -p {port} -k {root} -c fsync=off")
        server.start()
        for database in databases:
            import psycopg2

            con = psycopg2.connect(host=HOST, port=port, user=USER, password=password, dbname="postgres")
            con.autocommit = True
            con.cursor().execute(f'CREATE DATABASE "{database}"')
            con.close()
        yield server
    finally:
        if (data / "postmaster.pid").exists():
            run(str(bindir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop")
        shutil.rmtree(root, ignore_errors=True)
