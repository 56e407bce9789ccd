"""The QP solvers behind :class:`~ocpkit.solvers.qp.LinearMPC` (and through it the real-time iteration and the sampling
planners' preconditioner) by name: ProxQP (:mod:`ocpkit.qp.proxqp`), OSQP (:mod:`ocpkit.qp.osqp`), HPIPM
(:mod:`ocpkit.qp.hpipm`) and DAQP (:mod:`ocpkit.qp.daqp`) behind one small interface,
:class:`~ocpkit.qp.interface.QPBackend`.

A backend is made once per controller (:func:`make_backend`) and then asked, step after step, to ``solve`` the
step's QP (:class:`ocpkit.qp.transcription.QP`) with a warm start (the previous answer's ``duals``) and a deadline. It
sets itself up on the first solve (and again when the QP's structure changes), updates its numbers on the later
ones, and forgets everything on ``reset``. Every operation that cannot be stopped from outside starts only if its
measured time (``costs``) fits in what is left of the deadline.
"""

from __future__ import annotations

from ocpkit.qp.daqp import DAQP
from ocpkit.qp.hpipm import HPIPM
from ocpkit.qp.interface import QPBackend
from ocpkit.qp.osqp import OSQP
from ocpkit.qp.proxqp import ProxQP
from ocpkit.qp.sparse import SparseQP

QP_SOLVERS = ("proxqp", "osqp", "hpipm", "daqp")


def make_backend(qp: str, transcription, max_iter: int, eps: float) -> QPBackend:
    """The backend ``qp`` (one of :data:`QP_SOLVERS`) for QPs of ``transcription`` (ProxQP: its sparse backend
    for the sparse form; HPIPM: the stage order of the sparse traditional form)."""
    if qp == "proxqp":
        return ProxQP(isinstance(transcription, SparseQP), max_iter, eps)
    if qp == "hpipm":
        return HPIPM(transcription, max_iter, eps)
    return {"osqp": OSQP, "daqp": DAQP}[qp](max_iter, eps)
