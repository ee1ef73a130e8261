"""Overlays, the loss plot and the animation: what a person sees."""

from __future__ import annotations

import numpy as np
import pytest

from dsareg_engine.overlay import FINAL_BGR, INITIAL_BGR, Caption, crop_box, display_base, overlay_image
from dsareg_engine.plots import drawn_loss_figure, loss_figure


def _vessel(shape=(200, 240), shift=0):
    mask = np.zeros(shape, bool)
    mask[40:170, 100 + shift:110 + shift] = True
    mask[60:70, 60 + shift:180 + shift] = True
    return mask


def _colour_pixels(image: np.ndarray, bgr) -> int:
    return int(np.all(np.abs(image.astype(int) - np.array(bgr)) < 40, axis=-1).sum())


def test_overlay_shows_dsa_under_contours_with_caption_and_scale_bar():
    target, initial, final = _vessel(), _vessel(shift=12), _vessel(shift=1)
    rng = np.random.default_rng(0)
    dsa = 200.0 - 150.0 * target + rng.normal(0, 8, target.shape)  # vessels dark, noisy background
    caption = Caption(view="ap", dice=0.934, verdict="converged", ok=True, job="job abc123", mm_per_px=0.25)
    image = overlay_image(target, initial, final, dsa, caption=caption)
    assert image.dtype == np.uint8 and image.ndim == 3
    assert _colour_pixels(image, INITIAL_BGR) > 50 and _colour_pixels(image, FINAL_BGR) > 50
    band_start = np.nonzero((image[:, :, 0] == 40).all(axis=1))[0]
    assert len(band_start), "no caption band"
    picture = image[: band_start[0]]
    grey = picture[..., 0].astype(int)
    # the DSA is there (many grey levels), vessels darker than the background: readable contrast
    assert len(np.unique(grey)) > 30
    assert min(picture.shape[:2]) >= 256  # small images are enlarged
    caption_band = image[band_start[0]:]
    assert (caption_band > 200).any()  # text was drawn


def test_mask_only_overlay_has_readable_contrast():
    target = _vessel()
    base = display_base(target)
    assert int(base[~target].mean()) - int(base[target].mean()) >= 90  # grey vessels on a light background


def test_crop_box_frames_all_contours():
    target, initial = _vessel(), _vessel(shift=30)
    x0, y0, x1, y1 = crop_box([target, initial])
    rows, cols = np.nonzero(target | initial)
    assert x0 <= cols.min() and cols.max() < x1 and y0 <= rows.min() and rows.max() < y1
    assert crop_box([np.zeros((50, 60), bool)]) == (0, 0, 60, 50)


def test_loss_plot_is_log_scaled_with_legend_outside():
    history = [("ap+lat:1/4", list(np.geomspace(0.05, 0.03, 20))), ("ap+lat:1/1", list(np.geomspace(0.01, 0.007, 30))),
               ("ap+lat:1/1:refine", [0.003, 0.002, 0.0019])]
    image = loss_figure(history)
    assert image.shape == (450, 800, 3) and image.dtype == np.uint8
    # the legend sits right of the axes: the plot's right quarter has coloured text, the curves stay left of it
    assert (image[:, 600:, :] < 200).any()
    empty = loss_figure([])
    assert empty.shape == (450, 800, 3)


@pytest.mark.slow
def test_animation_starts_at_the_initial_contour_and_has_stage_labels(tmp_path):
    import torch
    from PIL import Image

    from dsareg_engine.geometry.rig import Rig
    from dsareg_engine.geometry.spec import load_rig
    from dsareg_engine.simulation.phantom import make_vessel_phantom
    from dsareg_engine.pipeline import animation_frames, write_outputs
    from dsareg_engine.registration.solver import register
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.registration.parameterization import random_start_poses
    from dsareg_engine.render import Camera, render_hard_silhouette

    mesh = make_vessel_phantom()
    paper = load_rig("paper")
    views = {n: v.resized(160, 160) for n, v in paper.views.items()}
    initial = random_start_poses(np.eye(4), mesh.centroid, 2, 4.0, 4.0, seed=2)[1]
    rig = Rig(views, initial)
    vertices, faces = mesh.torch(torch.float64)
    masks = {n: render_hard_silhouette(vertices, faces, torch.as_tensor(v.world_to_view)[None], Camera.from_view(v))[0]
             .numpy().astype(bool) for n, v in views.items()}
    result = register(mesh, masks, rig, RegistrationOptions(starts=1, max_iterations=40, animation=True))
    frames = animation_frames(result)
    assert len(frames) >= 20
    assert frames[0][0] == "initial" and np.allclose(frames[0][2], initial)
    assert frames[-1][0] == "registered" and np.allclose(frames[-1][2], result.mesh_to_world)
    stages = [name for name, _, _ in frames]
    assert set(result.metrics["iterations"]) <= set(stages)  # every stage appears, in order
    write_outputs(result, masks, tmp_path, mesh, rig, animation=True, label="job test")
    gif = Image.open(tmp_path / "animation.gif")
    assert gif.n_frames >= 20
    gif.seek(0)
    first = np.asarray(gif.convert("RGB"))[..., ::-1]
    assert _colour_pixels(first, INITIAL_BGR) > 0 or _colour_pixels(first, FINAL_BGR) > 0


def test_animation_last_frame_shows_the_dice_of_the_result(tmp_path, monkeypatch):
    """The registered frame reads the result's own Dice (full resolution), not its preview's."""
    import torch

    from dsareg_engine import pipeline
    from dsareg_engine.geometry.rig import Rig
    from dsareg_engine.geometry.spec import load_rig
    from dsareg_engine.simulation.phantom import make_vessel_phantom
    from dsareg_engine.registration.solver import register
    from dsareg_engine.registration.options import RegistrationOptions
    from dsareg_engine.render import Camera, render_hard_silhouette

    mesh = make_vessel_phantom()
    views = {n: v.resized(128, 128) for n, v in load_rig("paper").views.items()}
    rig = Rig(views, np.eye(4))
    vertices, faces = mesh.torch(torch.float64)
    masks = {n: render_hard_silhouette(vertices, faces, torch.as_tensor(v.world_to_view)[None], Camera.from_view(v))[0]
             .numpy().astype(bool) for n, v in views.items()}
    result = register(mesh, masks, rig, RegistrationOptions(starts=1, max_iterations=4, animation=True))
    captions: list[Caption] = []
    real = pipeline.overlay_image

    def recording(*args, caption=None, **kwargs):
        captions.append(caption)
        return real(*args, caption=caption, **kwargs)

    monkeypatch.setattr(pipeline, "overlay_image", recording)
    pipeline.write_animation(tmp_path / "a.gif", result, masks, mesh, rig, max_side=48)  # previews at 48 px
    last = captions[-len(result.views):]
    for caption in last:
        assert caption.dice == result.views[caption.view].dice and caption.dice_label == "Dice", caption
    previews = [c for c in captions[:-len(result.views)] if c.dice_label == "preview Dice"]
    assert previews and any(c.dice != result.views[c.view].dice for c in previews)


def test_unmatched_model_parts_are_filled_in_their_own_colour(tmp_path):
    from dsareg_engine.simulation.clinical_rig import clinical_biplane_rig, random_visible_pose, render_masks
    from dsareg_engine.overlay import UNMATCHED_BGR, write_png
    from dsareg_engine.simulation.partial_filling import early_filling
    from dsareg_engine.simulation.phantom import make_vessel_phantom
    from dsareg_engine.registration.partial import unmatched_pixels

    mesh = make_vessel_phantom()
    case = early_filling(mesh, 0.5)
    rig = clinical_biplane_rig(256)
    truth = random_visible_pose(mesh, rig, np.random.default_rng(0), 40.0)
    vessels, model = render_masks(case.visible, rig, truth)["ap"], render_masks(mesh, rig, truth)["ap"]
    unmatched = unmatched_pixels(model, vessels)
    assert unmatched.sum() > 0.1 * model.sum() and not (unmatched & vessels).any()
    image = overlay_image(vessels, model, model, caption=Caption(view="ap", unmatched_label="unfilled"),
                          unmatched=unmatched)
    plain = overlay_image(vessels, model, model, caption=Caption(view="ap"))
    write_png(tmp_path / "overlay_ap.png", image)
    assert UNMATCHED_BGR[0] - UNMATCHED_BGR[1] > 100 and UNMATCHED_BGR[2] - UNMATCHED_BGR[1] > 100

    def magenta(picture):  # blue and red well above green: neither the grey vessels, nor blue, nor orange contours
        b, g, r = (picture[..., k].astype(int) for k in range(3))
        return int(((b - g > 50) & (r - g > 50)).sum())

    assert magenta(image) > magenta(plain) + 5 * unmatched.sum()  # the fill, enlarged by the overlay's zoom
    assert magenta(plain) == 0


@pytest.mark.parametrize("decades", [0.3, 0.9, 1.3, 2.6])
def test_loss_plot_text_fits_and_tick_labels_do_not_overlap(decades):
    """Every label lies inside the image, the y label with room to spare, and no two y tick labels overlap
    (the page shows the plot whole; the earlier label ran nearly the full axes height, minor labels crowded)."""
    top, bottom = 0.08, 0.08 / 10 ** decades
    middle = float(np.sqrt(top * bottom))
    history = [("ap+lat:1/4", list(np.geomspace(top, middle, 40))), ("ap+lat:1/2", list(np.geomspace(middle, bottom, 30))),
               ("ap+lat:1/1:refine", [bottom] * 11)]
    figure = drawn_loss_figure(history, 800, 450, "Loss per iteration - job 0123456789abcdef0123456789abcdef")
    renderer = figure.canvas.get_renderer()
    (axes,) = figure.axes
    whole = figure.bbox
    texts = [axes.yaxis.label, axes.xaxis.label, axes.title, axes.get_legend()]
    for artist in texts:
        box = artist.get_window_extent(renderer)
        assert whole.x0 <= box.x0 and box.x1 <= whole.x1 and whole.y0 <= box.y0 and box.y1 <= whole.y1, artist
    assert axes.yaxis.label.get_window_extent(renderer).height <= 0.8 * axes.bbox.height
    labelled = [t for t in axes.yaxis.get_ticklabels(which="both") if t.get_visible() and t.get_text()]
    boxes = [t.get_window_extent(renderer) for t in labelled]
    shown = [box for box in boxes if axes.bbox.y0 - 2 <= box.y0 and box.y1 <= axes.bbox.y1 + 2]  # within the axes
    shown.sort(key=lambda box: box.y0)
    assert len(shown) >= 2
    for low, high in zip(shown, shown[1:]):
        assert low.y1 <= high.y0 + 0.5, (low, high)
