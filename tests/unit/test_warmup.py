"""A worker's warm-up runs one tiny job through every step, so its first real job pays no set-up."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from dsareg_engine.artifacts import REGISTRATION_FILES
from dsareg_engine.io.review_files import MASK_BIT, obj_as_given
from dsareg_engine.warmup import phantom_case_files, warm_up_job

REPO = Path(__file__).resolve().parents[2]


def test_warm_up_job_writes_what_a_job_writes(tmp_path):
    result = warm_up_job(tmp_path)
    assert len(result["mesh_to_world"]) == 4
    written = {p.name for p in tmp_path.iterdir()}
    assert set(REGISTRATION_FILES) - {"animation.gif"} <= written, written
    assert any(name.endswith(".dcm") for name in written), written
    # the review files: the model as given (the OBJ's own vertex order) and each view's C-arm and layers
    model = json.loads((tmp_path / "model.json").read_text())
    (tmp_path / "again").mkdir()
    given, faces = obj_as_given(phantom_case_files(tmp_path / "again")["mesh"])
    assert model["vertex_order"] == "file" and model["vertex_count"] == len(given)
    assert np.allclose(np.reshape(model["vertices"], (-1, 3)), given, atol=1e-4)
    assert model["faces"] == faces.ravel().tolist() and model["poses"]["registered"] == result["mesh_to_world"]
    for view in ("ap", "lat"):
        assert model["views"][view] == result["views"][view]["detector"]
        layers = cv2.imread(str(tmp_path / f"layers_{view}.png"))[..., ::-1]
        image = cv2.imread(str(tmp_path / f"image_{view}.png"), cv2.IMREAD_UNCHANGED)
        assert layers.shape[:2] == image.shape == tuple(model["views"][view]["image_size_px"][::-1])
        assert (layers[..., 1] == 255).any() and ((layers[..., 2] & MASK_BIT) > 0).any()


def test_service_warm_up_loads_what_the_first_job_would_load(tmp_path):
    """In a fresh process: after the worker's warm-up, the modules a job imports lazily are loaded
    and the first job costs about what the next one costs (was ~4x: 2.1 vs 0.5 CPU-s); torch's compiler is
    imported by neither (1.8 CPU s, 70 MB: :mod:`dsareg_engine.registration.optim`)."""
    script = textwrap.dedent(f"""
        import json, resource, sys
        from pathlib import Path
        from service.engine_adapter import engine
        from service.jobs.worker import warm_up
        from dsareg_engine.warmup import phantom_case_files
        engine.set_cpu_threads(1)
        warm_up()
        loaded = [m for m in ("torch._dynamo", "matplotlib.backends.backend_agg", "pydicom") if m in sys.modules]
        files = phantom_case_files(Path({str(tmp_path)!r}), 48)
        def cpu():
            r = resource.getrusage(resource.RUSAGE_SELF)
            return r.ru_utime + r.ru_stime
        costs = []
        for n in range(2):
            start = cpu()
            case_files = engine.CaseFiles(mesh=files["mesh"], mesh_name="m.obj", ap=files["ap"], ap_name="a.png",
                                          lat=files["lat"], lat_name="l.png",
                                          geometry=engine.parse_geometry(files["geometry"]))
            out = Path({str(tmp_path)!r}) / f"job{{n}}"
            engine.run_case(case_files, {{"max_iterations": 5}}, out, dicom="required")
            costs.append(cpu() - start)
        print(json.dumps({{"loaded": loaded, "costs": costs, "compiler": "torch._dynamo" in sys.modules}}))
    """)
    done = subprocess.run([sys.executable, "-c", script], check=False, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["loaded"] == ["matplotlib.backends.backend_agg", "pydicom"] and not report["compiler"]
    first, second = report["costs"]
    assert first < 2.0 * second + 0.3, report  # no second of imports left for the first job


def _python(script: str, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, "-c", textwrap.dedent(script)], check=False, cwd=REPO, capture_output=True,
                          text=True, timeout=timeout, env={**os.environ, **env})


@pytest.mark.slow
def test_a_helper_compiles_a_group_that_this_process_then_loads_from_the_cache(tmp_path):
    """The split warm-up is only worth it if the helper compiles the very specializations the worker
    calls: with an empty cache, after the helper compiled ``backward``, this process compiles nothing."""
    done = _python("""
        import json
        from dsareg_engine.threads import set_cpu_threads
        from dsareg_engine import warmup
        set_cpu_threads(1)
        before = warmup.group_cached("backward")
        helper = warmup.start_helper(["backward"])
        _, errors = helper.communicate(timeout=500)
        assert helper.returncode == 0, errors
        after = warmup.group_cached("backward")
        warmup._compile_backward()
        (kernel,) = warmup._group_dispatchers("backward")
        stats = kernel.stats
        print(json.dumps({"before": before, "after": after, "hits": sum(stats.cache_hits.values()),
                          "misses": sum(stats.cache_misses.values()), "signatures": len(kernel.signatures)}))
    """, {"NUMBA_CACHE_DIR": str(tmp_path / "cache")})
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report == {"before": False, "after": True, "hits": 2, "misses": 0, "signatures": 2}, report


def _cache_holding(cache_dir: Path, groups: tuple[str, ...]) -> Path:
    """A new numba cache (for ``NUMBA_CACHE_DIR``) holding only ``groups``' kernels for the 1-thread budget, copied
    from this checkout's cache (``dsareg warmup`` filled it; what it lacks, the test's processes compile)."""
    import inspect
    import shutil

    import numba
    from numba.core.caching import _CacheLocator

    from dsareg_engine import warmup

    before = numba.get_num_threads()
    numba.set_num_threads(1)  # the serial twins, as the test's processes (set_cpu_threads(1)) pick them
    try:
        dispatchers = [kernel for group in groups for kernel in warmup._group_dispatchers(group)]
    finally:
        numba.set_num_threads(before)
    for kernel in dispatchers:
        index = getattr(getattr(kernel, "_cache", None), "_cache_file", None)
        if index is None:  # numba's cache internals moved: copy nothing (the test's processes compile it all)
            continue
        target = cache_dir / _CacheLocator.get_suitable_cache_subpath(inspect.getfile(kernel.py_func))
        target.mkdir(parents=True, exist_ok=True)
        for path in Path(index._cache_path).glob(index._index_name.removesuffix(".nbi") + ".*"):  # .nbi and .N.nbc
            shutil.copy2(path, target)
    return cache_dir


@pytest.mark.slow
def test_the_search_group_holds_the_coverage_searchs_splat(tmp_path):
    """A partial-visibility job's coverage and branch searches splat with ``splat_images``: after the search
    group was compiled (by the background helper, another process) it loads from the cache, not compiled in
    the job. The cache starts with the other groups' kernels (the search group's tiny job renders), not its own."""
    env = {"NUMBA_CACHE_DIR": str(_cache_holding(tmp_path / "cache", ("forward", "backward", "tracking")))}
    compiled = _python("""
        from dsareg_engine.threads import set_cpu_threads
        from dsareg_engine import warmup
        set_cpu_threads(1)
        assert not warmup.group_cached("search")
        warmup.compile_group("search")
    """, env)
    assert compiled.returncode == 0, compiled.stderr[-3000:]
    done = _python("""
        import json
        import numpy as np
        from dsareg_engine.threads import set_cpu_threads
        from dsareg_engine import warmup
        from dsareg_engine.registration.search.coverage_search import _SPLAT, _splats, coverage_view
        from dsareg_engine.registration.search.settings import COVERAGE
        from dsareg_engine.geometry.rig import ViewGeometry
        set_cpu_threads(1)
        cached = warmup.group_cached("search")
        view = ViewGeometry(image_size=(64, 64), pixel_spacing_mm=(1.0, 1.0), sid_mm=1000.0,
                            principal_point_px=(31.5, 31.5), world_to_view=np.eye(4))
        mask = np.zeros((64, 64), bool)
        mask[20:40, 30:34] = True
        canvas = coverage_view(view, mask, np.array([0.0, 0.0, 700.0]), 10.0, COVERAGE)
        points = np.ascontiguousarray(np.random.default_rng(0).normal(size=(50, 3)))
        _splats(canvas, np.eye(3)[None].repeat(2, axis=0), np.array([0.0, 0.0, 700.0]), points, 1)
        stats = _SPLAT.pick(1).stats
        print(json.dumps({"cached": cached, "hits": sum(stats.cache_hits.values()), "misses": sum(stats.cache_misses.values())}))
    """, env)
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report == {"cached": True, "hits": 1, "misses": 0}, report


def _later_group_used_from_the_cache(group: str, use: str, tmp_path) -> dict:
    """Compile the later ``group`` in one process (as the background helper does), then run ``use`` (code that
    sets ``report``, a dict) in another with the same cache: ``report`` with the group's cache hits and misses
    there and whether it was found cached before the use."""
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    compiled = _python(f"""
        from dsareg_engine import warmup
        assert {group!r} in warmup.LATER_GROUPS
        warmup.compile_group({group!r})
    """, env)
    assert compiled.returncode == 0, compiled.stderr[-3000:]
    done = _python(f"""
        import json
        import numpy as np
        from dsareg_engine import warmup
        cached = warmup.group_cached({group!r})
        {textwrap.indent(textwrap.dedent(use), " " * 8).strip()}
        kernels = warmup._group_dispatchers({group!r})
        print(json.dumps({{**report, "cached": cached,
                          "hits": sum(sum(k.stats.cache_hits.values()) for k in kernels),
                          "misses": sum(sum(k.stats.cache_misses.values()) for k in kernels)}}))
    """, env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_hemodynamics_group_holds_the_kernels_a_hemodynamics_job_traces_with(tmp_path):
    """A worker's first hemodynamics job loads the ray-stretch kernels from the cache the background helper filled
    (another process), at a job's size and types, instead of compiling them."""
    report = _later_group_used_from_the_cache("hemodynamics", """
        from dsareg_engine.hemodynamics.measure import model_stretches
        from dsareg_engine.simulation.native_run import Plane
        from dsareg_engine.simulation.phantom import make_vessel_phantom
        mesh = make_vessel_phantom(seed=0, depth=2)
        pose = np.eye(4)
        pose[:3, 3] = -mesh.centroid
        stretches = model_stretches(mesh, Plane(0.0, 0.0, 1200.0, 800.0, 1.2).view(64), pose)
        report = {"covered": bool(stretches.covered.any())}
    """, tmp_path)
    assert report == {"cached": True, "covered": True, "hits": 2, "misses": 0}, report


def test_the_volumes_group_holds_the_distance_transform_a_tof_reading_takes(tmp_path):
    """A TOF-MRA reading's scalp band (7 mm: the wide path of ``within_mm``) loads the distance transform the
    background helper compiled (another process), instead of compiling it in the job."""
    report = _later_group_used_from_the_cache("volumes", """
        from scipy import ndimage
        from dsareg_engine.io.voxel_band import within_mm
        air = np.ones((30, 80, 80), bool)
        air[:, 5:75, 5:75] = False  # a head's section (21 mm square), the slab's faces cut through it
        band = within_mm(air, (0.6, 0.3, 0.3), 7.0)
        same = bool(np.array_equal(band, ndimage.distance_transform_edt(~air, sampling=(0.6, 0.3, 0.3)) <= 7.0))
        report = {"same": same, "interior": int((~band).sum())}
    """, tmp_path)
    assert report == {"cached": True, "same": True, "interior": 30 * 24 * 24, "hits": 1, "misses": 0}, report


def test_a_kernel_helper_dies_with_the_process_that_started_it(tmp_path):
    """A killed worker leaves no compile behind (fault tests count every process of the service)."""
    import os
    import signal
    import time

    parent = subprocess.Popen([sys.executable, "-c", textwrap.dedent("""
        import sys, time
        from dsareg_engine import warmup
        helper = warmup.start_helper(["tracking"], background=True)
        print(helper.pid, flush=True)
        time.sleep(600)
    """)], cwd=REPO, stdout=subprocess.PIPE, text=True,
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")})  # empty: the helper has minutes of work
    try:
        helper_pid = int(parent.stdout.readline())
        time.sleep(1.0)
        assert Path(f"/proc/{helper_pid}").exists(), "the helper should still be compiling"
        assert int(Path(f"/proc/{helper_pid}/stat").read_text().rsplit(")", 1)[1].split()[16]) == 19, "not niced"
    finally:
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
    deadline = time.monotonic() + 10
    while Path(f"/proc/{helper_pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not Path(f"/proc/{helper_pid}").exists(), "the helper outlived its parent"


def test_dsareg_warmup_says_what_it_does_before_the_first_compile(monkeypatch, capsys):
    """`dsareg warmup` printed nothing for its first 69 s: it says what it compiles, and how long that takes, before
    anything is compiled, and one line per step (the compile steps faked here)."""
    import argparse

    from dsareg_engine import warmup
    from dsareg_engine.commands import warmup as command

    seen: list[str] = []

    def step(name):
        def record(*args, **kwargs):
            seen.append((name, capsys.readouterr().err))
        return record

    monkeypatch.setattr(warmup, "compile_group", step("compile"))
    monkeypatch.setattr(warmup, "start_helper", lambda groups: None)
    monkeypatch.setattr(warmup, "warm_up_renderer", step("renderer"))
    monkeypatch.setattr(warmup, "warm_up_job", step("job"))
    assert command.run(argparse.Namespace()) == 0
    first_name, before_first = seen[0]
    assert first_name == "compile" and "warmup: compiling the numba kernels" in before_first
    assert "about a minute" in before_first and "kernel groups forward, backward (1/2)" in before_first
    assert all(text.strip() for name, text in seen if name != "job"), seen  # a line before each compile step
