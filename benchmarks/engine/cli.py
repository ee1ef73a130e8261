"""``python -m benchmarks.engine NAME``: the engine's benchmarks (render, table1, capture, track, robustness, autoinit,
partial, clinical, models, hemodynamics, jobcost). The parser only, so that ``--help`` and argument errors never load torch
(the runs are in :mod:`benchmarks.engine.phantom` and its siblings, imported when a benchmark starts); errors go
through the ``dsareg`` error path (one line, exit status 2 or 1, ``--debug`` for a traceback)."""

from __future__ import annotations

import argparse

from dsareg_engine.commands.deferred import deferred
from dsareg_engine.commands.kit import run_parsed
from dsareg_engine.registration.options import CONFIGURATIONS
from dsareg_engine.simulation.segmentation_errors import CORRUPTIONS

GREY_VARIANTS = {
    "default": ({}, 16),
    "noise2x": ({"noise_sigma": 0.02}, 16),
    "background2x": ({"background_variation": 0.5}, 16),
    "background_fine": ({"background_cells": 10}, 16),
    "saturating": ({"attenuation_per_mm": 0.3}, 16),
    "faint": ({"attenuation_per_mm": 0.05}, 16),
    "blur1px": ({"blur_px": 1.0}, 16),
    "8bit": ({}, 8),
    "noisefree": ({"noise_sigma": 0.0}, 16),
}
"""Grey-level image formations (:class:`~dsareg_engine.simulation.synthetic_dsa.DsaSettings` changes, bits per pixel)."""


def main(argv: list[str] | None = None) -> int:
    return run_parsed(build_parser().parse_args(argv))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.engine",
        description="Benchmarks that print Markdown tables. Every one runs on the built-in phantom unless --mesh "
                    "names a mesh (the paper's mesh is published in the authors' TwoViewsDSAReg repository).")
    parser.add_argument("--debug", action="store_true", help="show Python tracebacks of errors (for bug reports)")
    which = parser.add_subparsers(dest="bench", required=True, metavar="BENCHMARK")
    _add_render(which)
    _add_table1_capture(which)
    _add_track(which)
    _add_robustness(which)
    _add_autoinit(which)
    _add_partial(which)
    _add_clinical(which)
    _add_hemodynamics(which)
    _add_models(which)
    _add_job_cost(which)
    _add_views(which)
    _add_segmentation(which)
    _add_whole_head(which)
    _add_real_volumes(which)
    return parser


def _add_render(which) -> None:
    """``python -m benchmarks.engine``: the renderer's speed."""
    render = which.add_parser("render", help="ms per forward and forward+backward")
    _add_mesh(render)
    render.add_argument("--size", type=int, nargs="+", default=[256, 400, 800], help="image sides in px")
    render.add_argument("--sigma", type=float, nargs="+", default=[0.5, 1.0], help="silhouette edge softness in px")
    render.add_argument("--batch", type=int, default=1, help="poses rendered at once")
    render.add_argument("--repeats", type=int, default=20, help="timed runs (the median is printed)")
    render.add_argument("--backend", default="auto", choices=["auto", "numba", "torch"], help="rasterizer (default auto)")
    render.add_argument("--torch-threads", type=int, default=1, help="torch intra-op threads (registration uses 1 on CPU)")
    _add_device(render)
    render.set_defaults(func=deferred("benchmarks.engine.phantom:bench_render"))


def _add_table1_capture(which) -> None:
    """``python -m benchmarks.engine``: the paper's Table 1 and the capture range."""
    for name in ("table1", "capture"):
        sub = which.add_parser(name, help={"table1": "the paper's Table 1: accuracy per configuration",
                                           "capture": "capture range: success per initial mTRE bin"}[name])
        _add_mesh(sub)
        sub.add_argument("--starts", type=int, default=20, help="random initial poses (table1) / per bin (capture)")
        sub.add_argument("--seed", type=int, default=0, help="random seed of the initial poses")
        sub.add_argument("--size", type=int, default=800, help="image side in px")
        sub.add_argument("--configs", nargs="+", default=list(CONFIGURATIONS), help="configurations to run (default all)")
        sub.add_argument("--multistart", type=int, default=4, help="parallel starts inside each registration")
        sub.add_argument("--max-mtre", type=float, default=20.0, help="largest initial mTRE in mm")
        sub.add_argument("--options", default="{}", help="extra registration options as JSON (e.g. {\"coarse_to_fine\": false})")
        _add_device(sub)
        sub.set_defaults(func=deferred(f"benchmarks.engine.phantom:bench_{name}"))


def _add_track(which) -> None:
    """``python -m benchmarks.engine``: tracking."""
    track = which.add_parser("track", help="re-registration (options.mode track) along sequences of small motions")
    _add_mesh(track)
    track.add_argument("--sequences", type=int, default=5, help="independent motion sequences")
    track.add_argument("--frames", type=int, default=6, help="motions per sequence")
    track.add_argument("--seed", type=int, default=0, help="random seed of the motions")
    track.add_argument("--size", type=int, default=800, help="image side in px")
    track.add_argument("--rotation", type=float, nargs=2, default=[0.5, 3.0], metavar=("MIN", "MAX"),
                       help="per-frame rotation range (deg, random axis through the mesh centre)")
    track.add_argument("--translation", type=float, nargs=2, default=[0.5, 3.0], metavar=("MIN", "MAX"),
                       help="per-frame translation range (mm, random direction)")
    track.add_argument("--planes", nargs="+", default=["both"], choices=["both", "ap", "lat", "alternate"],
                       help="planes sent each frame, one table row per choice over the same motions: both, ap or lat "
                       "alone, alternate (AP, LAT, AP, ...)")
    track.add_argument("--grey", action="store_true", help="grey-level DSA images segmented as the service does, not true masks")
    track.add_argument("--model-scale", type=float, default=1.0, help="the images show the model scaled by this about "
                       "its centre (a 3D model of the wrong size); the model registered is as given")
    track.add_argument("--options", default="{}", help="extra registration options as JSON")
    _add_device(track)
    track.set_defaults(func=deferred("benchmarks.engine.tracking:bench_track"))


def _add_robustness(which) -> None:
    """``python -m benchmarks.engine``: segmentation errors and grey-level DSA."""
    robust = which.add_parser("robustness", help="accuracy when the masks carry simulated segmentation errors")
    _add_mesh(robust)
    robust.add_argument("--starts", type=int, default=5, help="initial poses per corruption")
    robust.add_argument("--seed", type=int, default=0, help="random seed of the initial poses")
    robust.add_argument("--size", type=int, default=800, help="image side in px")
    robust.add_argument("--offset", type=float, nargs=2, default=[10.0, 10.0], metavar=("DEG", "MM"),
                        help="initial rotation (deg) and translation (mm) offset")
    robust.add_argument("--corruptions", nargs="+", default=list(CORRUPTIONS), choices=list(CORRUPTIONS),
                        help="simulated segmentation errors to apply (default all)")
    robust.add_argument("--grey", nargs="*", default=["dsa", "dsa_binary", "otsu"], choices=["dsa", "dsa_binary", "otsu", "vesselness"],
                        help="also register from grey-level DSA synthesized from the model (uneven background, noise, "
                             "catheter), segmented by these methods ('dsa' is what 'auto' fits: sub-pixel vessel coverage; "
                             "'dsa_binary': its binary mask as before)")
    robust.add_argument("--grey-variants", nargs="+", default=["default"], choices=list(GREY_VARIANTS),
                        help="image formation of the grey-level rows (noise, background, contrast law, blur, bit depth)")
    robust.add_argument("--multistart", type=int, default=4, help="parallel starts inside each registration")
    robust.add_argument("--options", default="{}", help="extra registration options as JSON (e.g. {\"border_correction\": true})")
    _add_device(robust)
    robust.set_defaults(func=deferred("benchmarks.engine.phantom:bench_robustness"))


def _add_autoinit(which) -> None:
    """``python -m benchmarks.engine``: no initial pose."""
    auto = which.add_parser("autoinit", help="registration with no initial pose on a clinical-like rig (107°, mirrored LAT)")
    _add_mesh(auto)
    auto.add_argument("--cases", type=int, default=20, help="random poses (rotation uniform over SO(3))")
    auto.add_argument("--seed", type=int, default=0, help="random seed of the poses")
    auto.add_argument("--size", type=int, default=512, help="image side in px")
    auto.add_argument("--radius", type=float, default=60.0, help="mesh centre within this distance of the isocentre (mm)")
    auto.add_argument("--options", default="{}", help="extra registration options as JSON")
    auto.add_argument("--grey", action="store_true",
                      help="register from grey-level DSA synthesized from the model (segmented as 'auto' does)")
    auto.set_defaults(func=deferred("benchmarks.engine.phantom:bench_autoinit"))


def _image_size(text: str) -> tuple[int, int]:
    """``"512"`` → (512, 512); ``"1000x774"`` → (1000, 774) (width, height in px)."""
    try:
        sides = tuple(int(side) for side in text.lower().split("x"))
    except ValueError:
        sides = ()
    if len(sides) not in (1, 2) or min(sides) < 16:
        raise argparse.ArgumentTypeError(f"image size {text!r}: give one side in px (512) or width x height (1000x774)")
    return (sides[0], sides[-1])


def _add_partial(which) -> None:
    """``python -m benchmarks.engine``: partial visibility."""
    partial = which.add_parser("partial", help="no initial pose, images showing part of the model (early filling, "
                               "one injected branch, a model with an extra territory) plus safety cases")
    _add_mesh(partial)
    partial.add_argument("--cases", type=int, default=4, help="random poses per row")
    partial.add_argument("--seed", type=int, default=0, help="random seed of the poses and injection points")
    partial.add_argument("--size", type=_image_size, default=(512, 512), metavar="PX or WxH",
                         help="image side in px, or width x height (e.g. 1000x774, a clinical flat detector's aspect)")
    partial.add_argument("--detector-mm", type=float, default=400.0, help="detector width in mm (square pixels)")
    partial.add_argument("--fractions", type=float, nargs="+", default=[0.4, 0.5, 0.6],
                         help="visible fractions of the model's faces (early filling and one branch)")
    partial.add_argument("--kinds", nargs="+", default=["full", "early_filling", "selective_injection", "extra_territory"],
                         choices=["full", "early_filling", "selective_injection", "extra_territory", "reflux_injection",
                                  "foreign_territory", "bolus_front", "wrong_tree", "swapped_views",
                                  "swapped_views+early_filling", "image_extra_territory", "image_foreign_territory",
                                  "image_missing_small_branches", "image_background"],
                         help="rows to run (reflux_injection, foreign_territory, bolus_front: the second generator family; "
                         "image_*: the images hold more than the model (its mirror territory, another tree, its thinnest "
                         "branches, segmentation-like background); "
                         "wrong_tree, swapped_views, swapped_views+early_filling: one safety row, e.g. with --no-safety)")
    partial.add_argument("--no-safety", action="store_true", help="skip the wrong-tree and swapped-views rows")
    partial.add_argument("--initial", type=float, nargs=2, metavar=("DEG", "MM"),
                         help="give an initial pose this far from the true one (random axis and direction; Table 1's is "
                         "12.8 deg, 2-4 mm) instead of none")
    partial.add_argument("--options", default="{}", help="extra registration options as JSON")
    partial.add_argument("--corruption", default="none", choices=list(CORRUPTIONS),
                         help="segmentation errors applied to every mask (as in bench robustness; all = wider borders, "
                         "missing segments, a catheter, speckle)")
    partial.add_argument("--cases-out", metavar="FILE.jsonl", help="also write one JSON line per case (ADD, verdict, "
                         "reasons, what the pose search did)")
    partial.set_defaults(func=deferred("benchmarks.engine.phantom:bench_partial"))


def _add_clinical(which) -> None:
    """``python -m benchmarks.engine clinical``: one row per input kind (:data:`benchmarks.engine.clinical.CASE_KINDS`)."""
    sub = which.add_parser("clinical", help="registration from stored clinical inputs, per input kind "
                                            "(native XA runs, ...), with no geometry file and no initial pose")
    sub.add_argument("--cases", type=int, default=3, help="cases (seeds) per input kind")
    sub.add_argument("--seed", type=int, default=0, help="first seed")
    sub.add_argument("--size", type=int, default=160, help="image side in px")
    sub.add_argument("--kinds", nargs="*", default=[], help="only the kinds whose name contains one of these words")
    sub.add_argument("--options", default="{}", help="extra registration options as JSON")
    sub.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="options.device (auto: cpu)")
    sub.add_argument("--sweep", choices=["runs", "volumes"], help="runs: the native-run sweep (size, bits, encoding, "
                     "recipe, bolus, generator; each cell at its own size); volumes: CTA / TOF-MRA heads x generator "
                     "x tree x voxel size (0.3-1.0 mm, anisotropic)")
    sub.add_argument("--mesh", metavar="FILE", help="--sweep runs / volumes: add the cells drawn with this mesh's "
                                                    "vessel tree")
    sub.add_argument("--voxels", nargs="*", default=[], help="--sweep volumes: only these voxel sizes in mm "
                                                            "(0.5, 0.4x0.4x0.8)")
    sub.add_argument("--generators", nargs="*", default=[], choices=["A", "B"], help="--sweep volumes: only these "
                                                                                     "head generators")
    sub.add_argument("--trees", nargs="*", default=[], choices=["phantom", "mesh"],
                     help="--sweep volumes: only these vessel trees")
    sub.add_argument("--cells-out", metavar="FILE.jsonl", help="--sweep volumes: also append one JSON line per cell")
    sub.add_argument("--cisterns", action="store_true", help="--sweep volumes: generator B's heads with CSF cisterns "
                     "around the proximal tree (dsareg_engine.simulation.cisterns.Cisterns(); generator A has none)")
    sub.set_defaults(func=deferred("benchmarks.engine.clinical:bench_clinical"))


def _add_models(which) -> None:
    """``python -m benchmarks.engine models``: mesh units (GLB in metres) and handedness (mirrored models)."""
    sub = which.add_parser("models", help="a GLB in metres and mirrored models (x, y, z) on a clinical rig, "
                                          "no initial pose: ADD, verdicts, the mirror named, CPU s")
    sub.add_argument("--mesh", nargs="*", default=[], help="meshes in mm (default: the built-in phantom)")
    sub.add_argument("--cases", type=int, default=2, help="cases (seeds) per row")
    sub.add_argument("--seed", type=int, default=0, help="first seed")
    sub.add_argument("--size", type=int, default=256, help="image side in px")
    sub.add_argument("--rows", nargs="*", default=[], help="only the rows whose name contains one of these words")
    sub.add_argument("--options", default="{}", help="extra registration options as JSON")
    sub.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="options.device (auto: cpu)")
    sub.set_defaults(func=deferred("benchmarks.engine.models:bench_models"))


def _add_hemodynamics(which) -> None:
    """``python -m benchmarks.engine hemodynamics``: arrival / peak on the model from simulated bolus runs."""
    sub = which.add_parser("hemodynamics", help="contrast arrival and time to peak mapped onto the model from "
                                                "simulated biplane bolus runs with known times")
    sub.add_argument("--mesh", nargs="+", metavar="FILE", help="mesh files ('phantom' for the built-in one; default it)")
    sub.add_argument("--cases", type=int, default=2, help="cases (seeds) per row")
    sub.add_argument("--seed", type=int, default=0, help="first seed")
    sub.add_argument("--size", type=int, default=512, help="image side in px")
    sub.add_argument("--rows", nargs="*", default=[], help="only the rows whose name contains one of these words")
    sub.add_argument("--pictures", metavar="DIR", help="keep the first case's outputs and model pictures per row here")
    sub.set_defaults(func=deferred("benchmarks.engine.hemodynamics:bench_hemodynamics"))


def _add_job_cost(which) -> None:
    """``python -m benchmarks.engine jobcost``: one job's cost per stage on fixed native-run cases."""
    sub = which.add_parser("jobcost", help="job CPU s and iterations per stage on the nine native-run cases of "
                                           "docs/benchmarks/clinical.md round 10 (issue 30)")
    sub.add_argument("--only", nargs="*", default=[], metavar="CASE", help="only these cases, e.g. B1-512 A2-1024")
    sub.add_argument("--options", default="{}", help="extra registration options as JSON")
    sub.set_defaults(func=deferred("benchmarks.engine.job_cost:bench_job_cost"))


def _add_segmentation(which) -> None:
    """``python -m benchmarks.engine segmentation`` and ``segmentation-train``: real angiograms with expert labels."""
    from .segmentation_bench import add_parser as add_bench
    from .segmentation_training import add_parser as add_training

    add_bench(which)
    add_training(which)


def _add_whole_head(which) -> None:
    """``python -m benchmarks.engine whole-head``: a 512 x 512 x 440 CTA read and registered twice (issue 41)."""
    from .whole_head import add_parser

    add_parser(which)


def _add_real_volumes(which) -> None:
    """``python -m benchmarks.engine real-volumes``: the real vessel files of ../shared/data (issue 41)."""
    from .real_volumes import add_parser

    add_parser(which)


def _add_views(which) -> None:
    """``python -m benchmarks.engine views``: biplane angles, monoplane runs with head motion, swapped files (issue 42)."""
    from .views import add_parser

    add_parser(which)


def _add_mesh(parser) -> None:
    parser.add_argument("--mesh", metavar="FILE", help="mesh file (default: the built-in phantom)")


def _add_device(parser) -> None:
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                        help="options.device (auto: CUDA when available; tracking on the CPU)")
