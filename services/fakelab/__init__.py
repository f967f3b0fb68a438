"""The simulated lab: one world (semservo.simulation.world) shared by an emulated NV 40/3
amplifier that speaks its real serial protocol (over a pseudo-terminal and TCP) and a
simulated SEM that the image server's ``sim`` source scans.

``emulator`` is the NV 40/3's protocol state machine (bytes in, bytes out, no I/O);
``serial_links`` connects it to a pseudo-terminal and a TCP port; ``main`` wires the
world, the links, the scan socket and the control socket.
"""
