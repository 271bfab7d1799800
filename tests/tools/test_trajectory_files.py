"""TUM and KITTI files: exact nanosecond stamps, poses back to centimetre and 1e-6 rad, pairing
by stamp, and the typed errors on malformed lines."""

import numpy as np
import pytest

from common.errors import ExportError
from common.trajectory import (
    pair_by_stamp,
    read_kitti,
    read_tum,
    stamp_ns,
    stamp_text,
    write_kitti,
    write_tum,
)


def test_stamps_are_exact():
    for t in (0, 7, 999_999_999, 2_600_000_000_700_000_000, -1_500_000_001):
        assert stamp_ns(stamp_text(t)) == t
    assert stamp_ns("12.5") == 12_500_000_000 and stamp_ns("3") == 3_000_000_000


def test_tum_and_kitti_round_trip(tmp_path, rng):
    t = 2_600_000_000_000_000_000 + np.arange(50) * 100_000_000
    poses = np.stack([rng.uniform(-2e3, 2e3, 50), rng.uniform(-2e3, 2e3, 50),
                      rng.uniform(-np.pi, np.pi, 50)], axis=1)
    poses[7] = np.nan  # no estimate at frame 7: left out of TUM
    assert write_tum(tmp_path / "a.tum", t, poses) == 49
    t_back, p_back = read_tum(tmp_path / "a.tum")
    keep = np.arange(50) != 7
    assert np.array_equal(t_back, t[keep])
    assert np.abs(p_back[:, :2] - poses[keep, :2]).max() <= 5e-5
    assert np.abs(np.angle(np.exp(1j * (p_back[:, 2] - poses[keep, 2])))).max() < 1e-6
    with pytest.raises(ExportError):
        write_kitti(tmp_path / "a.kitti", poses)  # KITTI rows have no stamps to skip by
    write_kitti(tmp_path / "a.kitti", poses[keep])
    k = read_kitti(tmp_path / "a.kitti")
    assert np.abs(k[:, :2] - poses[keep, :2]).max() < 1e-3
    assert np.abs(np.angle(np.exp(1j * (k[:, 2] - poses[keep, 2])))).max() < 1e-6


def test_pairing_by_stamp():
    a = np.array([10, 20, 30, 40]) * 1_000_000
    b = np.array([41, 9, 31]) * 1_000_000 + 300_000
    ia, ib = pair_by_stamp(a, b, max_diff_ns=2_000_000)
    assert ia.tolist() == [0, 2, 3] and ib.tolist() == [1, 2, 0]


def test_malformed_lines_raise_naming_the_line(tmp_path):
    (tmp_path / "bad.tum").write_text("1.0 2 3 0 0 0 0 1\n1.1 2 3\n")
    with pytest.raises(ExportError, match="bad.tum:2"):
        read_tum(tmp_path / "bad.tum")
    (tmp_path / "bad.kitti").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(ExportError, match="12 numbers"):
        read_kitti(tmp_path / "bad.kitti")
