"""Off-screen rendering without a display.

VTK's Linux wheels carry both an X and an EGL render window and try X first: with no X
server that attempt prints ``bad X server connection`` before VTK falls back to EGL.
:func:`prefer_egl` names EGL as VTK's default window (``VTK_DEFAULT_OPENGL_WINDOW``) when
nothing can show a window, so a headless run renders through EGL straight away.
"""

from __future__ import annotations

import os
import sys

__all__ = ["prefer_egl"]


def prefer_egl(environ=None):
    """Make EGL VTK's default render window on a Linux machine without a display.

    Changes nothing where a display is set (``DISPLAY`` or ``WAYLAND_DISPLAY``), off Linux,
    where ``VTK_DEFAULT_OPENGL_WINDOW`` is already chosen, or where this VTK has no EGL
    window. Returns whether EGL was chosen. ``environ`` defaults to ``os.environ``.
    """
    env = os.environ if environ is None else environ
    if not sys.platform.startswith("linux") or "VTK_DEFAULT_OPENGL_WINDOW" in env:
        return False
    if env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"):
        return False
    try:
        from vtkmodules import vtkRenderingOpenGL2
    except ImportError:  # pragma: no cover - VTK without its OpenGL module
        return False
    if not hasattr(vtkRenderingOpenGL2, "vtkEGLRenderWindow"):
        return False
    env["VTK_DEFAULT_OPENGL_WINDOW"] = "vtkEGLRenderWindow"
    return True
