"""sarship workers: Dask cluster start-up and the code that submits tile work."""
