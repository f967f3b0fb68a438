"""The image server: acquires SEM frames from a pluggable source and publishes them.

``sources`` holds the sources (``replay`` now), ``core`` paces and numbers frames
without touching a socket, ``main`` wires the core to the PUB and control sockets.
"""
