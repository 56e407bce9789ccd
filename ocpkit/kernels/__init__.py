"""Taichi kernels for EMPC and the other sampling planners (CUDA or CPU).

``translate`` turns CasADi SX Functions into Taichi functions, ``rollout`` simulates candidate
populations with them, ``random`` draws seeded counter-based numbers, ``runtime`` starts Taichi
once per process, and ``bench`` times EMPC (``ocpkit bench empc``).
"""
