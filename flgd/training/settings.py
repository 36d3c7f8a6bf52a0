"""What a ``flgd train`` run is: its variant and settings (from the command line, checked against the run.json
record of a run being resumed) and its effective config.

Apart from ``flgd.training.run`` (which runs it) because ``flgd eval``, ``flgd export`` and the benches read
runs and variants without training.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

from flgd.config import CellConfig
from flgd.wiring import resume_seed

__all__ = ["RUN_FILE", "TRAIN_VARIANTS", "TRUNK_NETWORKS", "variant_network", "RunSettings", "RunFileError", "portable_config",
           "read_run_info", "effective_config", "command_line", "settings_from_command_line"]

RUN_FILE = "run.json"

# variant -> (network on the fast trunk, masks, paper method).  The variant picks the head and the masks;
# the config's learning.network picks the trunk (TRUNK_NETWORKS), so the paper's DenseNet-121 trains too.
TRAIN_VARIANTS: dict[str, tuple[str, bool, str]] = {
    "flg": ("fast", True, "FLG"),
    "dpen": ("fast", False, "DPEN"),
    "rho-fcn": ("rho-fcn-fast", True, "rho-FCN"),
}
# trunk -> variant -> learning.network.  Each learning.network names one trunk (rho-fcn is the VPG head on the
# DenseNet-121, rho-fcn-fast the same head on the fast trunk).
TRUNK_NETWORKS: dict[str, dict[str, str]] = {
    "fast": {"flg": "fast", "dpen": "fast", "rho-fcn": "rho-fcn-fast"},
    "densenet121": {"flg": "densenet121", "dpen": "densenet121", "rho-fcn": "rho-fcn"},
}
_TRUNK_OF = {net: trunk for trunk, nets in TRUNK_NETWORKS.items() for net in nets.values()}


def variant_network(variant: str, network: str) -> str:
    """The learning.network that trains ``variant`` on the trunk of the config's ``network``
    (fast or densenet121; its head, FLG or VPG, is the variant's)."""
    if variant not in TRAIN_VARIANTS:
        raise ValueError(f"variant: got {variant!r}, expected one of {', '.join(sorted(TRAIN_VARIANTS))}")
    if network not in _TRUNK_OF:
        raise ValueError(f"learning.network: got {network!r}, expected one of {', '.join(sorted(_TRUNK_OF))}")
    return TRUNK_NETWORKS[_TRUNK_OF[network]][variant]


@dataclass(frozen=True)
class RunSettings:
    variant: str = "flg"
    objects: int = 10
    steps: int = 1000
    seed: int = 0
    curriculum: bool = False
    grasp_only: bool = False
    init_policy: str = ""  # a new run starts from this policy file's weights (fresh replay and optimizer)
    give_up_after: int = 0  # new scene after this many actions in a row without a successful grasp (0 = never)
    overrides: list[str] = dataclasses.field(default_factory=list)  # --set items, applied to the config at every start

    def describe(self) -> str:
        scene = "curriculum 10->20 objects + presets" if self.curriculum else f"{self.objects} objects"
        mode = ", grasp only" if self.grasp_only else ""
        start = f", from {self.init_policy}" if self.init_policy else ""
        give_up = f", new scene after {self.give_up_after} actions without a grasp" if self.give_up_after else ""
        changed = f", config with {' '.join(self.overrides)}" if self.overrides else ""
        return (f"{self.variant} ({TRAIN_VARIANTS[self.variant][2]}), {scene}{mode}, seed {self.seed}{start}{give_up}"
                f"{changed}")


# keys a run sets itself (effective_config, the curriculum): a --set of one would be overwritten, so it is refused
# and the flag that sets it named instead
RUN_SET_KEYS = {"sim.objects": "--objects or --curriculum", "sim.seed": "--seed", "sim.scene": "a scene set per run",
                "learning.seed": "--seed", "learning.network": "--variant (the head) and the config file (the trunk)",
                "exploration.masks": "--variant", "exploration.grasp_only": "--grasp-only",
                "exploration.curriculum_steps": "--curriculum"}
# config keys that hold a file: a relative --set value is read from the current directory, as --init-policy is
PATH_KEYS = ("learning.init_trunk", "finetune.prior_sample")


def parse_set_items(items: list[str]) -> dict[str, object]:
    """``--set`` items as {dotted key: value}; ValueError naming ``--set``, the item and the problem."""
    from flgd.overrides import parse_override

    out: dict[str, object] = {}
    for item in items:
        try:
            key, value = parse_override(item)
        except ValueError as exc:
            raise ValueError(f"--set {item!r}: {exc}") from None
        if key in RUN_SET_KEYS:
            raise ValueError(f"--set {item!r}: the run sets {key} itself; use {RUN_SET_KEYS[key]}")
        if key in out:
            raise ValueError(f"--set {item!r}: {key} is given twice")
        if key in PATH_KEYS and isinstance(value, str) and value:
            value = os.path.abspath(value)
        out[key] = value
    return out


class RunFileError(ValueError):
    """A run directory's run.json that cannot be used; the message names the file, the problem and what to do."""


def read_run_info(out: Path) -> dict | None:
    """The run.json of run directory ``out``, None if it has none; a damaged one is a ``RunFileError``.

    Never guess: a run.json that does not parse or is not a run's record must not be taken for "no run"
    (a new run would be started over the old one's store and checkpoints)."""
    path = Path(out) / RUN_FILE
    if not path.exists():
        return None
    fix = (f"the run in {path.parent} was not changed; restore {RUN_FILE} (its settings are also in "
           f"the policy metadata of checkpoints/) or start the run in another directory")
    from flgd.training.records import read_json_record

    try:
        info = read_json_record(path, fix)
    except ValueError as exc:
        raise RunFileError(str(exc)) from None
    if not isinstance(info, dict):
        raise RunFileError(f"{path}: expected a JSON object (settings, segments, status), got "
                           f"{type(info).__name__}; {fix}")
    settings = info.get("settings")
    if not isinstance(settings, dict):
        raise RunFileError(f"{path}: key 'settings': expected an object of the run's settings, got "
                           f"{'nothing' if settings is None else type(settings).__name__}; {fix}")
    defaults = dataclasses.asdict(RunSettings())
    for key, value in settings.items():
        if key not in defaults:
            continue
        want = type(defaults[key])
        ok = isinstance(value, want) and (want is bool or not isinstance(value, bool))
        if want is list and ok:
            ok = all(isinstance(v, str) for v in value)
        if key == "variant" and ok and value not in TRAIN_VARIANTS:
            raise RunFileError(f"{path}: settings.variant: got {value!r}, expected one of "
                               f"{sorted(TRAIN_VARIANTS)}; {fix}")
        if not ok:
            raise RunFileError(f"{path}: settings.{key}: got {value!r}, expected {want.__name__}; {fix}")
    if not isinstance(info.get("segments", []), list):
        raise RunFileError(f"{path}: key 'segments': expected a list, got {type(info['segments']).__name__}; "
                           f"{fix}")
    return info


def effective_config(base: CellConfig, settings: RunSettings, out: Path, segment: int = 0) -> CellConfig:
    """The cell config of a run: variant, objects, seeds, curriculum and the run directory as state dir.
    The variant sets the head and the masks, ``base.learning.network`` the trunk (``variant_network``); a
    resumed segment's learning and sim seeds are streams 1 and 2 of ``flgd.wiring.resume_seed``."""
    from flgd.curriculum import Curriculum

    _, masks, _ = TRAIN_VARIANTS[settings.variant]
    network = variant_network(settings.variant, base.learning.network)
    cfg = dataclasses.replace(
        base,
        state_dir=str(out),
        policy="",
        learning=dataclasses.replace(base.learning, network=network, seed=resume_seed(settings.seed, segment, 1)),
        exploration=dataclasses.replace(base.exploration, masks=masks, grasp_only=settings.grasp_only),
        sim=dataclasses.replace(base.sim, objects=settings.objects, seed=resume_seed(settings.seed, segment, 2),
                                scene=""))
    if settings.curriculum:
        cfg = Curriculum().apply_to_config(cfg)
    return cfg


# ---------------------------------------------------------------------- command line

def command_line() -> argparse.ArgumentParser:
    """``flgd train``'s options (the settings of a run, and how to run it)."""
    p = argparse.ArgumentParser(
        prog="flgd train", description="Train a policy headless in sim_cell (the daemon's cycle, agent and "
                                       "learner; synchronous updates).  Run again with the same --out to resume.")
    p.add_argument("--config", help="cell config YAML (backend sim); optional when resuming --out")
    p.add_argument("--variant", choices=sorted(TRAIN_VARIANTS),
                   help="flg (default), dpen (no masks), rho-fcn (VPG head); the trunk is the config's "
                        "learning.network (fast or densenet121, the paper's)")
    p.add_argument("--objects", type=int, help="objects per random scene (default 10; not with --curriculum)")
    p.add_argument("--steps", type=int, help="train until this many steps (actions) in total (default 1000)")
    p.add_argument("--seed", type=int, help="seed of the sim, network, agent and replay (default 0)")
    p.add_argument("--out", required=True, help="run directory (created; resumed if it holds a run)")
    p.add_argument("--curriculum", action="store_true", default=None,
                   help="paper IV-A curriculum: few moves for 500 steps, 10 -> 20 objects from step 400, "
                        "preset piles after 1500 steps")
    p.add_argument("--grasp-only", action="store_true", default=None, help="never move (paper's Grasping-only)")
    p.add_argument("--init-policy", metavar="FILE",
                   help="start a new run from this policy file (e.g. to fine-tune the shipped policy on other "
                        "objects) instead of a fresh network; the replay and optimizer start empty")
    p.add_argument("--give-up-after", type=int, metavar="N",
                   help="start a new scene after N actions in a row without a successful grasp (default 0: never; "
                        "a run started without it keeps never)")
    p.add_argument("--threads", type=int, help="torch CPU threads of the learner (default: learning.threads of the "
                                               "config; each worker of --workers uses one)")
    p.add_argument("--workers", type=int, default=0, metavar="N",
                   help="collect with N simulated cells at once, each a Ray worker of one CPU, for one learner in "
                        "this process (default 0: one cell in this process, no Ray); a run may resume with another N")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="with --workers: join the Ray cluster at this address (`ray start --head` prints it) "
                        "instead of starting a local one for the run")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", dest="overrides",
                   help="the run's config with this key changed (repeatable; e.g. exploration.side_taper=0), kept "
                        "in run.json and applied at every resume; a resume may repeat them, not change them")
    p.add_argument("--log-every", type=int, default=25, help="steps between plain progress lines (no terminal)")
    return p


def settings_from_command_line(args: argparse.Namespace, previous: dict | None) -> RunSettings:
    """Settings from the command line, checked against a run being resumed."""
    given = {"variant": args.variant, "objects": args.objects, "steps": args.steps, "seed": args.seed,
             "curriculum": args.curriculum, "grasp_only": args.grasp_only,
             "init_policy": None if args.init_policy is None else str(Path(args.init_policy).resolve()),
             "give_up_after": args.give_up_after,
             "overrides": [f"{k}={v}" for k, v in parse_set_items(args.overrides).items()] or None}
    if previous:
        for key, value in given.items():
            before = previous.get(key, getattr(RunSettings(), key))  # a key newer than the run: its default
            if key != "steps" and value is not None and value != before:
                flag = "--set" if key == "overrides" else f"--{key.replace('_', '-')}"
                raise ValueError(f"{flag}: got {value!r}, but the run in --out was started "
                                 f"with {before!r}; use another --out for other settings")
        merged = {**dataclasses.asdict(RunSettings()), **previous, **{k: v for k, v in given.items() if v is not None}}
        return RunSettings(**{f.name: merged[f.name] for f in dataclasses.fields(RunSettings)})
    defaults = RunSettings()
    s = RunSettings(**{k: (getattr(defaults, k) if v is None else v) for k, v in given.items()})
    if s.curriculum and args.objects is not None:
        raise ValueError("--objects: the curriculum sets the object count (10 -> 20); drop one of the two")
    if s.curriculum:
        s = dataclasses.replace(s, objects=10)
    return s


def portable_config(cfg: CellConfig, dest: Path) -> CellConfig:
    """``cfg`` (paths absolute, as loaded) with its files relative to ``dest`` and its state directory ``.``, as
    a run's ``config.yaml`` in ``dest`` names them: a training run keeps its state in its own directory, and a
    run directory (or its carried copy) names no machine's paths."""
    def rel(path: str) -> str:
        return os.path.relpath(path, dest) if path and os.path.isabs(path) else path
    return dataclasses.replace(
        cfg, state_dir=".", policy=rel(cfg.policy),
        finetune=dataclasses.replace(cfg.finetune, prior_sample=rel(cfg.finetune.prior_sample)),
        learning=dataclasses.replace(cfg.learning, init_trunk=rel(cfg.learning.init_trunk)))
