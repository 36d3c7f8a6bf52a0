"""The extension point for another cell: ``flgd.cell.register_cell`` makes a third backend a config may name,
that ``make_cell`` builds and the daemon's ``backend`` command can swap to."""

from __future__ import annotations

import pytest

from flgd import backends
from flgd.cell import available_cells, make_cell, register_cell
from flgd.config import ConfigError, config_from_dict
from sim_cell.cell import SimCell


class MirroredSimCell(SimCell):
    """A third cell: the simulator under another name, as an integrator's own cell class would register."""


@pytest.fixture
def registry(monkeypatch):
    """The backend registry as it is, restored after the test."""
    monkeypatch.setattr(backends, "_FACTORIES", dict(backends._FACTORIES))


def test_a_registered_third_cell_is_named_by_a_config_and_built_by_make_cell(registry):
    with pytest.raises(ConfigError, match="backend: got 'mirror'"):
        config_from_dict({"backend": "mirror"})
    built = []

    def factory(config):
        built.append(config)
        return MirroredSimCell(config)

    register_cell("mirror", factory)
    assert available_cells() == ["mirror", "sim", "ur5e"]
    cfg = config_from_dict({"backend": "mirror"})
    cell = make_cell(cfg)
    try:
        assert isinstance(cell, MirroredSimCell) and built == [cfg]
        assert cell.capture().color.size > 0  # a working cell, not only a name
    finally:
        cell.close()


def test_a_third_cell_registered_by_module_path_loads_on_first_use_and_a_missing_module_is_named(registry):
    register_cell("mirror", "tests.test_register_cell:MirroredSimCell")
    register_cell("absent", "no_such_integrator_module:Cell")
    cell = make_cell(config_from_dict({"backend": "sim"}), backend="mirror")
    try:
        assert isinstance(cell, MirroredSimCell)
    finally:
        cell.close()
    with pytest.raises(ValueError, match="cell backend 'absent' cannot load \\(no_such_integrator_module\\)"):
        make_cell(config_from_dict({"backend": "sim"}), backend="absent")
