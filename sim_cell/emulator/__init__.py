"""The emulated real cell: a UR5e controller, an RG2 and a D415 over their own protocols, on SimCell's physics.

``flgd emulate`` runs them in one process on a loopback address so that the
production backend (flgd/hardware/) runs against them unmodified.  sim-only:
flgd never imports this package at module level.
"""
