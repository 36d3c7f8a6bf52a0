"""The three methods the paper compares (IV-A, Fig. "Comparisons to Baselines") as config settings.

* FLG     - the default network with the grasp/move masks;
* DPEN    - the same network without masks (Dense Pixel-wise Estimation Network);
* rho-FCN - the VPG-style head (x16 upsampling, no skip) with the masks.

"The same network" for DPEN is whatever ``learning.network`` the config names
(``fast`` by default, ``densenet121`` for a paper-faithful comparison).
"""

from __future__ import annotations

import dataclasses

from flgd.config import CellConfig

__all__ = ["METHODS", "configure_method"]

METHODS: tuple[str, ...] = ("FLG", "DPEN", "rho-FCN")


def configure_method(config: CellConfig, method: str) -> CellConfig:
    """``config`` with the network variant and masks of ``method``."""
    if method not in METHODS:
        raise ValueError(f"method: got {method!r}, expected one of {', '.join(METHODS)}")
    network = "rho-fcn" if method == "rho-FCN" else config.learning.network
    if method != "rho-FCN" and network == "rho-fcn":
        raise ValueError(f"method {method!r} needs the FLG head, but learning.network is 'rho-fcn'; "
                         "set learning.network to 'fast' or 'densenet121'")
    return dataclasses.replace(
        config,
        learning=dataclasses.replace(config.learning, network=network),
        exploration=dataclasses.replace(config.exploration, masks=method != "DPEN"))
