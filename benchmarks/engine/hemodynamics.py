"""``python -m benchmarks.engine hemodynamics``: arrival and peak on the model from simulated biplane bolus runs with known times.

Per case: a bolus run is simulated (:mod:`dsareg_engine.simulation.bolus_run`) at the true pose, written as DICOM
XA runs (:mod:`dsareg_engine.simulation.bolus_dicom`), read as a job reads them (:func:`load_case_files`, native
runs subtracted), and the hemodynamics step runs at the true pose (registration accuracy is benchmarked
elsewhere). Per vertex of the model file, the measured values are compared with the truth.
Columns: mapped (of the vertices contrast reached; in brackets those no view sees clean, mapped by unmixing),
arrival error median / p90 and peak-time error median in s and frame intervals, the same on the unmixed vertices
alone (frame intervals), the gamma-variate fit's mean transit time error (relative, gamma-shaped boluses only), the views' agreement median, vertices contrast never reached that got a value (a never-reached vertex whose
cross-section shares space with a vessel contrast fills, where the phantom's tubes interpenetrate, is counted apart:
"+ valued / all in a filled lumen"; contrast does arrive there, :func:`in_filled_lumen`), and the
step's CPU seconds (user + sys, all threads) per job.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.simulation.bolus_run import BolusSettings
from dsareg_engine.simulation.native_run import Plane

RUN_SECONDS = 8.0
FILL_OF_VIEW = 0.6


@dataclass(frozen=True)
class Scenario:
    """One row: a name, the bolus settings, the DICOM layout and the pose (``"random"`` or ``"overlap"``)."""

    name: str
    settings: BolusSettings
    layout: str = "recipe"
    pose: str = "random"


SCENARIOS = (
    Scenario("2 fps, gamma, Poisson, recipe", BolusSettings(fps=2.0)),
    Scenario("4 fps, gamma, Poisson, recipe", BolusSettings(fps=4.0)),
    Scenario("7.5 fps, gamma, Poisson, recipe", BolusSettings(fps=7.5)),
    Scenario("4 fps, ramp, Gaussian, no recipe, LAT 0.3 s later",
             BolusSettings(fps=4.0, shape="ramp", noise="gaussian", lat_delay_s=0.3), "no-recipe"),
    Scenario("2 fps, ramp, Gaussian, subtracted", BolusSettings(fps=2.0, shape="ramp", noise="gaussian"), "subtracted"),
    Scenario("7.5 fps, ramp, Gaussian, no recipe", BolusSettings(fps=7.5, shape="ramp", noise="gaussian"), "no-recipe"),
    Scenario("7.5 fps, gamma, Gaussian, enhanced XA, per-frame times ±20 ms",
             BolusSettings(fps=7.5, noise="gaussian", jitter_s=0.02), "enhanced"),
    Scenario("4 fps, gamma, partial filling", BolusSettings(fps=4.0, partial=True)),
    Scenario("4 fps, ramp, partial filling, no recipe", BolusSettings(fps=4.0, shape="ramp", partial=True), "no-recipe"),
    Scenario("4 fps, gamma, heavy-overlap view", BolusSettings(fps=4.0), pose="overlap"),
)


def planes_for(mesh: TriangleMesh) -> dict[str, Plane]:
    """Biplane AP / LAT planes whose field of view the model fills to about ``FILL_OF_VIEW``."""
    extent = float(np.ptp(mesh.vertices, axis=0).max())
    spacing = extent / FILL_OF_VIEW * (1200.0 / 800.0) / 160.0  # detector = field at the isocentre × SID / SOD
    return {"ap": Plane(-6.0, 8.0, 1200.0, 800.0, spacing), "lat": Plane(94.0, 1.0, 1180.0, 790.0, spacing)}


def overlap_pose(mesh: TriangleMesh, rig: Rig) -> np.ndarray:
    """The model's longest principal axis along the AP rays (the AP view looks down the tree), centred."""
    centred = mesh.vertices - mesh.centroid
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    ray = rig.views["ap"].world_to_view[2, :3]
    v, c = np.cross(axis, ray), float(axis @ ray)
    skew = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    pose = np.eye(4)
    pose[:3, :3] = np.eye(3) + skew + skew @ skew / (1.0 + c) if c > -0.999 else -np.eye(3)
    pose[:3, 3] = -pose[:3, :3] @ mesh.centroid
    return pose


def case_files(mesh: TriangleMesh, mesh_bytes: bytes, scenario: Scenario, seed: int, size_px: int, inflow_mm):
    """``(CaseFiles, pose, truth)`` of one simulated case."""
    from dsareg_engine.io.case import CaseFiles
    from dsareg_engine.simulation.bolus_dicom import bolus_xa
    from dsareg_engine.simulation.bolus_run import make_bolus_run
    from dsareg_engine.simulation.native_run import pose_in_view

    planes = planes_for(mesh)
    rig = Rig(views={name: plane.view(size_px) for name, plane in planes.items()})
    pose = overlap_pose(mesh, rig) if scenario.pose == "overlap" else pose_in_view(mesh, rig, seed)
    settings = replace(scenario.settings, n_frames=max(32, math.ceil(RUN_SECONDS * scenario.settings.fps)))
    run = make_bolus_run(mesh, rig, pose, settings, seed=seed, inflow_mm=inflow_mm)
    files = {name: bolus_xa(run.frames[name], planes[name], name, scenario.layout, settings.fps,
                            photons=settings.photons, lat_delay_s=settings.lat_delay_s, times_s=run.times_s[name])
             for name in planes}
    return CaseFiles(ap=files["ap"], lat=files["lat"], mesh=mesh_bytes, mesh_name="model.obj"), pose, run.truth


def mtt_truth_s(settings: BolusSettings, truth) -> np.ndarray:
    """``(V,)`` the gamma-variate bolus's mean transit time ``(α + 1) β`` (``β = τp / α``); NaN for the ramp shape."""
    from dsareg_engine.simulation.bolus_run import GAMMA_ALPHA, rise_time_s

    if settings.shape != "gamma":
        return np.full(len(truth.onset_s), np.nan)
    return (GAMMA_ALPHA + 1.0) / GAMMA_ALPHA * rise_time_s(settings, truth.onset_s)


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 32) -> np.ndarray:
    """``(P,)`` generalized winding number of the surface ``faces`` (``(F, 3)`` into ``vertices (V, 3)``) at
    ``points (P, 3)``: the summed signed solid angle of the triangles over 4π (Van Oosterom and Strackee's formula);
    ±1 inside a closed surface, 0 outside, near ±1 inside a long open tube."""
    triangles = vertices[faces]  # (F, 3, 3)
    out = np.empty(len(points))
    for start in range(0, len(points), chunk):
        a, b, c = (triangles[None, :, k, :] - points[start:start + chunk, None, :] for k in range(3))  # (P, F, 3)
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        numerator = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        denominator = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", a, c) * lb
                       + np.einsum("pfi,pfi->pf", b, c) * la)
        out[start:start + chunk] = 2.0 * np.arctan2(numerator, denominator).sum(axis=1) / (4.0 * np.pi)
    return out


def _first_exit(origins: np.ndarray, directions: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(P,)`` distance along each ray ``origins + t · directions`` (``(P, 3)``, unit) to its nearest triangle
    (``(F, 3, 3)``) beyond ``t > 1e-6`` (Möller–Trumbore); ``inf`` where it meets none."""
    a, e1, e2 = triangles[:, 0], triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0]
    p = np.cross(directions[:, None, :], e2[None])  # (P, F, 3)
    det = np.einsum("fi,pfi->pf", e1, p)
    inv = np.where(np.abs(det) > 1e-12, 1.0 / np.where(det == 0.0, 1.0, det), 0.0)
    s = origins[:, None, :] - a[None]
    u = np.einsum("pfi,pfi->pf", s, p) * inv
    q = np.cross(s, e1[None])
    v = np.einsum("pi,pfi->pf", directions, q) * inv
    t = np.einsum("fi,pfi->pf", e2, q) * inv
    hit = (inv != 0.0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6)
    return np.where(hit, t, np.inf).min(axis=1)


def cross_section_centres(mesh, points: np.ndarray, chunk: int = 16) -> np.ndarray:
    """``(P, 3)`` the centre of the vessel cross-section at each vertex ``points`` ``(P,)``: the middle of its
    diameter, from the vertex along its inward normal (area-weighted) to where that ray meets the opposite wall of
    its own connected part of the surface (the phantom's tubes are separate closed parts that interpenetrate; a
    measured model is one part). The vertex itself where the ray meets nothing."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from dsareg_engine.geometry.vessel_tree import vertex_normals

    n = len(mesh.vertices)
    edges = np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]]])
    part = connected_components(coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n)),
                                directed=False)[1]
    inward = -vertex_normals(mesh)[points]
    centres = mesh.vertices[points].astype(float)
    face_part = part[mesh.faces[:, 0]]
    for label in np.unique(part[points]):
        mine = np.flatnonzero(part[points] == label)
        triangles = mesh.vertices[mesh.faces[face_part == label]]
        for start in range(0, len(mine), chunk):
            rows = mine[start:start + chunk]
            t = _first_exit(centres[rows], inward[rows], triangles)
            centres[rows] += np.where(np.isfinite(t), 0.5 * t, 0.0)[:, None] * inward[rows]
    return centres


DIAMETER_SAMPLES = (0.0, 0.25, 0.5, 0.75)


def in_filled_lumen(mesh, never: np.ndarray) -> np.ndarray:
    """``(V,)`` the never-reached vertices whose vessel cross-section shares space with a vessel contrast fills: a
    point of its diameter (from the wall vertex to the opposite wall, :func:`cross_section_centres`, at
    ``DIAMETER_SAMPLES`` of it) has |winding number| of the filled faces > ½. A vertex's value is its vessel's
    cross-section's (what the images and the measurement see), not its wall point's alone. The phantom's tubes
    interpenetrate: at a junction the first rings of a blocked branch are centred on the bifurcation point, inside
    the filled parent and sibling, while half their wall vertices lie just outside them; where a filled tube runs
    through a blocked one, part of the blocked tube's cross-section is the filled tube's lumen. The simulated iodine
    is there (a ray's stretch through both is one stretch of the filled vessel), so these vertices are counted
    apart. Two vessels that touch without interpenetrating share no point of a diameter."""
    inside = np.zeros(len(never), bool)
    filled = ~never[mesh.faces].any(axis=1)
    if never.any() and filled.any():
        points = np.flatnonzero(never)
        wall = mesh.vertices[points]
        across = 2.0 * (cross_section_centres(mesh, points) - wall)
        samples = np.concatenate([wall + f * across for f in DIAMETER_SAMPLES])
        winding = np.abs(winding_numbers(samples, mesh.vertices, mesh.faces[filled])).reshape(len(DIAMETER_SAMPLES), -1)
        inside[points] = (winding > 0.5).any(axis=0)
    return inside


def score(document: dict, truth, file_to_model: np.ndarray, fps: float, cpu_s: float,
          mtt_s: np.ndarray | None = None, in_lumen: np.ndarray | None = None) -> dict:
    """One case's numbers (per file vertex); ``mtt_s`` the true mean transit time per model vertex (or NaN);
    ``in_lumen`` the never-reached model vertices whose cross-section lies partly in a filled vessel
    (:func:`in_filled_lumen`), counted apart."""
    def values(name: str) -> np.ndarray:
        return np.array([np.nan if v is None else v for v in document[name]], float)

    arrival, peak = values("arrival_s"), values("peak_s")
    lumen = (in_lumen if in_lumen is not None else np.zeros(len(truth.onset_s), bool))[file_to_model]
    never = truth.never[file_to_model] & ~lumen
    reached = ~truth.never[file_to_model]
    mapped = np.isfinite(arrival) & reached
    interval = 1.0 / fps
    error = np.abs(arrival[mapped] - truth.arrival_s[file_to_model][mapped])
    peak_error = np.abs(peak[mapped] - truth.peak_s[file_to_model][mapped])
    nan = float("nan")
    unmixed = np.asarray(document["unmixed"], bool)[mapped]
    mtt_true = (mtt_s if mtt_s is not None else np.full(len(truth.onset_s), np.nan))[file_to_model][mapped]
    mtt_error = np.abs(values("mtt_s")[mapped] / mtt_true - 1.0)
    mtt_error = mtt_error[np.isfinite(mtt_error)]
    return {"mapped": mapped.sum() / max(reached.sum(), 1), "arrival_med_s": np.median(error) if len(error) else nan,
            "unmixed_mapped": unmixed.sum() / max(reached.sum(), 1),
            "mtt_rel_med": np.median(mtt_error) if len(mtt_error) else nan,
            "unmixed_med_s": np.median(error[unmixed]) if unmixed.any() else nan,
            "unmixed_p90_s": np.percentile(error[unmixed], 90) if unmixed.any() else nan,
            "unmixed_peak_med_s": np.median(peak_error[unmixed]) if unmixed.any() else nan,
            "arrival_p90_s": np.percentile(error, 90) if len(error) else nan,
            "peak_med_s": np.median(peak_error) if len(peak_error) else nan, "interval_s": interval,
            "agreement_s": document["summary"].get("agreement_median_s") or nan,
            "never": int(never.sum()), "never_valued": int((never & np.isfinite(arrival)).sum()), "cpu_s": cpu_s,
            "in_lumen": int(lumen.sum()), "in_lumen_valued": int((lumen & np.isfinite(arrival)).sum()),
            "overlap_ap": float(np.mean(document["overlap_ap"])), "overlap_lat": float(np.mean(document["overlap_lat"]))}


def run_case(mesh, mesh_bytes, scenario: Scenario, seed: int, size_px: int, inflow_mm, picture_dir: Path | None) -> dict:
    """Simulate, read and measure one case; its numbers."""
    import json

    from scipy.spatial import cKDTree

    from dsareg_engine.hemodynamics.model_points import vertices_as_given
    from dsareg_engine.hemodynamics.run import hemodynamics_step
    from dsareg_engine.io.case import load_case_files

    files, pose, truth = case_files(mesh, mesh_bytes, scenario, seed, size_px, inflow_mm)
    case = load_case_files(files)
    with tempfile.TemporaryDirectory() as folder:
        out = Path(picture_dir) if picture_dir is not None else Path(folder)
        out.mkdir(parents=True, exist_ok=True)
        summary = hemodynamics_step(files, case, {"mesh_to_world": pose.tolist()}, out)
        document = json.loads((out / "hemodynamics.json").read_text())
        if picture_dir is not None:
            write_model_pictures(case, mesh_bytes, document, pose, out)
    file_to_model = cKDTree(mesh.vertices).query(vertices_as_given(mesh_bytes, "obj"))[1]
    return score(document, truth, file_to_model, scenario.settings.fps, summary["cpu_s"],
                 mtt_truth_s(scenario.settings, truth), in_filled_lumen(mesh, truth.never))


def write_model_pictures(case, mesh_bytes: bytes, document: dict, pose: np.ndarray, out: Path) -> None:
    """``model_{ap,lat}.png``: the coloured model seen from each view (what hemodynamics.ply shows)."""
    from scipy.spatial import cKDTree

    from dsareg_engine.hemodynamics.colours import TimeScale
    from dsareg_engine.hemodynamics.model_points import vertices_as_given
    from dsareg_engine.hemodynamics.picture import model_picture
    from dsareg_engine.overlay import write_png

    arrival = np.array([np.nan if v is None else v for v in document["arrival_s"]], float)
    per_working = arrival[cKDTree(vertices_as_given(mesh_bytes, "obj")).query(case.mesh.vertices)[1]]
    colours = document["summary"]["colour_scale"]
    scale = TimeScale(colours["low_s"], colours["high_s"])
    for name, view in case.rig.views.items():
        write_png(out / f"model_{name}.png", model_picture(case.mesh, per_working, view, pose, scale,
                                                           f"model seen from {name.upper()}: arrival time"))


def lumen_note(cases: list[dict]) -> str:
    """`` (+ valued / all in a filled lumen)`` when some never-reached vertices lie inside a filled vessel."""
    inside = sum(c.get("in_lumen", 0) for c in cases)
    return f" (+ {sum(c.get('in_lumen_valued', 0) for c in cases)} / {inside} in a filled lumen)" if inside else ""


def table(rows: list[tuple[str, str, list[dict]]]) -> list[str]:
    """Markdown: one line per (mesh, scenario), the medians over its cases."""
    lines = ["| model | run | cases | mapped (of it unmixed) | arrival error median (s / frames) | p90 (s / frames) | "
             "peak error median (s / frames) | unmixed: arrival median / p90, peak median (frames) | agreement median (s) "
             "| never reached: valued / all | overlap AP / LAT | MTT error median (gamma) | CPU s per job |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for model, name, cases in rows:
        def median(key: str) -> float:  # NaN where no case has the number (MTT of a ramp bolus), without a warning
            values = np.array([c[key] for c in cases], float)
            return float(np.nanmedian(values)) if np.isfinite(values).any() else float("nan")

        interval = cases[0]["interval_s"]
        never = sum(c["never"] for c in cases)
        lines.append(
            f"| {model} | {name} | {len(cases)} | {100 * median('mapped'):.1f} % ({100 * median('unmixed_mapped'):.1f} %) "
            f"| {median('arrival_med_s'):.3f} / "
            f"{median('arrival_med_s') / interval:.2f} | {median('arrival_p90_s'):.3f} / {median('arrival_p90_s') / interval:.2f} "
            f"| {median('peak_med_s'):.3f} / {median('peak_med_s') / interval:.2f} | "
            f"{median('unmixed_med_s') / interval:.2f} / {median('unmixed_p90_s') / interval:.2f}, "
            f"{median('unmixed_peak_med_s') / interval:.2f} | {median('agreement_s'):.3f} | "
            f"{sum(c['never_valued'] for c in cases)} / {never}{lumen_note(cases)} | {100 * median('overlap_ap'):.0f} / "
            f"{100 * median('overlap_lat'):.0f} % | {100 * median('mtt_rel_med'):.1f} % | {median('cpu_s'):.2f} (max {max(c['cpu_s'] for c in cases):.2f}) |")
    return lines


def _model(path: str | None) -> tuple[str, TriangleMesh, bytes, np.ndarray | None]:
    from dsareg_engine.io.mesh_io import read_mesh
    from dsareg_engine.simulation.native_run import tree_root
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    if path is None:
        mesh = make_vessel_phantom(seed=0, depth=4)
        return "phantom", mesh, _obj_bytes(mesh), tree_root(mesh)
    data = Path(path).read_bytes()
    return Path(path).name, read_mesh(data, path), data, None


def _obj_bytes(mesh: TriangleMesh) -> bytes:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    return ("\n".join(lines) + "\n").encode()


def bench_hemodynamics(args) -> int:
    """Print the table (see the module docstring)."""
    scenarios = [s for s in SCENARIOS if not args.rows or any(word in s.name for word in args.rows)]
    rows = []
    for path in args.mesh or [None]:
        model, mesh, data, inflow = _model(None if path == "phantom" else path)
        if model != "phantom":
            mesh = _read_as_job(data)
        for scenario in scenarios:
            cases = []
            for k in range(args.cases):
                picture = Path(args.pictures) / model / scenario.name.replace(" ", "_").replace(",", "") \
                    if args.pictures and k == 0 else None
                cases.append(run_case(mesh, data, scenario, args.seed + k, args.size, inflow, picture))
            rows.append((model, scenario.name, cases))
            print(table(rows[-1:])[-1], flush=True)
    print("\n".join(table(rows)))
    return 0


def _read_as_job(data: bytes) -> TriangleMesh:
    from dsareg_engine.io.mesh_io import read_mesh

    return read_mesh(data, "model.obj")
