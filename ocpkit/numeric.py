"""How a step computes: CasADi Functions called on numpy arrays through CasADi's evaluation buffer, and the
BLAS/OpenMP threads a step may use (:class:`ThreadLimit`).

``fn(x, u)`` wraps every argument in a DM and every result in a DM that numpy then copies: for a
large robot's affine model that conversion alone is a sizeable part of an MPC step. A
:class:`BufferedFunction` binds preallocated numpy arrays to the Function's inputs and outputs
once and evaluates in place.
"""

from __future__ import annotations

import sys
import threading

import casadi as ca
import numpy as np


class BufferedFunction:
    """``fn`` evaluated through its buffer: call it with array-likes (one per input, dense inputs
    only) to get new dense float64 arrays, one per output, of the output's shape."""

    def __init__(self, fn: ca.Function):
        if not isinstance(fn, ca.Function):
            raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
        sparse_in = [fn.name_in(i) for i in range(fn.n_in()) if not fn.sparsity_in(i).is_dense()]
        if sparse_in:
            raise ValueError(f"fn {fn.name()!r} has sparse inputs {sparse_in}: BufferedFunction takes dense inputs")
        self.fn = fn
        self._buffer, self._evaluate = fn.buffer()
        self._args = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self._results = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        for i, a in enumerate(self._args):
            self._buffer.set_arg(i, memoryview(a))
        for i, r in enumerate(self._results):
            self._buffer.set_res(i, memoryview(r))
        # Nonzeros are stored column by column: a dense output is a Fortran-ordered array, a sparse one
        # is scattered to its (row, column) triplets.
        self._outputs = []
        for i in range(fn.n_out()):
            sparsity = fn.sparsity_out(i)
            where = None if sparsity.is_dense() else tuple(np.asarray(v, dtype=np.intp) for v in sparsity.get_triplet())
            self._outputs.append((tuple(fn.size_out(i)), where))

    def __call__(self, *args) -> tuple[np.ndarray, ...]:
        if len(args) != len(self._args):
            raise TypeError(f"{self.fn.name()} takes {len(self._args)} arguments, got {len(args)}")
        for i, (slot, value) in enumerate(zip(self._args, args)):
            value = np.asarray(value, dtype=float)
            if value.size != slot.size:
                raise ValueError(
                    f"argument {self.fn.name_in(i)!r} of {self.fn.name()} must have {slot.size} "
                    f"entries, got {value.size}"
                )
            slot[:] = value.ravel(order="F")
        self._evaluate()
        out = []
        for values, (shape, where) in zip(self._results, self._outputs):
            if where is None:
                out.append(np.ascontiguousarray(values.reshape(shape, order="F")))
            else:
                dense = np.zeros(shape)
                dense[where] = values
                out.append(dense)
        return tuple(out)


class ThreadLimit:
    """BLAS/OpenMP threads limited (threadpoolctl) while any controller step runs in this process.

    The pools are process-wide, so nested or concurrent steps share one limit: the first step to enter sets
    it, the last to leave restores the original. Multithreaded BLAS on a step's small matrices only competes with
    the machine's other work, hence 1 thread by default.
    """

    _lock = threading.Lock()
    _active = 0
    _original = None  # each pool's thread count before the first step entered (None: no step in flight)
    _controller = None
    _modules = 0

    def __init__(self, threads: int | None):
        self.threads = threads

    def __enter__(self):
        if self.threads is None:
            return self
        cls = ThreadLimit
        with cls._lock:
            if cls._active == 0:
                # Rescan the loaded libraries when modules were imported since (a new BLAS may have come in).
                if cls._controller is None or cls._modules != len(sys.modules):
                    from threadpoolctl import ThreadpoolController

                    cls._controller = ThreadpoolController()
                    cls._modules = len(sys.modules)
                # threadpoolctl's limit() and restore, on the pools directly: its info() dictionaries cost 17 us
                # of a 0.2 ms step
                pools = cls._controller.lib_controllers
                cls._original = [pool.num_threads for pool in pools]
                for pool in pools:
                    pool.set_num_threads(self.threads)
            cls._active += 1
        return self

    def __exit__(self, *exc):
        if self.threads is None:
            return False
        cls = ThreadLimit
        with cls._lock:
            cls._active -= 1
            if cls._active == 0 and cls._original is not None:
                for pool, threads in zip(cls._controller.lib_controllers, cls._original):
                    pool.set_num_threads(threads)
                cls._original = None
        return False
