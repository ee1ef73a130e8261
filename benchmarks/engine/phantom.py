"""``python -m benchmarks.engine``: benchmarks that print numbers (render speed, Table 1, capture range, robustness).

The runs; their arguments are in :mod:`benchmarks.engine.cli` (parsed without loading torch)."""

from __future__ import annotations

import argparse
import contextlib
import json
import time

import numpy as np
import torch

from dsareg_engine.geometry.rig import Rig
from dsareg_engine.geometry.spec import load_rig
from dsareg_engine.metrics import mean_distance_mm
from dsareg_engine.geometry.pose import so3_log
from dsareg_engine.registration import RegistrationOptions
from dsareg_engine.registration.solver import register
from dsareg_engine.registration.parameterization import PoseIncrement, random_start_poses
from dsareg_engine.render import Camera, SilhouetteSettings, render_hard_silhouette, render_soft_silhouette
from dsareg_engine.simulation.segmentation_errors import corrupt
from .cli import GREY_VARIANTS
from dsareg_engine.commands.render import load_mesh_argument


def _device(requested: str = "auto") -> str:
    if requested == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: no GPU is available")
    return requested if requested != "auto" else ("cuda" if torch.cuda.is_available() else "cpu")


def _options(args: argparse.Namespace) -> dict:
    """``--options`` JSON plus ``--device``."""
    return {"device": _device(getattr(args, "device", "auto")), **json.loads(args.options)}


def bench_render(args: argparse.Namespace) -> int:
    import numba

    torch.set_num_threads(args.torch_threads)
    mesh = load_mesh_argument(args.mesh)
    rig = load_rig("paper")
    device = _device(args.device)
    vertices, faces = mesh.torch(torch.float32, device)
    print(f"device {device}, torch threads {torch.get_num_threads()}, numba threads {numba.get_num_threads()}, "
          f"faces {mesh.n_faces}, batch {args.batch}, view paper/ap, median of {args.repeats}")
    print("| size | sigma px | covered px | forward ms | forward+backward ms |")
    print("|---|---|---|---|---|")
    for size in args.size:
        view = rig.views["ap"].resized(size, size)
        camera = Camera.from_view(view)
        pose = torch.as_tensor(view.world_to_view, dtype=torch.float32, device=device)[None].repeat(args.batch, 1, 1)
        covered = int(render_hard_silhouette(vertices, faces, pose[:1], camera).sum())
        for sigma in args.sigma:
            settings = SilhouetteSettings(sigma_px=sigma, backend=args.backend)
            forward, both = [], []
            for repeat in range(args.repeats + 3):
                p = pose.clone().requires_grad_(True)
                _sync(device)
                t0 = time.perf_counter()
                alpha = render_soft_silhouette(vertices, faces, p, camera, settings)
                _sync(device)
                t1 = time.perf_counter()
                alpha.sum().backward()
                _sync(device)
                t2 = time.perf_counter()
                if repeat >= 3:
                    forward.append(t1 - t0)
                    both.append(t2 - t0)
            print(f"| {size} | {sigma} | {covered} | {1e3 * np.median(forward):.1f} | {1e3 * np.median(both):.1f} |")
    return 0


def _sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def _synthetic_case(mesh, size: int):
    rig = load_rig("paper")
    views = {name: view.resized(size, size) for name, view in rig.views.items()}
    vertices, faces = mesh.torch(torch.float64)
    masks = {
        name: render_hard_silhouette(vertices, faces, torch.as_tensor(view.world_to_view)[None], Camera.from_view(view))[0].numpy()
        for name, view in views.items()
    }
    return Rig(views, rig.initial_mesh_to_world), masks


def _perturbation(mesh, base: np.ndarray, rotation_rad: float, translation_mm: float, rng) -> np.ndarray:
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    delta = np.concatenate([rotation_rad * axis / np.linalg.norm(axis), translation_mm * direction / np.linalg.norm(direction)])
    return PoseIncrement(base[None], mesh.centroid, 1.0).poses(torch.as_tensor(delta[None]))[0]


def _summarise(rows: list[dict]) -> str:
    def stat(key, q):
        return np.percentile([r[key] for r in rows], q)

    success = np.mean([r["add_mm"] < 1.0 for r in rows]) * 100
    return (f"{stat('rotation_error_deg', 50):.4f} / {stat('rotation_error_deg', 90):.4f} | "
            f"{stat('translation_error_mm', 50):.4f} / {stat('translation_error_mm', 90):.4f} | "
            f"{stat('add_mm', 50):.4f} / {stat('add_mm', 90):.4f} | {success:.0f} % | {np.median([r['seconds'] for r in rows]):.2f} | "
            f"{np.median([r['cpu_seconds'] for r in rows]):.2f}")


def _run(mesh, rig, masks, initial, config: str, multistart: int, seed: int, extra: dict) -> dict:
    options = RegistrationOptions(configuration=config, starts=multistart, seed=seed, **extra,
                                  initial_mesh_to_world=initial.tolist(), ground_truth_mesh_to_world=np.eye(4).tolist())
    cpu = time.process_time()
    result = register(mesh, masks, rig, options)
    return {**result.metrics["ground_truth"], "seconds": result.metrics["seconds"]["total"], "converged": result.metrics["converged"],
            "cpu_seconds": time.process_time() - cpu,
            "verdict": result.metrics["confidence"]["verdict"], "signals": result.metrics["confidence"]["signals"]}


def bench_table1(args: argparse.Namespace) -> int:
    mesh = load_mesh_argument(args.mesh)
    rig, masks = _synthetic_case(mesh, args.size)
    paper_start = rig.initial_mesh_to_world
    angle = np.linalg.norm(so3_log(paper_start[:3, :3]))
    shift = np.linalg.norm(paper_start[:3, :3] @ mesh.centroid + paper_start[:3, 3] - mesh.centroid)
    rng = np.random.default_rng(args.seed)
    initials = [paper_start] + [_perturbation(mesh, np.eye(4), angle, shift, rng) for _ in range(args.starts)]
    print(f"mesh {mesh.n_faces} faces, {args.size}x{args.size} px, {len(initials)} initial poses "
          f"({np.degrees(angle):.1f} deg, {shift:.1f} mm centre shift), {args.multistart} parallel starts each, "
          f"device {_device(args.device)}, options {args.options}")
    print("| configuration | rotation ° median / p90 | translation mm median / p90 | ADD mm median / p90 | success (ADD < 1 mm) | median s "
          "| median CPU s (all threads) |")
    print("|---|---|---|---|---|---|---|")
    for config in args.configs:
        rows = [_run(mesh, rig, masks, initial, config, args.multistart, args.seed + i, _options(args)) for i, initial in enumerate(initials)]
        print(f"| {config} | {_summarise(rows)} |", flush=True)
    return 0


def _offset_with_mtre(mesh, target_mm: float, max_rotation_deg: float, rng) -> np.ndarray:
    """A random pose whose mTRE (over the vertices) to the identity is ``target_mm``.

    Random axis and direction; rotation angle uniform up to ``max_rotation_deg`` (reduced if it
    alone exceeds the target), then the translation length found by bisection.
    """
    axis = rng.normal(size=3)
    direction = rng.normal(size=3)
    rotation = np.radians(rng.uniform(0.0, max_rotation_deg))

    def pose(angle, shift):
        delta = np.concatenate([angle * axis / np.linalg.norm(axis), shift * direction / np.linalg.norm(direction)])
        return PoseIncrement(np.eye(4)[None], mesh.centroid, 1.0).poses(torch.as_tensor(delta[None]))[0]

    def error(angle, shift):
        return mean_distance_mm(pose(angle, shift), np.eye(4), mesh.vertices)

    while error(rotation, 0.0) > target_mm:
        rotation *= 0.8
    low, high = 0.0, 2.0 * target_mm + 1.0
    for _ in range(50):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if error(rotation, middle) < target_mm else (low, middle)
    return pose(rotation, 0.5 * (low + high))


def bench_capture(args: argparse.Namespace) -> int:
    mesh = load_mesh_argument(args.mesh)
    rig, masks = _synthetic_case(mesh, args.size)
    rng = np.random.default_rng(args.seed)
    print(f"mesh {mesh.n_faces} faces, {args.size}x{args.size} px, {args.starts} starts per 1-mm bin of initial mTRE, "
          f"rotations up to 30°, {args.multistart} parallel starts each, simultaneous, success = final mTRE < 1 mm")
    print("| initial mTRE mm | success % | median final mTRE mm | median s |")
    print("|---|---|---|---|")
    capture, contiguous = 0.0, True
    for low in np.arange(0.0, args.max_mtre, 1.0):
        rows = [
            _run(mesh, rig, masks, _offset_with_mtre(mesh, rng.uniform(low, low + 1.0), 30.0, rng), "simultaneous", args.multistart, 0, _options(args))
            for _ in range(args.starts)
        ]
        finals = np.array([row["mtre_mm"] for row in rows])
        success = float(np.mean(finals < 1.0) * 100)
        contiguous = contiguous and success >= 95
        if contiguous:
            capture = low + 1.0
        print(f"| {low:.0f}–{low + 1:.0f} | {success:.0f} | {np.median(finals):.3f} | {np.median([r['seconds'] for r in rows]):.1f} |", flush=True)
    print(f"capture range (largest initial mTRE with ≥ 95 % success in every bin up to it): {capture:.0f} mm")
    return 0


def bench_robustness(args: argparse.Namespace) -> int:
    """Simultaneous registrations against masks with simulated segmentation errors."""
    mesh = load_mesh_argument(args.mesh)
    rig, clean = _synthetic_case(mesh, args.size)
    degrees, millimetres = args.offset
    initials = random_start_poses(np.eye(4), mesh.centroid, args.starts + 1, degrees, millimetres, seed=args.seed + 1)[1:]
    print(f"mesh {mesh.n_faces} faces, {args.size}x{args.size} px, {args.starts} initial poses "
          f"({degrees:g} deg, {millimetres:g} mm), {args.multistart} parallel starts each, simultaneous, options {args.options}")
    print("| corruption | mask px AP / LAT (clean: " + " / ".join(str(int(clean[v].sum())) for v in ("ap", "lat"))
          + ") | ADD mm median / max | rotation ° median | success (ADD < 1 mm) | flagged not converged | median s | verdicts | fitted dice min / max abs border shift px / min runner-up fit gap |")
    print("|---|---|---|---|---|---|---|---|---|")
    grey = [f"grey_{method}@{variant}" for variant in args.grey_variants for method in args.grey]
    for name in list(args.corruptions) + grey:
        rows = []
        for index, initial in enumerate(initials):
            rng = np.random.default_rng(args.seed + 1000 * index)
            if name.startswith("grey_"):
                method, variant = name[len("grey_"):].split("@")
                masks = _grey_masks(mesh, rig, method, args.seed + index, variant)
            else:
                masks = {view: corrupt(mask, name, rng) for view, mask in clean.items()}
            row = _run(mesh, rig, masks, initial, "simultaneous", args.multistart, args.seed + index, _options(args))
            rows.append({**row, "pixels": [int(round(float(masks[v].sum()))) for v in ("ap", "lat")]})
        add = np.array([row["add_mm"] for row in rows])
        print(f"| {name} | {rows[0]['pixels'][0]} / {rows[0]['pixels'][1]} | {np.median(add):.3f} / {add.max():.3f} | "
              f"{np.median([row['rotation_error_deg'] for row in rows]):.3f} | {np.mean(add < 1.0) * 100:.0f} % | "
              f"{sum(not row['converged'] for row in rows)} | {np.median([row['seconds'] for row in rows]):.1f} | "
              f"{'/'.join(sorted(set(row['verdict'] for row in rows)))} | {_signal_summary([row['signals'] for row in rows])} |", flush=True)
    return 0


def _signal_summary(signals: list[dict]) -> str:
    """Worst confidence signals over runs: lowest fitted Dice, largest |border shift|, smallest runner-up gap."""
    lowest = min(min(s["dice"].values()) for s in signals)
    shift = max(max(abs(v) for v in s["border_shift_px"].values()) for s in signals)
    gaps = [s["runner_up"]["best_fit"] - s["runner_up"]["fit"] for s in signals if s.get("runner_up")]
    return f"{lowest:.3f} / {shift:.2f} / {min(gaps):.3f}" if gaps else f"{lowest:.3f} / {shift:.2f} / none"


def _grey_masks(mesh, rig, method: str, seed: int, variant: str = "default", truth: np.ndarray | None = None) -> dict:
    """Targets segmented (``method``; ``dsa``: the coverage registration fits, ``dsa_binary``: its former
    binary mask) from DSA images synthesized from the model at ``truth`` (default identity)."""
    from dsareg_engine.vision.segmentation import segment_vessels, vessel_coverage
    from dsareg_engine.simulation.synthetic_dsa import DsaSettings, synthesize_dsa

    changes, bits = GREY_VARIANTS[variant]
    images = synthesize_dsa(mesh, rig, np.eye(4) if truth is None else truth, seed=seed, settings=DsaSettings(**changes))
    full_scale, dtype = (65535, np.uint16) if bits == 16 else (255, np.uint8)
    quantized = {view: np.round(image * full_scale).astype(dtype) for view, image in images.items()}
    if method == "dsa_binary":
        return {view: segment_vessels(image, "dsa") for view, image in quantized.items()}
    if method == "dsa":
        return {view: vessel_coverage(image, "dsa") for view, image in quantized.items()}
    return {view: segment_vessels(image, method) for view, image in quantized.items()}


def bench_autoinit(args: argparse.Namespace) -> int:
    """No initial pose: uniform random rotations, positions anywhere the mesh stays in both views."""
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks

    mesh = load_mesh_argument(args.mesh)
    rig = clinical_biplane_rig(args.size)
    rng = np.random.default_rng(args.seed)
    extra = json.loads(args.options)
    print(f"mesh {mesh.n_faces} faces, clinical rig {args.size}x{args.size} px ({rig.angle_between_views_deg():.0f}° apart, "
          f"LAT mirrored, SID 1100 / 1200 mm), {args.cases} cases, no initial pose, "
          f"{'grey-level DSA' if args.grey else 'true masks'}, options {extra}")
    print("| case | ADD mm | rotation ° | search s | total s | verdict | fitted dice min / border shift / runner-up gap | dice AP / LAT |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for case in range(args.cases):
        truth = random_visible_pose(mesh, rig, rng, args.radius)
        options = RegistrationOptions(seed=args.seed + case, **extra, ground_truth_mesh_to_world=truth.tolist())
        masks = render_masks(mesh, rig, truth)
        if args.grey:
            masks = _grey_masks(mesh, rig, "dsa", args.seed + case, truth=truth)
        result = register(mesh, masks, rig, options)
        metrics = result.metrics
        row = {"add": metrics["ground_truth"]["add_mm"], "rotation": metrics["ground_truth"]["rotation_error_deg"],
               "search": metrics["initialization"]["seconds"], "total": metrics["seconds"]["total"],
               "verdict": metrics["confidence"]["verdict"]}
        rows.append(row)
        print(f"| {case} | {row['add']:.4f} | {row['rotation']:.3f} | {row['search']:.2f} | {row['total']:.1f} | {row['verdict']} | "
              f"{_signal_summary([metrics['confidence']['signals']])} | {result.views['ap'].dice:.3f} / {result.views['lat'].dice:.3f} |", flush=True)
    add = np.array([row["add"] for row in rows])
    counts = ", ".join(f"{verdict} {sum(row['verdict'] == verdict for row in rows)}" for verdict in ("ok", "check", "failed"))
    print(f"\nsuccess (ADD < 1 mm) {np.mean(add < 1.0) * 100:.0f} % | ADD median / p90 {np.median(add):.4f} / "
          f"{np.percentile(add, 90):.4f} mm | verdicts {counts} | "
          f"search s median {np.median([r['search'] for r in rows]):.2f} | "
          f"total s median / p90 {np.median([r['total'] for r in rows]):.1f} / {np.percentile([r['total'] for r in rows], 90):.1f}")
    return 0


_SAFETY_ROWS = {"wrong_tree": "wrong_tree", "swapped_views": "swapped_views", "swapped_views+early_filling": "swapped_early"}


def _image_extra_territory(mesh, tree, rng):
    from dsareg_engine.simulation import partial_filling as made

    return made.images_hold_more(made.extra_territory(mesh, tree), "image_extra_territory")


def _image_background(mesh, tree, rng):
    from dsareg_engine.simulation import partial_filling as made

    return made.full_visibility(mesh)  # the masks get add_background (bench_partial)


def _image_missing_small_branches(mesh, tree, rng):
    from dsareg_engine.simulation import partial_filling as made

    return made.missing_small_branches(mesh, 0.25, rng, tree)


_IMAGES_HOLD_MORE = {"image_extra_territory": _image_extra_territory, "image_background": _image_background,
                     "image_missing_small_branches": _image_missing_small_branches}
"""The rows whose images hold more than the model (``image_foreign_territory`` is ``foreign_territory`` turned round)."""


def _partial_cases(mesh, args: argparse.Namespace):
    """``(row name, fraction, PartialCase or a safety tag)`` for every row of ``bench partial``."""
    from dsareg_engine.geometry.vessel_tree import vessel_tree
    from dsareg_engine.simulation import partial_filling as made
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    tree = vessel_tree(mesh)
    rng = np.random.default_rng(args.seed)
    per_fraction = {"early_filling": lambda f: made.early_filling(mesh, f, tree),
                    "bolus_front": lambda f: made.bolus_front(mesh, f, tree),
                    "selective_injection": lambda f: made.selective_injection(mesh, f, rng, tree),
                    "reflux_injection": lambda f: made.reflux_injection(mesh, f, rng, tree)}
    rows = []
    for kind in args.kinds:
        if kind == "full":
            rows.append(("full", 1.0, lambda: made.full_visibility(mesh)))
        elif kind == "extra_territory":
            rows.append(("extra_territory", None, lambda: made.extra_territory(mesh, tree)))
        elif kind in _SAFETY_ROWS:
            rows.append((kind, 0.5 if kind == "swapped_views+early_filling" else None, _SAFETY_ROWS[kind]))
        elif kind in ("foreign_territory", "image_foreign_territory"):
            other = make_vessel_phantom(seed=args.seed + 3)
            turned = (lambda case, kind=kind: made.images_hold_more(case, kind)) if kind.startswith("image_") else (lambda case: case)
            rows.append((kind, None, lambda other=other, turned=turned: turned(made.foreign_territory(mesh, other, tree))))
        elif kind in _IMAGES_HOLD_MORE:
            rows.append((kind, None, lambda kind=kind: _IMAGES_HOLD_MORE[kind](mesh, tree, rng)))
        else:
            rows += [(kind, fraction, lambda f=fraction, kind=kind: per_fraction[kind](f)) for fraction in args.fractions]
    if not args.no_safety:
        rows += [(name, 0.5 if name == "swapped_views+early_filling" else None, tag) for name, tag in _SAFETY_ROWS.items()]
    return rows


def _partial_case(mesh, rig, rng, case, args):
    """``(model, masks, visible fraction, true pose)`` of one case of a ``bench partial`` row."""
    from dsareg_engine.simulation.clinical_rig import random_visible_pose, render_masks
    from dsareg_engine.simulation.partial_filling import early_filling
    from dsareg_engine.simulation.phantom import make_vessel_phantom

    if isinstance(case, str):
        truth = random_visible_pose(mesh, rig, rng, 40.0)
        if case == "wrong_tree":
            return mesh, render_masks(make_vessel_phantom(seed=args.seed + 7), rig, truth), 1.0, truth
        visible = mesh if case == "swapped_views" else early_filling(mesh, 0.5).visible
        masks = render_masks(visible, rig, truth)
        swapped = {"ap": _fit_size(masks["lat"], masks["ap"].shape), "lat": _fit_size(masks["ap"], masks["lat"].shape)}
        return mesh, swapped, visible.n_faces / mesh.n_faces, truth
    made = case()
    truth = random_visible_pose(made.model, rig, rng, 40.0)
    return made.model, render_masks(made.visible, rig, truth), made.visible_fraction, truth


def _fit_size(mask: np.ndarray, shape) -> np.ndarray:
    return mask if mask.shape == shape else np.zeros(shape, bool)


def bench_partial(args: argparse.Namespace) -> int:
    """Partial visibility: success / ADD / verdict per visible fraction, and the confusion table."""
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig

    mesh = load_mesh_argument(args.mesh)
    width, height = args.size
    rig = clinical_biplane_rig(width, detector_mm=args.detector_mm, rows_px=height)
    rng = np.random.default_rng(args.seed + 1)
    extra = json.loads(args.options)
    masks = "true masks" if args.corruption == "none" else f"masks with segmentation errors ({args.corruption})"
    start = "no initial pose" if args.initial is None else f"an initial pose {args.initial[0]:g} deg / {args.initial[1]:g} mm off"
    print(f"mesh {mesh.n_faces} faces, clinical rig {width}x{height} px, detector {args.detector_mm:g} mm wide, "
          f"{args.cases} cases per row, {start}, "
          f"{masks} of the visible part, options {extra}")
    print("| row | visible fraction | success (ADD < 1 mm) | ADD mm median / max | verdicts ok / check / failed "
          "| partial reason | median CPU s |")
    print("|---|---|---|---|---|---|---|")
    confusion = {(right, verdict): 0 for right in (True, False) for verdict in ("ok", "check", "failed")}
    with contextlib.ExitStack() as stack:
        cases_out = stack.enter_context(open(args.cases_out, "w")) if args.cases_out else None
        for name, _, case in _partial_cases(mesh, args):
            rows = []
            for index in range(args.cases):
                made = _corrupted(_partial_case(mesh, rig, rng, case, args), args.corruption, rng)
                if name == "image_background":
                    made = _corrupted(made, "background", rng)
                row, details = _partial_row(name, index, made, rig, args, extra)
                confusion[(row["right"], row["verdict"])] += 1
                rows.append(row)
                if cases_out is not None:
                    cases_out.write(json.dumps({"row": name, "case": index, **row, **details}) + "\n")
                    cases_out.flush()
            _print_partial_row(name, rows)
    print("\n| pose \\ verdict | ok | check | failed |\n|---|---|---|---|")
    for right in (True, False):
        print(f"| {'right (ADD < 1 mm)' if right else 'wrong (ADD ≥ 1 mm, or another tree)'} | "
              + " | ".join(str(confusion[(right, v)]) for v in ("ok", "check", "failed")) + " |")
    return 0


def _corrupted(made, corruption: str, rng):
    """A case with its masks put through a simulated segmentation error (:mod:`..simulation.segmentation_errors`)."""
    from dsareg_engine.simulation.segmentation_errors import corrupt

    if corruption == "none":
        return made
    model, masks, fraction, truth = made
    return model, {name: corrupt(mask, corruption, rng) for name, mask in masks.items()}, fraction, truth


def _partial_row(name: str, index: int, made, rig, args: argparse.Namespace, extra: dict) -> tuple[dict, dict]:
    """Register one ``bench partial`` case: its table entry and, for ``--cases-out``, the verdict's reasons and
    what the pose search did."""
    model, masks, fraction, truth = made
    if args.initial is not None:  # a start this far off, from its own generator (the cases stay those of no pose)
        rng = np.random.default_rng([args.seed, index, len(name)])
        extra = {**extra, "initial_mesh_to_world": _perturbation(model, truth, np.radians(args.initial[0]),
                                                                  args.initial[1], rng).tolist()}
    options = RegistrationOptions(seed=args.seed + index, **extra, ground_truth_mesh_to_world=truth.tolist())
    cpu = time.process_time()
    result = register(model, masks, rig, options)
    confidence = result.metrics["confidence"]
    add = result.metrics["ground_truth"]["add_mm"]
    row = {"add": add, "right": add < 1.0 and name != "wrong_tree", "verdict": confidence["verdict"],
           "cpu": time.process_time() - cpu, "fraction": fraction,
           "partial": any("do not show" in reason for reason in confidence["reasons"])}
    return row, {"reasons": confidence["reasons"], "signals": confidence["signals"], "initialization": result.metrics["initialization"],
                 "seconds": result.metrics.get("seconds")}


def _print_partial_row(name: str, rows: list[dict]) -> None:
    add = np.array([row["add"] for row in rows])
    verdicts = " / ".join(str(sum(row["verdict"] == v for row in rows)) for v in ("ok", "check", "failed"))
    print(f"| {name} | {np.mean([row['fraction'] for row in rows]):.2f} | {np.mean([row['right'] for row in rows]) * 100:.0f} % | "
          f"{np.median(add):.3f} / {add.max():.3f} | {verdicts} | {sum(row['partial'] for row in rows)}/{len(rows)} | "
          f"{np.median([row['cpu'] for row in rows]):.1f} |", flush=True)
