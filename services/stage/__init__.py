"""The stage service: owns the RS-232 link to the NV 40/3 piezo amplifier.

``core`` holds the link (through pyserial), the displacement-voltage models and every
safety rule (limits, step and rate, watchdog, stop) and can be tested without sockets;
``main`` wires it to the control socket.
"""
