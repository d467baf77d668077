"""A throwaway PostgreSQL server for the tests of studies shared across machines: ``initdb`` and ``pg_ctl`` from
Debian's ``postgresql`` package, a data folder in a temporary directory, trust authentication on 127.0.0.1 and a
free port.  As root (CI), the server runs as the ``postgres`` system user (initdb refuses root)."""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path


def _bin_dir() -> Path | None:
    found = shutil.which("initdb")
    dirs = [Path(found).resolve().parent] if found else []
    dirs += sorted(Path("/usr/lib/postgresql").glob("*/bin"), reverse=True)
    return next((d for d in dirs if (d / "initdb").is_file() and (d / "pg_ctl").is_file()), None)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class PostgresServer:
    def __init__(self):
        self.folder: Path | None = None
        self.port = _free_port()
        self.as_user: list[str] = []
        self.bin = _bin_dir()

    def start(self) -> str | None:
        """Start the server; None if it runs, else the reason it cannot (for ``pytest.skip``)."""
        if self.bin is None:
            return "PostgreSQL's initdb and pg_ctl are not installed (Debian: apt-get install postgresql)"
        self.folder = Path(tempfile.mkdtemp(prefix="graf-pg-"))
        if os.geteuid() == 0:
            try:
                pw = pwd.getpwnam("postgres")
            except KeyError:
                return "running as root with no 'postgres' user to run the server as (initdb refuses root)"
            os.chown(self.folder, pw.pw_uid, pw.pw_gid)
            self.as_user = ["runuser", "-u", "postgres", "--"]
        data = self.folder / "data"
        opts = f"-p {self.port} -k {self.folder} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200"
        log = str(self.folder / "server.log")
        for cmd in (
            [str(self.bin / "initdb"), "-D", str(data), "-A", "trust", "-U", "postgres", "--no-sync"],
            [str(self.bin / "pg_ctl"), "-D", str(data), "-l", log, "-w", "-o", opts, "start"],
        ):
            p = subprocess.run(self.as_user + cmd, capture_output=True, text=True, timeout=120)
            if p.returncode != 0:
                return f"PostgreSQL did not start ({cmd[0]}: {(p.stderr or p.stdout).strip()[-300:]})"
        return None

    def create_database(self, name: str) -> str:
        """A new database; its SQLAlchemy URL."""
        import psycopg2

        con = psycopg2.connect(host="127.0.0.1", port=self.port, user="postgres", dbname="postgres")
        con.autocommit = True
        with con.cursor() as cur:
            cur.execute(f'CREATE DATABASE "{name}"')
        con.close()
        return f"postgresql+psycopg2://postgres@127.0.0.1:{self.port}/{name}"

    def stop(self) -> None:
        if self.folder is None:
            return
        if (self.folder / "data" / "postmaster.pid").exists():
            subprocess.run(
                self.as_user + [str(self.bin / "pg_ctl"), "-D", str(self.folder / "data"), "-m", "immediate", "stop"],
                capture_output=True,
                timeout=60,
            )
        shutil.rmtree(self.folder, ignore_errors=True)
