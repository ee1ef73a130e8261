"""Simulated partial visibility: a run that shows less of the vessel tree than the model holds.

Three ways a clinical run and a 3D model disagree (the images are rendered from the returned
*visible* part, the registration gets the whole *model*):

* :func:`early_filling` — an early arterial frame: contrast has filled the tree from the inflow
  up to a geodesic distance, the distal branches not yet;
* :func:`selective_injection` — a microcatheter in one branch: only that branch and what lies
  downstream of it fill;
* :func:`extra_territory` — a model holding a territory the run does not inject (e.g. the other
  carotid's): the model is the mesh plus a mirrored copy of it joined at the inflow.

A second, different family (to measure the engine on cases its branch search was not built from):

* :func:`bolus_front` — an early frame whose contrast front has run faster in the thick vessels than in the
  thin ones (arrival time = path length / speed, speed ∝ diameter², as in Poiseuille flow): not the geodesic front of
  :func:`early_filling`, which the branch search's proximal parts are cut by;

* :func:`reflux_injection` — a catheter tip placed at random (not at the point whose branch has
  the asked share), contrast refluxing a few mm back into the parent vessel and the branch filled
  only part of its length: not a clean subtree;
* :func:`foreign_territory` — the model holds another vessel tree (e.g. another phantom) joined at
  the inflow and spreading away from the mesh, not a mirror copy.

The opposite case, the images holding more than the model (a model of one territory, a CTA model without
its small branches), to measure what the registration does with vessels it cannot explain:

* :func:`images_hold_more` — a case above turned round: the images show its model, the model registered is
  what it showed (``image_extra_territory``: the mesh and its mirror territory shown, the mesh registered;
  ``image_foreign_territory``: the mesh and another tree shown);
* :func:`missing_small_branches` — the model is the mesh less its thinnest distal branches (a CTA segmentation
  that missed them), the images show the whole mesh.

Fractions are of the model's faces (for the cases where the images hold more: the model's faces / the faces shown). Distances come from :mod:`dsareg_engine.geometry.vessel_tree`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from ..geometry.vessel_tree import VesselTree, compact, vessel_tree
from ..mesh import TriangleMesh


@dataclass(frozen=True)
class PartialCase:
    """A model and the part of it a run shows (both in the model's frame, mm).

    Attributes:
        model: what is registered.
        visible: what the images are rendered from.
        kind: ``"early_filling"``, ``"bolus_front"``, ``"selective_injection"``, ``"extra_territory"``, ``"reflux_injection"``,
            ``"foreign_territory"``, ``"full"``, or one where the images hold more: ``"image_extra_territory"``,
            ``"image_foreign_territory"``, ``"image_missing_small_branches"``.
        visible_fraction: visible faces / model faces (above 1 where the images hold more).
    """

    model: TriangleMesh
    visible: TriangleMesh
    kind: str
    visible_fraction: float


def full_visibility(mesh: TriangleMesh) -> PartialCase:
    return PartialCase(mesh, mesh, "full", 1.0)


def early_filling(mesh: TriangleMesh, fraction: float, tree: VesselTree | None = None) -> PartialCase:
    """The faces nearest the inflow (geodesically), ``fraction`` of them: the tree filled proximally."""
    tree = tree or vessel_tree(mesh)
    face_distance = tree.distances_from(tree.inflow)[mesh.faces].max(axis=1)
    keep = face_distance <= np.quantile(face_distance, fraction)
    return PartialCase(mesh, compact(mesh, keep), "early_filling", float(keep.mean()))


def bolus_front(mesh: TriangleMesh, fraction: float, tree: VesselTree | None = None, speed_exponent: float = 2.0
                ) -> PartialCase:
    """The ``fraction`` of the faces the contrast reaches first when it moves at a speed ∝ (local diameter) **
    ``speed_exponent`` (each surface edge takes its length / the mean speed of its two ends; a face is reached
    when its last vertex is). On the phantom its 45–55 % share 78–79 % of the faces with :func:`early_filling`'s,
    on the paper's mesh 95–96 % (its thick vessels are its proximal ones)."""
    tree = tree or vessel_tree(mesh)
    speed = (tree.thickness_mm / np.median(tree.thickness_mm)) ** speed_exponent
    edges = tree.graph.tocoo()
    weights = edges.data / (0.5 * (speed[edges.row] + speed[edges.col]))
    timed = sparse.csr_matrix((weights, (edges.row, edges.col)), shape=tree.graph.shape)
    arrival = csgraph.dijkstra(timed, directed=False, indices=tree.inflow)[mesh.faces].max(axis=1)
    keep = arrival <= np.quantile(arrival, fraction)
    return PartialCase(mesh, compact(mesh, keep), "bolus_front", float(keep.mean()))


def selective_injection(mesh: TriangleMesh, fraction: float, rng: np.random.Generator,
                        tree: VesselTree | None = None, candidates: int = 60) -> PartialCase:
    """One branch and everything downstream of it: of ``candidates`` random injection points away from
    the inflow, the one whose downstream part's face fraction is nearest ``fraction``."""
    tree = tree or vessel_tree(mesh)
    from_inflow = tree.distances_from(tree.inflow)
    eligible = np.flatnonzero(from_inflow > 0.1 * from_inflow.max())
    best, best_gap = None, np.inf
    for vertex in rng.choice(eligible, size=min(candidates, len(eligible)), replace=False):
        keep = tree.downstream_of(int(vertex))[mesh.faces].all(axis=1)
        gap = abs(keep.mean() - fraction)
        if gap < best_gap:
            best, best_gap = keep, gap
    return PartialCase(mesh, compact(mesh, best), "selective_injection", float(best.mean()))


def extra_territory(mesh: TriangleMesh, tree: VesselTree | None = None) -> PartialCase:
    """The model = the mesh and its mirror image across the plane through the inflow facing the mesh's
    centre (a second territory fed from the same point, spreading the other way); the images show the
    mesh alone."""
    tree = tree or vessel_tree(mesh)
    origin = mesh.vertices[tree.inflow]
    normal = mesh.centroid - origin
    normal /= max(np.linalg.norm(normal), 1e-9)
    mirrored = mesh.vertices - 2.0 * np.outer((mesh.vertices - origin) @ normal, normal)
    vertices = np.concatenate([mesh.vertices, mirrored])
    faces = np.concatenate([mesh.faces, mesh.faces[:, ::-1] + len(mesh.vertices)])  # a mirror turns the winding
    model = TriangleMesh(vertices, faces)
    return PartialCase(model, mesh, "extra_territory", mesh.n_faces / model.n_faces)


def reflux_injection(mesh: TriangleMesh, fraction: float, rng: np.random.Generator, tree: VesselTree | None = None,
                     reflux_mm: tuple[float, float] = (4.0, 12.0), filled: tuple[float, float] = (0.85, 1.0)) -> PartialCase:
    """A tip at a random vertex whose branch holds ``fraction`` / 0.85 ± 0.15 of the faces; the branch filled over a
    random share ``filled`` of its geodesic length from the tip, plus every vertex within a random
    ``reflux_mm`` of the tip along the surface (contrast flowing back into the parent vessel)."""
    tree = tree or vessel_tree(mesh)
    from_inflow = tree.distances_from(tree.inflow)
    eligible = rng.permutation(np.flatnonzero(from_inflow > 0.1 * from_inflow.max()))[:200]
    branches = tree.downstream_sets(eligible)
    shares = branches[:, mesh.faces].all(axis=2).mean(axis=1)
    near = np.flatnonzero(np.abs(shares - fraction / 0.85) <= 0.15)  # the fill and the reflux change the share
    pick = int(rng.choice(near)) if len(near) else int(np.argmin(np.abs(shares - fraction)))
    from_tip = tree.distances_from(int(eligible[pick]))
    branch = branches[pick]
    reach = rng.uniform(*filled) * from_tip[branch].max()
    visible = (branch & (from_tip <= reach)) | (from_tip <= rng.uniform(*reflux_mm))
    keep = visible[mesh.faces].all(axis=1)
    return PartialCase(mesh, compact(mesh, keep), "reflux_injection", float(keep.mean()))


def foreign_territory(mesh: TriangleMesh, other: TriangleMesh, tree: VesselTree | None = None,
                      other_tree: VesselTree | None = None) -> PartialCase:
    """The model = the mesh and ``other`` (another vessel tree) scaled to the mesh's RMS radius, its inflow placed
    on the mesh's and turned so that its centre lies opposite the mesh's centre; the images show the mesh alone."""
    tree, other_tree = tree or vessel_tree(mesh), other_tree or vessel_tree(other)
    origin, other_origin = mesh.vertices[tree.inflow], other.vertices[other_tree.inflow]
    away = origin - mesh.centroid
    toward = other.centroid - other_origin
    turn = _turn_between(toward / np.linalg.norm(toward), away / np.linalg.norm(away))
    scale = _rms_radius(mesh) / _rms_radius(other)
    placed = scale * (other.vertices - other_origin) @ turn.T + origin
    model = TriangleMesh(np.concatenate([mesh.vertices, placed]), np.concatenate([mesh.faces, other.faces + len(mesh.vertices)]))
    return PartialCase(model, mesh, "foreign_territory", mesh.n_faces / model.n_faces)


def _rms_radius(mesh: TriangleMesh) -> float:
    return float(np.sqrt(((mesh.vertices - mesh.centroid) ** 2).sum(axis=1).mean()))


def _turn_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation ``(3, 3)`` turning unit vector ``a`` onto unit vector ``b`` (Rodrigues; a half turn when opposite)."""
    axis, cosine = np.cross(a, b), float(a @ b)
    if np.linalg.norm(axis) < 1e-9:
        if cosine > 0:
            return np.eye(3)
        side = np.cross(a, np.eye(3)[int(np.argmin(np.abs(a)))])
        side /= np.linalg.norm(side)
        return 2.0 * np.outer(side, side) - np.eye(3)
    skew = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + skew + skew @ skew / (1.0 + cosine)


def images_hold_more(case: PartialCase, kind: str) -> PartialCase:
    """``case`` turned round: the images show ``case.model``, the model registered is ``case.visible``."""
    return PartialCase(case.visible, case.model, kind, case.model.n_faces / case.visible.n_faces)


def missing_small_branches(mesh: TriangleMesh, drop: float, rng: np.random.Generator, tree: VesselTree | None = None,
                           points: int = 400, largest_share: float = 0.1) -> PartialCase:
    """The model = ``mesh`` less its thinnest distal branches, about ``drop`` of its faces (a CTA model without its small
    vessels); the images show the whole mesh. Of ``points`` random points away from the inflow, the branches
    downstream of them holding at most ``largest_share`` of the faces are dropped thinnest first (median vessel
    thickness over the branch) until ``drop`` is reached; what stays is connected to the inflow."""
    tree = tree or vessel_tree(mesh)
    from_inflow = tree.distances_from(tree.inflow)
    eligible = rng.permutation(np.flatnonzero(from_inflow > 0.1 * from_inflow.max()))[:points]
    branches = tree.downstream_sets(eligible)[:, mesh.faces].all(axis=2)
    shares = branches.mean(axis=1)
    small = np.flatnonzero((shares > 0) & (shares <= largest_share))
    thickness = np.array([np.median(tree.thickness_mm[mesh.faces[branches[i]]]) for i in small])
    dropped = np.zeros(mesh.n_faces, bool)
    for index in small[np.argsort(thickness, kind="stable")]:
        if dropped.mean() >= drop:
            break
        dropped |= branches[index]
    model = compact(mesh, ~dropped)
    return PartialCase(model, mesh, "image_missing_small_branches", mesh.n_faces / model.n_faces)
