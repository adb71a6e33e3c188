"""Read and write the text files of IPAG's spectro-goniometers (SHINE, SHADOWS) and SSHADE.

:func:`mitsuba_powder.io.measurements.load_measurements` dispatches here; use it rather than the
readers below. Every file may end its lines with CRLF, LF or CR alone (old Macintosh files);
text is UTF-8, or Latin-1 when it is not valid UTF-8.

Multi-geometry file (``*_geo*.txt``), tab-separated, a trailing tab allowed on any row::

    Detectors noises: ...                      optional free-text lines (kept as comments)
    3                                          the number of geometries (older files), or
    Angles<TAB>physical                        (newer files and SSHADE)
    Incidence<TAB>0<TAB>20<TAB>20              one value per geometry, degrees
    Emergence<TAB>30<TAB>0<TAB>-30
    Azimuth<TAB>0<TAB>0<TAB>0
    Wavelength_S<TAB>Refl_S_i0e30a0<TAB>Err_S_i0e30a0<TAB>Refl_S_i20e0a0<TAB>...
    400<TAB>0.512<TAB>0.004<TAB>...            wavelength (nm), then reflectance factor and
                                               its 1-sigma error per geometry

``S`` is the sample name; the ``Err`` columns may be absent altogether (errors missing). The
k-th ``Refl``/``Err`` pair belongs to the k-th angle column, and its name must agree with the
angles to the digits the name shows.

Single-geometry file ``<sample>_i<inc>e<em>a<az>_c.txt`` (the geometry only in the name):
optional header lines (``Sample data file : ...``, ``Corrected by: ...``; any line before the
first row whose first field is not a number), then rows ``wavelength, reflectance factor,
error`` (tab- or space-separated; two columns: errors missing). A folder of them is one data
set of one sample; files of other extensions in it are ignored (and listed in the comments).

Angle conventions (the project's: light at azimuth 0, ``theta_o`` signed, positive on the
light's side; see :mod:`mitsuba_powder.io.measurements`):

- ``signed`` (older IPAG files: a geometry-count line, every azimuth 0): the emergence is
  signed, positive on the forward (specular) side, so ``theta_o = -emergence, phi = 0``.
- ``physical`` (``Angles physical`` files and SSHADE): the emergence is >= 0 and the azimuth
  has its origin at opposition (``i = e``, azimuth 0 is back-scattering, 180 the forward
  side), so ``theta_o = emergence, phi = azimuth``.

A multi-geometry file's header line decides (an ``Angles physical`` line: physical; a count
line: signed, which requires every azimuth 0). Without either, and for single-geometry files,
the angles decide: a negative emergence means signed; every emergence >= 0 with some azimuth
not 0 means physical; every emergence 0 means both agree (``"any"``); otherwise (emergences
>= 0, every azimuth 0) the convention cannot be decided and loading fails, asking for
``convention="signed"`` or ``"physical"`` (``--convention`` on the command line).

Values: ``NaN`` (any case) in a reflectance or error cell leaves that value out; a row whose
wavelength is 0 or NaN is left out whole. Both are counted in ``Measurements.skipped`` and in a
``loader:`` comment line, never dropped silently. Any other text that is not a number, an
infinite value, a negative reflectance, error or wavelength, a wrong number of columns or a
column name that disagrees with the angle rows raises :class:`MeasurementError` naming the
file, line and column.

Errors become ``sigma``. A negative error is malformed. Zero and missing errors: if no value
has a positive error (all zero, or no error column), ``sigma`` is ``None`` and a fit is
unweighted (stated in the comments). If only some are zero or missing, ``zero_error`` decides:
``"raise"`` (default; the message names the first lines), ``"unweighted"`` (drop every sigma),
or ``"skip"`` (leave those values out, counted).

Contradictions: one sample per data set. In a multi-geometry file every ``Refl``/``Err``
column names the sample of ``Wavelength_<sample>``; in a folder, every file name has the same
sample prefix, and files of the same geometry (replicates) must agree on every ``key : value``
header line except ``Sample data file`` (which names each file's raw data). Anything else at
the same geometry and wavelength is a replicate: a separate observation.

The work is split by job: :mod:`~mitsuba_powder.io.ipag_text` (lines, fields, numbers, file
kind), :mod:`~mitsuba_powder.io.ipag_angles` (conventions), :mod:`~mitsuba_powder.io.ipag_read`
(:func:`load_ipag`) and :mod:`~mitsuba_powder.io.ipag_write` (:func:`save_ipag`); this module
is where their public names are imported from.
"""

from __future__ import annotations

from .ipag_angles import decide_convention, from_project, to_project
from .ipag_read import load_ipag
from .ipag_text import (
    CONVENTIONS,
    LAYOUTS,
    NEWLINES,
    ZERO_ERROR,
    file_kind,
    geometry_tag,
    read_lines,
)
from .ipag_write import save_ipag

__all__ = [
    "CONVENTIONS",
    "LAYOUTS",
    "NEWLINES",
    "ZERO_ERROR",
    "decide_convention",
    "file_kind",
    "from_project",
    "geometry_tag",
    "load_ipag",
    "read_lines",
    "save_ipag",
    "to_project",
]
