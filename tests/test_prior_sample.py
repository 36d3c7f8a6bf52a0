"""The prior sample file: what `flgd prior-sample` writes is what the learner gets back, a file that does not fit
is refused naming the file, key and value (and the daemon does not start on it), and the shipped one loads."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flgd.actions import Action
from flgd.config import ConfigError, config_from_dict, load_config
from flgd.learning.prior_sample import PriorSampleError, load_prior_sample, write_prior_sample
from flgd.learning.replay import Transition, state_key
from flgd.perception import Heightmaps

REPO = Path(__file__).resolve().parents[1]
N = 32


def scene(seed: int) -> Heightmaps:
    rng = np.random.default_rng(seed)
    h = np.zeros((N, N), np.float32)
    h[4:10, 5:12] = rng.uniform(0.02, 0.05)
    color = rng.integers(0, 255, (N, N, 3)).astype(np.uint8)
    return Heightmaps(color, h)


def chain() -> list[Transition]:
    """Three transitions of one episode (s' of each is s of the next) and one that ends it."""
    s = [scene(k) for k in range(4)]
    return [Transition(s[0], Action("grasp", 5, 6, 3), 1.0, s[1], False),
            Transition(s[1], Action("push", 20, 7, 15), 0.5, s[2], False),
            Transition(s[2], Action("shift", 1, 30, 0), 0.0, s[3], False),
            Transition(s[3], Action("grasp", 31, 0, 8), 1.0, None, True)]


def test_a_written_sample_loads_back_as_the_same_transitions_with_shared_states_stored_once(tmp_path):
    path = tmp_path / "prior.npz"
    states = write_prior_sample(path, chain(), {"from": "test"})
    assert states == 4
    prior = load_prior_sample(path, 16, (N, N))
    assert prior.source == {"from": "test"} and len(prior) == 4
    for got, want in zip(prior.transitions, chain()):
        assert got.action == want.action and got.reward == want.reward and got.done == want.done
        assert np.array_equal(got.state.color, want.state.color)
        assert np.allclose(got.state.height, want.state.height, atol=1e-4)  # float16 heights
        if want.next_state is None:
            assert got.next_state is None and got.next_key is None
        else:
            assert got.next_key == state_key(got.next_state)  # the learner's argmax cache key
    assert prior.transitions[0].next_state is prior.transitions[1].state


def _rewrite(path: Path, **changes) -> None:
    with np.load(path, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for key, value in changes.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    with open(path, "wb") as f:
        np.savez(f, **arrays)


@pytest.mark.parametrize("changes, needle", [
    ({"format": np.array("flgd-prior-sample/9")}, "format is 'flgd-prior-sample/9'"),
    ({"reward": None}, "missing key(s) reward"),
    ({"rotations": np.array(8, np.int32)}, "rotations is 8, expected 16"),
    ({"row": np.array([5, 20, 1, 32], np.int32)}, "row[3] is 32, expected 0..31"),
    ({"primitive": np.array([0, 1, 7, 0], np.int8)}, "primitive[2] is 7"),
    ({"next_state": np.array([1, 2, 9, -1])}, "next_state[2] is 9, expected -1..3"),
    ({"done": np.array([False, False, False, False])}, "transition 3 has no next_state but done is false"),
    ({"reward": np.array([1, np.nan, 0, 1], np.float32)}, "reward[1] is nan"),
    ({"state": np.array([0, 1, 2])}, "key next_state has shape (4,), expected (3,)"),
    ({"states": np.zeros(10, np.uint8)}, "state_offsets do not cut 'states'"),
    ({"primitive": np.array(["grasp", "push", "shift", "grasp"])}, "key primitive holds <U5, expected integers"),
    ({"done": np.array([0.0, 0.0, 0.0, 1.0])}, "key done holds float64, expected booleans"),
])
def test_a_sample_that_does_not_fit_is_refused_naming_the_file_and_the_key(tmp_path, changes, needle):
    path = tmp_path / "prior.npz"
    write_prior_sample(path, chain(), {})
    _rewrite(path, **changes)
    with pytest.raises(PriorSampleError) as err:
        load_prior_sample(path, 16, (N, N))
    assert str(path) in str(err.value) and needle in str(err.value)


def test_a_corrupt_state_a_wrong_heightmap_size_and_a_file_that_is_no_sample_are_refused(tmp_path):
    path = tmp_path / "prior.npz"
    write_prior_sample(path, chain(), {})
    with pytest.raises(PriorSampleError, match=r"state 0 is a 32x32 heightmap, expected 224x224"):
        load_prior_sample(path, 16, (224, 224))
    with np.load(path, allow_pickle=False) as data:
        blob = data["states"].copy()
    blob[20:40] = 0  # inside the first state's zlib stream
    _rewrite(path, states=blob)
    with pytest.raises(PriorSampleError, match=r"state 0 cannot be unpacked"):
        load_prior_sample(path, 16, (N, N))
    text = tmp_path / "notes.npz"
    text.write_text("not a zip archive")
    with pytest.raises(PriorSampleError, match=r"notes\.npz: not a readable \.npz file"):
        load_prior_sample(text, 16, (N, N))
    with pytest.raises(PriorSampleError, match=r"missing\.npz: cannot be read"):
        load_prior_sample(tmp_path / "missing.npz", 16, (N, N))


def test_the_shipped_sample_loads_for_the_shipped_cells():
    for name in ("sim.yaml", "sim-shifted.yaml"):
        cfg = load_config(REPO / "cell_config" / name)
        prior = load_prior_sample(cfg.finetune.prior_sample, cfg.learning.rotations, cfg.workspace.shape)
        assert len(prior) == 200
        assert any(t.reward > 0 for t in prior.transitions) and any(t.action.is_move for t in prior.transitions)


def test_a_prior_share_needs_a_sample_and_its_range_is_checked():
    with pytest.raises(ConfigError, match=r"finetune\.prior_share: got 0\.25 with no finetune\.prior_sample"):
        config_from_dict({"finetune": {"prior_share": 0.25}})
    with pytest.raises(ConfigError, match=r"finetune\.prior_share"):
        config_from_dict({"finetune": {"prior_share": 1.0, "prior_sample": "x.npz"}})


def test_the_daemon_refuses_to_start_on_a_sample_it_cannot_use_and_names_it(tmp_path):
    from flgd.daemon.controller import Controller, StartupError
    from tests.fakes.daemon import write_config

    bad = tmp_path / "prior.npz"
    bad.write_text("not a sample")
    cfg = load_config(write_config(tmp_path, tmp_path / "state", policy=str(REPO / "policies" / "flg-sim.safetensors"),
                                   finetune={"prior_sample": str(bad), "prior_share": 0.25}))
    ctl = Controller(cfg)
    with pytest.raises(StartupError, match=r"finetune\.prior_sample: prior sample .*prior\.npz: not a readable"):
        ctl.setup()
    assert ctl.cell is None  # nothing was connected, nothing moved
    ctl.shutdown()


def test_the_daemon_mixes_the_configured_sample_into_its_learner_and_status_shows_it(tmp_path):
    from flgd.daemon.controller import Controller
    from tests.fakes.daemon import write_config

    path = tmp_path / "prior.npz"
    shipped = load_config(REPO / "cell_config" / "sim.yaml")
    prior = load_prior_sample(shipped.finetune.prior_sample, 16, shipped.workspace.shape)
    write_prior_sample(path, list(prior.transitions[:5]), {"from": "shipped"})
    cfg = load_config(write_config(tmp_path, tmp_path / "state", policy=str(REPO / "policies" / "flg-sim.safetensors"),
                                   finetune={"prior_sample": str(path), "prior_share": 0.5}))
    ctl = Controller(cfg)
    try:
        ctl.setup()
        assert ctl.learner.prior is not None and len(ctl.learner.prior) == 5 and ctl.learner.prior_share == 0.5
        status = ctl.status()
        assert status["learner_prior"] == {"path": str(path), "transitions": 5, "share": 0.5, "drawn": 0}
        from flgd.ctl import _human

        text = _human("status", {"result": status}, {})
        assert f"prior sample  {path}: 5 transitions, 50 % of each batch, 0 drawn so far" in text
    finally:
        ctl.shutdown()
    off = load_config(write_config(tmp_path, tmp_path / "state2", policy=str(REPO / "policies" / "flg-sim.safetensors"),
                                   finetune={"prior_sample": str(path), "prior_share": 0.0}))
    ctl = Controller(off)
    try:
        ctl.setup()
        assert ctl.learner.prior is None and ctl.status()["learner_prior"] is None
    finally:
        ctl.shutdown()


def test_flgd_prior_sample_writes_a_sample_from_a_store(tmp_path):
    from flgd.store import Store

    store = Store(tmp_path / "state")
    for k, t in enumerate(chain()):
        store.commit_cycle({"step": k, "time": 0.0, "outcome": "executed", "primitive": t.action.primitive}, t)
    store.close()
    out = tmp_path / "sample.npz"
    run = subprocess.run([sys.executable, "-m", "flgd.cli", "prior-sample", str(tmp_path / "state"), str(out),
                          "--count", "3"], capture_output=True, text=True, cwd=REPO)
    assert run.returncode == 0, run.stderr
    prior = load_prior_sample(out, 16, (N, N))
    assert len(prior) == 3 and prior.source["stored_transitions"] == 4 and len(prior.source["steps"]) == 3
    empty = subprocess.run([sys.executable, "-m", "flgd.cli", "prior-sample", str(tmp_path / "nothing"), str(out)],
                           capture_output=True, text=True, cwd=REPO)
    assert empty.returncode == 2 and "holds no store (flgd.sqlite)" in empty.stderr
