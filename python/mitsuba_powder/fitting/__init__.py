"""Goniometric fitting: the bounded least-squares optimiser shared by every fit
(:mod:`~mitsuba_powder.fitting.optimise`), the fit of the powder plugin's parameters to BRF
measurements (:mod:`~mitsuba_powder.fitting.fit`) and its reports
(:mod:`~mitsuba_powder.fitting.report`), the baseline models fitted the same way
(:mod:`~mitsuba_powder.fitting.baselines`) and their comparison with the powder model
(:mod:`~mitsuba_powder.fitting.comparison`), and the measurement protocols used to simulate
data (:mod:`~mitsuba_powder.fitting.protocols`)."""
