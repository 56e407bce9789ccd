"""ocpkit: parameterized and GPU-parallelized real-time MPC for high-DoF robots (Hyatt, Williams, Killpack)."""
import os

# Taichi prints a banner to stdout on import; keep stdout clean for `--json` output and reports.
os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "False")
