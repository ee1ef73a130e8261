"""A contrast bolus that passes along the vessel tree: it reaches the root first, the far branches last,
and washes out of the near vessels before the far ones peak (as in every real run at a few frames/s).

Each vessel pixel's contrast arrives at ``start_s + transit_s · a`` with ``a`` its arrival fraction
(:func:`.native_run.arrival_map`: 0 at the root, 1 at the farthest vertex); from then on its iodine
follows the bolus shape ``g(u)`` (``u``: seconds since arrival), 1 at its peak ``time_to_peak_s``:

* ``"gamma"``: a gamma variate ``(u / t_p)^α · exp(α (1 − u / t_p))`` (the indicator-dilution curve);
* ``"cosine"``: a raised cosine ``(1 − cos(π u / t_p)) / 2`` for ``0 ≤ u ≤ 2 t_p`` (a symmetric bolus, no tail).

Frame ``k`` is taken at ``k · frame_time_s``. No single frame shows the whole tree at full strength
when ``transit_s`` exceeds the bolus's width.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.rig import ViewGeometry
from ..mesh import TriangleMesh
from .native_run import IODINE_PER_MM, arrival_map, peak_of, tree_root, vessel_frames
from .synthetic_dsa import vessel_thickness_mm

SHAPES = ("gamma", "cosine")


@dataclass(frozen=True)
class Bolus:
    """Attributes:
        shape: ``"gamma"`` or ``"cosine"`` (module docstring).
        frames: frames in the run.
        frame_time_s: time between frames (0.25: 4 frames/s).
        start_s: when contrast reaches the root (frames before it are the masks).
        transit_s: from the root to the farthest branch.
        time_to_peak_s: from arrival to the peak, per pixel.
        alpha: the gamma variate's shape.
    """

    shape: str = "gamma"
    frames: int = 14
    frame_time_s: float = 0.25
    start_s: float = 0.7
    transit_s: float = 1.5
    time_to_peak_s: float = 0.75
    alpha: float = 3.0

    def concentration(self, since_s: np.ndarray) -> np.ndarray:
        """``g(u)`` for ``u`` seconds since arrival (0 before)."""
        u = np.maximum(np.asarray(since_s, float), 0.0) / self.time_to_peak_s
        if self.shape == "gamma":
            return np.where(u > 0, u ** self.alpha * np.exp(self.alpha * (1.0 - u)), 0.0)
        return np.where(u <= 2.0, 0.5 * (1.0 - np.cos(np.pi * u)), 0.0)

    @property
    def mask_frames(self) -> int:
        """Frames taken before contrast reaches the root."""
        return int(np.ceil(self.start_s / self.frame_time_s - 1e-9))


def bolus_frames(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, bolus: Bolus,
                 root: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``((N, H, W) iodine attenuation per frame, (H, W) path length mm)`` of the bolus passing from ``root``."""
    thickness = vessel_thickness_mm(mesh, view, mesh_to_world, supersample=3)
    arrival_s = bolus.start_s + bolus.transit_s * arrival_map(mesh, view, mesh_to_world, thickness, root)
    frames = [IODINE_PER_MM * thickness * bolus.concentration(k * bolus.frame_time_s - arrival_s)
              for k in range(bolus.frames)]
    return np.array(frames, np.float32), thickness


def run_iodine(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, fill, strength, bolus: Bolus | None = None,
               root: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``((N, H, W) iodine, (H, W) path length mm)``: a :class:`Bolus` passing from ``root``,
    or (``bolus`` None) the front ``fill`` / ``strength`` model of :func:`vessel_frames`."""
    if bolus is None:
        return vessel_frames(mesh, view, mesh_to_world, list(fill), list(strength), root)
    return bolus_frames(mesh, view, mesh_to_world, bolus, tree_root(mesh) if root is None else root)


def run_peak(iodine: np.ndarray, fill, strength, bolus: Bolus | None = None) -> int:
    """The peak frame: the front model's (:func:`peak_of`), or the frame holding the most iodine."""
    if bolus is None:
        return peak_of(list(fill), list(strength))
    return int(np.argmax(iodine.reshape(len(iodine), -1).sum(axis=1)))
