"""The flatness measure of ``flgd bench qmap_top``."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.qmap_top import top_shares


def test_a_peaked_map_has_a_small_top_and_a_flat_one_a_large_top():
    mask = np.zeros((8, 8), dtype=bool)
    mask[2:6, 2:6] = True                       # 16 object pixels x 2 rotations = 32 values
    peaked = np.zeros((2, 8, 8))
    peaked[0, 3, 3] = 2.0                       # one clear best grasp
    peaked[1, 4, 4] = 1.97                      # a second one within 0.05
    top, shares = top_shares(peaked, mask, (0.02, 0.05, 0.10))
    assert top == 2.0
    assert shares == [1 / 32, 2 / 32, 2 / 32]

    flat = np.full((2, 8, 8), 1.95)
    flat[0, 3, 3] = 2.0
    top, shares = top_shares(flat, mask, (0.02, 0.05, 0.10))
    assert top == 2.0
    assert shares == [1 / 32, 1.0, 1.0]


def test_values_off_the_mask_are_ignored():
    mask = np.zeros((4, 4), dtype=bool)
    mask[0, 0] = mask[0, 1] = True
    q = np.full((1, 4, 4), 9.0)                 # off the mask: higher than anything on it
    q[0, 0, 0], q[0, 0, 1] = 1.0, 0.5
    top, shares = top_shares(q, mask, (0.1,))
    assert top == 1.0 and shares == [0.5]


def test_bad_shapes_and_an_empty_mask_are_refused():
    with pytest.raises(ValueError, match="expected"):
        top_shares(np.zeros((4, 4)), np.ones((4, 4), dtype=bool))
    with pytest.raises(ValueError, match="empty"):
        top_shares(np.zeros((1, 4, 4)), np.zeros((4, 4), dtype=bool))


@pytest.mark.slow
def test_the_benchmark_measures_the_shipped_policy_on_sim_clutter_and_names_a_bad_policy_file(tmp_path, capsys):
    from benchmarks import qmap_top

    repo = qmap_top.REPO
    shipped = str(repo / "policies" / "flg-sim.safetensors")
    assert qmap_top.main(["--policy", shipped, "--scenes", "1", "--count", "3"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {shipped} |")]
    assert len(rows) == 1
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    top, median = float(cells[1]), float(cells[2])
    shares = [float(c.rstrip(" %")) for c in cells[3:]]
    assert top > median                          # a trained policy prefers some grasps over others
    assert shares == sorted(shares) and shares[-1] < 100.0

    bad = tmp_path / "not-a-policy.safetensors"
    bad.write_bytes(b"no header")
    assert qmap_top.main(["--policy", str(bad)]) == 1
    assert str(bad) in capsys.readouterr().err
