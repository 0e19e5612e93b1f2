"""EXR frames round-trip exactly with their names; damaged files are named in the error."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.cache import CacheError
from pipeline.exr import read_exr, write_exr


def test_float32_round_trip_is_exact_with_names(tmp_path):
    rng = np.random.default_rng(0)
    names = ["R", "G", "B", "A", "Z", "N.X", "N.Y", "N.Z", "target.N.X", "bilateral.Z", "thickness"]
    channels = {n: rng.normal(size=(33, 47)).astype(np.float32) * 1e3 for n in names}
    channels["Z"][0, 0] = np.float32(1e-30)
    write_exr(tmp_path / "frame_0001.exr", channels)
    back = read_exr(tmp_path / "frame_0001.exr")
    assert sorted(back) == sorted(names)
    for n in names:
        np.testing.assert_array_equal(back[n], channels[n])
        assert back[n].dtype == np.float32


def test_truncated_exr_is_named(tmp_path):
    write_exr(tmp_path / "f.exr", {"Z": np.ones((16, 16), np.float32)})
    raw = (tmp_path / "f.exr").read_bytes()
    (tmp_path / "f.exr").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(CacheError, match="f.exr"):
        read_exr(tmp_path / "f.exr")


def test_missing_channel_is_named(tmp_path):
    write_exr(tmp_path / "f.exr", {"Z": np.ones((4, 4), np.float32)})
    with pytest.raises(CacheError, match="N.X"):
        read_exr(tmp_path / "f.exr", ["N.X"])
