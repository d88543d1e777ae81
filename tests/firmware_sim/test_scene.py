"""The scene: determinism, geometry consistent with (K, R, t), real motion, honest ROIs."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_sim.board_scene import BoardScene
from firmware_sim.scene import LIN_LOG_KNEE, LOG_EPS, RIG_POSES_DEG, Scene, lin_log, log_lut
from rigd.core.pixels import mosaic_rggb


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(seed=3)


@pytest.mark.slow
def test_same_seed_same_images_other_seed_differs(scene: Scene) -> None:
    a = scene.render(scene.view("cam0", 320, 180), 1.25e6)
    b = Scene(seed=3).render("cam0", 1.25e6)
    c = Scene(seed=4).render("cam0", 1.25e6)
    np.testing.assert_array_equal(a, Scene(seed=3).render(Scene(seed=3).view("cam0", 320, 180), 1.25e6))
    assert b.shape == (720, 1280, 3)
    assert np.abs(b.astype(int) - c.astype(int)).mean() > 5


def test_homography_is_k_r1_r2_t_and_projects_plane_points(scene: Scene) -> None:
    for name in [*RIG_POSES_DEG, "somecam"]:
        k, r, t = scene.view_camera(name, 640, 360)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0)
        h = scene.plane_homography(name, 640, 360)
        np.testing.assert_allclose(h, k @ np.column_stack([r[:, 0], r[:, 1], t]))
        pw = np.array([0.3, -0.2, 0.0])
        pc = r @ pw + t
        assert pc[2] > 0  # in front of the camera
        px = k @ pc
        ph = h @ np.array([0.3, -0.2, 1.0])
        np.testing.assert_allclose(px[:2] / px[2], ph[:2] / ph[2], rtol=1e-12)
        # The plane centre is near the principal point: every view looks at it.
        c = h @ np.array([0.0, 0.0, 1.0])
        np.testing.assert_allclose(c[:2] / c[2], [320, 180], atol=1e-6)
    assert k[0, 0] == pytest.approx(500.0)


def test_views_are_distinct_positions_on_an_arc(scene: Scene) -> None:
    centers = {n: -scene.view_camera(n)[1].T @ scene.view_camera(n)[2] for n in RIG_POSES_DEG}
    xs = [centers[n][0] for n in ("cam0", "ev0", "cam1", "ev1", "cam2")]
    assert xs == sorted(xs)  # interleaved along the arc
    for c in centers.values():
        assert np.linalg.norm(c) == pytest.approx(3.0)


def test_object_homography_maps_sprite_centre_to_pose(scene: Scene) -> None:
    poses = scene.object_poses(2e6)
    hs = scene.object_homographies("cam1", 2e6)
    h_plane = scene.plane_homography("cam1")
    for o, pose, h in zip(scene.objects, poses, hs, strict=True):
        c = (o.texels - 1) / 2.0
        a = h @ np.array([c, c, 1.0])
        b = h_plane @ np.array([pose[0], pose[1], 1.0])
        np.testing.assert_allclose(a[:2] / a[2], b[:2] / b[2], atol=1e-9)


def test_render_shapes_and_dtypes(scene: Scene) -> None:
    v = scene.view("ev0", 320, 180)
    assert scene.render(v, 0.0).shape == (180, 320, 3)
    gray = scene.render(v, 0.0, gray=True)
    assert gray.shape == (180, 320)
    assert gray.dtype == np.uint8
    inten = scene.render_intensity(v, 0.0)
    assert inten.dtype == np.float32
    assert inten.shape == (180, 320)
    np.testing.assert_allclose(inten, gray.astype(np.float32), atol=1.5)
    roi = (10, 20, 110, 90)
    np.testing.assert_array_equal(scene.render(v, 5e5, roi=roi), scene.render(v, 5e5)[20:90, 10:110])
    with pytest.raises(ValueError, match="roi"):
        scene.render(v, 0.0, roi=(0, 0, 400, 10))
    assert gray.std() > 10  # textured, not flat


def test_sprites_move_at_hundreds_of_pixels_per_second(scene: Scene) -> None:
    v = scene.view("cam1")
    ts = np.linspace(0, 4e6, 401)
    corners = scene.object_corners(v, ts)  # (T, n, 4, 2)
    centres = corners.mean(axis=2)
    speed = np.linalg.norm(np.diff(centres, axis=0), axis=-1) / 0.01  # px/s
    assert 100 < speed.mean() < 800
    assert speed.max() < 1500
    a, b = scene.render(v, 1e6), scene.render(v, 1.05e6)
    assert np.abs(a.astype(int) - b.astype(int)).max() > 50


def test_changing_roi_contains_every_changed_pixel(scene: Scene) -> None:
    v = scene.view("ev1", 640, 360)
    for t0 in (0.0, 7.3e5, 3.1e6):
        t1 = t0 + 20_000
        roi = scene.changing_roi(v, t0, t1)
        assert roi is not None
        x0, y0, x1, y1 = roi
        diff = np.zeros((360, 640), bool)
        ref = scene.render_intensity(v, t0)
        for t in np.linspace(t0, t1, 9)[1:]:
            diff |= scene.render_intensity(v, float(t)) != ref
        ys, xs = np.nonzero(diff)
        assert len(xs) > 100
        assert xs.min() >= x0
        assert xs.max() < x1
        assert ys.min() >= y0
        assert ys.max() < y1
        outside = diff.copy()
        outside[y0:y1, x0:x1] = False
        assert not outside.any()


def test_static_scene_has_no_changing_roi() -> None:
    s = Scene(seed=1, speed=0.0)
    assert s.changing_roi("cam0", 0, 1e6) is None
    np.testing.assert_array_equal(s.render("cam0", 0.0), s.render("cam0", 5e6))


def test_lin_log_is_log_above_knee_linear_below_and_continuous() -> None:
    i = np.array([[0.0, 5.0, LIN_LOG_KNEE - LOG_EPS, 100.0, 255.0]], np.float32)
    out = lin_log(i)
    assert out[0, 3] == pytest.approx(np.log(100.0 + LOG_EPS), rel=1e-6)
    assert out[0, 2] == pytest.approx(np.log(LIN_LOG_KNEE), rel=1e-6)
    assert np.isfinite(out).all()
    assert (np.diff(out[0]) > 0).all()
    assert out[0, 1] - out[0, 0] == pytest.approx(5.0 / LIN_LOG_KNEE, rel=1e-5)
    lut = log_lut()
    xs = np.linspace(0, 255, 1001, dtype=np.float32)
    interp = np.interp(xs * 16, np.arange(lut.size), lut)
    np.testing.assert_allclose(interp, lin_log(xs[None])[0], atol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("make", [Scene, BoardScene], ids=["sprites", "board"])
@pytest.mark.parametrize("size", [(320, 180), (321, 181)], ids=["even", "odd"])
def test_bayer_render_is_exactly_the_mosaic_of_the_rgb_render(
    make: type[Scene], size: tuple[int, int]
) -> None:
    # The Bayer path blends only the sprites' pixels into the background's mosaic; sprites at
    # odd offsets, overlapping, or cut by the image border must not shift the filter's phase.
    s = make(seed=2)
    view = s.view("cam1", *size)
    for t in np.linspace(0.0, 20e6, 41):
        np.testing.assert_array_equal(s.render_bayer(view, t), mosaic_rggb(s.render(view, t)))
