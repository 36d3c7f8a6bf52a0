"""The simulated D415's depth noise: the bare model unchanged, outliers and stereo shadow on in a cell's defaults."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from flgd.config import ConfigError, SimConfig, config_from_dict, load_config
from sim_cell import camera as simcam
from sim_cell.camera import OUTLIER_SPAN, STEREO_BASELINE, DepthNoise, add_depth_noise

REPO = Path(__file__).resolve().parents[1]
FX = 615.0
QUIET = dict(std_at_half_metre=0.0, dropout_rate=0.0, edge_hole_rate=0.0)   # no noise but the knob under test


def old_add_depth_noise(depth, rng, noise=DepthNoise()):
    """A copy of add_depth_noise as it was before the outlier and stereo-shadow knobs."""
    z = depth.astype(np.float64)
    valid = z > 0
    std = noise.std_at_half_metre * (z / 0.5) ** 2
    out = z + rng.standard_normal(z.shape) * std
    step = np.zeros_like(z, dtype=bool)
    dz_x = np.abs(np.diff(z, axis=1)) > noise.edge_step
    dz_y = np.abs(np.diff(z, axis=0)) > noise.edge_step
    step[:, 1:] |= dz_x
    step[:, :-1] |= dz_x
    step[1:, :] |= dz_y
    step[:-1, :] |= dz_y
    holes = step & (rng.random(z.shape) < noise.edge_hole_rate)
    drops = rng.random(z.shape) < noise.dropout_rate
    out[~valid | holes | drops] = 0.0
    return out


def scene() -> np.ndarray:
    """A sloping table with boxes of several heights and a patch without readings: edges, holes, depth range."""
    h, w = 120, 160
    z = np.tile(np.linspace(0.68, 0.72, h, dtype=np.float32)[:, None], (1, w))
    z[20:50, 30:70] = 0.64
    z[60:100, 90:140] = 0.60
    z[70:80, 10:25] = 0.67
    z[100:110, 40:60] = 0.0
    return z


def flat_table_with_box(z_table=0.70, z_box=0.65):
    z = np.full((60, 200), z_table, dtype=np.float32)
    z[20:40, 80:120] = z_box
    return z


def test_the_default_model_is_bit_for_bit_the_old_one_and_draws_the_same_numbers():
    z = scene()
    for noise in (DepthNoise(), DepthNoise(std_at_half_metre=0.002, dropout_rate=0.01, edge_hole_rate=0.7)):
        off = dataclasses.replace(noise, outlier_rate=0.0, stereo_shadow=False)
        ref_rng = np.random.default_rng(11)
        expected = old_add_depth_noise(z, ref_rng, noise)
        for kwargs in ({}, {"fx": FX}):
            for model in (noise, off):
                rng = np.random.default_rng(11)
                got = add_depth_noise(z, rng, model, **kwargs)
                assert got.dtype == expected.dtype and np.array_equal(got, expected)
                assert rng.bit_generator.state == ref_rng.bit_generator.state   # no extra draws
    assert DepthNoise().outlier_rate == 0.0 and DepthNoise().stereo_shadow is False


def test_a_cell_config_without_depth_keys_renders_like_a_d415_not_kinder():
    """The config's default cell has the two parts of a D415's depth the bare model leaves out (docs/training-and-evaluation.md)."""
    noise = DepthNoise.from_config(SimConfig())
    assert noise == dataclasses.replace(DepthNoise(), outlier_rate=0.003, stereo_shadow=True)
    z = scene()
    bare = add_depth_noise(z, np.random.default_rng(2), DepthNoise(), fx=FX)
    cell = add_depth_noise(z, np.random.default_rng(2), noise, fx=FX)
    assert np.count_nonzero(cell == 0) > np.count_nonzero(bare == 0)           # the shadow beside the raised part
    assert np.count_nonzero(np.abs(cell - bare)[(cell != 0) & (bare != 0)] > 0.005) > 0   # gross outliers


def test_the_knobs_draw_after_the_old_draws_and_leave_them_unchanged():
    z = scene()
    expected = old_add_depth_noise(z, np.random.default_rng(5))
    # outliers: the same pixels are missing, and all but the outliers read exactly as before
    got = add_depth_noise(z, np.random.default_rng(5), DepthNoise(outlier_rate=0.05))
    assert np.array_equal(got == 0, expected == 0)
    changed = got != expected
    share = np.count_nonzero(changed) / np.count_nonzero(expected)
    assert 0.03 < share < 0.07
    assert np.all(np.abs(got - expected)[changed] <= OUTLIER_SPAN + 1e-12)
    # shadow: no draws of its own; it only removes readings
    rng = np.random.default_rng(5)
    shadowed = add_depth_noise(z, rng, DepthNoise(stereo_shadow=True), fx=FX)
    ref_rng = np.random.default_rng(5)
    old_add_depth_noise(z, ref_rng)
    assert rng.bit_generator.state == ref_rng.bit_generator.state
    kept = shadowed != 0
    assert np.array_equal(shadowed[kept], expected[kept]) and np.count_nonzero(~kept & (expected != 0)) > 0


def test_outliers_hit_the_configured_share_of_pixels_within_outlier_span():
    z = np.full((200, 300), 0.70, dtype=np.float32)
    z[:10, :10] = 0.0                                       # no reading: stays without one
    share = 0.02
    out = add_depth_noise(z, np.random.default_rng(3), DepthNoise(outlier_rate=share, **QUIET))
    valid = z > 0
    n = np.count_nonzero(valid)
    err = out[valid] - z[valid].astype(np.float64)
    assert np.all(out[~valid] == 0)
    assert np.all(np.abs(err) <= OUTLIER_SPAN)
    # any error at all: exactly the outliers, since nothing else perturbs the depth
    hit = np.count_nonzero(err != 0)
    assert abs(hit - n * share) < 4 * np.sqrt(n * share * (1 - share))
    # off by more than 5 mm: the outliers whose uniform error exceeds 5 mm, (1 - 5 mm / span) of them
    gross = share * (1 - 0.005 / OUTLIER_SPAN)
    assert abs(np.count_nonzero(np.abs(err) > 0.005) - n * gross) < 4 * np.sqrt(n * gross * (1 - gross))
    # they spread over the whole span, both ways
    assert np.abs(err).max() > 0.9 * OUTLIER_SPAN and err.min() < 0 < err.max()
    # off: no error anywhere
    assert np.array_equal(add_depth_noise(z, np.random.default_rng(3), DepthNoise(**QUIET)), np.where(valid, z, 0))


def test_the_stereo_shadow_is_a_band_left_of_a_raised_box_as_wide_as_the_disparity_step():
    z = flat_table_with_box(0.70, 0.65)
    width = round(FX * STEREO_BASELINE * (1 / 0.65 - 1 / 0.70))   # 3.72 px -> 4
    out = add_depth_noise(z, np.random.default_rng(0), DepthNoise(stereo_shadow=True, **QUIET), fx=FX)
    zero = out == 0
    rows, cols = np.nonzero(zero)
    assert rows.size > 0
    # only in the box's rows, only on the table left of the box (the right imager sits at +x), never on the box
    assert set(rows.tolist()) == set(range(20, 40))
    assert cols.max() == 79
    band = zero[20:40, :80].sum(axis=1)
    assert np.all(band == band[0]) and abs(int(band[0]) - width) <= 1
    assert np.all(zero[20:40, 80 - band[0]:80])          # one contiguous band next to the box
    assert not zero[20:40, 80:].any()                   # not on the box, not right of it
    assert not zero[:20].any() and not zero[40:].any()  # nor on the table elsewhere
    # the band is exactly what the formula gives: d_box - d_table - 0.5 px, floored
    assert band[0] == int(np.floor(FX * STEREO_BASELINE * (1 / 0.65 - 1 / 0.70) - 0.5))
    # off: no zeros; on without fx: refused
    assert not (add_depth_noise(z, np.random.default_rng(0), DepthNoise(**QUIET), fx=FX) == 0).any()
    with pytest.raises(ValueError, match="fx"):
        add_depth_noise(z, np.random.default_rng(0), DepthNoise(stereo_shadow=True, **QUIET))


def test_the_stereo_shadow_widens_with_the_step_and_ignores_pixels_without_a_reading():
    z = flat_table_with_box(0.70, 0.55)
    width = FX * STEREO_BASELINE * (1 / 0.55 - 1 / 0.70)           # 13.2 px
    hidden = simcam.stereo_shadow(z, FX)
    assert abs(int(hidden[30].sum()) - round(width)) <= 1 and not hidden[30, 80:].any()
    z[20:40, 60:80] = 0.0                                           # no reading left of the box already
    hidden = simcam.stereo_shadow(z, FX)
    assert not hidden[20:40, 60:80].any() and hidden[30].sum() == 0
    z[30, 100] = 0.0                                                # a hole in the box hides nothing
    assert np.array_equal(simcam.stereo_shadow(z, FX), hidden)


def test_sim_config_accepts_the_new_keys_and_refuses_a_negative_outlier_share():
    cfg = config_from_dict({"sim": {"depth_outliers": 0.01, "stereo_shadow": True}})
    assert cfg.sim.depth_outliers == 0.01 and cfg.sim.stereo_shadow is True
    noise = DepthNoise.from_config(cfg.sim)
    assert noise.outlier_rate == 0.01 and noise.stereo_shadow is True
    bare = config_from_dict({"sim": {"depth_outliers": 0, "stereo_shadow": False}})
    assert DepthNoise.from_config(bare.sim) == DepthNoise()          # the bare model stays one config away
    with pytest.raises(ConfigError, match=r"sim\.depth_outliers"):
        config_from_dict({"sim": {"depth_outliers": -0.01}})
    with pytest.raises(ConfigError, match=r"sim\.depth_outliers"):
        config_from_dict({"sim": {"depth_outliers": 0.5}})


def test_the_sim_cell_passes_its_fx_so_a_block_casts_a_stereo_shadow_in_its_frames():
    from sim_cell.cell import SimCell
    from sim_cell.objects import ObjectSpec

    base = load_config(REPO / "cell_config" / "sim.yaml")
    frames = {}
    for shadow in (False, True):
        sim = dataclasses.replace(base.sim, objects=0, domain_randomization=False, depth_noise=True,
                                  depth_noise_std=0.0, depth_dropout=0.0, depth_edge_holes=0.0,
                                  stereo_shadow=shadow)
        cell = SimCell(dataclasses.replace(base, sim=sim))
        try:
            cell.add_object(ObjectSpec(shape="bar", size=(0.06, 0.04, 0.05), color=(0.9, 0.2, 0.1),
                                       position=(-0.55, 0.0, 0.026), orientation=p.getQuaternionFromEuler([0, 0, 0])))
            frames[shadow] = cell.capture_labelled()
        finally:
            cell.close()
    (plain, labels), (shadowed, _) = frames[False], frames[True]
    lost = (plain.depth > 0) & (shadowed.depth == 0)
    assert np.count_nonzero(lost) > 20
    assert np.array_equal(shadowed.depth[~lost], plain.depth[~lost])
    # every lost pixel is just left of the block in its row
    on_block = labels > 0
    for r, c in zip(*np.nonzero(lost)):
        assert not on_block[r, c] and on_block[r, c + 1:c + 12].any()
