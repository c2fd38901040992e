"""``rovergate study``: the paper's controlled study. :mod:`.spec` holds its settings and run
specifications (the types every part shares), :mod:`.worker` runs one mission of it,
:mod:`.runner` runs them all (in worker processes, or on a Dask cluster: :mod:`.cluster`), and
:mod:`.tables` and :mod:`.validation` write its outputs."""
