"""How often, and at what cost, a DICOM case's inputs are parsed: ``load_case_files`` + the REG/SC writer.

``python -m benchmarks.service.dicom_reads OUT_DIR [REPEATS] [STUDY.pkl]`` prints the median and least CPU seconds,
wall seconds, the peak memory tracemalloc saw and the ``pydicom.dcmread`` calls of one pass, and writes each
pass's DICOM outputs (UIDs and times fixed) under OUT_DIR. The study (2 XA + a 43-slice 512 × 512 CT series
of the phantom) is saved to STUDY.pkl on the first run, so that another tree (e.g. ``git archive ad8dd6e``,
where the case has no ``sources`` and the writer's ``read_sources`` parses the files) reads the same bytes
and the outputs can be compared with ``cmp``. Numbers: docs/concepts/layout.md, "Inputs read once".
"""

from __future__ import annotations

import itertools
import pickle
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pydicom
from PIL import Image

from dsareg_engine.io import dicom_out
from dsareg_engine.io.case import CaseFiles, load_case_files
from dsareg_engine.simulation.phantom_study import make_biplane_study

CALLS = {"n": 0}


def _counting(real):
    def dcmread(*args, **kwargs):
        CALLS["n"] += 1
        return real(*args, **kwargs)
    return dcmread


def _study(path: Path) -> CaseFiles:
    if not path.exists():
        made = make_biplane_study(image_px=256, slice_px=512)
        path.write_bytes(pickle.dumps({"ap": made.ap, "lat": made.lat, "volume": list(made.volume)}))
    study = pickle.loads(path.read_bytes())  # noqa: S301 - the file this script wrote
    return CaseFiles(ap=study["ap"], lat=study["lat"], volume=study["volume"], ap_name="ap.dcm", lat_name="lat.dcm")


def one_pass(files: CaseFiles, target: Path) -> None:
    """Read the case, then write the REG and two overlay SCs with fixed UIDs and times."""
    target.mkdir(parents=True, exist_ok=True)
    for name in ("overlay_ap.png", "overlay_lat.png"):
        Image.fromarray(np.full((64, 80, 3), 90, np.uint8)).save(target / name)
    numbers = itertools.count(1)
    dicom_out.new_uid = lambda: f"2.25.{next(numbers)}"
    dicom_out._now = lambda: ("20261201", "000000.000000")
    case = load_case_files(files)
    sources = case.sources if hasattr(case, "sources") else dicom_out.read_sources(files.ap, files.lat, files.volume)
    dicom_out.write_dicom_outputs(target, np.eye(4), sources, target)


def main(argv: list[str]) -> None:
    out = Path(argv[0])
    repeats = int(argv[1]) if len(argv) > 1 else 5
    files = _study(Path(argv[2]) if len(argv) > 2 else out.parent / "dicom_reads_study.pkl")
    pydicom.dcmread = _counting(pydicom.dcmread)
    one_pass(files, out / "warm")
    rows = []
    for index in range(repeats):
        CALLS["n"] = 0
        tracemalloc.start()
        cpu, wall = time.process_time(), time.perf_counter()
        one_pass(files, out / f"run{index}")
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        rows.append((cpu, wall, tracemalloc.get_traced_memory()[1] / 2**20, CALLS["n"]))
        tracemalloc.stop()
    cpu_s, wall_s = sorted(r[0] for r in rows), sorted(r[1] for r in rows)
    print(f"inputs: 2 XA + {len(files.volume)} slices ({sum(map(len, files.volume)) / 2**20:.1f} MB volume)")
    print(f"cpu_s median {cpu_s[len(rows) // 2]:.3f} min {cpu_s[0]:.3f}; wall_s median {wall_s[len(rows) // 2]:.3f}; "
          f"peak_traced_MB {max(r[2] for r in rows):.1f}; dcmread calls {rows[-1][3]}")


if __name__ == "__main__":
    main(sys.argv[1:])
