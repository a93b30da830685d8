"""Tests of gcn_match_ros.track_image: views side by side, tracks in their colours."""
import numpy as np
import pytest

from gcn_match_ros.track_image import GAP_PX, TITLE_PX, draw_tracks, track_color


def test_views_side_by_side_with_each_track_in_its_colour():
    images = [np.full((100, 200), 200, np.uint8), None]
    kps = [np.array([[50.0, 50.0], [150.0, 20.0]]), np.array([[10.0, 10.0], [60.0, 50.0], [5.0, 90.0]])]
    track = np.array([0, -1, -1, 0, -1])
    out = draw_tracks(images, kps, track, image_sizes=[None, (100, 100)], height=100, title="w")
    assert out.shape == (TITLE_PX + 100, 200 + GAP_PX + 100, 3)
    # the track's members are dots of its colour, at their places in their views
    assert tuple(out[TITLE_PX + 50, 50]) == track_color(0)
    assert tuple(out[TITLE_PX + 50, 200 + GAP_PX + 60]) == track_color(0)
    # keypoints in no track are grey; the blank view is dark grey
    assert tuple(out[TITLE_PX + 20, 150]) == (170, 170, 170)
    assert tuple(out[TITLE_PX + 2, 200 + GAP_PX + 90]) == (40, 40, 40)
    assert len({track_color(t) for t in range(20)}) == 20


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="images"):
        draw_tracks([None], [np.zeros((1, 2)), np.zeros((1, 2))], np.zeros(2))
    with pytest.raises(ValueError, match="track"):
        draw_tracks([None], [np.zeros((2, 2))], np.zeros(3))
