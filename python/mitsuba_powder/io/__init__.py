"""Measurement files: the in-memory measurement set (:mod:`~mitsuba_powder.io.dataset`), the
project's CSV format and the loader that recognises every supported format
(:mod:`~mitsuba_powder.io.measurements`, whose :func:`load_measurements` is the entry point),
the text files of IPAG's goniometers and SSHADE (:mod:`~mitsuba_powder.io.ipag`), and the
converter of Germer's NIST PTFE data (:mod:`~mitsuba_powder.io.ptfe`). Angles in degrees,
wavelengths in nm, reflectance as BRF (``pi * BRDF``)."""
