"""Test doubles and helpers shared by test modules: the devices a real cell talks to (UR controller, RG2,
D415), the daemon as a subprocess, synthetic scenes.  Test modules import from here, never from each other."""
