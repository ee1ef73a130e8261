"""A failed fit on images whose roles no header states: would the AP and LAT images fit the other way round?

Images without DICOM headers (PNG, TIFF, masks; or DICOM given an explicit geometry) carry no beam angles to
name their views by (:mod:`dsareg_engine.io.view_roles`), so a pair given the wrong way round fits nothing and
the verdict says ``failed`` without saying why. Only then (a failed verdict, both images the same size) the
registration runs once more with the two targets exchanged; when that fits clearly better (lowest Dice at least
:data:`SWAP_MIN_DICE` and :data:`SWAP_GAIN` above the kept fit's, the rule of the mirror check) a reason saying
the images look swapped joins the verdict, which stays ``failed``: the pose returned is of the images as given.
"""

from __future__ import annotations

import numpy as np

from ..geometry.rig import Rig
from ..mesh import TriangleMesh
from .options import RegistrationOptions
from .result import RegistrationResult

SWAP_MIN_DICE = 0.7
SWAP_GAIN = 0.2


def swap_hint(mesh: TriangleMesh, targets: dict[str, np.ndarray], rig: Rig, result: RegistrationResult,
              options: RegistrationOptions) -> str | None:
    """The reason added to ``result``'s failed verdict when the exchanged images fit clearly better, else None."""
    from .solver import register

    confidence = result.metrics.get("confidence")
    if not options.mirror_check or not isinstance(confidence, dict) or confidence.get("verdict") != "failed" \
            or set(targets) != {"ap", "lat"}:
        return None
    if np.shape(targets["ap"]) != np.shape(targets["lat"]) or rig.views["ap"].image_size != rig.views["lat"].image_size:
        return None
    exchanged = {"ap": targets["lat"], "lat": targets["ap"]}
    other = register(mesh, exchanged, rig, options.model_copy(update={"mirror_check": False,
                                                                      "ground_truth_mesh_to_world": None}))
    before = min(view.dice for view in result.views.values())
    after = min(view.dice for view in other.views.values())
    if after < SWAP_MIN_DICE or after - before < SWAP_GAIN:
        return None
    reason = (f"the AP and LAT images look swapped: exchanged, the model fits both (lowest Dice {after:.2f} instead "
              f"of {before:.2f}); give the frontal image as ap and the lateral one as lat")
    confidence["reasons"] = list(confidence.get("reasons") or []) + [reason]
    return reason
