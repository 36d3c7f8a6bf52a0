"""Gate storage: only a file's content marks it unusable; a read the OS refuses leaves every record as it was.

Tests run as root, which ignores file modes, so ``Denied`` makes the reads that a daemon running as user flgd
would see fail after a ``chmod 000`` fail the same way (EACCES from open for a file; from listing it and from
anything inside it for a directory); it changes the modes too.
"""

from __future__ import annotations

import dataclasses
import errno
import os
from pathlib import Path

import pytest

from flgd.gate.keeper import GateError, GateFileUnreadable
from tests.fakes.gate import GateCell, gate_config, make_network, same_weights


def unpaused_cell(tmp, config, configured=None, **gate_options) -> GateCell:
    """The gate of ``tests.fakes.gate`` without the pauses between tries of an unreadable file."""
    return GateCell(tmp, config, configured, read_retry_delays=(0.0, 0.0, 0.0), **gate_options)


class Denied:
    """``chmod 000`` on ``path`` as a non-root daemon sees it, until ``allow``; ``times`` refusals at most
    (then without changing the mode: a refusal that passes by itself)."""

    def __init__(self, monkeypatch, path: Path, times: int | None = None):
        self.path, self.left = os.path.abspath(path), times
        self.mode = os.stat(path).st_mode & 0o7777
        if times is None:
            os.chmod(path, 0)
        real_stat, real_open, real_listdir, real_scandir = os.stat, os.open, os.listdir, os.scandir
        is_dir = os.path.isdir(path)

        def refused(p, inside_only: bool) -> bool:
            if isinstance(p, int) or self.left == 0:
                return False
            where = os.path.abspath(os.fsdecode(p))
            return where.startswith(self.path + os.sep) if inside_only else where == self.path

        def refuse(p):
            if self.left is not None:
                self.left -= 1
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fsdecode(p))

        def stat(p, *a, **k):
            if refused(p, inside_only=True):
                refuse(p)
            return real_stat(p, *a, **k)

        def open_(p, *a, **k):
            if refused(p, inside_only=is_dir):
                refuse(p)
            return real_open(p, *a, **k)

        def listdir(p="."):
            if is_dir and refused(p, inside_only=False):
                refuse(p)
            return real_listdir(p)

        def scandir(p="."):
            if is_dir and refused(p, inside_only=False):
                refuse(p)
            return real_scandir(p)

        for name, fn in (("stat", stat), ("open", open_), ("listdir", listdir), ("scandir", scandir)):
            monkeypatch.setattr(os, name, fn)

    def allow(self) -> None:
        self.left = 0
        os.chmod(self.path, self.mode)


def _roles(c: GateCell) -> dict[int, str]:
    return dict(c.store.query("SELECT id, role FROM policies"))


def _kinds(c: GateCell) -> list[str]:
    return [e["kind"] for e in c.gate.history(1000)]


def _line(c: GateCell, length: int) -> list:
    """Champions #1..#length, each promoted over the one before; their networks, in order."""
    nets = [c.configured]
    for k in range(2, length + 1):
        nets.append(make_network(100 + k))
        c.hand_over(nets[-1])
        c.gate.promote(c.step, "uid 0 pid 1", "by hand")
    assert c.gate.champion.id == length
    return nets


def test_a_champion_unreadable_across_a_restart_is_not_marked_and_acts_again_once_readable(tmp_path, monkeypatch):
    c = unpaused_cell(tmp_path, gate_config())
    nets = _line(c, 2)
    roles, kinds = _roles(c), _kinds(c)
    file = tmp_path / c.gate.champion.file
    denied = Denied(monkeypatch, file)
    with pytest.raises(GateFileUnreadable) as refused:
        c.reopen()
    message = str(refused.value)
    assert str(file) in message and "Permission denied" in message and "must be able to read" in message
    assert "Nothing was recorded" in message and "4 tries" in message
    assert _roles(c) == roles and _kinds(c) == kinds and file.is_file()
    denied.allow()
    c.reopen()
    assert c.gate.champion.id == 2 and same_weights(c.agent.network, nets[1]) and _kinds(c) == kinds


def test_a_read_refused_once_is_tried_again(tmp_path, monkeypatch):
    c = unpaused_cell(tmp_path, gate_config())
    nets = _line(c, 2)
    denied = Denied(monkeypatch, tmp_path / c.gate.champion.file, times=1)
    c.reopen()
    assert c.gate.champion.id == 2 and same_weights(c.agent.network, nets[1])
    assert "unusable" not in _kinds(c) and denied.left == 0


@pytest.mark.parametrize("what", ["the directory", "every file"])
def test_the_whole_gate_directory_unreadable_once_keeps_the_line_and_its_rollbacks(tmp_path, monkeypatch, what):
    c = unpaused_cell(tmp_path, gate_config())
    nets = _line(c, 4)
    roles = _roles(c)
    gate = tmp_path / "gate"
    denied = [Denied(monkeypatch, p) for p in ([gate] if what == "the directory" else sorted(gate.iterdir()))]
    with pytest.raises(GateFileUnreadable, match="Permission denied"):
        c.reopen()
    for d in denied:
        d.allow()
    c.reopen()
    assert _roles(c) == roles == {1: "retired", 2: "retired", 3: "retired", 4: "champion"}
    assert all((tmp_path / f).is_file() for (f,) in c.store.query("SELECT file FROM policies"))
    assert same_weights(c.agent.network, nets[3])
    for back_to in (3, 2, 1):
        c.gate.rollback(c.step, "uid 0 pid 1", "by hand")
        assert c.gate.champion.id == back_to and same_weights(c.agent.network, nets[back_to - 1])


def test_an_unreadable_challenger_is_not_dropped(tmp_path, monkeypatch):
    c = unpaused_cell(tmp_path, gate_config())
    challenger = make_network(30)
    c.hand_over(challenger)
    for k in range(6):
        c.act(2 if k % 2 else 1, True)
    denied = Denied(monkeypatch, tmp_path / c.gate.challenger.file)
    with pytest.raises(GateFileUnreadable):
        c.reopen()
    denied.allow()
    c.reopen()
    assert c.gate.challenger.id == 2 and same_weights(c.agent.challenger, challenger)
    assert c.gate.status()["challenger"]["tally"]["actions"] == 3 and "drop" not in _kinds(c)


def test_a_missing_gate_directory_refuses_until_restored_and_an_empty_one_gives_the_line_up(tmp_path):
    c = unpaused_cell(tmp_path, gate_config())
    nets = _line(c, 2)
    roles, gate, kept = _roles(c), tmp_path / "gate", tmp_path / "gate.kept"
    gate.rename(kept)
    with pytest.raises(GateFileUnreadable, match="is missing although the store records"):
        c.reopen()
    assert _roles(c) == roles
    kept.rename(gate)
    c.reopen()
    assert c.gate.champion.id == 2 and same_weights(c.agent.network, nets[1])
    gate.rename(kept)
    gate.mkdir()  # the operator gives the stored policies up
    c.configured = make_network(31)
    c.reopen()
    assert c.gate.champion.origin == "policy P" and same_weights(c.agent.network, c.configured)
    assert _roles(c)[1] == _roles(c)[2] == "unusable"


def test_another_network_variant_in_the_config_refuses_and_records_nothing(tmp_path):
    c = unpaused_cell(tmp_path, gate_config())
    roles = _roles(c)
    c.config = dataclasses.replace(c.config, learning=dataclasses.replace(c.config.learning, network="rho-fcn-fast"))
    with pytest.raises(GateError, match="set learning.network back to 'fast'"):
        c.reopen()
    assert _roles(c) == roles and (tmp_path / "gate" / "policy-000001.safetensors").is_file()


def _corrupt(file: Path) -> bytes:
    blob = bytearray(file.read_bytes())
    blob[-10] ^= 0xFF
    file.write_bytes(bytes(blob))
    return bytes(blob)


def test_a_corrupted_champion_is_marked_unusable_and_moved_aside_with_what_to_do(tmp_path):
    c = unpaused_cell(tmp_path, gate_config())
    _line(c, 2)
    file = tmp_path / c.gate.champion.file
    corrupted = _corrupt(file)
    c.reopen()
    assert c.gate.champion.id == 1 and same_weights(c.agent.network, c.configured) and _roles(c)[2] == "unusable"
    aside = list((tmp_path / "gate" / "unusable").iterdir())
    assert not file.exists() and len(aside) == 1 and aside[0].read_bytes() == corrupted
    assert c.store.query("SELECT file FROM policies WHERE id=2") == [(str(aside[0].relative_to(tmp_path)),)]
    event = [e for e in c.gate.history() if e["kind"] == "unusable"][0]
    assert str(aside[0]) in event["message"] and "flgctl policy load" in event["message"]
    c.reopen()  # the moved file is no stray, and nothing is recorded twice
    assert aside[0].is_file() and _kinds(c).count("unusable") == 1


def test_only_the_newest_unusable_files_are_kept(tmp_path, monkeypatch):
    c = unpaused_cell(tmp_path, gate_config(), keep_unusable=2)
    corrupted = {}
    for k in range(4):
        c.hand_over(make_network(40 + k))
        c.gate.promote(c.step, "uid 0 pid 1", "by hand")
        corrupted[c.gate.champion.id] = _corrupt(tmp_path / c.gate.champion.file)
        c.reopen()
        assert c.gate.champion.id == 1
    kept = sorted((tmp_path / "gate" / "unusable").iterdir())
    newest = sorted(corrupted)[-2:]
    assert [p.read_bytes() for p in kept] == [corrupted[i] for i in newest]
