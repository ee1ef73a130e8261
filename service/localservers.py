"""Throw-away Redis and PostgreSQL servers on loopback, for the scale-out tests and benchmark.

Each server runs in its own temporary directory on a free loopback port, without
persistence (Redis: no RDB/AOF; PostgreSQL: fsync off), so it can be killed and
restarted. Not for production: see docker/compose.yaml for a deployment.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, timeout: float, process: subprocess.Popen | None = None) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            return False
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return True
        except OSError:
            time.sleep(0.1)
    return False


class RedisServer:
    """``redis-server`` on loopback, no persistence (a restart loses every message)."""

    def __init__(self, port: int | None = None):
        self.binary = shutil.which("redis-server")
        self.port = port or free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="dsareg-redis-"))
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> RedisServer:
        if not self.binary:
            raise RuntimeError("redis-server not installed")
        self.log = open(self.dir / "redis.log", "ab")  # noqa: SIM115
        self.process = subprocess.Popen(
            [self.binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
             "--dir", str(self.dir), "--protected-mode", "yes"],
            stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        if not _wait_port(self.port, 15, self.process):
            self.stop()
            raise RuntimeError("redis-server did not start")
        return self

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        self.process = None

    def stop(self) -> None:
        self.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


class PostgresServer:
    """A throw-away PostgreSQL cluster (``initdb`` in a temp dir; run as user postgres when we are root)."""

    def __init__(self):
        bins = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"))
        self.bindir = Path(bins[-1]).parent if bins else (Path(shutil.which("initdb")).parent if shutil.which("initdb") else None)
        self.port = free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="dsareg-pg-"))
        self.data = self.dir / "data"
        self.started = False

    @property
    def url(self) -> str:
        return f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/dsareg"

    def _cmd(self, *args: str) -> list[str]:
        if os.geteuid() == 0:
            return ["runuser", "-u", "postgres", "--", *args]
        return list(args)

    def start(self) -> PostgresServer:
        if self.bindir is None:
            raise RuntimeError("PostgreSQL (initdb) not installed")
        if os.geteuid() == 0:
            user = pwd.getpwnam("postgres")
            os.chown(self.dir, user.pw_uid, user.pw_gid)
        run = dict(stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=120)  # noqa: C408
        subprocess.run(self._cmd(str(self.bindir / "initdb"), "-D", str(self.data), "-U", "postgres",
                                 "--auth=trust", "-E", "UTF8", "--no-sync"), check=True, **run)
        self.resume()
        import psycopg

        with psycopg.connect(host="127.0.0.1", port=self.port, user="postgres", dbname="postgres",
                             autocommit=True) as conn:
            conn.execute("CREATE DATABASE dsareg")
        return self

    def resume(self) -> None:
        """Start the server on the existing cluster (after :meth:`start` created it, or after :meth:`pause`)."""
        options = (f"-p {self.port} -k {self.dir} -c listen_addresses=127.0.0.1 -c fsync=off "
                   "-c synchronous_commit=off -c full_page_writes=off -c max_connections=200")
        subprocess.run(self._cmd(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-o", options,
                                 "-l", str(self.dir / "pg.log"), "-w", "-t", "60", "start"), check=True,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=120)
        self.started = True

    def pause(self) -> None:
        """Stop the server, keeping its data (an outage: clients get connection refused until :meth:`resume`)."""
        subprocess.run(self._cmd(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", "fast", "-w", "stop"),
                       check=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=120)
        self.started = False

    def stop(self) -> None:
        if self.started:
            subprocess.run(self._cmd(str(self.bindir / "pg_ctl"), "-D", str(self.data), "-m", "immediate", "stop"),
                           check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=60)
            self.started = False
        shutil.rmtree(self.dir, ignore_errors=True)
