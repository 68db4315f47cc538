"""The real Unitree G1 behind the executor's interface: joint layout, DDS frames (CRC), the
CycloneDDS transport, the controller (``rt/arm_sdk`` or ``rt/lowcmd``), the executor, and a
stand-in robot for tests. The transport does not import the controller.
"""
