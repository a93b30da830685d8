"""Candidate edges between keypoints of different views, pose-free: descriptor neighbours,
two-view geometric verification and geometry-guided candidates, with the features the
learned edge scorer reads.

- :mod:`.candidates`: the candidates of a window and their features;
- :mod:`.verify`: per view pair, a homography / fundamental (or essential) matrix fitted by OpenCV USAC;
- :mod:`.head`: a model's edge head at inference.
"""
