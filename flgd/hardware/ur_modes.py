"""What the UR controller's RTDE mode numbers mean, and which of them need a person at the cell.

The numbers are the RTDE guide's (the same as the primary interface's); ``flgd.hardware.ur_arm`` reads the modes
to tell a fault it may recover from (a protective stop) from one it must refuse to (an emergency stop, a
safeguard stop, a safety fault).
"""

from __future__ import annotations

__all__ = ["SAFETY_MODES", "ROBOT_MODES", "NEEDS_A_PERSON", "EMERGENCY", "NORMAL", "REDUCED", "PROTECTIVE",
           "ROBOT_RUNNING"]

# RTDE safety_mode values (UR RTDE guide; same numbers as the primary interface).
SAFETY_MODES = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP",
    6: "SYSTEMEMERGENCY_STOP", 7: "ROBOTEMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT",
    10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE", 12: "AUTOMATIC_MODE_SAFEGUARD_STOP",
    13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}
NORMAL, REDUCED, PROTECTIVE = 1, 2, 3
EMERGENCY = {6, 7}
NEEDS_A_PERSON = {
    4: "the arm is in RECOVERY mode (a joint is outside its limits): move it back on the pendant",
    5: "a safeguard stop is active (safety input open: door, light curtain?)",
    8: "the safety system reports a VIOLATION: inspect the cell and restart safety on the pendant",
    9: "the safety system reports a FAULT: inspect the cell and restart safety on the pendant",
    12: "an automatic-mode safeguard stop is active",
    13: "the three-position enabling device stopped the arm",
}
# RTDE robot_mode values.
ROBOT_MODES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF",
               4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE"}
ROBOT_RUNNING = 7
