"""The simulated lab's science: samples, the SEM that images them, and the piezo stage
that moves them. ``services/fakelab`` serves it; benchmarks and tests use it directly.

Nothing here is tuned to make semservo look good: the effects are those the SEM imaging
literature and the NV 40/3 / TRITOR facts in ``shared/reference`` describe.
"""
