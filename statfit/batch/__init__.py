"""Datasets: many fits, resumable, on a local process pool or a Dask cluster.

- :mod:`statfit.batch.plan`: the inputs a batch covers and the output each one gets.
- :mod:`statfit.batch.manifest`: the JSON-lines record of what was done, and what to skip.
- :mod:`statfit.batch.fits`: one fit as a picklable job a worker runs (register or render).
- :mod:`statfit.batch.engines`: the process pool and the Dask client, behind one interface.
- :mod:`statfit.batch.run`: the loop tying them together (failures isolated, workers replaced).
"""
