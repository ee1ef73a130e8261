"""Hemodynamics on the registered model: when contrast reaches each vessel point, from both runs.

With the pose found, every point of the model projects into both DSA runs; the time–density curve
of the vessel there (over its projected cross-section, background-corrected) gives the contrast
arrival time and the time to peak. Where another part of the model overlaps a point in one view,
that view is flagged for the point and the other carries it; where both are clean, both are
reported and combined, and their difference measures how well the two views (and the registration)
agree. Definitions: ``docs/concepts/hemodynamics.md``.

Modules: :mod:`.timing` (frame times from the files), :mod:`.frames` (the subtracted frame stack of a
run), :mod:`.model_points` (vessel centres and radii, the model file's own vertex order),
:mod:`.sampling` (cross-section footprints as a sparse matrix), :mod:`.overlap` (which view sees a
point clear of other vessels), :mod:`.parameters` (arrival, peak), :mod:`.combine` (the two views),
:mod:`.outputs` (files), :mod:`.run` (the whole step).
"""
