"""Cameras for a user's sequence: framing a box, orbiting it, and camera files in and out."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from pipeline.camera import camera_from_pose, framing_cameras, read_camera_file, write_camera_file
from pipeline.particles import Z_UP_TO_Y_UP

LO, HI = np.array([-0.3, 0.0, -1.2]), np.array([0.9, 0.5, 0.4])


def _corners(lo, hi) -> np.ndarray:
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


@pytest.mark.parametrize("orbit, size", [(False, (512, 512)), (False, (640, 360)), (True, (360, 640))])
def test_framing_keeps_the_whole_box_in_view(orbit, size):
    cams = framing_cameras(LO, HI, *size, count=12, orbit=orbit)
    for cam in cams:
        col, row, depth = cam.project(cam.to_view(_corners(LO, HI)))
        assert np.all(depth > 0)
        assert np.all((col > 0) & (col < cam.width) & (row > 0) & (row < cam.height))
        # and fills a fair part of it: the box is not a speck in the middle
        assert max(np.ptp(col) / cam.width, np.ptp(row) / cam.height) > 0.6
    eyes = np.array([c.eye for c in cams])
    centre = 0.5 * (LO + HI)
    distances = np.linalg.norm(eyes - centre, axis=1)
    np.testing.assert_allclose(distances, distances[0], rtol=1e-9)
    azimuths = np.unique(np.round(np.degrees(np.arctan2(eyes[:, 0] - centre[0], eyes[:, 2] - centre[2])), 6))
    assert len(azimuths) == (12 if orbit else 1)
    assert all(eye[1] > centre[1] for eye in eyes), "seen from above"


def test_blender_pose_and_lens_give_the_pinhole_they_describe():
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 5.0)  # at z = 5 looking down -Z, as Blender's default camera axes
    cam = camera_from_pose(pose, 50.0, 36.0, 640, 480)
    half_w = math.atan(18.0 / 50.0)  # the 36 mm sensor spans the wider side
    assert cam.fov_y_deg == pytest.approx(math.degrees(2 * math.atan(math.tan(half_w) * 480 / 640)))
    col, row, depth = cam.project(cam.to_view(np.array([[5 * math.tan(half_w), 0.0, 0.0]])))
    assert col[0] == pytest.approx(640) and row[0] == pytest.approx(240) and depth[0] == pytest.approx(5)


@pytest.mark.parametrize("up", ["y", "z"])
def test_camera_file_round_trip(tmp_path, up):
    cams = framing_cameras(LO, HI, 320, 200, count=5, orbit=True)
    frames = [3, 4, 5, 7, 8]
    write_camera_file(tmp_path / "camera.json", cams, frames, up=up)
    body = json.loads((tmp_path / "camera.json").read_text())
    assert body["up"] == up and [e["frame"] for e in body["frames"]] == frames
    if up == "z":  # the file's world is Z-up: the eyes' heights are in their third coordinate
        pose = np.asarray(body["frames"][0]["camera_to_world"])
        np.testing.assert_allclose(Z_UP_TO_Y_UP @ pose[:3, 3], cams[0].eye, atol=1e-8)
    back = read_camera_file(tmp_path / "camera.json", frames, 320, 200)
    for a, b in zip(cams, back, strict=True):
        np.testing.assert_allclose(b.view, a.view, atol=1e-8)
        assert b.fov_y_deg == pytest.approx(a.fov_y_deg, rel=1e-6)


def test_one_camera_serves_every_frame_and_missing_frames_are_named(tmp_path):
    cams = framing_cameras(LO, HI, 64, 64, count=1)
    write_camera_file(tmp_path / "one.json", cams, [1])
    assert len(read_camera_file(tmp_path / "one.json", [1, 2, 3], 64, 64)) == 3
    write_camera_file(tmp_path / "two.json", cams * 2, [1, 2])
    with pytest.raises(ValueError, match=r"two\.json: no camera for frames \[3\]"):
        read_camera_file(tmp_path / "two.json", [1, 2, 3], 64, 64)
    (tmp_path / "bad.json").write_text(json.dumps({"frames": [{"frame": 1, "camera_to_world": [[1, 0], [0, 1]],
                                                               "focal_length_mm": 35}]}))
    with pytest.raises(ValueError, match=r"bad\.json: frame 1: camera_to_world must be a finite 4x4"):
        read_camera_file(tmp_path / "bad.json", [1], 64, 64)
    (tmp_path / "cut.json").write_text('{"frames": [')
    with pytest.raises(ValueError, match=r"cut\.json"):
        read_camera_file(tmp_path / "cut.json", [1], 64, 64)
