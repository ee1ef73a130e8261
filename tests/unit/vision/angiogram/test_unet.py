import torch

from dsareg_engine.vision.angiogram.unet import UNetSettings, VesselUNet, padded_to_level


def test_logits_have_the_input_shape_after_padding():
    model = VesselUNet(UNetSettings(base_channels=4, levels=3)).eval()
    image = torch.zeros(1, 1, 37, 50)
    padded, (height, width) = padded_to_level(image, model.settings.multiple_px)
    assert padded.shape[-2:] == (40, 52) and (height, width) == (37, 50)
    with torch.no_grad():
        assert model(padded).shape == (1, 1, 40, 52)
