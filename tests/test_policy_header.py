"""``flgctl policy load``: a file that is no policy is refused from its header, before its body is read, and
every refusal is logged and recorded as an event with its reason."""

from __future__ import annotations

import dataclasses
import logging
import struct
from pathlib import Path

import pytest
import torch

from flgd.config import CellConfig
from flgd.daemon.commands import policy_load
from flgd.daemon.protocol import ProtocolError
from flgd.learning import policy_file
from flgd.learning.networks import build_network
from flgd.learning.policy_file import PolicyFileError, save_policy
from flgd.policy_header import check_policy_header

REPO = Path(__file__).resolve().parents[1]


class _Events:
    """The store's event table, as far as a refused load writes to it."""

    def __init__(self):
        self.rows: list[tuple[str, str]] = []

    def record_event(self, kind: str, message: str) -> None:
        self.rows.append((kind, message))


def _controller(tmp_path: Path):
    from flgd.daemon.controller import Controller

    ctl = Controller(dataclasses.replace(CellConfig(), state_dir=str(tmp_path / "state")))
    ctl.store = _Events()
    return ctl


@pytest.fixture
def body_reads(monkeypatch) -> list[Path]:
    """Every whole-file read of ``load_policy`` (the body), recorded."""
    reads: list[Path] = []
    read_file = policy_file._read_file

    def recording(path):
        reads.append(Path(path))
        return read_file(path)

    monkeypatch.setattr(policy_file, "_read_file", recording)
    return reads


def test_a_50_mb_zero_file_is_refused_from_its_header_logged_and_recorded(tmp_path, body_reads, caplog):
    zeros = tmp_path / "zeros.safetensors"
    with open(zeros, "wb") as f:
        f.write(bytes(50 * 1024 * 1024))
    ctl = _controller(tmp_path)
    with caplog.at_level(logging.WARNING, logger="flgd"), pytest.raises(ProtocolError) as err:
        policy_load(ctl, str(zeros), "uid 0 pid 1")
    assert err.value.code == "failed" and "running policy stays" in err.value.message
    assert str(zeros) in err.value.message and "header length of 0" in err.value.message
    assert body_reads == []  # the 50 MB were never read
    logged = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(logged) == 1 and str(zeros) in logged[0] and "header length of 0" in logged[0]
    assert len(ctl.store.rows) == 1
    kind, message = ctl.store.rows[0]
    assert kind == "policy" and "refused" in message and str(zeros) in message and "uid 0 pid 1" in message


def test_every_refused_load_is_logged_and_recorded_even_a_relative_path(tmp_path, caplog):
    ctl = _controller(tmp_path)
    with caplog.at_level(logging.WARNING, logger="flgd"), pytest.raises(ProtocolError):
        policy_load(ctl, "relative.safetensors")
    assert any("relative.safetensors" in r.getMessage() for r in caplog.records)
    assert ctl.store.rows and "path must be absolute" in ctl.store.rows[0][1]


def _saved(tmp_path: Path) -> Path:
    path = tmp_path / "good.safetensors"
    torch.manual_seed(0)
    save_policy(path, build_network("fast", 16, seed=0).eval(), {"training_steps": 1})
    return path


def test_a_policy_whose_body_is_cut_or_padded_is_refused_from_the_header(tmp_path):
    good = _saved(tmp_path)
    check_policy_header(good)
    check_policy_header(sorted(p for p in (REPO / "policies").glob("*.safetensors")
                               if not p.name.startswith("trunk"))[0])
    blob = good.read_bytes()
    for name, data in (("cut", blob[:-1]), ("padded", blob + b"\0")):
        bad = tmp_path / f"{name}.safetensors"
        bad.write_bytes(data)
        with pytest.raises(PolicyFileError, match="the header's tensors take"):
            check_policy_header(bad)


def test_a_header_that_is_json_but_no_flgd_policy_is_refused(tmp_path):
    other = tmp_path / "other.safetensors"
    header = b'{"w": {"dtype": "F32", "shape": [1], "data_offsets": [0, 4]}}'
    other.write_bytes(struct.pack("<Q", len(header)) + header + bytes(4))
    with pytest.raises(PolicyFileError, match="no flgd metadata"):
        check_policy_header(other)
