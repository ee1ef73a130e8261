"""``python -m benchmarks.engine views``: views as hospitals acquire them (issue 42), through the DICOM path.

Every case is a pair of DICOM XA files whose geometry is only in the tags (positioner angles, SID, SOD, imager
spacing), pixels = the phantom's silhouette (vessels dark), read by ``load_case`` and registered by
``run_registration_case`` from a start 3° / 3 mm off the truth (given pose; the capture range is not what is
measured here). Rows:

* ``biplane <angle>``: one biplane acquisition (``BIPLANE A`` / ``B``, one start time), the LAT plane
  ``angle`` from the AP plane (AP at LAO 10° ... as :func:`~dsareg_engine.simulation.clinical_rig.clinical_biplane_rig`
  turns it): ADD from the truth, verdicts.
* ``monoplane <mm>/<deg>``: two ``SINGLE PLANE`` runs 2 and 10 minutes apart (alternating), the head moved by that
  much between them (a rotation about the model's centre and a displacement of it, random axes): the joint pose's
  ADD from each run's truth, the per-run poses' ADD, the motion measured, the verdicts, how many are ``ok`` with a
  pose > 1 mm from a run's truth (the target: none).
* ``swapped``: the lateral run's file given as AP and the frontal as LAT: how many were swapped back, ADD, verdicts.
"""

from __future__ import annotations

import argparse
import io
import tempfile
import time
from pathlib import Path

import numpy as np

ANGLES = (30, 50, 70, 90, 110)
MOTIONS = ((0.0, 0.0), (1.5, 1.2), (3.0, 3.0))
AP_PRIMARY_DEG = -10.0
SID_MM, SOD_MM = 1100.0, 760.0


def add_parser(which) -> None:
    sub = which.add_parser("views", help="biplane angle 30-110°, monoplane runs minutes apart with head motion, "
                                         "swapped AP/LAT files: DICOM XA through load_case, ADD and verdicts")
    sub.add_argument("--cases", type=int, default=2, help="cases (seeds) per row")
    sub.add_argument("--seed", type=int, default=0, help="first seed")
    sub.add_argument("--size", type=int, default=160, help="image side in px")
    sub.add_argument("--spacing", type=float, default=0.8, help="detector pixel spacing, mm")
    sub.add_argument("--rows", nargs="*", default=[], help="only the rows whose name contains one of these words")
    sub.set_defaults(func=bench_views)


def _rotation(axis: np.ndarray, degrees: float) -> np.ndarray:
    from dsareg_engine.geometry.pose import rotation_about_axis

    return rotation_about_axis(axis / np.linalg.norm(axis), np.radians(degrees))


def _about_centre(rotation: np.ndarray, shift: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """A world motion turning by ``rotation`` about ``centre`` (world) and moving it by ``shift``."""
    from dsareg_engine.geometry.pose import make_transform

    return make_transform(rotation, centre + shift - rotation @ centre)


def _xa(mask: np.ndarray, primary: float, spacing: float, image_type: str, start: str) -> bytes:
    """A DICOM XA of ``mask`` (vessels dark) with the geometry tags and the run's plane and start time."""
    import pydicom

    from dsareg_engine.simulation.phantom_study import _xa as phantom_xa

    data, _ = phantom_xa(mask, (primary, 0.0), SID_MM, SOD_MM, spacing, "1.2.826.0.1.3680043.10.1.42", 10, "A")
    dataset = pydicom.dcmread(io.BytesIO(data))
    dataset.ImageType = ["ORIGINAL", "PRIMARY", image_type]
    dataset.AcquisitionDate, dataset.AcquisitionTime = "20260102", start
    buffer = io.BytesIO()
    dataset.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def _mask(mesh, view, pose: np.ndarray) -> np.ndarray:
    import torch

    from dsareg_engine.render import Camera, render_hard_silhouette

    vertices, faces = mesh.torch(torch.float64)
    return render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view @ pose)[None],
                                  Camera.from_view(view))[0].numpy().astype(bool)


def _register(stl: bytes, files: tuple[bytes, bytes], start: np.ndarray, truth: np.ndarray) -> tuple[dict, object]:
    from dsareg_engine.io.case import load_case
    from dsareg_engine.pipeline import run_registration_case
    from dsareg_engine.registration import RegistrationOptions

    case = load_case(mesh=stl, mesh_name="phantom.stl", ap=files[0], lat=files[1])
    options = RegistrationOptions(initialization="given", initial_mesh_to_world=start.tolist(), starts=2,
                                  mirror_check=False, ground_truth_mesh_to_world=truth.tolist())
    with tempfile.TemporaryDirectory() as folder:
        return run_registration_case(case, options, Path(folder)), case


def run_case(mesh, stl: bytes, row: str, seed: int, size: int, spacing: float) -> dict:
    """One case of ``row`` (see the module): its numbers."""
    from dsareg_engine.geometry.pose import make_transform
    from dsareg_engine.io.dicom_xa import view_from_angles
    from dsareg_engine.io.view_roles import beam_obliquity_deg
    from dsareg_engine.metrics import mean_distance_mm

    rng = np.random.default_rng(seed)
    truth = make_transform(_rotation(rng.normal(size=3), rng.uniform(2, 10)), rng.uniform(-4, 4, 3))
    start = make_transform(_rotation(rng.normal(size=3), 3.0), 3.0 * rng.normal(size=3) / np.sqrt(3)) @ truth
    angle = float(row.split()[1]) if row.startswith("biplane") else 90.0
    primaries = (AP_PRIMARY_DEG, AP_PRIMARY_DEG + angle)
    views = [view_from_angles(p, 0.0, SID_MM, SOD_MM, (spacing, spacing), (size, size)) for p in primaries]
    poses = [truth, truth]
    if row.startswith("monoplane"):
        mm, deg = (float(x) for x in row.split()[1].split("/"))
        centre = truth[:3, :3] @ mesh.vertices.mean(axis=0) + truth[:3, 3]
        shift = rng.normal(size=3)
        poses[1] = _about_centre(_rotation(rng.normal(size=3), deg), mm * shift / np.linalg.norm(shift), centre) @ truth
    sequential = row.startswith("monoplane")
    kinds = ("SINGLE PLANE", "SINGLE PLANE") if sequential else ("BIPLANE A", "BIPLANE B")
    times = ("101500", "101700" if seed % 2 == 0 else "102500") if sequential else ("101500", "101500")
    files = [_xa(_mask(mesh, v, p), prim, spacing, k, t) for v, p, prim, k, t in zip(views, poses, primaries, kinds, times)]
    if row == "swapped":
        files.reverse()
    began = time.perf_counter()
    data, case = _register(stl, tuple(files), start, truth)
    seconds = time.perf_counter() - began
    points = mesh.vertices
    joint = np.asarray(data["mesh_to_world"])
    out = {"verdict": data["verdict"], "seconds": seconds, "add": [mean_distance_mm(joint, p, points) for p in poses],
           "swapped": any(d.what == "view roles" and d.chosen == "swapped" for d in case.decisions),
           "ap_frontal": beam_obliquity_deg(case.rig.views["ap"]) < 45.0}
    runs = (data.get("acquisition") or {}).get("run_poses")
    if runs:
        out["run_add"] = [mean_distance_mm(np.asarray(runs[n]), p, points) for n, p in zip(("ap", "lat"), poses)]
        out["run_across"] = [_across_beam_mm(np.asarray(runs[n]), p, v, points) for n, p, v in zip(("ap", "lat"), poses, views)]
        out["motion"] = data["acquisition"]["motion"]
    return out


def _across_beam_mm(pose: np.ndarray, truth: np.ndarray, view, points: np.ndarray) -> float:
    """How far the model's centre is from the truth's across the view's beam (what one view measures), mm."""
    centre = points.mean(axis=0)
    error = pose[:3, :3] @ centre + pose[:3, 3] - (truth[:3, :3] @ centre + truth[:3, 3])
    beam = view.world_to_view[2, :3]
    return float(np.linalg.norm(error - (error @ beam) * beam))


def _rows(selected: list[str]) -> list[str]:
    rows = [f"biplane {a}" for a in ANGLES] + [f"monoplane {mm:g}/{deg:g}" for mm, deg in MOTIONS] + ["swapped"]
    return [r for r in rows if not selected or any(word in r for word in selected)]


def _line(row: str, cases: list[dict]) -> str:
    verdicts = ", ".join(f"{v} {sum(c['verdict'] == v for c in cases)}" for v in sorted({c["verdict"] for c in cases}))
    add = max(max(c["add"]) for c in cases)
    runs = [max(c["run_add"]) for c in cases if "run_add" in c]
    motion = [c["motion"] for c in cases if "motion" in c]
    bad_ok = sum(c["verdict"] == "ok" and max(c["add"]) > 1.0 for c in cases)
    across = [max(c["run_across"]) for c in cases if "run_across" in c]
    return (f"| {row} | {add:.3f} | {max(runs):.3f} | {max(across):.3f} | " if runs else f"| {row} | {add:.3f} | - | - | ") + (
        f"{np.median([m['rotation_deg'] for m in motion]):.2f}° / {np.median([m['translation_mm'] for m in motion]):.2f} mm"
        if motion else "-") + (f" | {verdicts} | {bad_ok} | {sum(c['swapped'] for c in cases)} / "
                               f"{sum(c['ap_frontal'] for c in cases)} | {np.median([c['seconds'] for c in cases]):.1f} |")


def bench_views(args: argparse.Namespace) -> int:
    import trimesh

    from dsareg_engine.simulation.phantom import make_vessel_phantom

    mesh = make_vessel_phantom(depth=3, seed=3)
    stl = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="stl")
    print(f"{args.cases} case(s) per row, {args.size} px at {args.spacing} mm, phantom depth 3 ({mesh.n_faces} faces), "
          f"start 3° / 3 mm off, seed {args.seed}")
    print("| row | joint pose ADD mm, max over cases and runs | per-run poses ADD mm, max | per-run centre error across "
          "its beam mm, max | motion measured, median | verdicts | ok with a pose > 1 mm off | swapped back / AP frontal "
          "| s per case |")
    print("|---|---|---|---|---|---|---|---|---|")
    for row in _rows(args.rows):
        cases = [run_case(mesh, stl, row, args.seed + i, args.size, args.spacing) for i in range(args.cases)]
        print(_line(row, cases), flush=True)
    return 0
