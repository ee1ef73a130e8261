"""voxelize_mesh: partial-volume voxels of a mesh, isotropic or one size per axis (slices thicker than pixels)."""

import numpy as np
import pytest
import trimesh

from dsareg_engine.mesh import TriangleMesh
from dsareg_engine.simulation.phantom_study import voxelize_mesh


def _sphere(radius_mm=6.0, centre=(1.3, -2.1, 4.7)):
    solid = trimesh.creation.icosphere(subdivisions=4, radius=radius_mm)
    return TriangleMesh(np.asarray(solid.vertices) + np.asarray(centre), np.asarray(solid.faces)), solid.volume


@pytest.mark.parametrize("pitch", [0.5, (0.4, 0.4, 0.8), (0.5, 0.5, 1.0)])
def test_the_voxels_hold_the_mesh_where_it_is(pitch):
    mesh, volume_mm3 = _sphere()
    occupancy, affine = voxelize_mesh(mesh, pitch, margin=1)
    spacing = np.broadcast_to(np.asarray(pitch, float), (3,))
    assert np.allclose(np.diag(affine)[:3], spacing)
    fraction = occupancy / 800.0
    # the fine voxels the surface crosses count whole: the surface lies up to half a fine voxel (≤ 0.25 mm) out
    assert volume_mm3 < fraction.sum() * np.prod(spacing) < 1.12 * volume_mm3
    # the occupancy's centroid, through the affine, is the sphere's centre (a sign or half-voxel slip moves it)
    centroid = (np.argwhere(fraction > -1) * fraction.ravel()[:, None]).sum(0) / fraction.sum()
    assert affine[:3, :3] @ centroid + affine[:3, 3] == pytest.approx(mesh.vertices.mean(0), abs=0.05)


def test_voxel_sizes_that_do_not_tile_are_refused():
    with pytest.raises(ValueError, match="whole multiple"):
        voxelize_mesh(_sphere()[0], (0.4, 0.4, 0.7))
