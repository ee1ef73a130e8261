"""Is the model mirrored? When a fit is poor, fit the model's mirror image too.

A model exported with one axis flipped (an LPS/RAS mix-up, a wrong export option) is the mirror image
of the patient's vessels: no rotation brings it onto the images, so the fit stays poor and the reasons
speak of a wrong pose or partial overlap. When the kept pose overlaps poorly (some view's Dice below
:attr:`MirrorSettings.trigger_dice`, and not explained as partial filling) the model mirrored through
its centre along its x axis is registered from a global search of rotations. If that fits clearly
better the verdict is ``failed`` with a reason naming the mirror. The cost is paid only by poor fits.

A mirror along any one axis equals the mirror along x followed by a rotation (flipping y is flipping x
then turning 180° about z), so one search covers all three axes. Which axis was flipped can be told
only against a frame: when an initial pose was given, the found pose of the mirror ``R_m`` relates to
it as ``R_given^T R_m = F_a F_x`` (``F_a`` flips axis ``a``): the identity for x, a half turn about z
for y, about y for z. Without a given pose the reason does not guess an axis.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ..mesh import TriangleMesh

AXES = ("x", "y", "z")

_FLIP_X = np.diag([-1.0, 1.0, 1.0])
AXIS_ROTATIONS = {axis: np.diag(flip) @ _FLIP_X for axis, flip in
                  zip(AXES, ([-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0]))}
"""``F_a F_x`` per flipped axis ``a``: the rotation between the given pose and the mirror's fitted pose."""


@dataclass(frozen=True)
class MirrorSettings:
    """When to fit the mirror and when it wins.

    Attributes:
        trigger_dice: fit the mirror when some view's Dice is below this (the confidence's ``check`` level).
        better_by: the mirror's lowest view Dice must exceed the model's by at least this ...
        fits_dice: ... and reach this, for the model to be called mirrored.
        axis_tolerance_deg: name the flipped axis when the relation to the given pose is within this of one axis's.
    """

    trigger_dice: float = 0.7
    better_by: float = 0.2
    fits_dice: float = 0.7
    axis_tolerance_deg: float = 30.0
    fit_options: dict = field(default_factory=dict)
    """Registration options of the mirror's fit over the job's own (none: the same schedule; without the final
    L-BFGS stage a mirror that fits reached only Dice 0.5 on a 160-px clinical-rig case, 0.99 / 0.91 with it)."""


def mirrored(mesh: TriangleMesh) -> TriangleMesh:
    """``mesh`` mirrored through its centroid along its x axis (faces turned to keep the normals outward)."""
    vertices = mesh.vertices.copy()
    vertices[:, 0] = 2.0 * mesh.centroid[0] - vertices[:, 0]
    return TriangleMesh(vertices, np.ascontiguousarray(mesh.faces[:, ::-1]))


def needs_mirror_check(confidence: dict, settings: MirrorSettings = MirrorSettings()) -> bool:
    """Whether the fit is poor enough to try the mirror: some view below ``trigger_dice`` and no partial filling."""
    signals = confidence.get("signals") or {}
    dice = signals.get("dice") or {}
    partial = any(reason.startswith("the model has vessels the images do not show")
                  for reason in confidence.get("reasons") or [])
    return bool(dice) and min(dice.values()) < settings.trigger_dice and not partial


def flipped_axis(given: np.ndarray | None, mirror_pose: np.ndarray, settings: MirrorSettings = MirrorSettings()
                 ) -> str | None:
    """The model axis that was flipped, judged against the ``given`` pose ``(4, 4)``; None without one or when
    the mirror's pose matches no axis within ``axis_tolerance_deg``."""
    if given is None:
        return None
    relation = np.asarray(given)[:3, :3].T @ np.asarray(mirror_pose)[:3, :3]
    angles = {axis: _angle_deg(rotation.T @ relation) for axis, rotation in AXIS_ROTATIONS.items()}
    axis = min(angles, key=angles.get)
    return axis if angles[axis] <= settings.axis_tolerance_deg else None


def _angle_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0))))


def check_mirror(confidence: dict, mesh: TriangleMesh, given: np.ndarray | None,
                 fit: Callable[[TriangleMesh], tuple[np.ndarray, dict[str, float]]],
                 settings: MirrorSettings = MirrorSettings()) -> dict:
    """``confidence`` (the result's ``metrics.confidence``) with ``signals.mirror`` set when the mirror was fitted,
    and when it fits clearly better, verdict ``failed`` with a reason naming the mirror first.

    Args:
        given: the initial pose the user gave (names the flipped axis), or None.
        fit: registers a mesh, returns its pose ``(4, 4)`` and Dice per view.
    """
    if not needs_mirror_check(confidence, settings):
        return confidence
    own = confidence["signals"]["dice"]
    pose, dice = fit(mirrored(mesh))
    better = (min(dice.values()) >= settings.fits_dice
              and min(dice.values()) - min(own.values()) >= settings.better_by)
    axis = flipped_axis(given, pose, settings) if better else None
    signals = {**confidence["signals"], "mirror": {"dice": {name: round(value, 4) for name, value in dice.items()},
                                                   "mirrored": better, "axis": axis}}
    if not better:
        return {**confidence, "signals": signals}
    return {**confidence, "verdict": "failed", "signals": signals,
            "reasons": [mirror_reason(own, dice, axis), *confidence.get("reasons", [])]}


def mirror_reason(own: dict[str, float], mirror: dict[str, float], axis: str | None) -> str:
    """The verdict's reason for a mirrored model."""
    views = " / ".join(f"{name} {mirror[name]:.2f} vs {own[name]:.2f}" for name in own)
    which = f" (its {axis} axis flipped, judging by the initial pose)" if axis else " (one axis flipped)"
    return (f"the model seems mirrored{which}: its mirror image fits the images far better (dice {views}); "
            "check LPS/RAS or the export, the pose of a mirrored model is meaningless")


def with_mirror_check(result, mesh: TriangleMesh, masks: dict[str, np.ndarray], rig, options, register_with: Callable,
                      settings: MirrorSettings | None = None):
    """``result`` (a :class:`~.result.RegistrationResult`) with :func:`check_mirror` applied to its confidence; the
    mirror is registered by ``register_with(mesh, masks, rig, options)`` from a search of rotations (no given pose,
    no ground truth), its time in ``metrics.seconds.mirror``. Tracking re-registrations and options with
    ``mirror_check`` off are left alone."""
    import time

    from ..geometry.rig import Rig

    settings = settings or MirrorSettings()

    confidence = result.metrics.get("confidence")
    if options.mode == "track" or not options.mirror_check or not confidence:
        return result
    search = options.model_copy(update={"initialization": "search", "initial_mesh_to_world": None, "region": None,
                                        "ground_truth_mesh_to_world": None, "animation": False,
                                        **settings.fit_options})

    def fit(mirror: TriangleMesh) -> tuple[np.ndarray, dict[str, float]]:
        started = time.perf_counter()
        fitted = register_with(mirror, masks, Rig(views=rig.views), search)
        result.metrics.setdefault("seconds", {})["mirror"] = round(time.perf_counter() - started, 4)
        return fitted.mesh_to_world, fitted.metrics["confidence"]["signals"]["dice"]

    given = options.initial_mesh_to_world if options.initial_mesh_to_world is not None else (
        rig.initial_mesh_to_world if rig.initial_pose_given else None)
    result.metrics["confidence"] = check_mirror(confidence, mesh, None if given is None else np.asarray(given, float),
                                                fit, settings)
    return result
