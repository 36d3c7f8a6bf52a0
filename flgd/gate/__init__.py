"""The champion/challenger gate: learned weights act on the cell only once they have done better than the policy
acting now.

``statistics`` -- the decisions as pure functions of outcome counts (tally, verdicts, the challenger's share);
``keeper`` -- which policy acts, on what evidence, fed one cycle outcome at a time;
``storage`` -- the gate's policy files and records in the state directory (reads tried again, unusable files set
aside, pruning).
"""
