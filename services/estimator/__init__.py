"""The estimator: measures each frame's motion against the taught reference.

``core`` holds the reference and turns frames into motion estimates without sockets;
``main`` wires it to the image server's frames (latest only), a PUB socket for motion
and the control socket (teach, clear, report).
"""
