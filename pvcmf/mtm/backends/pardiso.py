"""MKL PARDISO for the MTM, called through ctypes on the MKL runtime that pypardiso installs.

pypardiso's public :class:`pypardiso.PyPardisoSolver` runs the symbolic analysis again at
every ``factorize`` (phase 12), passes float64 only and converts the indices to one-based on
every call. Here the analysis (phase 11) is done once per pattern and every new material is a
numeric factorisation only (phase 22), which is what a Poisson sweep repeats; the upper
triangle (CSR, zero-based indices through ``iparm[34]``) is passed as it is stored. The thread
count is the caller's (None: MKL's own default) and is used by every phase (MKL expects the
analysis's count in the later phases). ``precision='single'`` makes a float32 numeric factor
(``iparm[27]``) whose answers the caller refines against the double matrix.

Without scikit-sparse, :func:`node_order` takes the METIS order of the node graph from a
PARDISO analysis of that (nine times smaller) graph; the solver numbers the unknowns node by
node in that order and :class:`Pardiso` analyses the dof matrix with it as the user
permutation (``natural=True``, ``iparm[4] = 1``) instead of running METIS on the dof graph.
"""

from __future__ import annotations

import ctypes

import numpy as np
import scipy.sparse as sp

from .._common import not_positive_definite

_MKL = []


def available():
    """True when pypardiso (and so MKL PARDISO) imports."""
    try:
        import pypardiso  # noqa: F401
    except ImportError:
        return False
    return True


def _mkl():
    """pypardiso's MKL runtime with the C signatures of PARDISO and the thread functions.

    (The lowercase ``mkl_set_num_threads*`` are the Fortran entry points, which take pointers.)
    """
    if not _MKL:
        from pypardiso import PyPardisoSolver

        lib = PyPardisoSolver().libmkl
        lib.pardiso.argtypes = [ctypes.c_void_p] * 16
        lib.pardiso.restype = None
        lib.MKL_Set_Num_Threads_Local.argtypes = [ctypes.c_int]
        lib.MKL_Set_Num_Threads_Local.restype = ctypes.c_int
        lib.MKL_Get_Max_Threads.argtypes = []
        lib.MKL_Get_Max_Threads.restype = ctypes.c_int
        _MKL.append(lib)
    return _MKL[0]


#: :attr:`pvcmf.mtm.Solver.node_ordering` of the node-graph order from :func:`node_order`
NODE_ORDERING = "pardiso-metis"


def _pardiso(lib, pt, phase, n, a, ia, ja, perm, iparm, b, x, threads, mtype=2):
    """One PARDISO call with ``threads`` MKL threads on this thread; returns the error code."""
    P = ctypes.c_void_p

    def i32(v):
        return ctypes.byref(ctypes.c_int32(v))

    err = ctypes.c_int32(0)
    previous = lib.MKL_Set_Num_Threads_Local(int(threads))  # this thread only
    try:
        lib.pardiso(pt.ctypes.data_as(P), i32(1), i32(1), i32(mtype), i32(phase), i32(n),
                    a.ctypes.data_as(P), ia.ctypes.data_as(P), ja.ctypes.data_as(P),
                    perm.ctypes.data_as(P), i32(1), iparm.ctypes.data_as(P), i32(0),
                    b.ctypes.data_as(P), x.ctypes.data_as(P), ctypes.byref(err))
    finally:
        lib.MKL_Set_Num_Threads_Local(previous)
    return err.value


def node_order(indptr, indices, free, threads=1):
    """METIS order of the node graph of the unknowns, by PARDISO's own analysis.

    ``indptr, indices`` is the node adjacency (block pattern, CSR, both triangles), ``free``
    the (3 n,) mask of unknown dofs. PARDISO analyses the upper triangle of the graph of the
    nodes with an unknown (a ninth of the entries of the dof matrix) and returns its METIS
    permutation (``iparm[4] = 2``). Numbered node by node in that order, the dof matrix is
    analysed with that order as a user permutation (no METIS on the dof graph), which costs
    less than METIS on the dof graph for no more fill. Returns ``(nodes, NODE_ORDERING)``:
    the nodes with an unknown in elimination order, or None when there are fewer than two.
    """
    n = len(indptr) - 1
    active = np.flatnonzero(np.asarray(free).reshape(n, 3).any(axis=1))
    m = active.size
    if m < 2:
        return None
    rank = np.full(n, -1, dtype=np.int64)
    rank[active] = np.arange(m)
    rows = np.repeat(np.arange(n), np.diff(indptr))
    r, c = rank[rows], rank[np.asarray(indices)]
    keep = (r >= 0) & (c >= r)  # upper triangle of the active nodes
    diag = np.arange(m)  # PARDISO needs every diagonal entry
    graph = sp.csr_matrix((np.ones(int(keep.sum()) + m), (np.concatenate([r[keep], diag]),
                                                          np.concatenate([c[keep], diag]))),
                          shape=(m, m))
    graph.sum_duplicates()  # sorted column indices, one entry each
    ip = np.zeros(64, dtype=np.int32)
    ip[0], ip[1], ip[4], ip[34] = 1, 2, 2, 1  # METIS, return the permutation, zero-based
    pt = np.zeros(64, dtype=np.int64)
    perm = np.zeros(m, dtype=np.int32)
    ia = np.ascontiguousarray(graph.indptr, dtype=np.int32)
    ja = np.ascontiguousarray(graph.indices, dtype=np.int32)
    a = np.ascontiguousarray(graph.data, dtype=np.float64)
    work = np.zeros(m)
    lib = _mkl()
    err = _pardiso(lib, pt, 11, m, a, ia, ja, perm, ip, work, work, threads)
    _pardiso(lib, pt, -1, m, a, ia, ja, perm, ip, work, work, threads)
    if err != 0:
        raise RuntimeError(f"PARDISO analysis of the node graph failed with error {err}")
    # perm[k]: the (active) node eliminated k-th
    return active[perm], NODE_ORDERING


class Pardiso:
    """MKL PARDISO, real symmetric positive definite (``mtype=2``), upper triangle in CSR.

    Parameters
    ----------
    upper : scipy.sparse.csr_matrix
        Upper triangle of the matrix; its pattern is analysed once.
    precision : {'double', 'single'}
        Precision of the numeric factor.
    threads : int, optional
        MKL threads of every phase; None: MKL's default (``MKL_Get_Max_Threads``).
    natural : bool
        The unknowns are already numbered in a fill-reducing order (skip PARDISO's METIS).
    """

    name = "pardiso"
    reads = "upper"

    def __init__(self, upper, *, precision="double", threads=None, natural=False):
        if precision not in ("double", "single"):
            raise ValueError(f"precision must be 'double' or 'single', got {precision!r}")
        self._lib = _mkl()
        n = self.n = upper.shape[0]
        self.precision = precision
        self.threads = int(threads) if threads is not None else int(self._lib.MKL_Get_Max_Threads())
        if self.threads < 1:
            raise ValueError(f"threads must be a positive integer, got {threads!r}")
        self._dtype = np.float32 if precision == "single" else np.float64
        self._pt = np.zeros(64, dtype=np.int64)
        ip = self._iparm = np.zeros(64, dtype=np.int32)
        ip[0] = 1  # iparm set here, zeros are defaults
        ip[1] = 2  # METIS nested dissection (unless a permutation is given)
        ip[4] = 1 if natural else 0  # perm holds the user's fill-reducing permutation
        ip[17] = -1  # report the factor's entries (factor_entries)
        ip[27] = 1 if precision == "single" else 0
        ip[34] = 1  # zero-based ia, ja
        self._ia = np.ascontiguousarray(upper.indptr, dtype=np.int32)
        self._ja = np.ascontiguousarray(upper.indices, dtype=np.int32)
        self._perm = np.arange(n, dtype=np.int32) if natural else np.zeros(n, dtype=np.int32)
        self._a = np.ascontiguousarray(upper.data, dtype=self._dtype)
        self._analysed = False
        self._call(11)
        self._analysed = True

    @property
    def factor_entries(self):
        """Entries of the factor that the analysis planned (PARDISO's ``iparm[17]``)."""
        return int(self._iparm[17])

    def _call(self, phase, b=None):
        if b is None:
            b = x = np.zeros(self.n, dtype=self._dtype)
        else:
            b = np.ascontiguousarray(b, dtype=self._dtype)
            x = np.empty_like(b)
        err = _pardiso(self._lib, self._pt, phase, self.n, self._a, self._ia, self._ja,
                       self._perm, self._iparm, b, x, self.threads)
        if err == -4:
            raise not_positive_definite(f"PARDISO error -4, zero or negative pivot "
                                        f"({self.precision})")
        if err != 0:
            raise RuntimeError(f"PARDISO phase {phase} failed with error {err}")
        return x

    def factor(self, upper):
        """Numeric factorisation of new values on the analysed pattern."""
        self._a = np.ascontiguousarray(upper.data, dtype=self._dtype)
        self._call(22)

    def solve(self, b):
        if self._dtype == np.float64:
            return self._call(33, b)
        scale = float(np.abs(b).max())  # float32 range: solve for b / max|b|
        if scale == 0.0:
            return np.zeros(self.n)
        return self._call(33, b / scale).astype(np.float64) * scale

    def __del__(self):
        try:  # release PARDISO's memory (phase -1)
            if self._analysed:
                self._call(-1)
        except Exception:  # noqa: BLE001 - interpreter shutdown, failed __init__
            pass
