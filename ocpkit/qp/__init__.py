"""The QP layer: the OCP transcribed into sparse and condensed QPs (``transcription``, ``task_rows``), the backends
that solve them (``interface``, ``backends``), the KKT certificate of an answer and the box-constrained QP."""
