"""Helpers of the service tests: the example case and a real server in a subprocess."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import pytest

from dsareg_engine.metrics import dice  # noqa: F401 - re-exported to the tests
from tests.support.result_contract import assert_result_contract
from tests.support.servers import free_port

REPO = Path(__file__).resolve().parents[2]
CASE_SIZE = 128
FAST_OPTIONS = {"starts": 1, "max_iterations": 20}


def engine_ready() -> bool:
    """The engine entry points the service calls can be imported."""
    try:
        from dsareg_engine.io.case import load_case  # noqa: F401
        from dsareg_engine.pipeline import RegistrationCanceled, run_registration_case  # noqa: F401
    except ImportError:
        return False
    return True


needs_engine = pytest.mark.skipif(not engine_ready(), reason="engine entry points load_case/run_registration_case missing")


@dataclass
class ExampleCase:
    mesh_obj: bytes
    ap_png: bytes
    lat_png: bytes
    geometry: dict
    masks: dict[str, np.ndarray]
    vertices: np.ndarray
    faces: np.ndarray


def png_bytes(mask: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(mask.astype(np.uint8) * 255).save(buffer, format="PNG")
    return buffer.getvalue()


def render_mask(vertices: np.ndarray, faces: np.ndarray, view, mesh_to_world: np.ndarray) -> np.ndarray:
    import torch

    from dsareg_engine.render import Camera, render_hard_silhouette

    mesh_to_view = torch.as_tensor((view.world_to_view @ mesh_to_world)[None], dtype=torch.float32)
    v = torch.as_tensor(vertices, dtype=torch.float32)
    f = torch.as_tensor(faces, dtype=torch.int64)
    return render_hard_silhouette(v, f, mesh_to_view, Camera.from_view(view))[0].numpy().astype(bool)


def small_views(size: int = CASE_SIZE) -> dict:
    from dsareg_engine.geometry.spec import load_rig

    rig = load_rig("paper")
    return {name: view.resized(size, size) for name, view in rig.views.items()}, rig


def make_example_case(tmp: Path, size: int = CASE_SIZE) -> ExampleCase:
    """The phantom seen by the paper rig shrunk to ``size`` px; the true pose is the identity."""
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    views, rig = small_views(size)
    mesh = make_vessel_phantom()
    path = tmp / "phantom.obj"
    mesh.save(path)
    masks = {name: render_mask(mesh.vertices, mesh.faces, view, np.eye(4)) for name, view in views.items()}
    geometry = {"views": {n: v.to_dict() for n, v in views.items()},
                "initial_mesh_to_world": rig.initial_mesh_to_world.tolist()}
    return ExampleCase(path.read_bytes(), png_bytes(masks["ap"]), png_bytes(masks["lat"]), geometry, masks,
                       np.asarray(mesh.vertices), np.asarray(mesh.faces))


class LoggedProcess:
    """A child process in its own session with its output in ``log_path``; stopped by SIGTERM, then SIGKILL."""

    process: subprocess.Popen | None = None
    log_path: Path

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def kill(self) -> None:
        if self.alive():
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(10)

    def logs(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def stop(self, timeout: float = 30.0) -> None:
        if self.process is None:
            return
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait(10)
        self.log.close()
        self.process = None


class Server(LoggedProcess):
    """``python -m service serve`` on a free loopback port with its own data dir."""

    def __init__(self, data_dir: Path, *, workers: int = 1, env: dict[str, str] | None = None,
                 host: str = "127.0.0.1", extra_args: list[str] | None = None):
        self.data_dir = Path(data_dir)
        self.workers = workers
        self.env = env or {}
        self.host = host
        self.extra_args = extra_args or []
        self.port = free_port()
        self.process: subprocess.Popen | None = None
        self.log_path = self.data_dir.parent / f"{self.data_dir.name}-server-{self.port}.log"

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self, wait_ready: bool = True, timeout: float = 90.0) -> Server:
        env = {**os.environ, "DSAREG_LEASE_SECONDS": "3", "DSAREG_POLL_SECONDS": "0.2",
               "DSAREG_PROGRESS_INTERVAL_SECONDS": "0.2", "DSAREG_VALIDATION_TIMEOUT_SECONDS": "60",
               # no warm-up job (≈ 8 CPU-s a start, load 9); test_readiness starts the production default
               "DSAREG_WARM_UP_JOB": "0", "PYTHONUNBUFFERED": "1", **self.env}
        for key in ("DSAREG_API_KEYS", "DSAREG_API_KEY_HASHES", "DSAREG_CONFIG"):
            if key not in self.env:
                env.pop(key, None)
        self.log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
        self.process = subprocess.Popen(
            [sys.executable, "-m", "service", "serve", "--host", self.host, "--port", str(self.port),
             "--data-dir", str(self.data_dir), "--workers", str(self.workers), *self.extra_args],
            cwd=REPO, env=env, stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True,
        )
        deadline = time.monotonic() + timeout
        path = "/readyz" if wait_ready and self.workers > 0 else "/healthz"
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited with {self.process.returncode}:\n{self.logs()[-3000:]}")
            try:
                if httpx.get(self.url + path, timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"server not ready after {timeout} s:\n{self.logs()[-3000:]}")

    def client(self, **kwargs) -> httpx.Client:
        return httpx.Client(base_url=self.url, timeout=60, **kwargs)


def submit(client: httpx.Client, case: ExampleCase, options: dict | None = None, headers: dict | None = None,
           geometry: dict | str | None = None, names: tuple[str, str, str] = ("phantom.obj", "ap.png", "lat.png"),
           files_override: dict[str, bytes] | None = None) -> httpx.Response:
    content = {"ap": case.ap_png, "lat": case.lat_png, **(files_override or {})}
    files = [("mesh", (names[0], case.mesh_obj, "application/octet-stream")),
             ("ap", (names[1], content["ap"], "image/png")), ("lat", (names[2], content["lat"], "image/png"))]
    geometry = case.geometry if geometry is None else geometry
    data = {"geometry": geometry if isinstance(geometry, str) else json.dumps(geometry),
            "options": json.dumps(FAST_OPTIONS if options is None else options)}
    return client.post("/v1/registrations", files=files, data=data, headers=headers or {})


def small_cta_case(voxel_mm: float = 1.2):
    """A small CTA (generator A, the phantom's tree to depth 2, a 60 × 60 × 80 mm head) as a DICOM series beside its
    XA pair (160 px, geometry in their tags): ``make_volume_case``'s."""
    from dsareg_engine.simulation.synthetic_volumes import make_volume_case

    return make_volume_case("cta", "a", voxel_mm=voxel_mm, depth=2, image_px=160, pixel_spacing_mm=0.9,
                            min_head_mm=(30.0, 30.0, 40.0))


def submit_volume(client: httpx.Client, case, options: dict) -> httpx.Response:
    """POST a volume case (``make_volume_case``'s: its series as the ``volume`` parts, the XA pair as DICOM)."""
    files = [("ap", ("ap.dcm", case.ap, "application/dicom")), ("lat", ("lat.dcm", case.lat, "application/dicom"))]
    files += [("volume", (f"s{i:03d}.dcm", part, "application/dicom")) for i, part in enumerate(case.volume.parts)]
    return client.post("/v1/registrations", files=files, data={"options": json.dumps(options)})


def wait_for(client: httpx.Client, job_id: str, statuses=("succeeded", "failed", "canceled"), timeout: float = 120.0,
             predicate=None) -> dict:
    deadline = time.monotonic() + timeout
    body: dict = {}
    while time.monotonic() < deadline:
        body = client.get(f"/v1/registrations/{job_id}").json()
        if body.get("status") in statuses and (predicate is None or predicate(body)):
            if body.get("result") is not None:  # every result the tests read holds the closed contract
                assert_result_contract(body["result"], f"job {job_id}'s result")
            return body
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} not in {statuses} after {timeout} s: {body}")


def generated_client(openapi_text: str, folder: Path):
    """A Python client generated from ``openapi_text`` with openapi-python-client (a test dependency),
    imported as the package ``dsareg_client``; call ``.cleanup()`` on the returned module list when done.
    Skips when the generator is not installed."""
    import importlib
    import shutil

    generator = shutil.which("openapi-python-client", path=str(Path(sys.executable).parent)) or shutil.which(
        "openapi-python-client")
    if generator is None:
        pytest.skip("openapi-python-client is not installed (pip install -e '.[test]')")
    (folder / "openapi.json").write_text(openapi_text)
    env_path = f"{Path(sys.executable).parent}:{Path(generator).parent}"
    proc = subprocess.run([generator, "generate", "--path", str(folder / "openapi.json"), "--meta", "none",
                           "--output-path", str(folder / "dsareg_client")], capture_output=True, text=True,
                          timeout=180, check=False, cwd=folder, env={"PATH": env_path, "HOME": str(folder)})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    sys.path.insert(0, str(folder))
    importlib.invalidate_caches()
    return importlib.import_module("dsareg_client")


def forget_generated_client(folder: Path) -> None:
    sys.path.remove(str(folder))
    for name in [m for m in sys.modules if m == "dsareg_client" or m.startswith("dsareg_client.")]:
        del sys.modules[name]
