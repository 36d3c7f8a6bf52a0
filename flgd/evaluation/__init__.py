"""Evaluation of a policy in the simulated cell (``flgd eval``): scene sets, VPG's metrics, reports."""
