"""The one learning stack (flgd/learning_stack.py) and the one override helper (flgd/overrides.py): what the
daemon, ``flgd eval --learn``, ``flgd train`` and the benches share."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from flgd.config import load_config
from flgd.learning_stack import CheckpointMeta, learning_config
from flgd.overrides import apply_overrides, parse_override, yaml_value

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "cell_config" / "sim.yaml"


def _with_curriculum(tmp_path):
    cfg = load_config(SIM)
    return dataclasses.replace(cfg, state_dir=str(tmp_path / "state"),
                               exploration=dataclasses.replace(cfg.exploration, curriculum_steps=500))


def test_eval_learn_runs_with_the_daemons_curriculum_rule(tmp_path):
    """What ``flgd eval --learn`` measures is what the daemon does: the few-moves phase is ``flgd train
    --curriculum``'s alone, so a config that sets it acts without it in both (the evaluator's copy kept it)."""
    from flgd.daemon.controller import Controller
    from flgd.evaluation.evaluator import EvalOptions, Evaluator
    from flgd.learning.networks import build_network

    cfg = _with_curriculum(tmp_path)
    daemon = Controller(cfg)
    assert daemon.learning.config.exploration.curriculum_steps == 0
    net = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=0)
    with Evaluator(cfg, net, EvalOptions(runs=1, learn=True)) as ev:
        assert ev.agent.config.exploration.curriculum_steps == 0
        assert ev.agent.config.exploration == daemon.learning.config.exploration
        assert ev.config.learning.learning_rate == daemon.learning.config.learning.learning_rate == \
            cfg.finetune.learning_rate


def test_eval_learn_restarts_the_learner_from_the_champion_after_a_drop_as_the_daemon_does(tmp_path):
    """The gate of ``flgd eval --learn`` resets its learner to the champion (the evaluator's copy left it going
    on from the dropped line): weights, trainer state and owed updates, as in the daemon."""
    import torch

    from flgd.evaluation.evaluator import EvalOptions, Evaluator
    from flgd.learning.networks import build_network

    cfg = load_config(SIM)
    cfg = dataclasses.replace(cfg, state_dir=str(tmp_path / "state"))
    net = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=0)
    champion = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=1)
    with Evaluator(cfg, net, EvalOptions(runs=1, learn=True)) as ev:
        assert ev.gate.reset_learner is not None
        ev.gate.reset_learner(champion)
        learned = ev.learner.snapshot().state_dict()
    assert all(torch.equal(learned[k], v) for k, v in champion.state_dict().items())


def test_only_flgd_train_keeps_the_few_moves_phase(tmp_path):
    cfg = _with_curriculum(tmp_path)
    assert learning_config(cfg, False).exploration.curriculum_steps == 0
    assert learning_config(cfg, True).exploration.curriculum_steps == 0
    assert learning_config(cfg, False, few_moves=True) is cfg


def test_checkpoint_metadata_is_one_record_for_the_daemon_and_training_runs():
    daemon = CheckpointMeta(-3, "sim", 40, "policy P").as_dict()
    assert daemon == {"training_steps": 0, "cell": "sim", "learner_updates": 40, "source": "policy P"}
    run = CheckpointMeta(12, "sim", 40, "flgd train r", {"method": "FLG", "seed": 3}).as_dict()
    assert run["training_steps"] == 12 and run["method"] == "FLG" and run["seed"] == 3


def test_overrides_read_yaml_values_and_exponent_numbers_as_floats():
    assert parse_override("finetune.learning_rate=3e-5") == ("finetune.learning_rate", 3e-5)
    assert parse_override("gate.enabled=false") == ("gate.enabled", False)
    assert parse_override("camera.depth_fill=none") == ("camera.depth_fill", "none")
    assert yaml_value("1E4") == 1e4 and yaml_value("inf-ish") == "inf-ish"
    for bad in ("finetune.learning_rate", "nodot=1", "=3", ".x=1"):
        with pytest.raises(ValueError):
            parse_override(bad)


def test_overrides_are_checked_as_a_config_is():
    cfg = load_config(SIM)
    changed = apply_overrides(cfg, {"finetune.learning_rate": 3e-5, "gate.share": 0.3}, source="test")
    assert changed.finetune.learning_rate == 3e-5 and changed.gate.share == 0.3
    with pytest.raises(ValueError, match="--set finetune.lerning_rate: no such config key"):
        apply_overrides(cfg, {"finetune.lerning_rate": 1.0}, source="test", label="--set ")
    with pytest.raises(ValueError, match="nosection is not a config section"):
        apply_overrides(cfg, {"nosection.x": 1}, source="test")
    with pytest.raises(ValueError, match="learning_rate"):
        apply_overrides(cfg, {"finetune.learning_rate": -1.0}, source="test")


LEARNING_PARTS = {"agent", "learner", "replay", "gate", "keeper"}


def part_assignments(source: str) -> list[str]:
    """``x.agent.attr = ...`` or ``learner.attr = ...``: an attribute of a learning part set from outside its class."""
    import ast

    found = []
    for node in ast.walk(ast.parse(source)):
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])
        for target in targets:
            for t in (target.elts if isinstance(target, ast.Tuple) else [target]):
                if not isinstance(t, ast.Attribute):
                    continue
                owner = t.value
                name = owner.id if isinstance(owner, ast.Name) else owner.attr if isinstance(owner, ast.Attribute) else ""
                if name in LEARNING_PARTS:
                    found.append(f"line {t.lineno}: {ast.unparse(t)}")
    return found


def test_no_attribute_of_a_learning_part_is_set_from_outside_its_class():
    """Agent, learner, replay and gate are built whole (``LearningStack.build``); nothing in the package sets one
    of their attributes afterwards (their own methods change their state)."""
    offenders = {str(path.relative_to(REPO)): hits for root in ("flgd", "sim_cell", "benchmarks")
                 for path in sorted((REPO / root).rglob("*.py"))
                 if (hits := part_assignments(path.read_text()))}
    assert offenders == {}


def test_the_scan_finds_a_part_patched_from_outside():
    assert part_assignments("learner.mailbox = None\nctl.agent.exploration_offset = 3\n"
                            "a, self.gate.reset_learner = 1, f\nself.updates = 0\n") == [
        "line 1: learner.mailbox", "line 2: ctl.agent.exploration_offset", "line 3: self.gate.reset_learner"]


def test_the_builder_connects_learner_gate_and_agent_as_the_daemon_runs_them(tmp_path):
    """Gate on: the learner posts to the gate's mailbox, the gate moves the learner's anchor and resets it; gate
    off: the learner posts to the agent; no store: it hands nothing over (nothing acts unvetted)."""
    from flgd.learning.networks import build_network
    from flgd.learning_stack import GateStart, Handover, LearningStack
    from flgd.store import Store

    cfg = dataclasses.replace(load_config(SIM), state_dir=str(tmp_path / "state"))
    net = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=0)
    start = GateStart(0, configured=lambda: (net, {"training_steps": 4000}, "policy P"),
                      fresh=lambda: (net, {"training_steps": 0}, "fresh"))
    stack = LearningStack(cfg, fine_tune=True, state_dir=tmp_path / "on", store=Store(tmp_path / "on"))
    on = stack.build(net, handover=Handover.GATE, gate=start)
    assert on.gate is not None and on.learner.mailbox is on.gate.handovers is not on.agent.mailbox
    assert on.gate.on_champion == on.learner.set_anchor and on.gate.reset_learner == stack.restart_learner_from
    assert on.agent.exploration_offset == 4000 and on.agent.max_epsilon == cfg.finetune.max_epsilon

    off_cfg = dataclasses.replace(cfg, gate=dataclasses.replace(cfg.gate, enabled=False))
    off = LearningStack(off_cfg, fine_tune=True, state_dir=tmp_path / "off", store=Store(tmp_path / "off")).build(
        net, handover=Handover.GATE, gate=start)
    assert off.gate is not None and off.learner.mailbox is off.agent.mailbox

    unvetted = LearningStack(cfg, fine_tune=True, state_dir=tmp_path / "none").build(
        net, handover=Handover.GATE, gate=start)
    assert unvetted.gate is None and unvetted.learner.mailbox is None
    with pytest.raises(ValueError, match="handover must be gate"):
        LearningStack(cfg, fine_tune=True, state_dir=tmp_path / "on", store=Store(tmp_path / "x")).build(
            net, handover=Handover.AGENT, gate=start)


def test_a_rebuild_whose_gate_fails_part_way_keeps_the_learners_own_weights(tmp_path, monkeypatch):
    """The daemon's reset after the store came back: the gate loads its champion into the agent, then fails (its
    records cannot be written); the stack is built again without a gate, and the learner goes on from its own
    weights, not the champion's it never learned."""
    import torch

    from flgd.learning.networks import build_network
    from flgd.learning_stack import GateStart, Handover, LearningStack
    from flgd.store import Store, StoreError

    cfg = dataclasses.replace(load_config(SIM), state_dir=str(tmp_path / "state"))
    own = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=0)
    champion = build_network(cfg.learning.network, rotations=cfg.learning.rotations, seed=1)
    store = Store(tmp_path / "state")
    stack = LearningStack(cfg, fine_tune=True, state_dir=tmp_path / "state", store=store)
    stack.build(own, handover=Handover.GATE)

    def refuse(*_args, **_kwargs):
        raise StoreError("disk full")

    monkeypatch.setattr(store, "set_counter", refuse)  # the exploration offset of a first start is not recorded
    with pytest.raises(StoreError, match="disk full"):
        stack.rebuild(0, GateStart(0, configured=lambda: (champion, {"training_steps": 3000}, "policy P"),
                                   fresh=lambda: (champion, {"training_steps": 0}, "fresh")))
    try:
        assert stack.gate is None and stack.learner.mailbox is None
        learned = stack.learner.snapshot().state_dict()
        assert all(torch.equal(learned[k], v) for k, v in own.state_dict().items())
    finally:
        stack.learner.stop(timeout=10.0, why="test over")
