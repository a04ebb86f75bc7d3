"""Synthetic CTs of body parts that are not a head, for the refusal tests: a chest (an
elliptic torso with lungs, a trachea, a spine and ribs) and a knee (a limb cross-section
with the femur's shaft and condyles, the tibia and the patella), in HU and the patient frame
(x left, y anterior, z superior)."""

from __future__ import annotations

import numpy as np
import pyvista as pv

from pvcmf import arrays


def _image(vol, spacing):
    img = pv.ImageData(dimensions=vol.shape, spacing=(spacing,) * 3)
    img[arrays.CT] = np.asarray(vol, dtype=np.float32).ravel(order="F")
    return img


def _grid(shape, spacing):
    g = np.indices(shape).astype(np.float32) * spacing
    return [g[a] - 0.5 * spacing * (shape[a] - 1) for a in range(3)]  # mm from the centre


def chest(spacing=3.0, seed=0):
    """Torso 330 x 230 mm, 210 mm long: skin and fat, muscle, two lungs (-850 HU), the
    trachea, a heart, a spine (vertebral bodies and canal) and ribs every 25 mm."""
    shape = tuple(int(round(s / spacing)) for s in (400.0, 300.0, 210.0))
    x, y, z = _grid(shape, spacing)
    vol = np.full(shape, -1000.0, dtype=np.float32)
    torso = (x / 165.0) ** 2 + (y / 115.0) ** 2
    vol[torso < 1.0] = -100.0  # fat
    vol[torso < 0.85] = 40.0  # muscle and organs
    # ribs: elliptic rings, 8 mm thick, 25 mm apart
    rib = (np.abs(np.sqrt(torso) - 0.8) < 0.025) & (np.abs((z + 200.0) % 25.0 - 12.5) < 4.0)
    vol[rib & (y > -80.0)] = 900.0
    for side in (-1.0, 1.0):  # lungs, narrowing toward the apex
        lung = (((x - side * 75.0) / 60.0) ** 2 + ((y + 5.0) / 80.0) ** 2
                + ((z + 40.0) / 160.0) ** 2)
        vol[lung < 1.0] = -850.0
    vol[((x / 45.0) ** 2 + ((y - 10.0) / 50.0) ** 2 + ((z + 60.0) / 70.0) ** 2) < 1.0] = 40.0
    vol[(x ** 2 + (y - 30.0) ** 2 < 8.0 ** 2) & (z > 20.0)] = -1000.0  # trachea
    body = x ** 2 + (y + 70.0) ** 2  # spine: vertebral bodies, canal behind
    vol[body < 20.0 ** 2] = 1100.0
    vol[body < 16.0 ** 2] = 250.0
    vol[(np.abs((z + 200.0) % 30.0 - 15.0) < 3.0) & (body < 20.0 ** 2)] = 40.0  # discs
    canal = x ** 2 + (y + 100.0) ** 2
    vol[(canal < 14.0 ** 2) & (canal >= 9.0 ** 2)] = 1100.0
    vol[canal < 9.0 ** 2] = 10.0
    vol += np.random.default_rng(seed).normal(0.0, 15.0, shape).astype(np.float32)
    return _image(vol, spacing)


def knee(spacing=2.0, seed=1):
    """A limb 130 mm across and 200 mm long: skin and fat, muscle, the femur (cortex 1500 HU
    round a fatty marrow) ending in its condyles (cancellous bone in a thin cortex), the
    tibia below the joint space and the patella in front."""
    shape = tuple(int(round(s / spacing)) for s in (160.0, 160.0, 200.0))
    x, y, z = _grid(shape, spacing)
    vol = np.full(shape, -1000.0, dtype=np.float32)
    r = np.hypot(x, y)
    vol[r < 65.0] = -100.0
    vol[r < 55.0] = 40.0
    shaft = (r < 14.0) & (z > 30.0)
    vol[shaft] = 1500.0
    vol[(r < 9.0) & (z > 30.0)] = -60.0
    condyle = (x / 40.0) ** 2 + (y / 30.0) ** 2 + ((z - 15.0) / 30.0) ** 2
    vol[condyle < 1.0] = 700.0
    vol[condyle < 0.85] = 250.0
    plateau = (x / 38.0) ** 2 + (y / 28.0) ** 2 < 1.0
    vol[plateau & (z < -20.0)] = 700.0
    vol[plateau & (z < -23.0) & ((x / 34.0) ** 2 + (y / 24.0) ** 2 < 1.0)] = 250.0
    vol[(x / 22.0) ** 2 + ((y - 42.0) / 9.0) ** 2 + ((z - 20.0) / 22.0) ** 2 < 1.0] = 900.0
    vol += np.random.default_rng(seed).normal(0.0, 15.0, shape).astype(np.float32)
    return _image(vol, spacing)
