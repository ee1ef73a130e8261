"""Biplane DSA runs of a contrast bolus through a vessel model, with the arrival at every vertex known.

Contrast enters at the tree's inflow at ``start_s`` and reaches each vertex after its geodesic distance from
the inflow (along the surface graph, :mod:`dsareg_engine.geometry.vessel_tree`) over the tree's longest
distance times ``transit_s``: that is the vertex's **onset**. From its onset, the vertex's concentration
follows the bolus shape, normalised to a peak of 1, its time scale ``peak_after_s`` growing by
``dispersion`` from the inflow to the farthest vertex (a bolus spreads as it travels). Two shapes that differ:

* ``gamma``: the gamma variate ``(τ/τp)^α · exp(α (1 − τ/τp))``: smooth rise, peak at ``τp``, long tail;
* ``ramp``: linear rise over ``τp``, a plateau of ``plateau_s``, exponential washout; its peak is taken as the
  plateau's middle.

Per vertex the truth is its own curve's half-peak rise (``arrival_s``) and peak (``peak_s``); ``inf`` for a
vertex contrast never reaches (``partial`` filling: a branch of the tree, about a third of it, gets none).

Each frame is an instantaneous snapshot: iodine ``IODINE_PER_MM`` × the length of each stretch of vessel a ray
crosses × that stretch's concentration (:mod:`dsareg_engine.render.ray_layers`: overlapping vessels at different depths keep
their own times), rendered at ``supersample``× and area-averaged, blurred. Noise: ``poisson`` (photon counts
of a native run over a smooth anatomical background, LIN pixels) or ``gaussian`` (additive in the log domain).
The DICOM files (:mod:`.bolus_dicom`) carry the frame times.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..geometry.rig import Rig, ViewGeometry
from ..geometry.vessel_tree import vessel_tree
from ..mesh import TriangleMesh
from ..render.ray_layers import ray_layers
from .native_run_texture import fractal_texture

IODINE_PER_MM = 0.12
GAMMA_ALPHA = 3.0
SHAPES = ("gamma", "ramp")
NOISES = ("poisson", "gaussian")


@dataclass(frozen=True)
class BolusSettings:
    """One simulated pair of runs.

    Attributes:
        shape: ``"gamma"`` or ``"ramp"``; noise: ``"poisson"`` or ``"gaussian"``.
        fps: frames per second; n_frames: frames per run.
        start_s: contrast reaches the inflow; transit_s: ... and the farthest vertex this much later.
        peak_after_s: the bolus's rise time scale at the inflow; dispersion: its relative growth to the farthest.
        plateau_s, washout_s: the ``ramp`` shape's plateau and washout time constant.
        partial: a branch of the tree never fills.
        photons: counts per pixel behind the background (``poisson``); noise_sigma: log-domain σ (``gaussian``).
        supersample: rendering factor per side; blur_px: detector blur σ.
        lat_delay_s: the LAT run starts this much later than the AP run (its frames are that much later).
        jitter_s: each frame after the first is acquired up to this much (uniform ±) off its regular time (real
            per-frame times are not exactly regular; only per-frame DateTimes can say so).
    """

    shape: str = "gamma"
    noise: str = "poisson"
    fps: float = 4.0
    n_frames: int = 32
    start_s: float = 1.5
    transit_s: float = 2.0
    peak_after_s: float = 1.5
    dispersion: float = 0.5
    plateau_s: float = 0.8
    washout_s: float = 1.5
    partial: bool = False
    photons: float = 2.0e4
    noise_sigma: float = 0.01
    supersample: int = 2
    blur_px: float = 0.6
    lat_delay_s: float = 0.0
    jitter_s: float = 0.0


def half_rise_fraction(alpha: float = GAMMA_ALPHA) -> float:
    """``x < 1`` with ``x^α e^{α(1−x)} = ½``: the gamma variate's half-peak rise as a fraction of ``τp``."""
    x = np.linspace(1e-6, 1.0, 1_000_001)
    return float(x[np.argmax(x ** alpha * np.exp(alpha * (1.0 - x)) >= 0.5)])


def concentration(settings: BolusSettings, since_onset_s: np.ndarray, rise_s: np.ndarray) -> np.ndarray:
    """The bolus shape (peak 1) ``since_onset_s`` after onset, with rise time scale ``rise_s`` (broadcast)."""
    tau = np.maximum(since_onset_s, 0.0)
    if settings.shape == "gamma":
        x = tau / rise_s
        return np.where(since_onset_s > 0, x ** GAMMA_ALPHA * np.exp(GAMMA_ALPHA * (1.0 - x)), 0.0)
    after = tau - rise_s - settings.plateau_s
    return np.where(tau < rise_s, tau / rise_s, np.where(after <= 0, 1.0, np.exp(-np.maximum(after, 0.0) / settings.washout_s)))


def rise_time_s(settings: BolusSettings, onset_s: np.ndarray) -> np.ndarray:
    """Each onset's rise time scale: ``peak_after_s`` growing with the distance travelled."""
    travelled = np.clip((onset_s - settings.start_s) / max(settings.transit_s, 1e-9), 0.0, 1.0)
    return settings.peak_after_s * (1.0 + settings.dispersion * np.where(np.isfinite(onset_s), travelled, 0.0))


@dataclass
class BolusTruth:
    """Per vertex ``(V,)``: ``onset_s``, ``arrival_s`` and ``peak_s`` (``inf``: never reached)."""

    onset_s: np.ndarray
    arrival_s: np.ndarray
    peak_s: np.ndarray

    @property
    def never(self) -> np.ndarray:
        return ~np.isfinite(self.onset_s)


def vertex_onsets(mesh: TriangleMesh, settings: BolusSettings, rng: np.random.Generator,
                  inflow_mm: np.ndarray | None = None) -> np.ndarray:
    """``(V,)`` onset per vertex (``inf`` in a blocked branch when ``partial``)."""
    tree = vessel_tree(mesh, inflow_mm)
    distance = tree.distances_from(tree.inflow)
    onset = settings.start_s + settings.transit_s * distance / distance.max()
    if settings.partial:
        candidates = rng.permutation(np.flatnonzero((distance > 0.25 * distance.max()) & (distance < 0.6 * distance.max())))
        for vertex in candidates[:40]:
            blocked = tree.downstream_of(int(vertex))
            if 0.2 <= blocked.mean() <= 0.45:
                return np.where(blocked, np.inf, onset)
    return onset


def truth_of(settings: BolusSettings, onset_s: np.ndarray) -> BolusTruth:
    rise = rise_time_s(settings, onset_s)
    if settings.shape == "gamma":
        half, peak = half_rise_fraction() * rise, rise
    else:
        half, peak = 0.5 * rise, rise + 0.5 * settings.plateau_s
    return BolusTruth(onset_s, onset_s + half, onset_s + peak)


def frame_times_s(settings: BolusSettings, rng: np.random.Generator) -> np.ndarray:
    """``(T,)`` acquisition times from the run's first frame: regular, each off by up to ``jitter_s``."""
    regular = np.arange(settings.n_frames) / settings.fps
    jitter = rng.uniform(-settings.jitter_s, settings.jitter_s, settings.n_frames) if settings.jitter_s > 0 else 0.0
    times = regular + jitter
    return times - times[0]


def iodine_frames(mesh: TriangleMesh, view: ViewGeometry, mesh_to_world: np.ndarray, onset_s: np.ndarray,
                  settings: BolusSettings, times_s: np.ndarray) -> np.ndarray:
    """``(T, H, W)`` iodine attenuation (log domain, ≥ 0) at ``times_s`` (on the contrast's clock)."""
    fine = view.resized(view.width * settings.supersample, view.height * settings.supersample)
    mesh_to_view = fine.world_to_view @ mesh_to_world
    vertices = mesh.vertices @ mesh_to_view[:3, :3].T + mesh_to_view[:3, 3]
    face_onset = onset_s[mesh.faces].mean(axis=1)
    length, onset = ray_layers(vertices, mesh.faces, face_onset, fine.focal_px, fine.principal_point_px, fine.image_size)
    crossed = length.sum(axis=2) > 0  # only rays through the model change from frame to frame
    length, onset = length[crossed], onset[crossed]
    rise = rise_time_s(settings, onset)
    frames = []
    for t in times_s:
        fine_frame = np.zeros(crossed.shape, np.float32)
        fine_frame[crossed] = IODINE_PER_MM * (length * concentration(settings, t - onset, rise)).sum(axis=1)
        small = cv2.resize(fine_frame, view.image_size, interpolation=cv2.INTER_AREA)
        frames.append(cv2.GaussianBlur(small, (0, 0), settings.blur_px) if settings.blur_px > 0 else small)
    return np.array(frames, np.float32)


def anatomy(shape: tuple[int, int], rng: np.random.Generator, cells: int = 6) -> np.ndarray:
    """A background attenuation (log domain, about 1 to 2.5): a smooth field and a fractal texture (the anatomy
    every frame of a native run shows)."""
    coarse = rng.uniform(0.0, 1.0, (cells, cells)).astype(np.float32)
    smooth = cv2.resize(coarse, shape[::-1], interpolation=cv2.INTER_CUBIC).clip(0.0, 1.0)
    return (1.2 + smooth + 0.5 * fractal_texture(shape, 2.6, rng)).astype(np.float32)


def noisy_log_frames(iodine: np.ndarray, settings: BolusSettings, rng: np.random.Generator) -> np.ndarray:
    """``(T, H, W)`` log-domain attenuation of a native run: anatomy + iodine, with the settings' noise."""
    background = anatomy(iodine.shape[1:], rng)
    total = background[None] + iodine
    if settings.noise == "poisson":
        counts = rng.poisson(settings.photons * np.exp(-total)).astype(np.float64)
        return -np.log(np.maximum(counts, 1.0) / settings.photons)
    return total + rng.normal(0.0, settings.noise_sigma, total.shape)


@dataclass
class BolusRun:
    """A simulated biplane pair: per view the log-domain frames ``(T, H, W)``, the clean iodine and the frame
    times ``(T,)`` from that run's first frame (the LAT run starts ``lat_delay_s`` after the AP run), the truth
    (on the AP clock), the mesh, pose and rig."""

    frames: dict[str, np.ndarray]
    iodine: dict[str, np.ndarray]
    truth: BolusTruth
    mesh: TriangleMesh
    mesh_to_world: np.ndarray
    rig: Rig
    times_s: dict[str, np.ndarray]
    settings: BolusSettings


def make_bolus_run(mesh: TriangleMesh, rig: Rig, mesh_to_world: np.ndarray, settings: BolusSettings = BolusSettings(),
                   seed: int = 0, inflow_mm: np.ndarray | None = None) -> BolusRun:
    """Simulate both views' runs of one bolus (see the module docstring)."""
    rng = np.random.default_rng(seed)
    onset = vertex_onsets(mesh, settings, rng, inflow_mm)
    frames, iodine, times = {}, {}, {}
    for name, view in rig.views.items():
        times[name] = frame_times_s(settings, rng)
        delay = settings.lat_delay_s if name == "lat" else 0.0
        iodine[name] = iodine_frames(mesh, view, mesh_to_world, onset, settings, delay + times[name])
        frames[name] = noisy_log_frames(iodine[name], settings, rng).astype(np.float32)
    return BolusRun(frames, iodine, truth_of(settings, onset), mesh, np.asarray(mesh_to_world, float), rig, times,
                    settings)
