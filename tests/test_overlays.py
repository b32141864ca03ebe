import cv2
import imageio.v3 as iio
import numpy as np
import pytest

from monose3.errors import Monose3Error
from monose3.report.overlays import denoising_strip, draw_overlay, image_grid, save_animation, save_image
from monose3.report.plots import plot_add_distribution, plot_curves


def scene(h=120, w=160):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 120, size=(h, w, 3), dtype=np.uint8)
    mask = np.zeros((h, w), bool)
    mask[40:80, 50:100] = True
    return image, mask


def test_overlay_outline_changes_far_pixels_do_not():
    image, mask = scene()
    out = draw_overlay(image, mask, color=(0, 255, 0), legend=False)
    assert out.shape == image.shape and out.dtype == np.uint8
    assert not np.shares_memory(out, image)
    # every boundary pixel of the mask is drawn in the outline colour (green channel high)
    boundary = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.all(out[boundary][:, 1] >= 200)
    # interior is tinted, not replaced
    inner = out[55:65, 70:80].astype(int)
    assert np.all(inner[..., 1] > image[55:65, 70:80, 1]) and np.all(inner[..., 1] < 200)
    # pixels well away from the robot are untouched
    far = np.ones(mask.shape, bool)
    far[30:90, 40:110] = False
    np.testing.assert_array_equal(out[far], image[far])


def test_overlay_has_a_legend_for_its_colours():
    image, mask = scene()
    h = image.shape[0]
    plain = draw_overlay(image, mask, legend=False)
    est = draw_overlay(image, mask)
    both = draw_overlay(image, mask, gt_keypoints_uv=[[140, 100]])
    # the key sits in the bottom-left corner on a dark box, one row per colour shown
    assert not np.array_equal(est[h - 12 :, :40], plain[h - 12 :, :40])
    rows = lambda img: int((img[:, 0] == 0).all(axis=1).sum())  # noqa: E731 - dark rows of the box's left edge
    assert rows(both) > rows(est) > 0
    assert np.array_equal(est[:20, -20:], plain[:20, -20:])  # nothing elsewhere


def test_overlay_keypoints_and_text():
    image, mask = scene()
    plain = draw_overlay(image, mask)
    # the cross sits top right: the key's box fills the bottom rows of so small an image (OpenCV 5's font)
    with_kp = draw_overlay(image, mask, keypoints_uv=[[20, 20]], gt_keypoints_uv=[[140, 30], [np.nan, 3]])
    assert tuple(with_kp[20, 20]) == (0, 255, 0)  # predicted dot in colour
    r, g, b = (int(c) for c in with_kp[30, 140])
    assert r >= 240 and g <= 20 and b <= 20  # gt cross centre in red (anti-aliased)
    assert np.array_equal(with_kp[60:62, 60:62], plain[60:62, 60:62])
    labelled = draw_overlay(image, mask, text="step 3")
    assert not np.array_equal(labelled[:20, :60], plain[:20, :60])
    with pytest.raises(Monose3Error, match="mask is"):
        draw_overlay(image, mask[:10])


def test_save_image_makes_dirs(tmp_path):
    image, mask = scene()
    p = save_image(tmp_path / "a" / "b" / "o.png", image)
    back = cv2.cvtColor(cv2.imread(str(p)), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(back, image)
    with pytest.raises(Monose3Error, match="extension"):
        save_image(tmp_path / "o.notanimage", image)


def test_gif_roundtrip(tmp_path):
    frames = [np.full((24, 32, 3), 40 * i, np.uint8) for i in range(5)]
    p = save_animation(frames, tmp_path / "anim" / "x.gif", fps=5)
    back = iio.imread(p, index=None)
    assert back.shape[0] == 5 and back.shape[1:3] == (24, 32)
    assert abs(int(back[3, 0, 0, 0]) - 120) <= 4


def test_mp4_and_bad_inputs(tmp_path):
    frames = [np.full((48, 64, 3), 50 * i, np.uint8) for i in range(4)]
    p = save_animation(frames, tmp_path / "x.mp4", fps=4)
    cap = cv2.VideoCapture(str(p))
    n = 0
    while cap.read()[0]:
        n += 1
    cap.release()
    assert n == 4
    with pytest.raises(Monose3Error, match="differ in size"):
        save_animation([frames[0], frames[1][:10]], tmp_path / "y.gif")
    with pytest.raises(Monose3Error, match="unsupported"):
        save_animation(frames, tmp_path / "y.avi")


def test_image_grid_layout():
    a = np.full((10, 20, 3), 10, np.uint8)
    b = np.full((6, 20), 200, np.uint8)  # grey, smaller: centred
    g = image_grid([a, a, b], cols=2)
    assert g.shape == (20, 40, 3)
    assert np.all(g[:10, :20] == 10) and np.all(g[12:18, :20] == 200) and np.all(g[10:12, :20] == 0)
    assert image_grid([a, a], cols=5).shape == (10, 40, 3)
    assert image_grid([a, a], cols=1, pad=3).shape == (23, 20, 3)


def test_denoising_strip(tmp_path):
    image, mask = scene()
    masks = [np.roll(mask, s, axis=1) for s in (30, 15, 0)]
    strip = denoising_strip(image, masks, ["t=100", "t=50", "final"], tmp_path / "strip.png")
    assert strip.shape == (120, 3 * 160 + 2 * 4, 3)
    assert (tmp_path / "strip.png").stat().st_size > 0
    with pytest.raises(Monose3Error, match="labels"):
        denoising_strip(image, masks, ["a"], None)


def test_plots_write_png(tmp_path):
    rng = np.random.default_rng(1)
    adds = {"ours": rng.exponential(0.02, 200), "baseline": np.r_[rng.exponential(0.04, 190), [np.inf] * 10]}
    p = plot_add_distribution(adds, tmp_path / "plots" / "add.png")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 5000
    q = plot_curves(np.arange(10), {"train": np.linspace(1, 0.1, 10)}, tmp_path / "loss.png", "epoch", "loss", "t")
    assert q.stat().st_size > 1000 and cv2.imread(str(q)) is not None
    with pytest.raises(Monose3Error, match="one value per x"):
        plot_curves([0, 1], {"a": [1, 2, 3]}, tmp_path / "bad.png")
