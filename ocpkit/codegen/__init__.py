"""CasADi Functions made into fast code: compiled C libraries (``compiled``) built into a safe cache (``builder``,
``cache``), and Taichi kernels (``kernels``)."""
