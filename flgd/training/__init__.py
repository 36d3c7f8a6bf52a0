"""``flgd train``: headless sim training on the daemon's cycle (see flgd.training.run)."""
