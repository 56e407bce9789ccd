"""Running studies: trials over a grid of parameters (``study``, ``trial``), on local processes or a Dask cluster
(``cluster``), claimed from and stored in a durable store (``claims``, ``store``, its SQLite file: ``database``, a
trial as a row: ``rows``), each with what computed it (``provenance``)."""
