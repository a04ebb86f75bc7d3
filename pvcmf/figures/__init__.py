"""Figure builders: one module per paper figure, shared by the gallery and the image tests.

Each function builds a ``pyvista.Plotter`` (off screen) or a ``matplotlib.figure.Figure``
from pvcmf's own pipeline; ``gallery/`` scripts save them, tests image-compare them.
Importing the package (as :mod:`pvcmf.pipeline`, :mod:`pvcmf.outputs` and the planner do)
makes EGL VTK's default window on a Linux machine without a display
(:func:`pvcmf.figures.offscreen.prefer_egl`), so offscreen figures render without VTK's
failed X attempt and its warning.
"""

from .offscreen import prefer_egl

prefer_egl()
