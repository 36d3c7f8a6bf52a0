"""``flgd bench depth_model``: what it reads off a pair of renders, and the training cell against a D415."""

import json

import numpy as np

from benchmarks import depth_model
from benchmarks.depth_model import depth_stats, stereo_rms


def test_stereo_rms_is_intels_formula_at_the_cells_distance():
    # 0.7^2 m^2 * 0.08 px / (615 px * 0.055 m)
    assert abs(stereo_rms(0.70, 615.0) - 0.49 * 0.08 / (615.0 * 0.055)) < 1e-12
    assert abs(1000 * stereo_rms(0.70, depth_model.D415_HD_FX) - 0.71) < 0.01   # 1280x720, 65 deg HFOV


def test_depth_stats_separate_noise_gross_errors_holes_and_the_band_beside_objects():
    rng = np.random.default_rng(0)
    clean = np.full((200, 200), 0.70)
    labels = np.zeros((200, 200), np.int32)
    clean[80:120, 80:120] = 0.65
    labels[80:120, 80:120] = 7
    noisy = clean + rng.normal(0, 0.002, clean.shape)
    noisy[10, 10:20] += 0.025                       # ten gross errors on the flat table
    noisy[:30, 150:] = 0.0                          # 1,500 flat-table pixels without a reading
    noisy[80:120, 76:80] = 0.0                      # a 4 px hole band beside the block
    s = depth_stats(noisy, clean, labels)
    assert abs(s["table_z_m"] - 0.70) < 1e-9
    assert abs(s["flat_rms_m"] - 0.002) < 0.0002    # the gross errors do not count as noise
    assert s["flat_gross_share"] * (s["flat_fill_rate"] * s["flat_pixels"]) == 10
    assert abs((1 - s["flat_fill_rate"]) * s["flat_pixels"] - 1500) < 0.5
    beside = (52 * 52 - 40 * 40)                    # the 6 px ring round the block
    assert abs(s["beside_objects_missing_share"] - 160 / beside) < 1e-9
    assert s["object_missing_share"] == 0.0


def test_the_training_cell_is_no_kinder_than_intels_formula_and_the_bare_model_has_no_gross_errors(tmp_path):
    out = tmp_path / "d.json"
    assert depth_model.main(["--scenes", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["medians"]["flat_rms_m"] > r["d415"]["rms_m_at_config_fx"]
    assert 0.001 < r["medians"]["flat_gross_share"] < 0.003          # 0.3 % outliers, 2/3 of them beyond 10 mm
    assert r["medians"]["beside_objects_missing_share"] > 0.02        # edge holes and the stereo shadow
    bare = tmp_path / "bare.yaml"
    text = (depth_model.DEFAULT_CONFIG).read_text().replace("  depth_noise: true\n",
                                                           "  depth_noise: true\n  depth_outliers: 0\n")
    text = text.replace("../policies/", str(depth_model.REPO / "policies") + "/")
    bare.write_text(text)
    assert depth_model.main(["--config", str(bare), "--scenes", "1", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["medians"]["flat_gross_share"] < 1e-4   # a 5-sigma tail pixel at most


def test_a_config_without_depth_noise_is_refused(tmp_path, capsys):
    cfg = tmp_path / "quiet.yaml"
    cfg.write_text("backend: sim\nsim:\n  depth_noise: false\n")
    assert depth_model.main(["--config", str(cfg)]) == 1
    assert "sim.depth_noise is off" in capsys.readouterr().err
