"""FLG's learning core (paper III-C, III-D, IV): Q-map networks, the masked agent, the learner,
prioritized replay and policy files.

Arrays in, arrays out: nothing here knows about a cell, PyBullet or robot
hardware, so every part can be tested on synthetic heightmaps.
"""
