"""Headless rendering: EGL is chosen only where nothing can show a window."""

import os
import subprocess
import sys

import pytest

from pvcmf.figures.offscreen import prefer_egl

linux = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux only")


@linux
def test_egl_is_chosen_without_a_display():
    env = {}
    assert prefer_egl(env) is True
    assert env == {"VTK_DEFAULT_OPENGL_WINDOW": "vtkEGLRenderWindow"}


@pytest.mark.parametrize("env", [{"DISPLAY": ":0"}, {"WAYLAND_DISPLAY": "wayland-0"},
                                 {"VTK_DEFAULT_OPENGL_WINDOW": "vtkXOpenGLRenderWindow"}])
def test_a_display_or_a_choice_is_left_alone(env):
    before = dict(env)
    assert prefer_egl(env) is False
    assert env == before


def headless(code, png):
    """``code`` then a sphere rendered to ``png``, in a Python without a display; prints
    the render window's class last."""
    code += (";import pyvista as pv; p = pv.Plotter(off_screen=True); p.add_mesh(pv.Sphere());"
             "p.screenshot(%r); print(p.ren_win.GetClassName())" % str(png))
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=120)


@linux
def test_headless_render_uses_egl_without_an_x_attempt(tmp_path):
    out = headless("from pvcmf.figures.offscreen import prefer_egl; prefer_egl()",
                   tmp_path / "s.png")
    if out.returncode != 0 or "EGL" not in out.stdout:
        pytest.skip(f"no EGL rendering on this machine: {out.stderr[-300:]}")
    assert "bad X server connection" not in out.stderr


@linux
def test_the_pipeline_renders_headless_without_an_x_attempt(tmp_path):
    """Python users (a script, the gallery) get EGL from importing the pipeline, as the
    command line does: the face views render with no "bad X server" line."""
    out = headless("import pvcmf.pipeline, os; print(os.environ.get('VTK_DEFAULT_OPENGL_WINDOW'))",
                   tmp_path / "s.png")
    assert out.returncode == 0, out.stderr[-500:]
    assert out.stdout.splitlines()[0] == "vtkEGLRenderWindow"
    if "EGL" not in out.stdout.splitlines()[-1]:
        pytest.skip(f"no EGL rendering on this machine: {out.stderr[-300:]}")
    assert "bad X server connection" not in out.stderr
