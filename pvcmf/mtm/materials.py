"""Material tables and the transversely isotropic constitutive law of the MTM.

Pure numpy (no loop over cells); nothing here depends on the mesh.

Convention (transverse isotropy, the one the tests use)
-------------------------------------------------------
Local frame with ``e3`` = the unit fibre direction. Voigt order 11, 22, 33, 23, 13, 12 with
engineering shear strains. The compliance ``S`` (strain = S stress) is::

    normal block  [[ 1/Ec,   -nu/Ec, -nu/Ec],
                   [-nu/Ec,   1/Ec,  -nu/Ec],
                   [-nu/Ec,  -nu/Ec,  1/Ef ]]
    shear         diag(1/Gf, 1/Gf, 2 (1 + nu) / Ec),   Gf = Ef / (2 (1 + nu))

with ``Ef`` = ``E_fiber`` and ``Ec`` = ``E_cross``. With ``Ef == Ec`` it is isotropic. A bar
loaded along the fibre contracts laterally by ``nu * Ef / Ec``; loaded across, by ``nu``.
The stiffness ``C = S^-1`` is positive definite iff ``Ef > 0``, ``Ec > 0``, ``-1 < nu < 1``
and ``(1 - nu) Ec > 2 nu^2 Ef`` (for ``Ef == Ec``: ``-1 < nu < 1/2``). Writing ``-nu/Ef``
in the fibre column instead (the other convention found in the literature) makes paper 000's
Table I muscle indefinite; :func:`check_positive_definite` names such cells.

In the global frame, with fibre ``a`` and ``A = a a^T``, the stiffness tensor is the
invariant form::

    C = lam I(x)I + 2 muT II + alpha (A(x)I + I(x)A)
        + (muL - muT) (A_ik d_jl + A_il d_jk + A_jk d_il + A_jl d_ik) + beta A(x)A

whose five coefficients :func:`elastic_coefficients` computes from ``(Ef, Ec, nu)``; the
assembly (:mod:`pvcmf.mtm.assembly`) uses them directly, so no 6x6 matrix is rotated per cell.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "TABLES",
    "material_table",
    "elastic_coefficients",
    "constitutive_matrix",
    "check_positive_definite",
    "positive_definite_mask",
    "VOIGT_PAIRS",
]

#: Voigt index pairs, order 11, 22, 33, 23, 13, 12
VOIGT_PAIRS = ((0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1))

#: Material tables, as data. Each entry maps ``"fat"`` and ``"muscle"`` to
#: ``{"E_fiber", "E_cross", "nu"}`` (MPa, MPa, -). Paper 001 normalises by ``E_fat`` (only the
#: ratio matters when all loads are prescribed displacements), so its ``E_fat`` is 1.
TABLES = {
    "paper000": {
        "fat": {"E_fiber": 0.003, "E_cross": 0.003, "nu": 0.46},
        "muscle": {"E_fiber": 0.5, "E_cross": 0.79, "nu": 0.43},
        "source": "paper 000 Table I (transversely isotropic muscle)",
    },
    "paper001_homogeneous": {
        "fat": {"E_fiber": 1.0, "E_cross": 1.0, "nu": 0.46},
        "muscle": {"E_fiber": 1.0, "E_cross": 1.0, "nu": 0.46},
        "source": "paper 001 sec. 2.1, optimal homogeneous nu = 0.46",
    },
    "paper001_inhomogeneous": {
        "fat": {"E_fiber": 1.0, "E_cross": 1.0, "nu": 0.485},
        "muscle": {"E_fiber": 1.0, "E_cross": 1.0, "nu": 0.43},
        "source": "paper 001 sec. 2.2, nu_fat = 0.485, nu_muscle = 0.43, E_muscle/E_fat = e_ratio",
    },
}

_KEYS = ("E_fiber", "E_cross", "nu")


def material_table(table="paper000", *, e_ratio=None, fat=None, muscle=None):
    """Return the fat and muscle properties of a named table, with overrides.

    Parameters
    ----------
    table : str or dict
        A key of :data:`TABLES` or a dict shaped like its entries.
    e_ratio : float, optional
        ``E_muscle / E_fat``: the muscle's ``E_fiber`` and ``E_cross`` are set to
        ``e_ratio`` times the fat's (isotropic muscle), as in paper 001's sweep.
    fat, muscle : dict, optional
        Overrides of ``E_fiber``, ``E_cross``, ``nu``; a key ``E`` sets both moduli.

    Returns
    -------
    dict
        ``{"fat": {...}, "muscle": {...}}`` with float values.

    Examples
    --------
    >>> from pvcmf.mtm import material_table
    >>> material_table("paper001_inhomogeneous", e_ratio=8)["muscle"]
    {'E_fiber': 8.0, 'E_cross': 8.0, 'nu': 0.43}
    """
    if isinstance(table, str):
        if table not in TABLES:
            raise ValueError(f"table must be one of {sorted(TABLES)}, got {table!r}")
        base = TABLES[table]
    elif isinstance(table, dict):
        base = table
    else:
        raise TypeError(f"table must be a str or dict, got {type(table).__name__}")
    out = {}
    for tissue, over in (("fat", fat), ("muscle", muscle)):
        if tissue not in base:
            raise ValueError(f"table must have a {tissue!r} entry, got keys {sorted(base)}")
        props = {k: float(base[tissue][k]) for k in _KEYS}
        if over is not None:
            if not isinstance(over, dict):
                raise TypeError(f"{tissue} must be a dict of overrides, got {type(over).__name__}")
            bad = set(over) - set(_KEYS) - {"E"}
            if bad:
                raise ValueError(
                    f"{tissue} overrides must use keys {_KEYS + ('E',)}, got {sorted(bad)}"
                )
            if "E" in over:
                props["E_fiber"] = props["E_cross"] = float(over["E"])
            props.update({k: float(v) for k, v in over.items() if k != "E"})
        out[tissue] = props
    if e_ratio is not None:
        e_ratio = float(e_ratio)
        if not e_ratio > 0:
            raise ValueError(f"e_ratio must be > 0, got {e_ratio}")
        e = e_ratio * out["fat"]["E_cross"]
        out["muscle"]["E_fiber"] = out["muscle"]["E_cross"] = e
    return out


def positive_definite_mask(E_fiber, E_cross, nu):
    """Boolean array: True where the convention above gives a positive definite stiffness."""
    ef, ec, nu = np.broadcast_arrays(*(np.asarray(x, dtype=float) for x in (E_fiber, E_cross, nu)))
    with np.errstate(invalid="ignore"):
        ok = (ef > 0) & (ec > 0) & (nu > -1) & (nu < 1) & ((1 - nu) * ec > 2 * nu**2 * ef)
    return ok & np.isfinite(ef) & np.isfinite(ec) & np.isfinite(nu)


def check_positive_definite(E_fiber, E_cross, nu, what="cell"):
    """Raise ``ValueError`` naming the cells whose 6x6 stiffness is not positive definite.

    Examples
    --------
    >>> from pvcmf.mtm import check_positive_definite
    >>> check_positive_definite([0.5], [0.79], [0.43])      # paper 000 muscle: fine
    >>> check_positive_definite([0.79 / 0.43 * 2], [0.79], [0.43])  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    ValueError: material is not positive definite in 1 cell(s)...
    """
    ef, ec, nu = np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, dtype=float))
                                       for x in (E_fiber, E_cross, nu)))
    bad = np.flatnonzero(~positive_definite_mask(ef, ec, nu))
    if bad.size:
        shown = ", ".join(
            f"{what} {i}: E_fiber={ef[i]:.6g}, E_cross={ec[i]:.6g}, nu={nu[i]:.6g}" for i in bad[:5]
        )
        more = f" (and {bad.size - 5} more)" if bad.size > 5 else ""
        raise ValueError(
            f"material is not positive definite in {bad.size} {what}(s): {shown}{more}. "
            "pvcmf's transverse isotropy puts nu over E_cross (S13 = -nu/E_cross) and needs "
            "E_fiber > 0, E_cross > 0, -1 < nu < 1 and (1 - nu) * E_cross > 2 * nu**2 * E_fiber; "
            "values given for the nu-over-E_fiber convention must be converted"
        )


def elastic_coefficients(E_fiber, E_cross, nu):
    """The five coefficients ``(lam, muT, alpha, muL, beta)`` of the invariant stiffness form.

    Closed-form inverse of the compliance of the module docstring; arrays broadcast.
    For ``E_fiber == E_cross`` they reduce to Lame's ``(lam, mu, 0, mu, 0)``.

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.mtm import elastic_coefficients
    >>> lam, mu, alpha, muL, beta = elastic_coefficients(1.0, 1.0, 0.25)
    >>> float(lam), float(mu), float(alpha), float(beta)
    (0.4, 0.4, 0.0, 0.0)
    """
    ef, ec, nu = (np.asarray(x, dtype=float) for x in (E_fiber, E_cross, nu))
    # symmetric part of the normal block: [[s + t, u], [2u, r]] on (sigma1 = sigma2, sigma3)
    den = (1 - nu) * ec - 2 * nu**2 * ef  # = D * Ec^2 * Ef
    c11_plus_c12 = ec * ec / den  # r / D
    c11_minus_c12 = ec / (1 + nu)  # 1 / (s - t)
    c13 = nu * ec * ef / den  # -u / D
    c33 = (1 - nu) * ec * ef / den  # (s + t) / D
    lam = 0.5 * (c11_plus_c12 - c11_minus_c12)
    muT = 0.5 * c11_minus_c12
    muL = ef / (2 * (1 + nu))
    alpha = c13 - lam
    beta = c33 - lam - 2 * muT - 2 * alpha - 4 * (muL - muT)
    iso = ef == ec  # exact zeros for isotropic cells (no round-off fibre terms)
    alpha, beta, muL = np.where(iso, 0.0, alpha), np.where(iso, 0.0, beta), np.where(iso, muT, muL)
    return lam, muT, alpha, muL, beta


def _unit_fibers(fiber, n):
    a = np.zeros((n, 3)) if fiber is None else np.asarray(fiber, dtype=float).reshape(-1, 3)
    if a.shape[0] == 1 and n > 1:
        a = np.repeat(a, n, axis=0)
    norm = np.linalg.norm(a, axis=1)
    out = np.zeros_like(a)
    nz = norm > 0
    out[nz] = a[nz] / norm[nz, None]
    return out


def constitutive_matrix(E_fiber, E_cross, nu, fiber=None):
    """Per-cell 6x6 stiffness in the global frame (Voigt 11, 22, 33, 23, 13, 12, engineering shear).

    Parameters
    ----------
    E_fiber, E_cross, nu : array_like, shape (m,) or scalars
    fiber : array_like, shape (m, 3) or (3,), optional
        Fibre directions (normalised here); zero or None where isotropic.

    Returns
    -------
    numpy.ndarray, shape (m, 6, 6)

    Examples
    --------
    >>> import numpy as np
    >>> from pvcmf.mtm import constitutive_matrix
    >>> C = constitutive_matrix([0.5], [0.79], [0.43], [[0, 0, 1]])[0]
    >>> bool(np.isclose(np.linalg.inv(C)[2, 2], 1 / 0.5))
    True
    """
    ef, ec, nu = np.broadcast_arrays(*(np.atleast_1d(np.asarray(x, dtype=float))
                                       for x in (E_fiber, E_cross, nu)))
    check_positive_definite(ef, ec, nu)
    m = ef.shape[0]
    a = _unit_fibers(fiber, m)
    aniso = ef != ec
    if np.any(aniso & (np.linalg.norm(a, axis=1) == 0)):
        raise ValueError("fiber must be a nonzero vector where E_fiber != E_cross")
    lam, muT, alpha, muL, beta = elastic_coefficients(ef, ec, nu)
    d = np.eye(3)
    A = np.einsum("mi,mj->mij", a, a)
    C = (
        lam[:, None, None, None, None] * np.einsum("ij,kl->ijkl", d, d)[None]
        + muT[:, None, None, None, None]
        * (np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d))[None]
        + alpha[:, None, None, None, None]
        * (np.einsum("mij,kl->mijkl", A, d) + np.einsum("ij,mkl->mijkl", d, A))
        + (muL - muT)[:, None, None, None, None]
        * (np.einsum("mik,jl->mijkl", A, d) + np.einsum("mil,jk->mijkl", A, d)
           + np.einsum("mjk,il->mijkl", A, d) + np.einsum("mjl,ik->mijkl", A, d))
        + beta[:, None, None, None, None] * np.einsum("mij,mkl->mijkl", A, A)
    )
    out = np.empty((m, 6, 6))
    for p, (i, j) in enumerate(VOIGT_PAIRS):
        for q, (k, l) in enumerate(VOIGT_PAIRS):
            out[:, p, q] = C[:, i, j, k, l]
    return out
