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


@linux
def test_headless_render_uses_egl_without_an_x_attempt(tmp_path):
    code = ("import pyvista as pv; from pvcmf.figures.offscreen import prefer_egl; prefer_egl();"
            "p = pv.Plotter(off_screen=True); p.add_mesh(pv.Sphere());"
            "p.screenshot(%r); print(p.ren_win.GetClassName())" % str(tmp_path / "s.png"))
    env = {k: v for k, v in os.environ.items()
           if k not in ("DISPLAY", "WAYLAND_DISPLAY", "VTK_DEFAULT_OPENGL_WINDOW")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, timeout=120)
    if out.returncode != 0 or "EGL" not in out.stdout:
        pytest.skip(f"no EGL rendering on this machine: {out.stderr[-300:]}")
    assert "bad X server connection" not in out.stderr
