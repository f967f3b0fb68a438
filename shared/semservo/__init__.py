"""semservo: image-guided nanopositioning for scanning electron microscopes.

The importable library that every service, lab script and benchmark shares:
wire messages (:mod:`semservo.messages`, :mod:`semservo.wire`), ZeroMQ transport
(:mod:`semservo.transport`), settings (:mod:`semservo.config`), the service runtime
(:mod:`semservo.service`), image files (:mod:`semservo.imagefiles`) and the launcher
(:mod:`semservo.launcher`).

The method is Marturi et al., "Image-Guided Nanopositioning Scheme for SEM".
"""

__version__ = "0.1.0"
