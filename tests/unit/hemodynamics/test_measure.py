"""The measurement on simulated bolus runs: an overlap that one view must carry, a branch that never fills."""

from __future__ import annotations

import numpy as np

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.hemodynamics.measure import RunFrames, measure
from dsareg_engine.hemodynamics.timing import RunTiming
from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.simulation.bolus_run import BolusSettings, make_bolus_run
from dsareg_engine.simulation.native_run import Plane, tree_root
from dsareg_engine.simulation.phantom import _tube, make_vessel_phantom

SQUARE = {"ap": Plane(0.0, 0.0, 1200.0, 800.0, 1.2), "lat": Plane(90.0, 0.0, 1200.0, 800.0, 1.2)}


def _runs(run) -> dict[str, RunFrames]:
    """Opacity stacks as the subtraction gives them: each frame minus the first (log domain)."""
    return {name: RunFrames((frames - frames[0]).astype(np.float32), RunTiming(run.times_s[name], "FrameTime"))
            for name, frames in run.frames.items()}


def _crossing_tubes() -> TriangleMesh:
    """Tube A on the diagonal of the x–z plane at y = −15 mm, tube B along z at y = +15 mm: in AP (rays along y)
    they cross at the origin 30 mm apart in depth; in LAT (rays along x) they lie apart."""
    ring = np.linspace(0.0, 1.0, 40)[:, None]
    a = np.array([-30.0, -15.0, -30.0]) + ring * np.array([60.0, 0.0, 60.0])
    b = np.array([0.0, 15.0, -32.0]) + ring * np.array([0.0, 0.0, 64.0])
    va, fa = _tube(a, np.full(40, 1.6), 12)
    vb, fb = _tube(b, np.full(40, 1.6), 12)
    return TriangleMesh(np.concatenate([va, vb]), np.concatenate([fa, fb + len(va)]))


def test_where_vessels_cross_in_one_view_the_other_view_carries_the_point():
    mesh = _crossing_tubes()
    rig = Rig(views={name: plane.view(128) for name, plane in SQUARE.items()})
    settings = BolusSettings(fps=4.0, n_frames=28, noise="gaussian", supersample=1, transit_s=3.0)
    run = make_bolus_run(mesh, rig, np.eye(4), settings, seed=1, inflow_mm=np.array([-30.0, -15.0, -30.0]))
    found = measure(mesh, np.eye(4), rig, _runs(run)).values
    on_a = np.arange(len(mesh.vertices)) < 480
    at_crossing = on_a & (np.abs(mesh.vertices[:, 0]) < 2.0)
    far = on_a & (np.abs(mesh.vertices[:, 0]) > 12.0)
    assert not found["clean_ap"][at_crossing].any() and found["clean_lat"][at_crossing].all()
    assert found["clean_ap"][far].all() and found["clean_lat"][far].all()
    carried = found["arrival_s"][at_crossing]
    assert np.isfinite(carried).all() and np.isnan(found["arrival_s_ap"][at_crossing]).all()
    assert np.abs(carried - run.truth.arrival_s[at_crossing]).max() < 0.5 / settings.fps
    assert np.nanmedian(found["agreement_s"][far]) < 0.5 / settings.fps


def test_phantom_run_meets_the_targets_and_a_blocked_branch_stays_null():
    mesh = make_vessel_phantom(seed=0, depth=3)
    rig = Rig(views={"ap": Plane(-6.0, 8.0, 1200.0, 800.0, 1.2).view(160),
                     "lat": Plane(94.0, 1.0, 1180.0, 790.0, 1.2).view(160)})
    pose = np.eye(4)
    pose[:3, 3] = -mesh.centroid
    settings = BolusSettings(fps=4.0, n_frames=28, partial=True, supersample=1)
    run = make_bolus_run(mesh, rig, pose, settings, seed=3, inflow_mm=tree_root(mesh))
    found = measure(mesh, pose, rig, _runs(run)).values
    never = run.truth.never
    assert 0.15 < never.mean() < 0.5
    assert not np.isfinite(found["arrival_s"][never]).any()
    filled = ~never
    mapped = np.isfinite(found["arrival_s"]) & filled
    assert mapped.sum() >= 0.75 * filled.sum()
    error = np.abs(found["arrival_s"][mapped] - run.truth.arrival_s[mapped])
    interval = 1.0 / settings.fps
    assert np.median(error) <= 0.5 * interval and np.percentile(error, 90) <= 2 * interval
    assert np.median(np.abs(found["peak_s"][mapped] - run.truth.peak_s[mapped])) <= interval


def _tube_along(start, end, count: int = 40, radius_mm: float = 1.6):
    ring = np.linspace(0.0, 1.0, count)[:, None]
    return _tube(np.asarray(start, float) + ring * (np.asarray(end, float) - np.asarray(start, float)),
                 np.full(count, radius_mm), 12)


def test_a_point_both_views_overlap_is_unmixed_from_the_vessels_crossing_it():
    """Tube A runs along (1, 1, 1) through the origin; tube B (along z at y = 20 mm) crosses it there in AP (rays along
    y), tube C (along z at x = 20 mm) in LAT (rays along x): no view sees A's middle clean. B fills early and C late,
    so a mixed curve would move A's arrival or peak; the unmixed one keeps A's own (truth from its own onset)."""
    from dsareg_engine.simulation.bolus_run import iodine_frames, noisy_log_frames, truth_of

    parts = [_tube_along([-25.0] * 3, [25.0] * 3), _tube_along([0.0, 20.0, -12.0], [0.0, 20.0, 12.0]),
             _tube_along([20.0, 0.0, -12.0], [20.0, 0.0, 12.0])]
    offsets = np.cumsum([0] + [len(v) for v, _ in parts])
    mesh = TriangleMesh(np.concatenate([v for v, _ in parts]),
                        np.concatenate([f + o for (_, f), o in zip(parts, offsets)]))
    part = np.searchsorted(offsets, np.arange(len(mesh.vertices)), side="right") - 1
    along_a = mesh.vertices.sum(axis=1) / np.sqrt(3.0)
    onset = np.where(part == 0, 2.5 + along_a / 43.3, np.where(part == 1, 1.0, 4.0))
    rig = Rig(views={name: plane.view(128) for name, plane in SQUARE.items()})
    settings = BolusSettings(fps=4.0, n_frames=32, noise="gaussian", supersample=1)
    rng = np.random.default_rng(2)
    times = np.arange(settings.n_frames) / settings.fps
    runs = {}
    for name, view in rig.views.items():
        log = noisy_log_frames(iodine_frames(mesh, view, np.eye(4), onset, settings, times), settings, rng)
        runs[name] = RunFrames((log - log[0]).astype(np.float32), RunTiming(times, "FrameTime"))
    found = measure(mesh, np.eye(4), rig, runs).values
    truth = truth_of(settings, onset)
    middle = (part == 0) & (np.abs(along_a) < 1.5)
    assert middle.sum() >= 12
    assert not (found["clean_ap"] | found["clean_lat"])[middle].any()
    assert found["unmixed_ap"][middle].all() and found["unmixed_lat"][middle].all()
    assert np.isfinite(found["arrival_s"][middle]).all()
    interval = 1.0 / settings.fps
    assert np.median(np.abs(found["arrival_s"][middle] - truth.arrival_s[middle])) <= 0.5 * interval
    assert np.median(np.abs(found["peak_s"][middle] - truth.peak_s[middle])) <= interval


def test_a_footprint_reaching_past_its_walls_onto_a_filled_vessel_beside_it_gives_no_value():
    """Tube T (radius 0.5 mm, along z at x = 75 mm, outside the AP field) never fills; tube F (radius 1.6 mm, filled)
    runs beside it in LAT (rays along x) 95 mm nearer the detector, its wall 0.5 px from T's: no ray crosses both.
    T's points are given a 1 mm radius (a local radius overestimated), so their footprints reach onto F's pixels:
    their curves are F's contrast. They are overlapped (beside) in LAT, unmixed, and stay null; F keeps its values."""
    from dsareg_engine.hemodynamics.model_points import VesselPoints, vessel_points
    from dsareg_engine.simulation.bolus_run import iodine_frames, noisy_log_frames

    parts = [_tube_along([75.0, 0.5, -30.0], [75.0, 0.5, 30.0], 60, 0.5), _tube_along([-20.0, 2.6, -12.0], [-20.0, 2.6, 12.0])]
    mesh = TriangleMesh(np.concatenate([parts[0][0], parts[1][0]]), np.concatenate([parts[0][1], parts[1][1] + len(parts[0][0])]))
    on_t = np.arange(len(mesh.vertices)) < len(parts[0][0])
    rig = Rig(views={name: plane.view(128) for name, plane in SQUARE.items()})
    settings = BolusSettings(fps=4.0, n_frames=24, noise="gaussian", supersample=1, blur_px=0.0)
    rng = np.random.default_rng(0)
    times = np.arange(settings.n_frames) / settings.fps
    onset = np.where(on_t, np.inf, 1.5)
    runs = {}
    for name, view in rig.views.items():
        log = noisy_log_frames(iodine_frames(mesh, view, np.eye(4), onset, settings, times), settings, rng)
        runs[name] = RunFrames((log - log[0]).astype(np.float32), RunTiming(times, "FrameTime"))
    given = vessel_points(mesh)
    radii = np.where(on_t, 1.0, given.radii_mm)
    inward = (mesh.vertices - given.centres_mm) / given.radii_mm[:, None]
    found = measure(mesh, np.eye(4), rig, runs, points=VesselPoints(mesh.vertices - inward * radii[:, None], radii)).values
    beside = on_t & ~found["clean_lat"] & found["unmixed_lat"]
    assert beside.sum() >= 60 and not found["clean_ap"][on_t].any()
    assert not np.isfinite(found["arrival_s"][on_t]).any()
    assert np.isfinite(found["arrival_s"][~on_t]).all()
