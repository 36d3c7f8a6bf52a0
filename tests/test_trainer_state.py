"""The trainer state (target network, Adam moments) that a resumed run and a restarted daemon get back:
a round trip continues training exactly, a state of another network is refused whole, and an edited
learning rate in the config wins over the saved one."""

from __future__ import annotations


import numpy as np
import pytest
import torch

from flgd.actions import Action
from flgd.config import CellConfig
from flgd.learning.learner import Learner
from flgd.learning.networks import build_network
from flgd.learning.replay import PrioritizedReplay, Transition
from flgd.training.state import TRAINER_STATE, load_trainer_state, remove_temporary, restore_learner, save_trainer_state
from tests.fakes.learning import block_scene, learner_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def config(**learning) -> CellConfig:
    """The learner tests' config, with no target sync during a test and a fixed seed."""
    return learner_config(**{"target_update_every": 1000, "seed": 3, **learning})


def filled_replay(cfg: CellConfig) -> PrioritizedReplay:
    replay = PrioritizedReplay.from_config(cfg.learning)
    for k in range(6):
        replay.add(Transition(block_scene(k), Action("grasp", 8 + k, 12, k), float(k % 2), block_scene(k + 10), k == 5))
    return replay


def trained_learner(cfg: CellConfig, width: int = 8, updates: int = 4) -> Learner:
    lrn = Learner(cfg, build_network("fast", 16, seed=0, width=width), filled_replay(cfg))
    for _ in range(updates):
        lrn.update()
    # a target that differs from the online weights, as between two target syncs
    lrn.target.load_state_dict(build_network("fast", 16, seed=9, width=width).state_dict())
    return lrn


def fresh_learner_with_weights_of(cfg: CellConfig, source: Learner, width: int = 8) -> Learner:
    net = build_network("fast", 16, seed=1, width=width)
    net.load_state_dict(source.online.state_dict())
    lrn = Learner(cfg, net, filled_replay(cfg))
    lrn.updates = source.updates
    return lrn


def test_round_trip_restores_target_and_moments_and_training_continues_identically(tmp_path):
    cfg = config()
    original = trained_learner(cfg)
    path = tmp_path / "trainer-state.safetensors"
    save_trainer_state(path, original, np.zeros(0, np.int64), np.zeros(0))
    state = load_trainer_state(path)
    assert state.updates == 4

    resumed = fresh_learner_with_weights_of(cfg, original)
    # before restoring, a resumed learner differs: its target is its online net and Adam has no moments
    assert not torch.equal(resumed.target.enc1[0].weight, original.target.enc1[0].weight)
    assert len(resumed.optimizer.state) == 0
    restore_learner(resumed, state)
    for name, value in original.target.state_dict().items():
        assert torch.equal(resumed.target.state_dict()[name], value), name
    p_orig = list(original.online.parameters())
    p_res = list(resumed.online.parameters())
    for a, b in zip(p_orig, p_res):
        sa, sb = original.optimizer.state[a], resumed.optimizer.state[b]
        assert torch.equal(sa["exp_avg"], sb["exp_avg"]) and torch.equal(sa["exp_avg_sq"], sb["exp_avg_sq"])
        assert float(sa["step"]) == float(sb["step"]) == 4.0

    # the same batch and weights give the same step on both: the restored optimizer is the original
    batch = [Transition(block_scene(20), Action("grasp", 10, 10, 2), 1.0, block_scene(21), False),
             Transition(block_scene(22), Action("push", 14, 9, 7), 0.0, None, True)]
    w = np.ones(2, np.float32)
    for lrn in (original, resumed):
        lrn.optimizer.zero_grad(set_to_none=True)
        lrn.loss_terms(batch, w).loss.backward()
        lrn.optimizer.step()
    for a, b in zip(p_orig, p_res):
        assert torch.allclose(a, b, atol=1e-7)


def test_a_state_of_another_network_is_refused_and_leaves_the_learner_untouched(tmp_path):
    cfg = config()
    wide = trained_learner(cfg, width=8)
    path = tmp_path / "trainer-state.safetensors"
    save_trainer_state(path, wide, np.zeros(0, np.int64), np.zeros(0))
    narrow = trained_learner(cfg, width=4, updates=2)
    target_before = {k: v.clone() for k, v in narrow.target.state_dict().items()}
    moments_before = [narrow.optimizer.state[p]["exp_avg"].clone() for p in narrow.online.parameters()]
    with pytest.raises(ValueError, match="shape"):
        restore_learner(narrow, load_trainer_state(path))
    for k, v in narrow.target.state_dict().items():
        assert torch.equal(v, target_before[k]), k
    for p, before in zip(narrow.online.parameters(), moments_before):
        assert torch.equal(narrow.optimizer.state[p]["exp_avg"], before)


def test_the_configured_learning_rate_wins_over_the_saved_one(tmp_path):
    original = trained_learner(config(learning_rate=5e-4))
    path = tmp_path / "trainer-state.safetensors"
    save_trainer_state(path, original, np.zeros(0, np.int64), np.zeros(0))
    finetune = fresh_learner_with_weights_of(config(learning_rate=1e-4), original)
    restore_learner(finetune, load_trainer_state(path))
    assert finetune.optimizer.param_groups[0]["lr"] == pytest.approx(1e-4)
    p = next(finetune.online.parameters())
    assert float(finetune.optimizer.state[p]["step"]) == 4.0  # the moments did come back


def test_reset_trainer_state_gives_what_a_new_learner_starts_with():
    lrn = trained_learner(config())
    lrn.reset_trainer_state()
    assert len(lrn.optimizer.state) == 0
    for name, value in lrn.online.state_dict().items():
        assert torch.equal(lrn.target.state_dict()[name], value), name
    assert lrn.update() is not None  # and it still trains


def test_an_unreadable_or_incomplete_file_is_a_value_error_naming_it(tmp_path):
    garbage = tmp_path / "trainer-state.safetensors"
    garbage.write_bytes(b"half a file, cut off by a power cut")
    with pytest.raises(ValueError, match="trainer-state.safetensors.*not a readable trainer state"):
        load_trainer_state(garbage)
    from safetensors.torch import save_file

    partial = tmp_path / "partial.safetensors"
    save_file({"target.x": torch.zeros(2)}, str(partial), metadata={"updates": "4", "adam_groups": "[]"})
    with pytest.raises(ValueError, match="partial.safetensors.*incomplete.*priority.ids"):
        load_trainer_state(partial)


def test_only_the_temporaries_of_interrupted_trainer_state_writes_are_removed(tmp_path):
    stale = [tmp_path / f".{TRAINER_STATE}.{suffix}.tmp" for suffix in ("a1b2c3", "zz9")]
    keep = [tmp_path / TRAINER_STATE, tmp_path / ".checkpoint-0000000002.safetensors.x.tmp",
            tmp_path / f".{TRAINER_STATE}.note", tmp_path / "flgd.db"]
    for p in stale + keep:
        p.write_bytes(b"x")
    assert remove_temporary(tmp_path) == 2
    assert not any(p.exists() for p in stale)
    assert all(p.exists() for p in keep)
    assert remove_temporary(tmp_path / "missing") == 0


def test_a_resumed_learner_takes_back_the_remembered_a_prime_and_searches_no_next_state_again(tmp_path):
    cfg = config(actor_argmax=True, gamma=0.5)
    original = trained_learner(cfg)
    _, batch, _ = original.replay.sample(4)  # replayed transitions carry their next state's key
    batch = [t for t in batch if not t.done]
    assert original.argmax_computed > 0 and original.remembered_argmax()
    path = tmp_path / TRAINER_STATE
    save_trainer_state(path, original, np.zeros(0, np.int64), np.zeros(0))

    resumed = fresh_learner_with_weights_of(cfg, original)
    restore_learner(resumed, load_trainer_state(path))
    assert sorted(resumed.remembered_argmax()) == sorted(original.remembered_argmax())
    resumed.targets(batch)
    assert resumed.argmax_computed == 0 and resumed.argmax_reused == len(batch)


def test_a_trainer_state_without_remembered_a_prime_loads_with_none(tmp_path):
    from safetensors.torch import load_file, save_file
    cfg = config(actor_argmax=True)
    original = trained_learner(cfg)
    assert original.remembered_argmax()
    path = tmp_path / TRAINER_STATE
    save_trainer_state(path, original, np.zeros(0, np.int64), np.zeros(0))
    from safetensors import safe_open
    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata()
    older = {k: v for k, v in load_file(str(path)).items() if not k.startswith("argmax.")}
    save_file(older, str(path), metadata=meta)
    assert load_trainer_state(path).argmax == []
