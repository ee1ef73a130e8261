"""Simulated partial visibility: a run that shows less of the vessel tree than the model holds.

Three ways a clinical run and a 3D model disagree (the images are rendered from the returned
*visible* part, the registration gets the whole *model*):

* :func:`early_filling` — an early arterial frame: contrast has filled the tree from the inflow
  up to a geodesic distance, the distal branches not yet;
* :func:`selective_injection` — a microcatheter in one branch: only that branch and what lies
  downstream of it fill;
* :func:`extra_territory` — a model holding a territory the run does not inject (e.g. the other
  carotid's): the model is the mesh plus a mirrored copy of it joined at the inflow.

Fractions are of the model's faces. Distances come from :mod:`dsareg_engine.geometry.vessel_tree`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.vessel_tree import VesselTree, compact, vessel_tree
from ..mesh import TriangleMesh


@dataclass(frozen=True)
class PartialCase:
    """A model and the part of it a run shows (both in the model's frame, mm).

    Attributes:
        model: what is registered.
        visible: what the images are rendered from.
        kind: ``"early_filling"``, ``"selective_injection"``, ``"extra_territory"`` or ``"full"``.
        visible_fraction: visible faces / model faces.
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
