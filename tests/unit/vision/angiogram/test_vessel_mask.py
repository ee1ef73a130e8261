import numpy as np

from dsareg_engine.vision.angiogram.vessel_mask import MaskSettings, vessel_mask


def test_edge_pieces_and_coverage_cap():
    probability = np.zeros((100, 100), np.float32)
    probability[40:60, 10:90] = 0.9  # a vessel
    probability[0:100, 0:2] = 0.99  # the field's edge ring
    probability[5, 50] = 0.9  # one-pixel speckle
    field = np.ones((100, 100), bool)
    mask, record = vessel_mask(probability, field)
    assert not mask[:, :3].any() and not mask[5, 50]
    assert mask[40:60, 10:90].all()
    assert record["coverage_of_field"] < 0.25
    everything = np.full((100, 100), 0.8, np.float32) + np.linspace(0, 0.1, 100, dtype=np.float32)[None]
    capped, record = vessel_mask(everything, field, MaskSettings())
    assert capped.mean() <= 0.26 and record["threshold"] > 0.5
