"""Thermo Fisher and TESCAN microscopes (and OpenFIBSEM's ``DemoMicroscope``) through
OpenFIBSEM (``fibsem`` on PyPI, the ``semservo[openfibsem]`` extra).

* :class:`OpenFibsemSource` (:mod:`.source`): an image source, ``acquire_image`` with the
  scan the settings ask for (resolution, dwell, horizontal field width, beam), the
  image's own metadata in every frame header. Entry point ``openfibsem`` of
  ``semservo.image_sources``.
* :class:`OpenFibsemMotion` (:mod:`.motion`): a motion driver in micrometres, the stage
  (``stable_move``) and the beam shift. Entry point ``openfibsem`` of
  ``semservo.stage_drivers``; ``openfibsem://MANUFACTURER@HOST`` (:mod:`.session`).
* :class:`Positioner` (:mod:`.positioner`): semservo's estimator, controller and stage
  rules in the lab script's own process, on the microscope it already holds.
* :mod:`.units`: metres and micrometres, fibsem's axes and semservo's, in one place.
* :mod:`.demo`: the DemoMicroscope's frames rendered by semservo's simulated SEM at the
  demo's own stage position and beam shift (its own frames do not follow them).

Importing this package does not import fibsem; using any of these does, and says how to
install it when it is missing.
"""

from __future__ import annotations

from typing import Any

__all__ = ["OpenFibsemMotion", "OpenFibsemSource", "Positioner", "SimulatedDemoFrames"]

_WHERE = {"OpenFibsemMotion": "motion", "OpenFibsemSource": "source", "Positioner": "positioner",
          "SimulatedDemoFrames": "demo"}


def __getattr__(name: str) -> Any:
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"semservo.openfibsem.{_WHERE[name]}"), name)
    raise AttributeError(f"module 'semservo.openfibsem' has no attribute {name!r}")
