"""Tests of gcn_match_ros.data.homography_sequence: views related by exact homographies, in the Oxford layout."""
import cv2
import numpy as np
import pytest

from gcn_match_ros.data.convert import make_problem
from gcn_match_ros.data.scenes import DatasetError, load_scene
from gcn_match_ros.data.homography_sequence import (SequenceConfig, homography_sequence, make_sequence, source_image,
                                               view_quads, view_size, write_sequence)

# geometry only: no photometric change, so views can be compared pixel by pixel
GEOMETRY_ONLY = SequenceConfig(gain_range=(1, 1), gamma_range=(1, 1), blur_probability=0, noise_sigma=0)


def smooth_texture(h=480, w=640, seed=0):
    noise = np.random.default_rng(seed).uniform(0, 255, (h, w)).astype(np.float32)
    img = cv2.GaussianBlur(noise, (0, 0), 4)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return np.rint(img).astype(np.uint8)


def test_source_image_gray_and_long_side():
    colour = np.zeros((300, 451, 3), np.uint8)
    out = source_image(colour, 800)
    assert out.shape == (532, 800) and out.dtype == np.uint8
    assert source_image(np.zeros((1000, 500), np.uint8), 800).shape == (800, 400)
    with pytest.raises(ValueError, match=r"\(300, 451, 2\)"):
        source_image(np.zeros((300, 451, 2), np.uint8), 800)
    with pytest.raises(ValueError, match="float32"):
        source_image(np.zeros((30, 40), np.float32), 800)


def test_quads_start_centred_stay_inside_and_are_seeded():
    size = (800, 600)
    q = view_quads(size, SequenceConfig(), np.random.default_rng(3))
    w, h = view_size(size, SequenceConfig())
    assert q.shape == (6, 4, 2) and (w, h) == (480, 360)
    x0, y0 = (800 - w) / 2, (600 - h) / 2
    np.testing.assert_allclose(q[0], [[x0, y0], [x0 + w - 1, y0], [x0 + w - 1, y0 + h - 1], [x0, y0 + h - 1]])
    assert (q[..., 0] >= 0).all() and (q[..., 0] <= 799).all() and (q[..., 1] >= 0).all() and (q[..., 1] <= 599).all()
    np.testing.assert_array_equal(q, view_quads(size, SequenceConfig(), np.random.default_rng(3)))
    assert not np.allclose(q, view_quads(size, SequenceConfig(), np.random.default_rng(4)))


def test_impossible_geometry_is_a_clear_error():
    cfg = SequenceConfig(view_fraction=1.0, max_draws=5)  # a full-size view cannot move and stay inside
    with pytest.raises(ValueError, match="5 draws"):
        view_quads((640, 480), cfg, np.random.default_rng(0))
    with pytest.raises(ValueError, match="n_views"):
        SequenceConfig(n_views=1)


def test_written_homographies_map_view_1_onto_view_n(tmp_path):
    source = smooth_texture()
    views, to_source = homography_sequence(source, GEOMETRY_ONLY, np.random.default_rng(1))
    assert len(views) == 6 and to_source.shape == (6, 3, 3)
    assert all(v.shape == views[0].shape == (288, 384) for v in views)
    # view 1 is the source's centred crop, untouched
    np.testing.assert_array_equal(views[0], source[96:384, 128:512])
    write_sequence(tmp_path / "homography" / "toy", views, to_source)
    scene = load_scene(tmp_path, "homography/toy")
    assert scene.name == "homography_toy" and scene.kind == "homography" and scene.n_views == 6
    for n in range(1, 6):
        H1toN = np.linalg.inv(scene.homographies[n])  # scene stores view n -> view 1
        warped = cv2.warpPerspective(views[0].astype(np.float32), H1toN, views[n].shape[::-1], flags=cv2.INTER_LINEAR)
        covered = cv2.warpPerspective(np.ones_like(views[0], np.float32), H1toN, views[n].shape[::-1]) > 0.999
        covered = cv2.erode(covered.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        assert covered.mean() > 0.2
        diff = np.abs(warped - views[n])[covered]
        assert np.median(diff) < 1.0 and np.percentile(diff, 99) < 4.0, (n, np.median(diff))


def test_photometric_change_leaves_view_1_alone_and_is_seeded():
    source = smooth_texture()
    a, Ha = homography_sequence(source, SequenceConfig(), np.random.default_rng(7))
    b, Hb = homography_sequence(source, SequenceConfig(), np.random.default_rng(7))
    g, _ = homography_sequence(source, GEOMETRY_ONLY, np.random.default_rng(7))
    np.testing.assert_array_equal(Ha, Hb)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    np.testing.assert_array_equal(a[0], g[0])
    assert all(not np.array_equal(x, y) for x, y in zip(a[1:], g[1:]))


def test_sequence_problem_labels_pairs_by_the_exact_homography(tmp_path):
    views, to_source = homography_sequence(smooth_texture(seed=2), SequenceConfig(), np.random.default_rng(0))
    write_sequence(tmp_path / "homography" / "toy", views, to_source)
    scene = load_scene(tmp_path, "homography/toy")
    problem = make_problem(scene, [0, 1, 2], "sift", 300)
    assert problem.name == "homography_toy_sift_123"
    tracks = problem.gt_track[problem.gt_track >= 0]
    assert len(np.unique(tracks)) > 20  # a textured image gives many labelled tracks
    with pytest.raises(DatasetError, match="no such scene folder"):
        load_scene(tmp_path, "homography/missing")


def test_write_sequence_checks_its_input(tmp_path):
    with pytest.raises(ValueError, match="one homography each"):
        write_sequence(tmp_path, [np.zeros((4, 4), np.uint8)] * 3, np.tile(np.eye(3), (2, 1, 1)))


def test_make_sequence_writes_the_three_steps_sequence_once(tmp_path):
    photo = cv2.cvtColor(smooth_texture(600, 900, seed=3), cv2.COLOR_GRAY2BGR)  # a colour photograph
    config = SequenceConfig(n_views=3)
    views, to_source = homography_sequence(source_image(photo, config.long_side), config, np.random.default_rng(7))
    write_sequence(tmp_path / "by_steps", views, to_source)
    reads = []

    def read():
        reads.append(1)
        return photo

    folder = make_sequence(tmp_path / "made", read, np.random.default_rng(7), config)
    assert folder == tmp_path / "made" and len(reads) == 1
    for name in ("img1.png", "img2.png", "img3.png", "H1to2p", "H1to3p"):
        assert (folder / name).read_bytes() == (tmp_path / "by_steps" / name).read_bytes(), name
    assert make_sequence(folder, read, np.random.default_rng(8), config) == folder and len(reads) == 1  # kept

