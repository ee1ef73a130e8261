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


class _ChildServer:
    """A server process of ours in a temporary directory: ``kill`` it (SIGKILL), ``stop`` = kill + remove the directory."""

    process: subprocess.Popen | None
    dir: Path

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        self.process = None

    def stop(self) -> None:
        self.kill()
        shutil.rmtree(self.dir, ignore_errors=True)


class RedisServer(_ChildServer):
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


class OrthancServer(_ChildServer):
    """Orthanc + its DICOMweb plugin on loopback (temp storage, own JSON config, HTTP basic auth).

    For the DICOMweb tests and ``examples/pacs``. ``lua`` (optional) is a Lua script installed
    as the server's ``LuaScripts``; ``stable_age`` seconds without a new instance make a study
    *stable* (Orthanc's ``OnStableStudy`` event).
    """

    PLUGIN_GLOBS = ("/usr/lib/orthanc/libOrthancDicomWeb.so*", "/usr/share/orthanc/plugins/libOrthancDicomWeb.so*",
                    "/usr/local/share/orthanc/plugins/libOrthancDicomWeb.so*")

    def __init__(self, user: str = "dsareg", password: str = "dsareg-test", lua: str | None = None,
                 stable_age: int = 2, port: int | None = None, dicom_modalities: dict | None = None,
                 dicom_aet: str = "ORTHANC"):
        self.binary = shutil.which("Orthanc")
        plugins = [p for pattern in self.PLUGIN_GLOBS for p in sorted(glob.glob(pattern))]
        self.plugin = plugins[0] if plugins else None
        self.user, self.password = user, password
        self.port = port or free_port()
        self.dicom_port = free_port()
        self.dir = Path(tempfile.mkdtemp(prefix="dsareg-orthanc-"))
        self.lua = lua
        self.stable_age = stable_age
        self.dicom_modalities, self.dicom_aet = dicom_modalities, dicom_aet  # {name: [AET, host, port]}: DIMSE on
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def dicomweb_url(self) -> str:
        return f"{self.url}/dicom-web"

    def config(self) -> dict:
        config = {
            "Name": "dsareg-test", "StorageDirectory": str(self.dir / "db"), "IndexDirectory": str(self.dir / "db"),
            "HttpPort": self.port, "DicomPort": self.dicom_port, "DicomServerEnabled": False,
            "RemoteAccessAllowed": False, "AuthenticationEnabled": True,
            "RegisteredUsers": {self.user: self.password}, "HttpCompressionEnabled": False,
            "Plugins": [self.plugin], "StableAge": self.stable_age, "ConcurrentJobs": 1,
            "UnknownSopClassAccepted": True, "OrthancExplorerEnabled": False, "WebDavEnabled": False,
            "DicomWeb": {"Enable": True, "Root": "/dicom-web/", "EnableWado": False, "Host": "127.0.0.1",
                         "StudiesMetadata": "Full", "SeriesMetadata": "Full"},
            "SaveJobs": False,
        }
        if self.dicom_modalities is not None:  # the DICOM server on, and the modalities it may send to
            config.update({"DicomServerEnabled": True, "DicomAet": self.dicom_aet, "DicomCheckCalledAet": True,
                           "DicomModalities": self.dicom_modalities, "DicomScpTimeout": 10})
        if self.lua:
            (self.dir / "trigger.lua").write_text(self.lua)
            config["LuaScripts"] = [str(self.dir / "trigger.lua")]
        return config

    def start(self, timeout: float = 30.0) -> OrthancServer:
        import json

        if not self.binary or not self.plugin:
            raise RuntimeError("Orthanc or its DICOMweb plugin is not installed (apt-get install orthanc orthanc-dicomweb)")
        (self.dir / "db").mkdir(parents=True, exist_ok=True)
        (self.dir / "orthanc.json").write_text(json.dumps(self.config(), indent=1))
        self.log = open(self.dir / "orthanc.log", "ab")  # noqa: SIM115
        self.process = subprocess.Popen([self.binary, str(self.dir / "orthanc.json")], stdout=self.log,
                                        stderr=subprocess.STDOUT, start_new_session=True, cwd=self.dir)
        if not _wait_port(self.port, timeout, self.process):
            self.kill()
            raise RuntimeError(f"Orthanc did not start: {self.logs()[-2000:]}")
        return self

    def logs(self) -> str:
        try:
            return (self.dir / "orthanc.log").read_text(errors="replace")
        except OSError:
            return ""
