"""The controller: turns motion estimates into stage moves (paper eq. 30-37).

``core`` holds the run state machine, the freshness and confidence rules and the run
records, and reaches the stage through a port (no sockets); ``main`` wires it to the
estimator's motion stream, the stage service (every axis, the rotation stage too), a
control socket and a status stream.
"""
