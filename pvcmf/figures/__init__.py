"""Figure builders: one module per paper figure, shared by the gallery and the image tests.

Each function builds a ``pyvista.Plotter`` (off screen) or a ``matplotlib.figure.Figure``
from pvcmf's own pipeline; ``gallery/`` scripts save them, tests image-compare them.
"""
