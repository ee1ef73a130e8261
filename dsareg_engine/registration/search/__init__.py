"""The pose search without an initial pose: which starts the solver gets.

* :mod:`.settings` — :class:`~.settings.SearchSettings`, the one settings type of every search below;
* :mod:`.initialization` — the centroid search (triangulated position, SO(3) grid) and what decides whether the
  partial searches run;
* :mod:`.coverage_search` — candidates placed and scored by how much of the vessels the model explains;
* :mod:`.branch_search` — the model cut into parts (proximal, branches, rests), each searched alone;
* :mod:`.rotation_grid`, :mod:`.rotation_refine`, :mod:`.search_kernels` — the grid, the hill-climb, the numba kernels.

Nothing is re-exported: import from the module that defines a name.
"""
