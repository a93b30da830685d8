"""Tests of gcn_match_ros.data.scenes: the Oxford, Strecha and Middlebury scene readers and their errors."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from gcn_match_ros.data.scenes import DatasetError, load_scene, read_middlebury, read_oxford, read_strecha

from conftest import (SHARED_DATA as DATA, blurred_noise_image as _texture, look_at, need_shared as _need,
                      rigid_motion_2d as _similarity, write_oxford_like_scene as _oxford_like)


def test_read_oxford(tmp_path: Path) -> None:
    H = _similarity(0, 6, 4)
    _oxford_like(tmp_path / "oxford" / "toy", H, n=3)
    scene = read_oxford(tmp_path / "oxford" / "toy")
    assert scene.name == "oxford_toy" and scene.kind == "homography" and scene.n_views == 3
    assert scene.view_labels == ("1", "2", "3")
    np.testing.assert_array_equal(scene.image_sizes, [[240, 180]] * 3)
    np.testing.assert_allclose(scene.homographies[2], np.linalg.inv(H @ H))


@pytest.mark.parametrize("content, message", [
    ("1 0 0\n0 1 0\n0 0", "expected 9"),
    ("1 0 0\n0 1 x\n0 0 1", "expected 9"),
    ("1 0 0\n1 0 0\n0 0 1", "singular"),
])
def test_read_oxford_rejects_bad_homography(tmp_path: Path, content: str, message: str) -> None:
    _oxford_like(tmp_path / "toy", _similarity(0, 6, 4))
    (tmp_path / "toy" / "H1to2p").write_text(content)
    with pytest.raises(DatasetError, match=message) as err:
        read_oxford(tmp_path / "toy")
    assert "H1to2p" in str(err.value)


def test_read_oxford_missing_homography(tmp_path: Path) -> None:
    _oxford_like(tmp_path / "toy", _similarity(0, 6, 4))
    (tmp_path / "toy" / "H1to2p").unlink()
    with pytest.raises(DatasetError, match="H1to2p"):
        read_oxford(tmp_path / "toy")


def _strecha_like(folder: Path, n: int = 3) -> None:
    folder.mkdir(parents=True)
    for v in range(n):
        cv2.imwrite(str(folder / f"{v:04d}.png"), _texture(seed=v))
        R, t = look_at(np.array([v, -10.0, 0.0]), np.zeros(3))
        (folder / f"{v:04d}.cam").write_text(
            "# toy\nK 500 0 120 0 500 90 0 0 1\n"
            f"R {' '.join(map(str, R.ravel()))}\nt {' '.join(map(str, t))}\n")


def test_read_strecha(tmp_path: Path) -> None:
    _strecha_like(tmp_path / "strecha" / "toy")
    scene = load_scene(tmp_path, "strecha/toy")
    assert scene.name == "strecha_toy" and scene.kind == "poses" and scene.n_views == 3
    assert scene.K.shape == (3, 3, 3) and scene.t.shape == (3, 3)
    C = -np.einsum("vji,vj->vi", scene.R, scene.t)
    np.testing.assert_allclose(C[2], [2, -10, 0], atol=1e-9)


@pytest.mark.parametrize("bad, message", [
    ("K 500 0 120 0 500 90 0 0", "K: expected 9"),
    ("R 1 0 0 0 1 0 0 0 2", "not a rotation"),
    ("t 1 2", "t: expected 3"),
    ("Q 1 2 3", "unexpected line"),
])
def test_read_strecha_rejects_bad_cam(tmp_path: Path, bad: str, message: str) -> None:
    _strecha_like(tmp_path / "toy")
    cam = tmp_path / "toy" / "0001.cam"
    lines = cam.read_text().splitlines()
    key = bad.split()[0]
    lines = [bad if ln.startswith(key + " ") else ln for ln in lines] + ([bad] if key == "Q" else [])
    cam.write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=message) as err:
        read_strecha(tmp_path / "toy")
    assert "0001.cam" in str(err.value)


def test_read_strecha_missing_line(tmp_path: Path) -> None:
    _strecha_like(tmp_path / "toy")
    cam = tmp_path / "toy" / "0002.cam"
    cam.write_text("\n".join(ln for ln in cam.read_text().splitlines() if not ln.startswith("t ")))
    with pytest.raises(DatasetError, match=r"0002\.cam: missing line\(s\) t"):
        read_strecha(tmp_path / "toy")


def test_read_middlebury_rejects_bad_par(tmp_path: Path) -> None:
    folder = tmp_path / "middlebury_toy"
    folder.mkdir()
    row = "1500 0 300 0 1500 240 0 0 1 1 0 0 0 1 0 0 0 1 0 0 1"
    for v in (1, 2):
        cv2.imwrite(str(folder / f"toy{v:04d}.png"), _texture(seed=v))
    par = folder / "templeSR_par.txt"
    par.write_text(f"2\ntoy0001.png {row}\ntoy0002.png {row}\n")
    assert read_middlebury(folder).view_labels == ("1", "2")
    par.write_text(f"3\ntoy0001.png {row}\ntoy0002.png {row}\n")
    with pytest.raises(DatasetError, match="templeSR_par.txt: header says 3"):
        read_middlebury(folder)
    par.write_text(f"2\ntoy0001.png {row}\ntoy0002.png {row[:-2]}\n")
    with pytest.raises(DatasetError, match="templeSR_par.txt: image toy0002.png: expected 21"):
        read_middlebury(folder)


def test_load_scene_errors(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no such scene folder"):
        load_scene(tmp_path, "oxford/nowhere")
    with pytest.raises(DatasetError, match="unknown dataset"):
        load_scene(tmp_path, "kitti/00")


def test_real_readers() -> None:
    fountain = load_scene(_need(DATA), "strecha/fountain-P11")
    assert fountain.n_views == 11 and fountain.image_sizes.tolist() == [[768, 512]] * 11
    temple = load_scene(DATA, "middlebury_temple")
    assert temple.n_views == 6 and temple.view_labels[0] == "6"
