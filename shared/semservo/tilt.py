"""The tilts from focus: moved to :mod:`semservo.estimation.tilt` (section II-B-2 of the
paper, beside the estimator's other sections). This name stays for lab scripts written
against it: it is the very same module, not a copy."""

import sys

from semservo.estimation import tilt

sys.modules[__name__] = tilt
