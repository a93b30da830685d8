"""Data for training and evaluation: real scenes with ground truth, and generated ones.

- :mod:`.scenes`: the scene folders of ``shared/data`` (images, homographies or poses);
- :mod:`.labels`: ground truth of a window (homography, pose and photometric labels);
- :mod:`.convert`: problem files from scenes; :mod:`.plane_sweep`: depth by photo-consistency;
- :mod:`.synthetic`, :mod:`.permutation_noise`, :mod:`.homography_sequence`: generated data.
"""
