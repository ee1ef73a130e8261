"""``python -m benchmarks.engine clinical --sweep runs``: native XA runs across the axes real runs vary on.

Each row is one cell of the sweep, at its own image size: generator A (skull, photon noise, classic XA)
or B (texture, Gaussian noise, enhanced XA, LOG / MONOCHROME1), image side 512 / 1024 / 2048 px, bits
8 / 10 / 12 / 16, LIN / LOG / DISP, MONOCHROME1 / 2, with or without a subtraction recipe, patient motion
with a small rotation and a contrast-filled catheter, a bolus that passes along the tree, and the vessel tree
of the phantom or of a mesh file (``--mesh``, e.g. the paper's; its inlet taken as its lowest vertex along
+y, the model's head direction). 2048² runs have fewer frames (8) to keep the bench affordable.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from dsareg_engine.simulation.native_run_bolus import Bolus
from dsareg_engine.simulation.native_run_skull import SkullRunSettings
from dsareg_engine.simulation.native_run_texture import TextureRunSettings

FILL_12 = (0.0, 0.0, 0.0, 0.1, 0.3, 0.55, 0.8, 1.0, 1.2, 1.3, 1.3, 1.3)
STRENGTH_12 = (1.0,) * 9 + (0.95, 0.85, 0.7)
FILL_8 = (0.0, 0.0, 0.3, 0.7, 1.0, 1.2, 1.3, 1.3)
STRENGTH_8 = (1.0,) * 6 + (0.9, 0.75)
SKULL = SkullRunSettings(fill=FILL_12, strength=STRENGTH_12, mask_frames=(1, 2, 3), motion_px=(0.8, -0.5),
                         rotation_deg=0.5, catheter_mm=2.0)
TEXTURE = TextureRunSettings(rotation_deg=-0.4)


def _skull(size: int, **changes) -> SkullRunSettings:
    if size >= 2048:
        changes = {"fill": FILL_8, "strength": STRENGTH_8, "mask_frames": (1, 2), **changes}
    return replace(SKULL, size_px=size, **changes)


def _texture(size: int, **changes) -> TextureRunSettings:
    if size >= 2048:
        changes = {"fill": (0.0, 0.0, 0.0, 0.3, 0.7, 1.0, 1.2, 1.3), "strength": (1.0,) * 7 + (0.8,), **changes}
    return replace(TEXTURE, size_px=size, **changes)


def _build(generator: str, settings, mesh_path: str | None) -> Callable[[int], object]:
    def build(seed: int):
        """The :class:`~dsareg_engine.simulation.native_run.NativeRunCase` of ``seed``."""
        mesh, root = None, None
        if mesh_path is not None:
            from pathlib import Path

            from dsareg_engine.io.mesh_io import read_mesh
            from dsareg_engine.simulation.native_run import lowest_point

            mesh = read_mesh(Path(mesh_path).read_bytes(), Path(mesh_path).name)
            root = lowest_point(mesh)
        if generator == "A":
            from dsareg_engine.simulation.native_run_skull import make_skull_run

            run = make_skull_run(seed, settings, mesh, root)
        else:
            from dsareg_engine.simulation.native_run_texture import make_texture_run

            run = make_texture_run(seed, settings, mesh, root)
        return run
    return build


def run_rows(mesh_path: str | None) -> list[tuple[str, int, str, Callable[[int], object]]]:
    """``(name, size px, description, build(seed))`` per cell; the mesh rows only with ``mesh_path``."""
    rows = [
        ("A recipe", 512, "12-bit LIN MONOCHROME2, AVG_SUB recipe", "A", _skull(512)),
        ("A no recipe", 512, "as above without recipe or viewing mode", "A", _skull(512, recipe=False)),
        ("A recipe", 1024, "", "A", _skull(1024)),
        ("A no recipe", 1024, "the issue's case: 0.5° + (0.8, -0.5) px, catheter", "A", _skull(1024, recipe=False)),
        ("A recipe", 2048, "8 frames, 2 masks", "A", _skull(2048)),
        ("A no recipe", 2048, "8 frames, 2 masks", "A", _skull(2048, recipe=False)),
        ("A no recipe 8-bit DISP", 512, "", "A", _skull(512, recipe=False, bits=8, relationship="DISP")),
        ("A no recipe 10-bit LOG MONO1", 512, "", "A",
         _skull(512, recipe=False, bits=10, relationship="LOG", photometric="MONOCHROME1")),
        ("A no recipe 16-bit LIN MONO1", 512, "", "A", _skull(512, recipe=False, bits=16, photometric="MONOCHROME1")),
        ("B no recipe", 512, "12-bit LOG sign -1 MONOCHROME1, enhanced XA, -0.4°", "B", _texture(512)),
        ("B no recipe", 1024, "", "B", _texture(1024)),
        ("B no recipe", 2048, "8 frames", "B", _texture(2048)),
        ("A bolus passage (gamma)", 512, "4 frames/s, transit 1.5 s, no recipe", "A",
         _skull(512, recipe=False, bolus=Bolus())),
        ("A bolus passage (gamma)", 1024, "", "A", _skull(1024, recipe=False, bolus=Bolus())),
        ("B bolus passage (cosine)", 512, "", "B", _texture(512, bolus=Bolus(shape="cosine"))),
    ]
    if mesh_path is not None:
        rows += [
            ("A no recipe, mesh", 512, "the mesh's tree", "A", _skull(512, recipe=False)),
            ("B bolus passage, mesh", 512, "the mesh's tree", "B", _texture(512, bolus=Bolus(shape="cosine"))),
        ]
    return [(name, size, text, _build(generator, settings, mesh_path if "mesh" in name else None))
            for name, size, text, generator, settings in rows]


def bench_runs(args, options: dict, run_one, case_of) -> int:
    """Print the sweep's table (``case_of(run)``: the clinical case of a native run; ``run_one(case, options)
    → {add_mm, verdict, cpu_s, wall_s}``)."""
    rows = [row for row in run_rows(getattr(args, "mesh", None))
            if not args.kinds or any(word.lower() in row[0].lower() for word in args.kinds)]
    print(f"{args.cases} case(s) per cell, seed {args.seed}; no geometry file, no initial pose, default options")
    print("| run | px | cases | ok, ADD <= 0.1 mm | ADD mm median / max | verdicts | wrong poses read ok | CPU s median |")
    print("|---|---|---|---|---|---|---|---|")
    for name, size, _, build in rows:
        results = [run_one(case_of(build(args.seed + i)), options) for i in range(args.cases)]
        adds = [r["add_mm"] for r in results]
        good = sum(r["verdict"] == "ok" and r["add_mm"] <= 0.1 for r in results)
        wrong = sum(r["verdict"] == "ok" and r["add_mm"] > 1.0 for r in results)
        verdicts = ", ".join(f"{v} {sum(r['verdict'] == v for r in results)}" for v in sorted({r["verdict"] for r in results}))
        print(f"| {name} | {size} | {len(results)} | {good}/{len(results)} | {np.median(adds):.3f} / {max(adds):.3f} | "
              f"{verdicts} | {wrong} | {np.median([r['cpu_s'] for r in results]):.1f} |", flush=True)
    return 0
