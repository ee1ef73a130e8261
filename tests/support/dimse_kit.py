"""Helpers of the DIMSE tests: studies with fresh UIDs, dcmtk tools, a pynetdicom SCU, the job list."""

from __future__ import annotations

import io
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pydicom
import pytest

from dsareg_engine.io.dicom_out import new_uid
from tests.support.servers import free_port
from tests.support.service_testkit import REPO, LoggedProcess

DCMTK = all(shutil.which(tool) for tool in ("echoscu", "storescu", "storescp"))


def need_dcmtk() -> None:
    if not DCMTK:
        pytest.skip("dcmtk (echoscu, storescu, storescp) not installed (Debian package dcmtk; .ci/run installs it)")


def renamed_study(study, folder: Path) -> tuple[str, list[Path]]:
    """The study's instances with new Study / Series / SOP Instance UIDs (same pixels), as files."""
    folder.mkdir(parents=True, exist_ok=True)
    study_uid, series = new_uid(), {}
    paths = []
    for index, data in enumerate(study.instances()):
        ds = pydicom.dcmread(io.BytesIO(data))
        ds.StudyInstanceUID = study_uid
        ds.SeriesInstanceUID = series.setdefault(ds.SeriesInstanceUID, new_uid())
        ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = new_uid()
        if "FrameOfReferenceUID" in ds:
            ds.FrameOfReferenceUID = series.setdefault("frame:" + ds.FrameOfReferenceUID, new_uid())
        path = folder / f"{index:03d}.dcm"
        ds.save_as(path, enforce_file_format=True)
        paths.append(path)
    return study_uid, paths


def storescu(port: int, paths: list[Path], calling: str = "STORESCU", called: str = "DSAREG",
             options: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    """dcmtk ``storescu`` of ``paths`` in one association (``options``: e.g. ``-xs`` to propose JPEG Lossless)."""
    return subprocess.run(["storescu", *options, "-aet", calling, "-aec", called, "127.0.0.1", str(port),
                           *map(str, paths)],
                          capture_output=True, text=True, timeout=120, check=False)


def echoscu(port: int, calling: str = "STORESCU", called: str = "DSAREG") -> subprocess.CompletedProcess:
    return subprocess.run(["echoscu", "-aet", calling, "-aec", called, "127.0.0.1", str(port)],
                          capture_output=True, text=True, timeout=60, check=False)


class StoreScp(LoggedProcess):
    """dcmtk ``storescp`` (AE ``title``) writing what it receives into ``folder``: an export destination.

    It listens on every interface: dcmtk's storescp (3.6.7, Debian's) has no bind-address option (only a port,
    or ``--inetd``), so it cannot be held to loopback as dsareg's own listeners in the tests are (``serve`` and
    the DICOM node bind 127.0.0.1). Its port is a free ephemeral one, it lives for the test only, and it accepts
    what any peer sends: test data, never patient data."""

    def __init__(self, folder: Path, title: str = "STORESCU", port: int | None = None):
        self.folder, self.title, self.port = Path(folder), title, port or free_port()
        self.folder.mkdir(parents=True, exist_ok=True)
        self.log_path = self.folder.parent / f"storescp-{self.port}.log"

    def start(self) -> StoreScp:
        self.log = open(self.log_path, "ab")  # noqa: SIM115 - closed with the process
        self.process = subprocess.Popen(["storescp", "-aet", self.title, "-od", str(self.folder), str(self.port)],
                                        stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True, cwd=REPO)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and echoscu(self.port, "PROBE", self.title).returncode != 0:
            time.sleep(0.2)
        return self

    def files(self) -> list[Path]:
        return sorted(p for p in self.folder.iterdir() if p.is_file())


def scu_send(port: int, paths: list[Path], calling: str, *, abort_after: int | None = None) -> list[int]:
    """Send ``paths`` with pynetdicom as ``calling``; A-ABORT after ``abort_after`` instances. The statuses."""
    from pynetdicom import AE

    datasets = [pydicom.dcmread(p) for p in paths]
    ae = AE(ae_title=calling)
    for uid in sorted({str(ds.SOPClassUID) for ds in datasets}):
        ae.add_requested_context(uid, "1.2.840.10008.1.2.1")
    assoc = ae.associate("127.0.0.1", port, ae_title="DSAREG")
    assert assoc.is_established, "association refused"
    statuses = []
    for index, ds in enumerate(datasets):
        if abort_after is not None and index == abort_after:
            assoc.abort()
            return statuses
        statuses.append(int(assoc.send_c_store(ds).Status))
    assoc.release()
    return statuses


def large_xa(size_mb: float, study: str, series: str, number: int = 1) -> bytes:
    """One multi-frame XA instance of about ``size_mb`` MB (1024² uint16 frames of noise: nothing compresses it),
    Part 10, Explicit VR Little Endian; synthetic, no patient."""
    import numpy as np

    from dsareg_engine.io.dicom_out import new_instance

    frames = max(1, round(size_mb * 2**20 / (1024 * 1024 * 2)))
    ds = new_instance("1.2.840.10008.5.1.4.1.1.12.1", new_uid(), charset="ISO_IR 100")
    ds.PatientName, ds.PatientID, ds.StudyInstanceUID, ds.SeriesInstanceUID = "TEST^LARGE", "TEST", study, series
    ds.Modality, ds.InstanceNumber, ds.NumberOfFrames = "XA", number, frames
    ds.Rows = ds.Columns = 1024
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
    ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
    ds.PixelData = np.random.default_rng(number).integers(0, 4000, (frames, 1024, 1024), dtype=np.uint16).tobytes()
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


_STUDY_OF_JOB: dict[tuple[str, str], str | None] = {}
"""(server URL, job link) → the job's ``source.dimse.study_uid``: set at submission, never changed, so a job of
another study is fetched once, not at every poll of every wait (the polls fetched every job of the server)."""


def jobs_of_study(client, study_uid: str) -> list[dict]:
    """Every job of the service made from ``study_uid`` (by its ``source.dimse``), each as fetched now."""
    found = []
    cursor = None
    while True:
        page = client.get("/v1/registrations", params={"limit": 100, **({"cursor": cursor} if cursor else {})}).json()
        for item in page["items"]:
            key = (str(client.base_url), item["links"]["self"])
            if key in _STUDY_OF_JOB and _STUDY_OF_JOB[key] != study_uid:
                continue
            job = client.get(item["links"]["self"]).json()
            _STUDY_OF_JOB[key] = ((job.get("source") or {}).get("dimse") or {}).get("study_uid")
            if _STUDY_OF_JOB[key] == study_uid:
                found.append(job)
        cursor = page.get("next_cursor")
        if not cursor:
            return found


class Listener(LoggedProcess):
    """``dsareg dicom-listener`` as its own process (``env``: its DSAREG_* settings), on ``port``."""

    def __init__(self, data_dir: Path, port: int, env: dict[str, str]):
        self.data_dir, self.port, self.env = data_dir, port, env
        self.log_path = data_dir.parent / f"listener-{port}.log"

    def start(self, timeout: float = 120.0) -> Listener:
        self.log = open(self.log_path, "ab")  # noqa: SIM115 - closed with the process
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **self.env}
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service", "dicom-listener", "--port", str(self.port), "--data-dir", str(self.data_dir)],
            cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"listener exited: {self.logs()[-2000:]}")
            if echoscu(self.port).returncode == 0:
                return self
            time.sleep(0.3)
        raise RuntimeError(f"listener not up after {timeout} s: {self.logs()[-2000:]}")
