"""A procedural vessel tree: branching tubes of tapering radius (mm), seeded.

Used by tests, examples and benchmarks so nothing needs patient data. The tree grows
from a trunk along +y; each segment is a curved tube (a ring of ``n_sides`` vertices
swept along a smooth centreline) with capped ends. Tubes overlap at branch points,
which is harmless for silhouettes.
"""

from __future__ import annotations

import numpy as np

from ..mesh import TriangleMesh


def make_vessel_phantom(
    seed: int = 0,
    depth: int = 4,
    trunk_radius_mm: float = 2.2,
    trunk_length_mm: float = 32.0,
    n_sides: int = 12,
    rings_per_segment: int = 16,
) -> TriangleMesh:
    """Build the phantom; about 12k faces with the defaults, centred on its vertex mean.

    Args:
        seed: RNG seed; the same seed gives the same mesh.
        depth: levels of bifurcation below the trunk.
        trunk_radius_mm, trunk_length_mm: size of the first segment; children taper
            to 70 % of the radius and 75 % of the length.
        n_sides: vertices per ring.
        rings_per_segment: rings along each segment's centreline.
    """
    rng = np.random.default_rng(seed)
    vertex_blocks: list[np.ndarray] = []
    face_blocks: list[np.ndarray] = []
    offset = 0
    stack = [(np.zeros(3), np.array([0.0, 1.0, 0.0]), trunk_radius_mm, trunk_length_mm, 0)]
    while stack:
        start, direction, radius, length, level = stack.pop()
        centreline, end_direction = _curved_centreline(rng, start, direction, length, rings_per_segment)
        radii = np.linspace(radius, radius * 0.85, rings_per_segment)
        vertices, faces = _tube(centreline, radii, n_sides)
        vertex_blocks.append(vertices)
        face_blocks.append(faces + offset)
        offset += len(vertices)
        if level < depth:
            for sign in (1.0, -1.0):
                child_dir = _deflect(rng, end_direction, sign)
                stack.append((centreline[-1], child_dir, radius * 0.7, length * 0.75, level + 1))
    vertices = np.concatenate(vertex_blocks)
    vertices -= vertices.mean(axis=0)
    return TriangleMesh(vertices, np.concatenate(face_blocks).astype(np.int64))


def _curved_centreline(rng, start, direction, length, n_points):
    """A gently curving polyline from ``start`` (``(n_points, 3)``) and its end tangent."""
    bend = rng.normal(size=3)
    bend -= bend.dot(direction) * direction
    bend /= np.linalg.norm(bend) + 1e-12
    curvature = rng.uniform(0.2, 0.6)  # radians of turn over the segment
    points = [start]
    heading = direction.copy()
    step = length / (n_points - 1)
    for _ in range(n_points - 1):
        heading = heading + bend * (curvature / (n_points - 1))
        heading /= np.linalg.norm(heading)
        points.append(points[-1] + step * heading)
    return np.array(points), heading


def _deflect(rng, direction, sign):
    """A child direction 25–45° off ``direction``, on alternating sides of a random plane."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(direction[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    side = np.cross(direction, helper)
    side /= np.linalg.norm(side)
    twist = rng.uniform(0.0, 2.0 * np.pi)
    other = np.cross(direction, side)
    lateral = np.cos(twist) * side + np.sin(twist) * other
    angle = np.radians(rng.uniform(25.0, 45.0))
    child = np.cos(angle) * direction + sign * np.sin(angle) * lateral
    return child / np.linalg.norm(child)


def _tube(centreline: np.ndarray, radii: np.ndarray, n_sides: int) -> tuple[np.ndarray, np.ndarray]:
    """Closed tube (capped ends) around a polyline; faces wind outward."""
    n_rings = len(centreline)
    tangents = np.gradient(centreline, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    # Parallel-transport frames avoid twisting of the rings.
    normal = np.cross(tangents[0], [1.0, 0.0, 0.0])
    if np.linalg.norm(normal) < 1e-6:
        normal = np.cross(tangents[0], [0.0, 0.0, 1.0])
    normal /= np.linalg.norm(normal)
    angles = np.linspace(0.0, 2.0 * np.pi, n_sides, endpoint=False)
    rings = []
    for i in range(n_rings):
        normal = normal - normal.dot(tangents[i]) * tangents[i]
        normal /= np.linalg.norm(normal)
        binormal = np.cross(tangents[i], normal)
        circle = np.cos(angles)[:, None] * normal + np.sin(angles)[:, None] * binormal
        rings.append(centreline[i] + radii[i] * circle)
    vertices = np.concatenate([np.concatenate(rings), centreline[[0, -1]]])
    faces = []
    for i in range(n_rings - 1):
        for k in range(n_sides):
            a, b = i * n_sides + k, i * n_sides + (k + 1) % n_sides
            c, d = a + n_sides, b + n_sides
            faces += [[a, b, d], [a, d, c]]
    first_cap, last_cap = n_rings * n_sides, n_rings * n_sides + 1
    last_ring = (n_rings - 1) * n_sides
    for k in range(n_sides):
        faces.append([first_cap, (k + 1) % n_sides, k])
        faces.append([last_cap, last_ring + k, last_ring + (k + 1) % n_sides])
    return vertices, np.array(faces, dtype=np.int64)
