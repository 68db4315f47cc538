"""The real Unitree G1 behind the executor's interface: joint layout, DDS frames (CRC), the robot
state, the CycloneDDS transport, the controller (``rt/arm_sdk`` or ``rt/lowcmd``), the executor, a
stand-in robot for tests, and the backend's errors. The transport does not import the controller.
"""
