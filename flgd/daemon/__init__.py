"""The flgd daemon: state machine, control socket, systemd notify, metrics, and ``flgd run``.

The daemon orchestrates and contains no math: the cycle is ``flgd.cycle``, the
learning is ``flgd.learning``, persistence is ``flgd.store``.
"""
