"""A small Python client of the registration service (httpx); see docs/api/python-client.md.

    with RegistrationClient("http://127.0.0.1:8000") as client:
        job = client.submit(mesh=Path("vessel.obj"), ap=Path("ap.dcm"), lat=Path("lat.dcm"))
        final = client.wait(job["id"])
        if final["status"] == "succeeded" and final["verdict"] == "ok": ...
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import httpx

FINISHED = ("succeeded", "failed", "canceled")
LINKED_FILES = {"overlay_ap": "overlay_ap.png", "overlay_lat": "overlay_lat.png", "mask_ap": "mask_ap.png",
                "mask_lat": "mask_lat.png", "loss_plot": "loss.png", "animation": "animation.gif",
                "dicom_reg": "reg.dcm", "dicom_overlay_ap": "overlay_ap.dcm", "dicom_overlay_lat": "overlay_lat.dcm",
                "dicom_loss": "loss.dcm", "hemodynamics": "hemodynamics.json", "hemodynamics_ply": "hemodynamics.ply",
                "hemodynamics_vtk": "hemodynamics.vtk", "parametric_ap": "parametric_ap.png",
                "parametric_lat": "parametric_lat.png", "dicom_parametric_ap": "parametric_ap.dcm",
                "dicom_parametric_lat": "parametric_lat.dcm"}
"""The job's links that lead to files, and the file names they are saved as."""
DICOM_NAMES = ("reg.dcm", "overlay_ap.dcm", "overlay_lat.dcm", "loss.dcm")


class ServiceError(Exception):
    """An error answer (problem details) or an unreachable server."""

    def __init__(self, status: int, problem: dict[str, Any] | None, text: str = ""):
        self.status = status
        self.problem = problem or {}
        detail = self.problem.get("detail") or text or "error"
        field = self.problem.get("field")
        message = f"HTTP {status}: {detail}" + (f" (field {field})" if field else "")
        super().__init__(message)

    def cli_explanation(self) -> tuple[bool, str]:
        """For the command line (:func:`dsareg_engine.commands.failures.explain`): (the caller's fault?, one line)."""
        text = str(self)
        if self.problem.get("accepted"):
            text += f" (accepted: {self.problem['accepted']})"
        return 400 <= self.status < 500 and self.status not in (408, 429), text


def _raise_for(response: httpx.Response) -> None:
    if response.status_code < 400:
        return
    problem = None
    if "json" in response.headers.get("content-type", ""):
        try:
            problem = response.json()
        except ValueError:
            problem = None
    raise ServiceError(response.status_code, problem, response.text[:200])


def parse_event_stream(lines: Iterable[str]) -> Iterator[dict[str, Any]]:
    """SSE frames from text lines: ``{"event", "id", "data"}`` per frame with data (``data`` parsed as JSON);
    comments (``: …``) and ``retry`` lines are skipped."""
    fields: dict[str, str] = {}
    data: list[str] = []
    for line in lines:
        if not line:
            if data:
                yield {"event": fields.get("event", "message"), "id": fields.get("id"), "data": json.loads("\n".join(data))}
            fields, data = {}, []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if name == "data":
            data.append(value)
        elif name in ("event", "id"):
            fields[name] = value


class RegistrationClient:
    def __init__(self, base_url: str, *, api_key: str | None = None, timeout: float = 120.0,
                 transport: httpx.BaseTransport | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self.http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout, transport=transport)

    def close(self) -> None:
        self.http.close()

    def __enter__(self) -> RegistrationClient:  # noqa: PYI034
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- calls ------------------------------------------------------------------------------
    def submit(self, *, ap: Path | bytes, lat: Path | bytes, mesh: Path | bytes | None = None,
               volume: Path | bytes | Iterable[Path | bytes] | None = None, geometry: str | dict | Path | None = None,
               options: dict | str | None = None, idempotency_key: str | None = None,
               callback_url: str | None = None) -> dict[str, Any]:
        """Submit a job (files); returns the job status (``id``, ``status``, ``links``...)."""
        files: list[tuple[str, tuple[str, bytes, str]]] = []

        def add(field: str, item: Path | bytes, default_name: str) -> None:
            if isinstance(item, (str, Path)):
                path = Path(item)
                files.append((field, (path.name, path.read_bytes(), "application/octet-stream")))
            else:
                files.append((field, (default_name, bytes(item), "application/octet-stream")))

        if mesh is not None:
            add("mesh", mesh, "mesh.obj")
        if volume is not None:
            items = [volume] if isinstance(volume, (str, Path, bytes)) else list(volume)
            for i, item in enumerate(items):
                add("volume", item, f"volume{i}.dcm")
        add("ap", ap, "ap.png")
        add("lat", lat, "lat.png")
        data: dict[str, str] = {}
        if isinstance(geometry, Path):
            files.append(("geometry", ("geometry.json", geometry.read_bytes(), "application/json")))
        elif isinstance(geometry, dict):
            data["geometry"] = json.dumps(geometry)
        elif geometry is not None:
            data["geometry"] = geometry
        if options is not None:
            data["options"] = options if isinstance(options, str) else json.dumps(options)
        if callback_url:
            data["callback_url"] = callback_url
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        response = self.http.post("/v1/registrations", files=files, data=data, headers=headers)
        _raise_for(response)
        return response.json()

    def submit_reference(self, dicomweb: dict[str, Any], *, options: dict | None = None, store_results: bool = True,
                         callback_url: str | None = None, idempotency_key: str | None = None) -> dict[str, Any]:
        """Submit a job whose inputs the server fetches from a PACS: ``dicomweb`` is
        ``{"url", "study_uid", "ap": {"series_uid"}, "lat": {"series_uid"}, "volume": {"series_uid"}}``."""
        body: dict[str, Any] = {"source": {"dicomweb": dicomweb}, "options": options or {},
                                "store_results": store_results}
        if callback_url:
            body["callback_url"] = callback_url
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else {}
        response = self.http.post("/v1/registrations", json=body, headers=headers)
        _raise_for(response)
        return response.json()

    def track(self, job_id: str, *, ap: Path | bytes | None = None, lat: Path | bytes | None = None,
              options: dict | None = None, callback_url: str | None = None) -> dict[str, Any]:
        """Re-register a succeeded job's model to a later run of either plane (``ap`` or ``lat`` alone) or both from
        its pose; the new job's status (its result's ``metrics.tracking``: the motion since the first job's pose)."""
        if ap is None and lat is None:
            raise ValueError("give ap, lat or both")
        files = []
        for field, item in (("ap", ap), ("lat", lat)):
            if item is None:
                continue
            name, content = (Path(item).name, Path(item).read_bytes()) if isinstance(item, (str, Path)) else (
                f"{field}.png", bytes(item))
            files.append((field, (name, content, "application/octet-stream")))
        data = {"options": json.dumps(options)} if options else {}
        if callback_url:
            data["callback_url"] = callback_url
        response = self.http.post(f"/v1/registrations/{job_id}/track", files=files, data=data)
        _raise_for(response)
        return response.json()

    def get(self, job_id: str) -> dict[str, Any]:
        response = self.http.get(f"/v1/registrations/{job_id}")
        _raise_for(response)
        return response.json()

    def list(self, status: str | None = None, limit: int = 20, cursor: str | None = None) -> dict[str, Any]:
        params: dict[str, Any] = {"limit": limit}
        if status:
            params["status"] = status
        if cursor:
            params["cursor"] = cursor
        response = self.http.get("/v1/registrations", params=params)
        _raise_for(response)
        return response.json()

    def wait(self, job_id: str, *, progress: Callable[[dict], None] | None = None, timeout: float = 3600.0,
             interval: float = 0.5) -> dict[str, Any]:
        """Poll until the job finishes; ``progress(status)`` after each poll."""
        deadline = time.monotonic() + timeout
        while True:
            status = self.get(job_id)
            if progress is not None:
                progress(status)
            if status["status"] in FINISHED:
                return status
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {status['status']} after {timeout:g} s")
            time.sleep(interval)

    def events(self, job_id: str) -> Iterator[dict[str, Any]]:
        """The job's Server-Sent Events (``GET /v1/registrations/{id}/events``) as they come:
        ``{"event": "progress" | "end" | "gone", "id": "<n>", "data": {...}}``; ends after ``end`` (data: the job
        summary, with ``status`` and ``verdict``) or ``gone``. Closing the iterator early closes the stream."""
        with self.http.stream("GET", f"/v1/registrations/{job_id}/events",
                              headers={"Accept": "text/event-stream"}) as response:
            if response.status_code >= 400:
                response.read()
                _raise_for(response)
            for event in parse_event_stream(response.iter_lines()):
                yield event
                if event["event"] in ("end", "gone"):
                    return

    def result(self, job_id: str) -> dict[str, Any]:
        response = self.http.get(f"/v1/registrations/{job_id}/result")
        _raise_for(response)
        return response.json()

    def download(self, job_id: str, kind: str, view: str | None = None) -> bytes:
        """``kind``: 'overlays' | 'masks' (with view 'ap'/'lat') or 'animation'."""
        path = f"/v1/registrations/{job_id}/animation.gif" if kind == "animation" else f"/v1/registrations/{job_id}/{kind}/{view}.png"
        response = self.http.get(path)
        _raise_for(response)
        return response.content

    def download_dicom(self, job_id: str, name: str = "reg.dcm") -> bytes:
        """A DICOM result: ``reg.dcm`` (Spatial Registration), ``overlay_ap.dcm``, ``overlay_lat.dcm``, ``loss.dcm``."""
        if name not in DICOM_NAMES:
            raise ValueError(f"name must be one of {', '.join(DICOM_NAMES)}")
        response = self.http.get(f"/v1/registrations/{job_id}/dicom/{name}")
        _raise_for(response)
        return response.content

    def download_overlays(self, job_id: str, out_dir: Path) -> list[Path]:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for view in ("ap", "lat"):
            path = out_dir / f"overlay_{view}.png"
            path.write_bytes(self.download(job_id, "overlays", view))
            written.append(path)
        return written

    def download_all(self, job_id: str, out_dir: Path) -> list[Path]:
        """result.json and every file the job links to: overlays, masks, loss plot, animation, DICOM objects."""
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        links = self.get(job_id).get("links") or {}
        written: list[Path] = []
        for key, filename in LINKED_FILES.items():
            if key not in links:
                continue
            response = self.http.get(links[key])
            if response.status_code == 404 and key == "animation":  # older servers link it always
                continue
            _raise_for(response)
            path = out_dir / filename
            path.write_bytes(response.content)
            written.append(path)
        result_path = out_dir / "result.json"
        result_path.write_text(json.dumps(self.result(job_id), indent=2))
        written.append(result_path)
        return written

    def cancel(self, job_id: str) -> dict[str, Any]:
        response = self.http.post(f"/v1/registrations/{job_id}/cancel")
        _raise_for(response)
        return response.json()

    def delete(self, job_id: str) -> None:
        response = self.http.delete(f"/v1/registrations/{job_id}")
        _raise_for(response)
