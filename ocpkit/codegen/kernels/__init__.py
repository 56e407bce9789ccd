"""Taichi kernels for EMPC and the other sampling planners (CUDA or CPU).

``translate`` turns CasADi SX Functions into Taichi functions, ``rollout`` simulates candidate
populations with them, ``random`` draws seeded counter-based numbers, ``runtime`` starts Taichi
once per process (its CPU backend uses ``OCPKIT_CPU_THREADS`` threads if set, else all cores).
"""

CPU_THREADS = "OCPKIT_CPU_THREADS"
